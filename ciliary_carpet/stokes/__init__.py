"""Stokes flow of point forces: Green's functions (free space, above a no-slip wall) and the
evaluators that sum them (direct, treecode, FMM, CUDA)."""
