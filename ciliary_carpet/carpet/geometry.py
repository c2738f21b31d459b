"""Where each cilium's beat plane lies in space: planar and standing carpets.

Every cilium beats on a planar limit cycle (the table's, field along e2). A carpet's geometry
says where that plane lies (DESIGN.md "Geometry"; MODEL.md section 6):

* ``"planar"``: every filament lies in the plane z = 0, beats in it and the field lies in it
  (direction ``direction`` in the plane); an optional no-slip wall lies parallel below.
* ``"standing"``: cilium j is clamped at its base b_j on the substrate z = 0 with the field along
  +z; its beat plane contains the normal and is turned about it by the azimuth psi_j fixed at
  fabrication, e_psi = (cos psi_j, sin psi_j, 0): a point (x, y) of its cycle in the field frame
  lies at b_j + x e_psi + y e_z and a force (f_x, f_y) acts along f_x e_psi + f_y e_z. Its mean
  force leans from the normal towards e_psi by the thrust angle (positive chi_N), so (chi_N, psi)
  give a tangential thrust of any direction; (chi_N, psi) and (-chi_N, psi + pi) are the same
  cilium (the table's mirror symmetry).

:class:`Embedding` holds the map per cilium: 3D position = ``origin[j] + axes[j] @ p`` for a
point p of the cilium's 2D frame, 3D force = ``axes[j] @ f``. The 2D frame is the carpet's plane
for a planar carpet (its cycles are rotated by the field direction and placed at their bases in
it; axes the identity, origin 0) and the beat plane itself for a standing one (clamp at the
origin; origin = (b_j, 0), axes = [e_psi, e_z]). The levels of detail (:mod:`.carriers`) work in
each cilium's 2D frame and place their carriers through the same map.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Embedding", "GEOMETRIES", "planar", "standing"]

GEOMETRIES = ("planar", "standing")
"""The carpet geometries (:class:`~ciliary_carpet.carpet.carpet.Carpet` ``geometry``, scene key
``[carpet] geometry``)."""


@dataclass(frozen=True, eq=False)
class Embedding:
    """The map from each cilium's 2D frame to space (module docstring).

    origin (N, 3), axes (N, 3, 2) with orthonormal columns; ``in_plane``: every axis lies in the
    plane z = 0 (a planar carpet: forces and source displacements parallel to a wall, whose
    Taylor constants are the smaller ones, :attr:`Kernel.c1 <ciliary_carpet.stokes.kernel.Kernel.c1>`)."""

    origin: np.ndarray
    axes: np.ndarray

    def __post_init__(self) -> None:
        o = np.ascontiguousarray(self.origin, dtype=float)
        a = np.ascontiguousarray(self.axes, dtype=float)
        if o.ndim != 2 or o.shape[1] != 3 or a.shape != (o.shape[0], 3, 2):
            raise ValueError(f"an Embedding needs origin (N, 3) and axes (N, 3, 2), got {o.shape} and {a.shape}")
        gram = np.einsum("nqa,nqb->nab", a, a)
        if not np.allclose(gram, np.eye(2), atol=1e-12):
            raise ValueError("an Embedding's axes must be orthonormal")
        object.__setattr__(self, "origin", o)
        object.__setattr__(self, "axes", a)

    @property
    def n(self) -> int:
        return self.origin.shape[0]

    @property
    def in_plane(self) -> bool:
        """Whether every cilium's frame is the plane z = 0 (no axis has a z component)."""
        return bool(np.all(self.axes[:, 2, :] == 0.0))

    def points(self, p: np.ndarray, js=None) -> np.ndarray:
        """(..., 3) the points ``p`` (K, ..., 2) of cilia ``js`` (K,) (default all) in space."""
        o, a = self._of(js)
        p = np.asarray(p, dtype=float)
        extra = (None,) * (p.ndim - 2)
        return o[(slice(None),) + extra] + np.einsum("kqa,k...a->k...q", a, p)

    def vectors(self, v: np.ndarray, js=None) -> np.ndarray:
        """(..., 3) the vectors (forces, velocities) ``v`` (K, ..., 2) of cilia ``js`` in space."""
        _, a = self._of(js)
        return np.einsum("kqa,k...a->k...q", a, np.asarray(v, dtype=float))

    def _of(self, js):
        if js is None:
            return self.origin, self.axes
        js = np.asarray(js, dtype=np.int64).reshape(-1)
        return self.origin[js], self.axes[js]


def planar(n: int) -> Embedding:
    """The embedding of a planar carpet of ``n`` cilia: its 2D frame is the plane z = 0."""
    axes = np.zeros((n, 3, 2))
    axes[:, 0, 0] = axes[:, 1, 1] = 1.0
    return Embedding(np.zeros((n, 3)), axes)


def standing(bases: np.ndarray, psi: np.ndarray) -> Embedding:
    """The embedding of standing cilia clamped at ``bases`` (N, 2) on z = 0 with beat-plane
    azimuths ``psi`` (N,) (radians, anticlockwise from +x): origin (b_j, 0), axes e_psi, e_z."""
    b = np.asarray(bases, dtype=float)
    psi = np.asarray(psi, dtype=float)
    n = b.shape[0]
    axes = np.zeros((n, 3, 2))
    axes[:, 0, 0] = np.cos(psi)
    axes[:, 1, 0] = np.sin(psi)
    axes[:, 2, 1] = 1.0
    return Embedding(np.concatenate([b, np.zeros((n, 1))], axis=1), axes)


def wrap(psi) -> np.ndarray:
    """Azimuths wrapped into [0, 2 pi)."""
    return np.mod(np.asarray(psi, dtype=float), 2.0 * math.pi)
