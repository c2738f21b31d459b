"""A carpet of cilia: where they stand, how they beat, the flow they drive, and what that model
leaves out."""
