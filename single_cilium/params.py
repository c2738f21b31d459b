"""Dimensionless parameters of one filament, and their conversion from and to SI units.

Scalings (MODEL.md): length by the filament length ``L``, time by the relaxation time ``tau`` of
the spontaneous curvature, force by ``B / L**2`` with ``B`` the bending stiffness. Three groups
remain:

* ``chi_E = L * kappa_E``: the stimulus, ``kappa_E`` the target curvature the field induces per
  unit ``sin(theta)`` (its sign is the sign of the field along ``e2``);
* ``eta = mu_par * L**4 / (tau * B)``: drag against bending, ``mu_par`` the parallel resistive
  coefficient (the normal one is ``2 * mu_par``);
* ``chi_N = L * kappa_N``: the natural curvature fixed at fabrication.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["CiliumParams", "PhysicalCilium"]


def _finite(name: str, value: float) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x}")
    return x


def _positive(name: str, value: float) -> float:
    x = _finite(name, value)
    if x <= 0.0:
        raise ValueError(f"{name} must be > 0, got {x}")
    return x


@dataclass(frozen=True)
class CiliumParams:
    """The three dimensionless groups of one filament.

    Parameters
    ----------
    chi_E : float
        Stimulus ``L kappa_E`` (any sign; the field is ``E e2``).
    eta : float
        Drag-to-bending ratio ``mu_par L^4 / (tau B)``; must be > 0.
    chi_N : float, default 0
        Natural curvature ``L kappa_N`` (any sign; ``-chi_N`` is the mirror image).

    Raises
    ------
    ValueError
        Naming the field, if a value is not a finite real number or ``eta <= 0``.
    """

    chi_E: float
    eta: float
    chi_N: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "chi_E", _finite("chi_E", self.chi_E))
        object.__setattr__(self, "eta", _positive("eta", self.eta))
        object.__setattr__(self, "chi_N", _finite("chi_N", self.chi_N))

    def mirrored(self) -> "CiliumParams":
        """The mirror image ``chi_N -> -chi_N`` (``theta -> -theta``, ``e1 -> -e1``)."""
        return CiliumParams(self.chi_E, self.eta, -self.chi_N)

    @classmethod
    def from_physical(
        cls,
        length: float,
        relaxation_time: float,
        bending_stiffness: float,
        drag_coefficient: float,
        target_curvature: float,
        natural_curvature: float = 0.0,
    ) -> "CiliumParams":
        """Dimensionless groups from SI values.

        Parameters
        ----------
        length : float
            Filament length ``L`` [m], > 0.
        relaxation_time : float
            Relaxation time ``tau`` of the spontaneous curvature [s], > 0.
        bending_stiffness : float
            Bending stiffness ``B`` [N m^2], > 0.
        drag_coefficient : float
            Parallel resistive coefficient ``mu_par`` [N s m^-2], > 0.
        target_curvature : float
            Field-induced target curvature ``kappa_E`` [1/m] (signed).
        natural_curvature : float
            Natural curvature ``kappa_N`` [1/m] (signed).
        """
        L = _positive("length", length)
        tau = _positive("relaxation_time", relaxation_time)
        B = _positive("bending_stiffness", bending_stiffness)
        mu = _positive("drag_coefficient", drag_coefficient)
        kE = _finite("target_curvature", target_curvature)
        kN = _finite("natural_curvature", natural_curvature)
        return cls(chi_E=L * kE, eta=mu * L**4 / (tau * B), chi_N=L * kN)

    def to_physical(
        self, length: float, relaxation_time: float, bending_stiffness: float
    ) -> "PhysicalCilium":
        """SI values of these groups for a filament of given length, relaxation time and stiffness."""
        L = _positive("length", length)
        tau = _positive("relaxation_time", relaxation_time)
        B = _positive("bending_stiffness", bending_stiffness)
        return PhysicalCilium(
            length=L,
            relaxation_time=tau,
            bending_stiffness=B,
            drag_coefficient=self.eta * tau * B / L**4,
            target_curvature=self.chi_E / L,
            natural_curvature=self.chi_N / L,
        )


@dataclass(frozen=True)
class PhysicalCilium:
    """A filament in SI units, with the scales that turn dimensionless results into SI ones.

    ``force_scale = B / L^2`` [N] (multiply a dimensionless force, e.g. the clamp force),
    ``time_scale = tau`` [s], ``velocity_scale = L / tau`` [m/s].
    """

    length: float
    relaxation_time: float
    bending_stiffness: float
    drag_coefficient: float
    target_curvature: float
    natural_curvature: float = 0.0

    def __post_init__(self) -> None:
        for name in ("length", "relaxation_time", "bending_stiffness", "drag_coefficient"):
            object.__setattr__(self, name, _positive(name, getattr(self, name)))
        for name in ("target_curvature", "natural_curvature"):
            object.__setattr__(self, name, _finite(name, getattr(self, name)))

    @property
    def force_scale(self) -> float:
        return self.bending_stiffness / self.length**2

    @property
    def time_scale(self) -> float:
        return self.relaxation_time

    @property
    def velocity_scale(self) -> float:
        return self.length / self.relaxation_time

    def to_params(self) -> CiliumParams:
        """Back to the dimensionless groups."""
        return CiliumParams.from_physical(
            self.length,
            self.relaxation_time,
            self.bending_stiffness,
            self.drag_coefficient,
            self.target_curvature,
            self.natural_curvature,
        )
