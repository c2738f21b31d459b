"""Transport in a carpet's flow: path lines of massless tracers and mixing (FTLE)."""
