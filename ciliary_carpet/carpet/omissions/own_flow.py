"""A sampled cilium's own resolved line of Stokeslets, and its flow: what is subtracted from the
carpet's flow to leave the flow of the *other* cilia (the same kernel, blob, wall and Simpson
weights as the carpet's sum, at the same phase, so that the subtraction removes exactly that
cilium's term, to rounding)."""
from __future__ import annotations

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.stokes import stokeslet_velocity_ranges

__all__ = ["own_flow", "own_line", "others_mean_flow_in_space", "pad"]


def own_flow(carpet: Carpet, targets: np.ndarray, src: np.ndarray, frc: np.ndarray, per: int, blk: int) -> np.ndarray:
    """Velocity at ``targets`` ((len(js) * per, 3), ``per`` consecutive targets per cilium) of
    each cilium's own sources only (block i of ``blk`` rows of ``src``, ``frc``)."""
    m = targets.shape[0]
    i = np.arange(m) // per
    ranges = np.stack([i * blk, (i + 1) * blk], axis=1).astype(np.int64)
    ptr = np.arange(m + 1, dtype=np.int64)
    return stokeslet_velocity_ranges(targets, src, frc, ptr, ranges, carpet.mu, kernel=carpet.kernel,
                                     backend=carpet.backend)


def own_line(carpet: Carpet, t: float, js: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The resolved lines of cilia ``js`` at time ``t`` in space: sources and forces times the
    Simpson weights ``w``, (len(js) x n_s, 3) each (what the carpet sums for them at ``t``)."""
    pos, frc, _ = carpet.placement.shapes(carpet, t, js)
    return pos.reshape(-1, 3), (frc * w[None, :, None]).reshape(-1, 3)


def others_mean_flow_in_space(carpet: Carpet, js: np.ndarray, tol: float) -> np.ndarray:
    """(len(js), 3) the others' cycle-mean flow at the force centres of a standing carpet's cilia
    ``js``, in space: the carpet's :class:`~ciliary_carpet.carpet.carpet.CycleMean` flow at each
    centre minus the cilium's own cycle-averaged resolved line (the same weights as the carpet's
    resolved mean, as :meth:`Carpet.others_mean_flow
    <ciliary_carpet.carpet.carpet.Carpet.others_mean_flow>` does in a planar carpet's plane)."""
    cen = carpet.in_space("centres", js)
    u = carpet.velocity(cen, CycleMean(), tol)
    w = carpet.cycles.weights
    xs, fs = carpet.cycle_samples(js)  # (m, n_phase, n_s, 2) in each beat plane
    m, n_p, n_s = xs.shape[:3]
    src = carpet.embedding.points(xs.reshape(m, -1, 2), js).reshape(-1, 3)
    frc = carpet.embedding.vectors((fs * (w / n_p)[None, None, :, None]).reshape(m, -1, 2), js).reshape(-1, 3)
    return u - own_flow(carpet, cen, np.ascontiguousarray(src), np.ascontiguousarray(frc), 1, n_p * n_s)


def pad(a: np.ndarray) -> np.ndarray:
    """Points or vectors of the plane z = 0, (..., 2), as 3-vectors (..., 3)."""
    return np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)
