"""Transport in a carpet's flow: path lines of massless tracers, their accuracy, and mixing (FTLE)."""
