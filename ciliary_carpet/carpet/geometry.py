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

:class:`Geometry` is the rest of what differs between the two, as one object per geometry
(:data:`GEOMETRIES`, by name): the azimuths a carpet takes, where its wall may lie, the map of its
cilia's frames, the reach of a beat, the points its flow is asked at, the distance from its
filaments, its cilia's shapes and force centres in space, their heights above the wall and the
floor a tracer's stage is held above. A new geometry (cilia on a curved surface, say) is one subclass implementing these
methods and an entry in :data:`GEOMETRIES`; a :class:`~ciliary_carpet.carpet.carpet.Carpet` asks
its geometry and never tests its name.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["Embedding", "GEOMETRIES", "Geometry", "Planar", "Standing", "planar", "standing"]


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


def _pad(p: np.ndarray) -> np.ndarray:
    """``p`` (..., 2) with a zero third component: points or vectors of the plane z = 0 in space."""
    return np.concatenate([p, np.zeros(p.shape[:-1] + (1,))], axis=-1)


def wrap(psi) -> np.ndarray:
    """Azimuths wrapped into [0, 2 pi)."""
    return np.mod(np.asarray(psi, dtype=float), 2.0 * math.pi)


class Geometry(ABC):
    """Where a carpet's cilia beat: the methods a :class:`~ciliary_carpet.carpet.carpet.Carpet`
    asks of its geometry (module docstring). A subclass sets :attr:`name` and implements each
    method; arrays are per cilium (N,) or per point (M, 3), lengths in L, angles in radians."""

    name: ClassVar[str]

    @abstractmethod
    def azimuths(self, azimuth, direction: float, n: int) -> np.ndarray | None:
        """The carpet's ``azimuth`` checked and normalised for its ``n`` cilia under a field of
        ``direction`` (None where the geometry takes none); ValueError naming what is wrong."""

    @abstractmethod
    def check_wall(self, wall: float | None, filament_radius: float) -> None:
        """ValueError when ``wall`` (the distance of a no-slip plane below the clamps, or None)
        cannot be this geometry's wall for filaments of radius ``filament_radius``."""

    @abstractmethod
    def frames(self, bases: np.ndarray, azimuth: np.ndarray | None, rotation: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, Embedding | None]:
        """Where each cilium's cycle is placed in its 2D frame and how the frame lies in space:
        (bases in the frame (N, 2), rotation of the field frame into it (2, 2), the
        :class:`Embedding`, None for the plane z = 0)."""

    def check_cycles(self, cycles, chi_N: np.ndarray) -> None:
        """ValueError when a cilium's beat leaves the fluid (its cycle data ``cycles``, a
        :class:`~ciliary_carpet.carpet.cycles.CycleData`, and curvatures ``chi_N`` (N,))."""

    @abstractmethod
    def reach(self, centre: np.ndarray, bases: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """(N,) how far each cilium's beat reaches from its base (at most the length 1), from its
        force centre ``centre`` (N, 2) and swept radius ``radius`` (N,) in its frame."""

    @abstractmethod
    def targets(self, p: np.ndarray) -> np.ndarray:
        """(M, 3) the points ``p`` (M, 2) or (M, 3) (finite) the flow is asked at, in space."""

    @abstractmethod
    def filament_distance(self, carpet, points: np.ndarray, t: float) -> np.ndarray:
        """(M,) the distance of ``points`` from the nearest sampled filament point of ``carpet``
        at time ``t``."""

    @abstractmethod
    def shapes(self, carpet, t: float, js=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``carpet``'s filaments (of cilia ``js``, default all) at time ``t`` in space: positions
        (N, n_s, 3), forces per length on the fluid (N, n_s, 3) and phases (N,)."""

    @abstractmethod
    def centres(self, carpet, js) -> np.ndarray:
        """(len(js), 3) the force centres of ``carpet``'s cilia ``js`` in space."""

    @abstractmethod
    def mean_heights(self, carpet) -> np.ndarray | None:
        """(N,) each cilium's mean height (its force centre's) above ``carpet``'s wall, or None where
        every filament lies at the wall's distance (or there is no wall)."""

    @abstractmethod
    def floor(self, wall: float | None) -> float | None:
        """The height z below which a point is outside the fluid and a tracer's integration stage
        is held on the wall (no slip: the flow there is zero), for a wall ``wall`` below the clamps;
        None where points are left alone."""


class Planar(Geometry):
    """Every filament in the plane z = 0, the field in it along ``direction``; a wall parallel below
    at a distance of at least a filament diameter."""

    name = "planar"

    def azimuths(self, azimuth, direction: float, n: int) -> None:
        if azimuth is not None:
            raise ValueError("azimuth is for standing carpets (geometry = 'standing'); a planar carpet's field "
                             "direction turns it")
        return None

    def check_wall(self, wall: float | None, filament_radius: float) -> None:
        if wall is not None and not (math.isfinite(wall) and wall > 0):
            raise ValueError(f"wall must be a positive distance below the plane (or None), got {wall!r}")
        if wall is not None and wall < 2.0 * filament_radius:
            raise ValueError(f"wall must be at least a filament diameter, 2 blob = {2.0 * filament_radius:g} L, "
                             f"below the plane of a planar carpet (its filaments must not cut it), got {wall!r}")

    def frames(self, bases, azimuth, rotation):
        return bases, rotation, None

    def reach(self, centre, bases, radius):
        return np.minimum(np.linalg.norm(centre - bases, axis=1) + radius, 1.0)

    def targets(self, p):
        if p.shape[1] == 2:
            p = np.concatenate([p, np.zeros((p.shape[0], 1))], axis=1)
        return p

    def filament_distance(self, carpet, points, t):
        p = np.asarray(points, dtype=float)[:, :2]
        pos, _, _ = carpet.state(t)
        return cKDTree(pos.reshape(-1, 2)).query(p)[0]

    def shapes(self, carpet, t, js=None):
        pos, frc, ph = carpet.state(t, js)
        return _pad(pos), _pad(frc), ph

    def centres(self, carpet, js):
        return _pad(carpet.centres[js])

    def mean_heights(self, carpet):
        return None

    def floor(self, wall):
        return None


class Standing(Geometry):
    """Cilium j clamped at b_j on the substrate z = 0, the field along +z, its beat plane turned
    about the normal by its azimuth psi_j; the wall (the substrate itself at 0, or a plane below
    the clamps) at a distance >= 0, or none."""

    name = "standing"

    def azimuths(self, azimuth, direction: float, n: int) -> np.ndarray:
        psi = np.zeros(n) if azimuth is None else np.broadcast_to(
            np.asarray(azimuth, dtype=float), (n,)).copy() if np.ndim(azimuth) == 0 \
            else np.array(azimuth, dtype=float)
        if psi.shape != (n,) or not np.all(np.isfinite(psi)):
            raise ValueError(f"azimuth must be {n} finite angles (radians), got shape {psi.shape}")
        if direction != 0.0:
            raise ValueError("a standing carpet's field is along +z, normal to its substrate: turn its cilia "
                             f"with azimuth, not direction (got direction = {direction!r})")
        return np.mod(psi, 2.0 * math.pi)

    def check_wall(self, wall: float | None, filament_radius: float) -> None:
        if wall is not None and not (math.isfinite(wall) and wall >= 0):
            raise ValueError(f"wall must be a distance >= 0 below the clamps below the plane (or None), got {wall!r}")

    def frames(self, bases, azimuth, rotation):
        n = bases.shape[0]
        return np.zeros((n, 2)), np.eye(2), standing(bases, azimuth)  # each frame its beat plane, clamp at 0

    def check_cycles(self, cycles, chi_N):
        """A standing cilium stays above its substrate (its frame's second axis is the height)."""
        n = cycles.n
        low = np.concatenate([np.min(cycles.samples(np.arange(lo, min(lo + 256, n)))[0][..., 1], axis=(1, 2))
                              for lo in range(0, n, 256)])
        bad = np.nonzero(low < -1e-6)[0]
        if bad.size:
            j = int(bad[np.argmin(low[bad])])
            raise ValueError(f"standing cilium {j} (chi_N = {chi_N[j]:g}) dips {-low[j]:.3g} L below its "
                             "substrate during its beat: choose a smaller |chi_N| for it (a planar carpet has no "
                             "substrate)")

    def reach(self, centre, bases, radius):
        return np.minimum(np.abs(centre[:, 0] - bases[:, 0]) + radius, 1.0)  # horizontal: along e_psi

    def targets(self, p):
        if p.shape[1] == 2:
            raise ValueError("a standing carpet's flow is three-dimensional: give points (M, 3) (heights above "
                             "its substrate z = 0)")
        return p

    def filament_distance(self, carpet, points, t):
        p = carpet.targets(points)
        pos = carpet.state_in_space(t)[0]
        return cKDTree(pos.reshape(-1, 3)).query(p)[0]

    def shapes(self, carpet, t, js=None):
        return carpet.state_in_space(t, js)

    def centres(self, carpet, js):
        return carpet.in_space("centres", js)

    def mean_heights(self, carpet):
        if carpet.wall is None:
            return None
        return carpet.in_space("centres")[:, 2] + float(carpet.wall)

    def floor(self, wall):
        return None if wall is None else -float(wall)


GEOMETRIES: dict[str, Geometry] = {g.name: g for g in (Planar(), Standing())}
"""The carpet geometries by name (:class:`~ciliary_carpet.carpet.carpet.Carpet` ``geometry``,
scene key ``[carpet] geometry``)."""
