"""Dimensionless parameters of one filament, and their conversion from and to SI units.

Scalings (MODEL.md): length by the filament length ``L``, time by the relaxation time ``tau`` of
the spontaneous curvature, force by ``B / L**2`` with ``B`` the bending stiffness. Three groups
remain:

* ``chi_E = L * kappa_E``: the stimulus, ``kappa_E`` the target curvature the field induces per
  unit ``sin(theta)`` (its sign is the sign of the field along ``e2``);
* ``eta = mu_par * L**4 / (tau * B)``: drag against bending, ``mu_par`` the parallel resistive
  coefficient (the normal one is ``2 * mu_par``);
* ``chi_N = L * kappa_N``: the natural curvature fixed at fabrication.

An optional uniform background flow ``U = (U1, U2)`` of the fluid (field frame: ``e2`` along the
field; units ``L / tau``) makes the drag act on the velocity relative to the stream,
``d = -eta ((v - U).t t + 2 (v - U).n n)`` (MODEL.md section 2 with ``v -> v - U``); the default
``(0, 0)`` is the fluid at rest.
"""
from __future__ import annotations

from dataclasses import dataclass

from .checks import finite, positive

__all__ = ["CiliumParams", "PhysicalCilium"]


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
    background : (float, float), default (0, 0)
        Uniform background flow ``U = (U1, U2)`` of the fluid far from the filament, in the
        field frame (``U1`` along ``e1``, ``U2`` along ``e2``, the field direction), in units of
        ``L / tau``. The drag per unit length (force of the fluid ON the filament) becomes
        ``d = -eta ((v - U).t t + 2 (v - U).n n)`` with ``v`` the filament's velocity; a
        filament at rest in the stream feels ``d = eta (U.t t + 2 U.n n)`` and exerts
        ``F = -int_0^1 d ds`` on the fluid. Stored as a tuple of two floats.

    Raises
    ------
    ValueError
        Naming the field, if a value is not a finite real number, ``eta <= 0`` or
        ``background`` is not a pair.
    """

    chi_E: float
    eta: float
    chi_N: float = 0.0
    background: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "chi_E", finite("chi_E", self.chi_E))
        object.__setattr__(self, "eta", positive("eta", self.eta))
        object.__setattr__(self, "chi_N", finite("chi_N", self.chi_N))
        try:
            U1, U2 = self.background
        except (TypeError, ValueError):
            raise ValueError(f"background must be a pair (U1, U2) of real numbers, got {self.background!r}") from None
        object.__setattr__(self, "background", (finite("background U1", U1) + 0.0, finite("background U2", U2) + 0.0))

    def __repr__(self) -> str:
        # the background is shown only when there is one (still-fluid messages do not mention it)
        U = f", background={self.background!r}" if self.has_background else ""
        return f"CiliumParams(chi_E={self.chi_E!r}, eta={self.eta!r}, chi_N={self.chi_N!r}{U})"

    @property
    def has_background(self) -> bool:
        """True when the background flow ``U`` is not zero."""
        return self.background != (0.0, 0.0)

    def with_background(self, background: tuple[float, float]) -> "CiliumParams":
        """The same filament in the background flow ``background = (U1, U2)`` (field frame, ``L / tau``)."""
        return CiliumParams(self.chi_E, self.eta, self.chi_N, background)

    def mirrored(self) -> "CiliumParams":
        """The mirror image ``chi_N -> -chi_N`` (``theta -> -theta``, ``e1 -> -e1``; the background
        flow ``(U1, U2) -> (-U1, U2)``)."""
        U1, U2 = self.background
        return CiliumParams(self.chi_E, self.eta, -self.chi_N, (-U1 if U1 else 0.0, U2))

    @classmethod
    def from_physical(
        cls,
        length: float,
        relaxation_time: float,
        bending_stiffness: float,
        drag_coefficient: float,
        target_curvature: float,
        natural_curvature: float = 0.0,
        background_flow: tuple[float, float] = (0.0, 0.0),
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
        background_flow : (float, float)
            Uniform background flow [m/s] in the field frame (along ``e1``, along the field ``e2``);
            divided by ``L / tau``.
        """
        L = positive("length", length)
        tau = positive("relaxation_time", relaxation_time)
        B = positive("bending_stiffness", bending_stiffness)
        mu = positive("drag_coefficient", drag_coefficient)
        kE = finite("target_curvature", target_curvature)
        kN = finite("natural_curvature", natural_curvature)
        try:
            u1, u2 = background_flow
        except (TypeError, ValueError):
            raise ValueError(f"background_flow must be a pair of velocities, got {background_flow!r}") from None
        U = (finite("background_flow", u1) * tau / L, finite("background_flow", u2) * tau / L)
        return cls(chi_E=L * kE, eta=mu * L**4 / (tau * B), chi_N=L * kN, background=U)

    def to_physical(
        self, length: float, relaxation_time: float, bending_stiffness: float
    ) -> "PhysicalCilium":
        """SI values of these groups for a filament of given length, relaxation time and stiffness."""
        L = positive("length", length)
        tau = positive("relaxation_time", relaxation_time)
        B = positive("bending_stiffness", bending_stiffness)
        return PhysicalCilium(
            length=L,
            relaxation_time=tau,
            bending_stiffness=B,
            drag_coefficient=self.eta * tau * B / L**4,
            target_curvature=self.chi_E / L,
            natural_curvature=self.chi_N / L,
            background_flow=(self.background[0] * L / tau, self.background[1] * L / tau),
        )


@dataclass(frozen=True)
class PhysicalCilium:
    """A filament in SI units, with the scales that turn dimensionless results into SI ones.

    ``force_scale = B / L^2`` [N] (multiply a dimensionless force, e.g. the clamp force),
    ``time_scale = tau`` [s], ``velocity_scale = L / tau`` [m/s]. ``background_flow`` [m/s] is
    the uniform flow of the fluid in the field frame (default at rest).
    """

    length: float
    relaxation_time: float
    bending_stiffness: float
    drag_coefficient: float
    target_curvature: float
    natural_curvature: float = 0.0
    background_flow: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        try:
            u1, u2 = self.background_flow
        except (TypeError, ValueError):
            raise ValueError(f"background_flow must be a pair of velocities, got {self.background_flow!r}") from None
        object.__setattr__(self, "background_flow", (finite("background_flow", u1), finite("background_flow", u2)))
        for name in ("length", "relaxation_time", "bending_stiffness", "drag_coefficient"):
            object.__setattr__(self, name, positive(name, getattr(self, name)))
        for name in ("target_curvature", "natural_curvature"):
            object.__setattr__(self, name, finite(name, getattr(self, name)))

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
            self.background_flow,
        )
