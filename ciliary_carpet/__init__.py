"""Arrays of artificial cilia under one uniform field: inverse design of curvature layouts,
Stokeslet flows at the fidelity a scene needs, path lines and VTK output.

This layer depends on :mod:`single_cilium` only through its public API and its lookup table.
It is being built (see the project's issues); nothing is exported yet.
"""
from single_cilium.numba_cache import ensure_writable_cache as _ensure_writable_cache

_ensure_writable_cache(__path__[0])  # before any module compiles: a read-only install, an unwritable home
