"""Carpet layouts: where the cilia are clamped (lattices) and how their beats are phased.

Base points are in the lab frame, in the plane z = 0, in units of the filament length L.
Phases are fractions of a cycle in [0, 1): cilium j is at phase ``phases[j]`` at t = 0 and
advances at its own rate 1/T(chi_N_j) (see :class:`~ciliary_carpet.carpet.carpet.Carpet`).
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["row", "square", "hexagonal", "points", "random_phases", "synchronous_phases", "wave_phases", "neighbours"]


def _count(name: str, n) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"{name} must be a positive integer, got {n!r}")
    return int(n)


def _spacing(spacing) -> float:
    s = float(spacing)
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"spacing must be a positive finite number, got {spacing!r}")
    return s


def _origin(origin) -> np.ndarray:
    o = np.asarray(origin, dtype=float).reshape(-1)
    if o.shape != (2,) or not np.all(np.isfinite(o)):
        raise ValueError(f"origin must be two finite numbers, got {origin!r}")
    return o


def row(n: int, spacing: float = 2.0, origin=(0.0, 0.0)) -> np.ndarray:
    """``n`` base points along +x: shape (n, 2)."""
    n = _count("n", n)
    return _origin(origin) + np.column_stack([np.arange(n) * _spacing(spacing), np.zeros(n)])


def square(nx: int, ny: int, spacing: float = 2.0, origin=(0.0, 0.0)) -> np.ndarray:
    """A square lattice of nx x ny base points, x fastest: shape (nx*ny, 2)."""
    nx, ny, h = _count("nx", nx), _count("ny", ny), _spacing(spacing)
    X, Y = np.meshgrid(np.arange(nx) * h, np.arange(ny) * h)
    return _origin(origin) + np.column_stack([X.ravel(), Y.ravel()])


def hexagonal(nx: int, ny: int, spacing: float = 2.0, origin=(0.0, 0.0)) -> np.ndarray:
    """A hexagonal (triangular) lattice: ny rows of nx points at nearest-neighbour distance
    ``spacing``, odd rows shifted by spacing/2, rows sqrt(3)/2 spacing apart: shape (nx*ny, 2)."""
    nx, ny, h = _count("nx", nx), _count("ny", ny), _spacing(spacing)
    j, i = np.divmod(np.arange(nx * ny), nx)
    x = (i + 0.5 * (j % 2)) * h
    y = j * h * math.sqrt(3.0) / 2.0
    return _origin(origin) + np.column_stack([x, y])


def points(xy) -> np.ndarray:
    """Any list of base points, validated: shape (n, 2) finite."""
    p = np.asarray(xy, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 1:
        raise ValueError(f"base points must have shape (n, 2) with n >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("base points contain NaN or inf")
    return p


def random_phases(n: int, seed: int = 0) -> np.ndarray:
    """Independent uniform phases in [0, 1), reproducible from ``seed``."""
    return np.random.default_rng(seed).random(_count("n", n))


def synchronous_phases(n: int) -> np.ndarray:
    """All cilia start at phase 0 (they drift apart if their periods differ)."""
    return np.zeros(_count("n", n))


def wave_phases(bases, wave_vector) -> np.ndarray:
    """A travelling wave at t = 0: phase = -(k . x) / (2 pi) mod 1 for wave vector k (rad per L),
    so that phase crests move along +k as the cilia advance (a metachronal wave)."""
    b = points(bases)
    k = np.asarray(wave_vector, dtype=float).reshape(-1)
    if k.shape != (2,) or not np.all(np.isfinite(k)):
        raise ValueError(f"wave_vector must be two finite numbers, got {wave_vector!r}")
    return np.mod(-(b @ k) / (2.0 * math.pi), 1.0)


def neighbours(bases) -> np.ndarray:
    """(E, 2) neighbour pairs i < j of the base points (N, 2): the edges of their Delaunay
    triangulation (a row, collinear points: consecutive points along it). What the designs'
    smoothness terms run over."""
    bases = np.asarray(bases, dtype=float)
    n = bases.shape[0]
    if n < 2:
        return np.zeros((0, 2), np.int64)
    try:
        from scipy.spatial import Delaunay

        tri = Delaunay(bases).simplices
        e = np.vstack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [0, 2]]])
    except Exception:  # collinear bases: order along the line
        o = np.argsort(bases @ (bases[-1] - bases[0]))
        e = np.column_stack([o[:-1], o[1:]])
    e = np.sort(e, axis=1)
    return np.unique(e, axis=0)
