"""The plain-numpy reference of the velocity sums (slow; for tests and benchmarks).

:func:`stokeslet_velocity_numpy` evaluates :func:`~ciliary_carpet.stokes.dispatch.stokeslet_velocity`
through each Green's function's own numpy reference
(:meth:`~ciliary_carpet.stokes.kernel.Kernel.reference`: free space in the vector form
``(f (r^2 + 2 eps^2) + R (R.f)) / (r^2 + eps^2)^{3/2}``, the walls as full 3x3 tensors written term
by term), an algebra independent of the compiled pair formulas that the tests hold them to.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ciliary_carpet.stokes.backend import kernel_of, validated
from ciliary_carpet.stokes.kernel import Kernel, Wall

__all__ = ["stokeslet_velocity_numpy"]


def stokeslet_velocity_numpy(targets: Any, sources: Any, forces: Any, mu: float = 1.0,
                             wall: Wall | None = None, *, chunk_pairs: int = 65536,
                             kernel: Kernel | None = None) -> np.ndarray:
    """Plain-numpy reference of :func:`~ciliary_carpet.stokes.dispatch.stokeslet_velocity`.

    Vectorised over all pairs of a chunk of targets (about ``chunk_pairs`` pairs at a time, which
    bounds the memory: a few hundred bytes per pair of the chunk). Same arguments, conventions
    and validation as :func:`~ciliary_carpet.stokes.dispatch.stokeslet_velocity`; always exact
    (no FMM).
    """
    k = kernel_of(kernel, wall)
    t, s, f, m = validated(k, targets, sources, forces, mu)
    M, N = t.shape[0], s.shape[0]
    out = np.zeros((M, 3))
    if M == 0 or N == 0:
        return out
    z = k.z_origin
    if z is not None:
        t = t.copy()
        t[:, 2] -= z
        s = s.copy()
        s[:, 2] -= z
    step = max(1, int(chunk_pairs) // N)
    for lo in range(0, M, step):
        out[lo:lo + step] = k.reference(t[lo:lo + step], s, f) / (8.0 * np.pi * m)
    return out
