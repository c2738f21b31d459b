"""The carpet geometry a target refers to: :class:`Frame`.

A frame holds the carpet's ``centre`` (centre of the bounding box of the base points), the
straight-flow direction ``d0`` (``flow_direction``: minus the field direction, where a straight
filament pushes the fluid) and the ``spacing``. The cross-stream axis is ``cross = d0`` rotated
by +90 degrees (for the field along +y: d0 = -y, cross = +x). A deflection ``delta`` (radians,
anticlockwise positive) asks for the mean flow along ``d0`` rotated by ``delta``, i.e.
``cos(delta) d0 + sin(delta) cross``: a positive delta turns the flow toward +cross.

The array checks the target modules share (:func:`checked_xy`, :func:`checked_points`,
:func:`readonly`) are here too: each raises :class:`~ciliary_carpet.design.errors.TargetError`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.design.errors import TargetError

__all__ = ["Frame", "checked_xy", "checked_points", "readonly"]


def checked_xy(name: str, v, shape=None) -> np.ndarray:
    """``v`` as a float array (of ``shape`` when given); TargetError naming ``name`` for another
    shape or a NaN or inf."""
    a = np.asarray(v, dtype=float)
    if shape is not None and a.shape != shape:
        raise TargetError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TargetError(f"{name} contains NaN or inf")
    return a


def checked_points(name: str, v) -> np.ndarray:
    """``v`` as (P, 2) float points (one point (2,) as (1, 2)); TargetError naming ``name`` for
    another shape or a NaN or inf."""
    a = np.asarray(v, dtype=float)
    if a.ndim == 1 and a.shape == (2,):
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 2:
        raise TargetError(f"{name} must have shape (P, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TargetError(f"{name} contain NaN or inf")
    return a


def readonly(a: np.ndarray) -> np.ndarray:
    """A read-only float copy of ``a``."""
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a

@dataclass(frozen=True, eq=False)
class Frame:
    """The carpet geometry the patterns refer to.

    centre (2,): the carpet's centre; flow_direction (2,): the unit vector d0 (normalised here);
    spacing: the lattice spacing (the default pattern width)."""

    centre: np.ndarray
    flow_direction: np.ndarray
    spacing: float

    def __post_init__(self) -> None:
        c = checked_xy("Frame.centre", self.centre, (2,))
        d = checked_xy("Frame.flow_direction", self.flow_direction, (2,))
        n = float(np.hypot(*d))
        if n == 0:
            raise TargetError("Frame.flow_direction must be a non-zero vector")
        s = float(self.spacing)
        if not (math.isfinite(s) and s > 0):
            raise TargetError(f"Frame.spacing must be a positive number, got {self.spacing!r}")
        object.__setattr__(self, "centre", readonly(c))
        object.__setattr__(self, "flow_direction", readonly(d / n))
        object.__setattr__(self, "spacing", s)

    @property
    def cross(self) -> np.ndarray:
        """The cross-stream axis: d0 rotated by +90 degrees."""
        d = self.flow_direction
        return np.array([-d[1], d[0]])

    @classmethod
    def from_bases(cls, bases, spacing: float, direction_rad: float) -> "Frame":
        """The frame of a carpet with base points ``bases`` (N, 2) under a field at
        ``direction_rad`` (RADIANS anticlockwise from +y, as :class:`Carpet` takes it):
        centre = centre of the bases' bounding box, d0 = (sin a, -cos a)."""
        b = checked_points("bases", bases)
        a = float(direction_rad)
        return cls(0.5 * (b.min(axis=0) + b.max(axis=0)), np.array([math.sin(a), -math.cos(a)]), spacing)

    def cross_coordinate(self, points) -> np.ndarray:
        """(P,) coordinate of ``points`` along the cross-stream axis, from the centre."""
        return (checked_points("points", points) - self.centre) @ self.cross

    def directions(self, delta) -> np.ndarray:
        """(P, 2) unit flow directions for deflections ``delta`` (P,): cos d d0 + sin d cross."""
        d = np.atleast_1d(np.asarray(delta, dtype=float))
        return np.cos(d)[:, None] * self.flow_direction + np.sin(d)[:, None] * self.cross
