"""Target flows: what a carpet's mean flow is designed to do (:class:`Target`).

A target is one kind of the registry :data:`~ciliary_carpet.design.patterns.PATTERNS` with its
geometry and the design's settings, resolved to numbers: angles in radians, the control-point
file's samples read. It refers to the carpet through a :class:`~ciliary_carpet.design.frame.Frame`
(centre, straight-flow direction d0, spacing): a deflection ``delta`` asks for the mean flow along
d0 rotated by ``delta``; the table's reachable |delta| is ``table.thrust_angle_range()`` (about
[0, 0.925] rad for chi_E = 200, eta = 1). A scene's ``[target]`` section
(:class:`~ciliary_carpet.scenes.target_spec.TargetSpec`) is resolved into a Target by
:func:`~ciliary_carpet.scenes.target_spec.resolve_target`; the fields' defaults here are the
section's. Where the design compares the flow with the target: :mod:`~ciliary_carpet.design.control`;
control-point files: :mod:`~ciliary_carpet.design.target_files`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.design.errors import TargetError, UnreachableTargetError
from ciliary_carpet.design.frame import Frame, checked_points, checked_xy, readonly
from ciliary_carpet.design.patterns import KINDS, SURFACE_KINDS, PATTERN_OF, Pattern
from ciliary_carpet.design.surface_target import surface_directions as _surface_directions
from ciliary_carpet.design.tolerance import DEFAULT_SAMPLES

__all__ = ["Target", "TargetError", "UnreachableTargetError", "DEFAULT_ANGLE_FRACTION", "DEFAULT_SPEED_FLOOR"]

DEFAULT_ANGLE_FRACTION = 0.9
"""Without ``target.angle`` the amplitude is this fraction of the table's reachable maximum."""
DEFAULT_SPEED_FLOOR = 0.3
"""The speed a design keeps along the target direction at each control point, as a fraction of
what the straight cilia near it make there (``[target] speed_floor``)."""


