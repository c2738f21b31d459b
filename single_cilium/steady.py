"""The equilibrium of the filament in a background flow: the steady state of the discrete system.

In fluid at rest the equilibrium has a closed form (:mod:`single_cilium.equilibrium`). In a
uniform stream ``U = params.background`` (field frame, units ``L / tau``) the drag of the stream on
the filament held still, ``d = eta (U.t t + 2 U.n n)`` (MODEL.md section 2 with ``v = 0``), bends it
further and there is none: :func:`steady_state` solves the Galerkin system of
:mod:`single_cilium.filament` for its steady state instead, by Newton's method continued in ``|U|``.
"""
from __future__ import annotations

import numpy as np

from .filament import Filament
from .mesh import Mesh
from .params import CiliumParams

__all__ = ["SteadyState", "steady_state"]


class SteadyState:
    """The equilibrium of the discrete filament (what :func:`steady_state` returns).

    Attributes
    ----------
    params, mesh : the problem solved.
    s : (n,) mesh nodes.
    theta, kappa : (n,) nodal values (``kappa = -chi_E sin theta``).
    x, y : (n,) the shape ``r(s) = int_0^s t`` (field frame).
    drag : (n, 2) force per length of the fluid ON the filament held still in the stream,
        ``d = eta (U.t t + 2 U.n n)``.
    force : (2,) ``F = -int_0^1 d ds``, the force the filament exerts on the fluid (MODEL.md
        section 5; zero in fluid at rest).
    error : float
        ``max |theta - theta_coarse|`` against the same elements with the degree lowered by 2
        (the coarser solution's error: an upper estimate for this one).
    """

    def __init__(self, params, mesh, s, theta, kappa, x, y, drag, force, error):
        self.params, self.mesh, self.s, self.theta, self.kappa = params, mesh, s, theta, kappa
        self.x, self.y, self.drag, self.force, self.error = x, y, drag, force, error

    def __repr__(self) -> str:
        return (f"SteadyState({self.params}, tip angle {self.theta[-1]:.6g}, force ({self.force[0]:.6g}, "
                f"{self.force[1]:.6g}), error {self.error:.1e})")


def steady_state(params: CiliumParams, *, mesh=None, degree: int = 12) -> SteadyState:
    """The equilibrium of the filament in its background flow, as the steady state of the discrete
    (Galerkin) system: ``theta_t = 0``, ``kappa = -chi_E sin theta`` and
    ``K theta + B (chi_E sin theta - chi_N) + g_U(theta) = 0``, with ``g_U`` the load of the drag
    ``d = eta (U.t t + 2 U.n n)`` of the stream ``U = params.background`` (field frame, units
    ``L / tau``) on the filament held still (:mod:`single_cilium.filament`). Solved by Newton's
    method from the still-fluid closed form (:func:`~single_cilium.equilibrium.equilibrium`), continued in ``|U|``
    (:meth:`~single_cilium.filament.Filament.equilibrium_state`). For ``U = 0`` it is the discrete
    form of :func:`~single_cilium.equilibrium.equilibrium`. It is the branch continued from the still fluid, which need not
    be stable: a stream against the filament (``U . t < 0``) compresses it and beyond a critical
    ``eta |U|`` buckles it (e.g. ``chi_E = chi_N = 0``, ``U = (0, -30)``: the straight state is
    returned, and :func:`~single_cilium.stability` reports divergence); check with
    :func:`~single_cilium.stability`.

    Parameters
    ----------
    params : CiliumParams
    mesh : Mesh, optional
        Default ``Mesh.for_params(params, degree)``.

    Returns
    -------
    SteadyState
        Including the force ``F = -int d ds`` the held filament exerts on the fluid and an error
        estimate of ``theta`` (degree lowered by 2).

    Raises
    ------
    RuntimeError
        When the continuation in the flow meets a fold (e.g. buckling under a strong stream
        against the filament) or the mesh does not resolve the state.
    """
    if not isinstance(params, CiliumParams):
        raise TypeError(f"params must be a CiliumParams, got {type(params).__name__}")
    mesh = mesh if mesh is not None else Mesh.for_params(params, degree)
    fil = Filament(params, mesh)
    theta, kappa = fil.split(fil.equilibrium_state())
    coarse = Mesh(mesh.breaks, max(2, mesh.degree - 2))
    fc = Filament(params, coarse)
    th_c = fc.split(fc.equilibrium_state())[0]
    error = float(np.max(np.abs(coarse.interpolate(th_c, mesh.nodes) - theta)))
    d = fil.drag(theta, np.zeros_like(theta))
    r = fil.shape(theta)
    return SteadyState(params, mesh, mesh.nodes.copy(), theta, kappa, r[:, 0], r[:, 1], d,
                       fil.clamp_force(d), error)
