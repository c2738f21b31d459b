"""What a render writes: VTK files, pictures, the summary in words, the ParaView script, and the
output folder that holds them."""