@dataclass(frozen=True, eq=False)
class Target:
    """A resolved target (for a scene: :func:`~ciliary_carpet.scenes.assembly.target_of`).

    Attributes
    ----------
    kind : str
        One of :data:`~ciliary_carpet.design.patterns.KINDS`.
    amplitude : float or None
        RADIANS: the deflection (uniform, signed) or the pattern amplitude (> 0); for the surface
        kinds the direction or axis (default 0); None for "none" and "points".
    line, width, centre, control, residual, strict, speed_floor, inside_swept, smoothness, sigma, samples, robust,
    sense, separation, height, sigma_psi :
        as the keys of :class:`~ciliary_carpet.scenes.target_spec.TargetSpec`, which takes its
        defaults from these: width None = ``frame.spacing``,
        centre None = ``frame.centre``, separation None = half the carpet's width along the axis
        (:meth:`surface_directions`); sigma_psi in DEGREES; ``control`` see
        :func:`~ciliary_carpet.design.control.control_points`; the design
        settings go to :func:`~ciliary_carpet.design.inverse.design_layout` (``robust``: its
        ``robust_sigma``) and :func:`~ciliary_carpet.design.tolerance.tolerance_study`.
    data_points, data_velocities : ndarray or None
        (P, 2) arrays for kind "points" (else None); see :meth:`velocities`.
    data_uncertainty : ndarray or None
        (P, 2) standard uncertainties of the target velocities' components (L/tau, >= 0), for kind
        "points" when the file gives them (columns du, dv); see :meth:`sample_weights`.
    source : str or None
        The control-point file for kind "points" (for messages).
    """

    kind: str
    amplitude: float | None = None
    line: float = 0.0
    width: float | None = None
    centre: tuple | None = None
    control: object = "cells"
    residual: float = 0.05
    strict: bool = False
    speed_floor: float = DEFAULT_SPEED_FLOOR
    inside_swept: str = "use"
    smoothness: float = 0.0
    sigma: float = 0.0
    samples: int = DEFAULT_SAMPLES
    robust: bool = False
    sense: str = "anticlockwise"
    separation: float | None = None
    height: float = 1.5
    sigma_psi: float = 0.0
    data_points: np.ndarray | None = None
    data_velocities: np.ndarray | None = None
    data_uncertainty: np.ndarray | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise TargetError(f"target kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.is_angle:
            if self.amplitude is None or not math.isfinite(self.amplitude):
                raise TargetError(f"target kind {self.kind!r} needs a finite amplitude (rad), got {self.amplitude!r}")
            if not self.pattern.signed and self.amplitude <= 0:
                raise TargetError(f"the amplitude of a {self.kind!r} target must be > 0, got {self.amplitude!r}")
            object.__setattr__(self, "amplitude", float(self.amplitude))
        if self.is_surface:
            a = 0.0 if self.amplitude is None else float(self.amplitude)
            if not math.isfinite(a):
                raise TargetError(f"target kind {self.kind!r} needs a finite direction (rad), got {self.amplitude!r}")
            object.__setattr__(self, "amplitude", a)
        if self.sense not in ("anticlockwise", "clockwise"):
            raise TargetError(f"target sense must be \"anticlockwise\" or \"clockwise\", got {self.sense!r}")
        if self.separation is not None and not (math.isfinite(self.separation) and self.separation > 0):
            raise TargetError(f"target separation must be a positive number, got {self.separation!r}")
        if not (math.isfinite(self.height) and self.height > 0):
            raise TargetError(f"target height must be a positive number, got {self.height!r}")
        if not (math.isfinite(self.sigma_psi) and self.sigma_psi >= 0):
            raise TargetError(f"target sigma_psi must be a number >= 0 (degrees), got {self.sigma_psi!r}")
        if self.inside_swept not in ("use", "downweight", "drop"):
            raise TargetError(f"target inside_swept must be \"use\", \"downweight\" or \"drop\", got "
                              f"{self.inside_swept!r}")
        if self.robust and not (self.sigma > 0 or self.sigma_psi > 0):
            raise TargetError(f"target robust = true designs for the fabrication tolerance sigma (or sigma_psi), which "
                              f"must then be > 0, got sigma = {self.sigma!r}")
        if self.width is not None and not (math.isfinite(self.width) and self.width > 0):
            raise TargetError(f"target width must be a positive number, got {self.width!r}")
        if not math.isfinite(self.line):
            raise TargetError(f"target line must be finite, got {self.line!r}")
        if self.centre is not None:
            object.__setattr__(self, "centre", tuple(map(float, checked_xy("target centre", self.centre, (2,)))))
        if self.kind == "points":
            if self.data_points is None or self.data_velocities is None:
                raise TargetError("a 'points' target needs data_points and data_velocities (P, 2)")
            p = checked_points("target data_points", self.data_points)
            v = checked_points("target data_velocities", self.data_velocities)
            if p.shape != v.shape or p.shape[0] == 0:
                raise TargetError(f"target data_points {p.shape} and data_velocities {v.shape} must match")
            object.__setattr__(self, "data_points", readonly(p))
            object.__setattr__(self, "data_velocities", readonly(v))
            if self.data_uncertainty is not None:
                e = checked_points("target data_uncertainty", self.data_uncertainty)
                if e.shape != p.shape or np.any(e < 0):
                    raise TargetError(f"target data_uncertainty must be (P, 2) = {p.shape} numbers >= 0, got shape "
                                      f"{e.shape}")
                object.__setattr__(self, "data_uncertainty", readonly(e))

    # -------------------------------------------------------------------- evaluation
    @property
    def pattern(self) -> Pattern:
        """This kind's entry of :data:`~ciliary_carpet.design.patterns.PATTERNS`."""
        return PATTERN_OF[self.kind]

    @property
    def is_angle(self) -> bool:
        """True for deflection targets (uniform and the patterns)."""
        return self.pattern.deflection is not None

    @property
    def is_surface(self) -> bool:
        """True for the surface-flow kinds of standing carpets."""
        return self.pattern.surface

    def surface_directions(self, points, frame: Frame, bases=None) -> tuple[np.ndarray, np.ndarray]:
        """(directions (P',) [rad, anticlockwise from +x], keep (P,) bool) of a surface kind at
        ``points`` (P, 2): the direction of its model field
        (:func:`~ciliary_carpet.design.surface_target.surface_directions`) at the points kept (those
        not within half a spacing of the pattern's singular points). ``centre`` None: the frame's;
        ``separation`` None: half the extent of ``bases`` (default the points) along the axis."""
        if not self.is_surface:
            raise TargetError(f"a {self.kind!r} target is not a surface flow (kinds {', '.join(SURFACE_KINDS)})")
        x = checked_points("points", points)
        c = frame.centre if self.centre is None else np.asarray(self.centre)
        d = self.separation
        if d is None:
            b = x if bases is None else checked_points("bases", bases)
            e = np.array([math.cos(self.amplitude), math.sin(self.amplitude)])
            d = 0.5 * float(np.ptp(b @ e)) or frame.spacing
        return _surface_directions(self.kind, x, c, frame.spacing, self.amplitude, d,
                                  1 if self.sense == "anticlockwise" else -1)

    def deflection(self, points, frame: Frame) -> np.ndarray:
        """(P,) target deflection delta [rad] at ``points`` (P, 2) for the angle kinds (the
        formulas: :data:`~ciliary_carpet.design.patterns.PATTERNS`)."""
        if not self.is_angle:
            raise TargetError(f"a {self.kind!r} target has no deflection angles"
                              + (" (use velocities())" if self.kind == "points" else ""))
        return self.pattern.deflection(self, checked_points("points", points), frame)

    def directions(self, points, frame: Frame) -> np.ndarray:
        """(P, 2) unit target flow directions at ``points`` (d0 rotated by the deflection)."""
        return frame.directions(self.deflection(points, frame))

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """For kind "points": control points (P, 2) and target velocities (P, 2), lab frame
        (copies)."""
        if self.kind != "points":
            raise TargetError(f"a {self.kind!r} target has no target velocities (only kind 'points')")
        return np.array(self.data_points), np.array(self.data_velocities)

    def sample_weights(self) -> np.ndarray | None:
        """For kind "points" with uncertainties: (P,) weights of the samples in the design's
        objective and rms residual, ``1 / (s_k^2 + s_0^2)`` scaled to mean 1, with ``s_k^2 = du_k^2 +
        dv_k^2`` and ``s_0`` a tenth of the rms ``s`` (a sample given as exact does not outweigh
        the others without bound); None without uncertainties (all weights 1)."""
        if self.kind != "points" or self.data_uncertainty is None:
            return None
        s2 = np.sum(np.asarray(self.data_uncertainty) ** 2, axis=1)
        s0 = 0.01 * float(np.mean(s2))
        if s0 == 0.0:  # every sample given as exact
            return None
        w = 1.0 / (s2 + s0)
        return w / w.mean()

    def noise(self) -> float:
        """For kind "points" with uncertainties: the samples' relative rms noise ``n`` =
        sqrt(sum w_k s_k^2 / sum w_k |U_k|^2) (weights :meth:`sample_weights`), the rms residual a
        design that makes the true flow exactly has against the samples, in the units of the
        velocity residual (relative to the rms target speed); 0 without uncertainties."""
        w = self.sample_weights()
        if w is None:
            return 0.0
        s2 = np.sum(np.asarray(self.data_uncertainty) ** 2, axis=1)
        u2 = np.sum(np.asarray(self.data_velocities) ** 2, axis=1)
        return float(math.sqrt(np.sum(w * s2) / max(float(np.sum(w * u2)), 1e-300)))

    def threshold(self) -> float:
        """The rms residual at which the target counts as met: ``residual``, combined with the
        samples' own noise for sampled velocities with uncertainties, sqrt(residual^2 + noise^2)."""
        return float(math.hypot(self.residual, self.noise()))
