"""Arrays of artificial cilia under one uniform field: inverse design of curvature layouts,
Stokeslet flows at the fidelity a scene needs, path lines and VTK output.

This layer depends on :mod:`single_cilium` only through its public API and its lookup table.
It is being built (see the project's issues); nothing is exported yet.
"""
