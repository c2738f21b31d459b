"""Nonlinear dynamics of one filament: :func:`simulate`, the front door of the time integration.

It integrates the Galerkin system of :mod:`single_cilium.filament` (MODEL.md section 2)

    D(theta) theta_t = -K theta + B (kappa + chi_N) - g_U(theta),   kappa_t = -kappa - chi_E sin(theta)

(``g_U``: the drag of the background flow ``U = params.background`` on the filament held still,
zero in fluid at rest; the drag is ``d = -eta ((v - U).t t + 2 (v - U).n n)``, ``U`` in the field
frame in units ``L / tau``) with the Radau IIA(5) method of :mod:`single_cilium.radau` and returns a
labelled time series with an estimate of its error.
"""
from __future__ import annotations

import logging
import math
import time as _time
from dataclasses import dataclass

import numpy as np
import xarray as xr

from .version import __version__
from cilia_runtime.blas import single_threaded_blas
from .filament import Filament
from .mesh import Mesh
from .params import CiliumParams
from cilia_runtime.progress import Progress
from .radau import ConvergenceError, Radau, RadauStats

logger = logging.getLogger(__name__)

__all__ = ["simulate", "Simulation", "initial_state", "check_resolution", "ConvergenceError"]

_RTOL_RANGE = (1e-13, 1e-2)


def perturbation_shape(s: np.ndarray, seed: int | None) -> np.ndarray:
    """Seeded smooth shape ``g(s) (a_0 + a_1 (1-s)^3 + a_2 (1-s)^6)``, max norm 1, with
    ``g = s^4 (15 - 24 s + 10 s^2)``: it vanishes at the clamp with its first three derivatives
    and has zero slope and curvature at the tip, so the perturbed state keeps ``M(1) = 0`` and
    ``M_s(1) = 0`` (the tip conditions ``M(1) = V(1) = 0``)."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal(3)
    a[0] = abs(a[0]) + 0.5  # keep a tip deflection
    g = s**4 * (15.0 - 24.0 * s + 10.0 * s**2)
    shape = g * (a[0] + a[1] * (1.0 - s) ** 3 + a[2] * (1.0 - s) ** 6)
    return shape / np.max(np.abs(shape))


def initial_state(filament: Filament, amplitude: float = 1e-3, seed: int | None = 0) -> np.ndarray:
    """The discrete equilibrium with ``theta`` perturbed by ``amplitude *`` :func:`perturbation_shape`.

    The perturbation satisfies the tip conditions. Where the equilibrium is curved at the clamp
    (``theta_s(0) = chi_N != 0``) no simple perturbation satisfies the clamp's compatibility
    condition ``M_ss(0) = A(0) theta_s(0)`` as well: the motion then starts with a short initial
    layer (duration about 1e-3) that the solver resolves, and the clamp force at ``t = 0``
    (computed from the state alone) converges only slowly in space. From ``t > 0`` on, F(t)
    converges spectrally.
    """
    if not math.isfinite(amplitude):
        raise ValueError(f"amplitude must be finite, got {amplitude}")
    y = filament.equilibrium_state()
    theta, kappa = filament.split(y)
    theta = theta + amplitude * perturbation_shape(filament.mesh.nodes, seed)
    return filament.join(theta, kappa)


def check_resolution(params: CiliumParams, mesh: Mesh, state: np.ndarray | None = None,
                     limit: float = 1e-2) -> float:
    """Refuse a mesh that cannot represent the problem; return the resolution indicator.

    The indicator (:meth:`Mesh.tail`, about the relative interpolation error) is taken of the
    closed-form (still-fluid) equilibrium ``theta`` (the clamp boundary layer, of width about
    ``1/(|chi_E| cos theta_lim)``) and, when given, of the initial state (``cos theta``,
    ``sin theta`` and ``kappa``: an initial coil must be resolved too). Above ``limit`` a
    ValueError says which mesh would do.
    """
    from .equilibrium import equilibrium

    still = params.with_background((0.0, 0.0))

    def worst(m: Mesh, th0: np.ndarray | None, ka0: np.ndarray | None) -> float:
        fields = [equilibrium(still, m.nodes)]
        if th0 is not None:
            fields += [np.cos(th0), np.sin(th0), ka0]
        return max(m.tail(f) for f in fields)

    th0 = ka0 = None
    if state is not None:
        th0, ka0 = Filament(params, mesh).split(state)
    e = worst(mesh, th0, ka0)
    if e <= limit:
        return e
    turns = 0.0 if th0 is None else float(np.ptp(th0)) / (2 * math.pi)
    hint = "refine the mesh"
    for deg in range(6, 41, 2):
        cand = Mesh.for_params(params, degree=deg, turns=turns)
        if th0 is None:
            ok = worst(cand, None, None) <= 0.1 * limit
        else:
            th_c, ka_c = mesh.interpolate(th0, cand.nodes), mesh.interpolate(ka0, cand.nodes)
            ok = worst(cand, th_c, ka_c) <= 0.1 * limit
        if ok:
            arg = f", turns={turns:.3g}" if turns > 1 else ""
            hint = f"Mesh.for_params(params, degree={deg}{arg}) ({cand.describe()}) resolves it"
            break
    raise ValueError(
        f"mesh ({mesh.describe()}) is too coarse: resolution indicator {e:.2g} > {limit:g} "
        f"(the clamp boundary layer, width ~{_layer_width(params):.2g}, or the initial state is not "
        f"resolved); {hint}")


def _layer_width(p: CiliumParams) -> float:
    d = (abs(p.chi_E) - abs(p.chi_N)) * (abs(p.chi_E) + abs(p.chi_N))
    return 1.0 / math.sqrt(d) if d > 1.0 else 1.0


@dataclass(frozen=True)
class Simulation:
    """Result of :func:`simulate`.

    Attributes
    ----------
    params, mesh : the problem solved.
    data : xarray.Dataset
        dims ``time`` (output times) and ``s`` (mesh nodes). Variables: ``theta``, ``kappa``,
        ``theta_t`` (time, s); ``x``, ``y`` (shape); ``dx``, ``dy`` (drag density: force per
        length of the fluid ON the filament, ``d = -eta ((v - U).t t + 2 (v - U).n n)`` with the
        background flow ``U``); ``Fx``, ``Fy`` (time): the clamp force ``F = -int_0^1 d ds``, the
        force the filament exerts on the fluid (in a stream, including the stream's drag on the
        filament); ``energy`` (time):
        the discrete bending energy. Field frame: ``e2`` along the field, angles anticlockwise
        from ``e2``.
    stats : RadauStats
        Work counters of the main run.
    error_time, error_space : float
        Estimates of the error of F(t) for ``t > 0``, relative to ``max_t |F|``: the difference
        from a companion run with ``10 * rtol`` (time) and with the degree lowered by 4 on the
        same elements (space). Each is the error of the cheaper run, hence an upper estimate
        for this one when both converge (spectrally in space, at order 5 in time). NaN when
        ``error_estimate=False``.
    wall_time : float
        Seconds spent in the main run.
    status, message : str
        ``"success"``; ``"inaccurate"`` when the estimated error exceeds ``1e-3`` (the message
        says which resolution to raise); ``"unchecked"`` without error estimate.
    """

    params: CiliumParams
    mesh: Mesh
    data: xr.Dataset
    stats: RadauStats
    error_time: float = math.nan
    error_space: float = math.nan
    wall_time: float = math.nan
    status: str = "success"
    message: str = ""

    @property
    def error(self) -> float:
        """Combined error estimate of F(t), relative: ``error_time + error_space``."""
        return self.error_time + self.error_space

    @property
    def force(self) -> np.ndarray:
        """Clamp force F(t), shape ``(n_time, 2)``."""
        return np.stack([self.data["Fx"].values, self.data["Fy"].values], axis=-1)

    def save(self, path) -> None:
        """Write the dataset as NetCDF4/HDF5 (engine h5netcdf), atomically."""
        from cilia_runtime.files import write_netcdf

        write_netcdf(self.data, path)


def simulate(
    params: CiliumParams,
    t_end: float,
    *,
    state: tuple[np.ndarray, np.ndarray] | None = None,
    mesh: Mesh | None = None,
    rtol: float = 1e-8,
    n_out: int = 1001,
    amplitude: float = 1e-3,
    seed: int | None = 0,
    error_estimate: bool = True,
    progress: Progress | None = None,
    max_steps: int = 2_000_000,
) -> Simulation:
    """Integrate the nonlinear filament (MODEL.md section 2) from ``t = 0`` to ``t_end``.

    Parameters
    ----------
    params : CiliumParams
        With ``params.background = (U1, U2)``, the filament in that uniform flow (field frame,
        ``e2`` along the field, units ``L / tau``): the drag acts on the velocity relative to it.
    t_end : float
        Final time (units of the relaxation time tau), > 0.
    state : (theta, kappa), optional
        Initial nodal values on ``mesh.nodes`` (each of shape ``(mesh.n_nodes,)``; ``theta[0]``
        must be 0, the clamp). Default: the discrete equilibrium (in a background flow: the
        steady state, :meth:`Filament.equilibrium_state`) with ``theta`` perturbed by
        ``amplitude`` times a seeded smooth shape that keeps the tip conditions
        (:func:`initial_state`).
    mesh : Mesh, optional
        Default :meth:`Mesh.for_params` (degree 12); checked, with the initial state, by
        :func:`check_resolution`.
    rtol : float
        Relative tolerance of the local error (absolute: ``rtol`` for theta and
        ``rtol * max(1, |chi_E|, |chi_N|)`` for kappa).
    n_out : int
        Number of uniformly spaced output times in ``[0, t_end]``; the steps land on them.
    error_estimate : bool
        Run the two companion runs that estimate the error (about 1.5x the work).
    progress : Progress, optional
        E.g. :class:`~cilia_runtime.progress.TqdmProgress`.

    Returns
    -------
    Simulation

    Raises
    ------
    ValueError
        Naming the argument, for a bad ``t_end``, ``rtol``, ``n_out``, ``state`` or a mesh that
        does not resolve the clamp boundary layer.
    ConvergenceError
        When the integrator cannot continue; carries the time reached and what to change.
    """
    if not isinstance(params, CiliumParams):
        raise TypeError(f"params must be a CiliumParams, got {type(params).__name__}")
    try:
        t_end = float(t_end)
    except (TypeError, ValueError):
        raise ValueError(f"t_end must be a number, got {t_end!r}") from None
    if not (math.isfinite(t_end) and t_end > 0):
        raise ValueError(f"t_end must be finite and > 0, got {t_end}")
    if not (_RTOL_RANGE[0] <= rtol <= _RTOL_RANGE[1]):
        raise ValueError(f"rtol must lie in [{_RTOL_RANGE[0]:g}, {_RTOL_RANGE[1]:g}], got {rtol}")
    if int(n_out) != n_out or n_out < 2:
        raise ValueError(f"n_out must be an integer >= 2, got {n_out}")
    mesh = mesh if mesh is not None else Mesh.for_params(params)
    fil = Filament(params, mesh)
    if state is None:
        check_resolution(params, mesh)
        y0 = initial_state(fil, amplitude, seed)
    else:
        y0 = _state_vector(fil, state)
        check_resolution(params, mesh, y0)
    t_out = np.linspace(0.0, t_end, int(n_out))
    progress = progress if progress is not None else Progress()

    start = _time.perf_counter()
    Y, Yd, stats = _run(fil, y0, t_out, rtol, max_steps, progress, "simulate")
    wall = _time.perf_counter() - start
    data = _dataset(fil, t_out, Y, Yd, rtol, stats)

    err_t = err_s = math.nan
    if error_estimate:
        F = np.stack([data["Fx"].values, data["Fy"].values], -1)
        scale = max(np.max(np.abs(F[1:])), 1e-300)
        Y_t, Yd_t, _ = _run(fil, y0, t_out, min(10 * rtol, _RTOL_RANGE[1]), max_steps, Progress(), "")
        F_t = _force(fil, Y_t, Yd_t)
        err_t = float(np.max(np.abs(F_t[1:] - F[1:])) / scale)
        coarse = Mesh(mesh.breaks, max(2, mesh.degree - 4))
        fil_c = Filament(params, coarse)
        th, ka = fil.split(y0)
        y0_c = fil_c.join(mesh.interpolate(th, coarse.nodes), mesh.interpolate(ka, coarse.nodes))
        Y_c, Yd_c, _ = _run(fil_c, y0_c, t_out, rtol, max_steps, Progress(), "")
        F_c = _force(fil_c, Y_c, Yd_c)
        err_s = float(np.max(np.abs(F_c[1:] - F[1:])) / scale)
        data.attrs.update(error_time=err_t, error_space=err_s)
        logger.info("simulate %s: F(t) error estimates time %.2e, space %.2e", params, err_t, err_s)
        message = f"estimated relative error of F(t): time {err_t:.1e}, space {err_s:.1e}"
        status = "success"
        if err_t + err_s > 1e-3:
            status = "inaccurate"
            fix = "lower rtol" if err_t >= err_s else "raise the mesh degree"
            message += f"; above 1e-3: {fix}"
    else:
        status, message = "unchecked", "no error estimate (error_estimate=False)"
    return Simulation(params, mesh, data, stats, err_t, err_s, wall, status, message)


def _state_vector(fil: Filament, state) -> np.ndarray:
    try:
        theta, kappa = state
    except (TypeError, ValueError):
        raise ValueError("state must be a pair (theta, kappa) of nodal arrays") from None
    theta = np.asarray(theta, dtype=float)
    kappa = np.asarray(kappa, dtype=float)
    n = fil.n
    for name, a in (("theta", theta), ("kappa", kappa)):
        if a.shape != (n,):
            raise ValueError(f"state: {name} must have shape ({n},) (the mesh nodes), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"state: {name} contains NaN or inf")
    if theta[0] != 0.0:
        raise ValueError(f"state: theta[0] must be 0 (the clamp angle), got {theta[0]}")
    return fil.join(theta, kappa)


def _run(fil, y0, t_out, rtol, max_steps, progress, desc):
    solver = Radau(fil, rtol=rtol, atol=rtol * fil.scale, max_steps=max_steps)
    progress.start(float(t_out[-1]), desc)
    try:
        with single_threaded_blas():
            Y, Yd, stats = solver.integrate(y0, t_out, callback=lambda t, y: progress.update(t))
    finally:
        progress.close()
    return Y, Yd, stats


def _force(fil: Filament, Y: np.ndarray, Yd: np.ndarray) -> np.ndarray:
    theta, _ = fil.split(Y)
    theta_t, _ = fil.split(Yd)
    return fil.clamp_force(fil.drag(theta, theta_t))


def _dataset(fil: Filament, t: np.ndarray, Y, Yd, rtol, stats: RadauStats) -> xr.Dataset:
    p = fil.params
    theta, kappa = fil.split(Y)
    theta_t, _ = fil.split(Yd)
    d = fil.drag(theta, theta_t)
    F = fil.clamp_force(d)
    r = fil.shape(theta)
    E = fil.bending_energy(theta, kappa)

    def var(dims, values, long_name):
        return (dims, values, {"long_name": long_name, "units": "1"})

    ds = xr.Dataset(
        {
            "theta": var(("time", "s"), theta, "tangent angle from e2, anticlockwise"),
            "kappa": var(("time", "s"), kappa, "spontaneous curvature"),
            "theta_t": var(("time", "s"), theta_t, "time derivative of theta"),
            "x": var(("time", "s"), r[..., 0], "position along e1"),
            "y": var(("time", "s"), r[..., 1], "position along e2 (field direction)"),
            "dx": var(("time", "s"), d[..., 0], "drag density on the filament, e1 component"),
            "dy": var(("time", "s"), d[..., 1], "drag density on the filament, e2 component"),
            "Fx": var(("time",), F[:, 0], "clamp force -int d ds (filament on fluid), e1 component"),
            "Fy": var(("time",), F[:, 1], "clamp force -int d ds (filament on fluid), e2 component"),
            "energy": var(("time",), E, "discrete bending energy"),
        },
        coords={
            "time": ("time", t, {"long_name": "time / relaxation time", "units": "1"}),
            "s": ("s", fil.mesh.nodes, {"long_name": "arc length / filament length", "units": "1"}),
        },
        attrs={
            "chi_E": p.chi_E, "eta": p.eta, "chi_N": p.chi_N,
            "background_U1": p.background[0], "background_U2": p.background[1],
            "field_direction": "e2 (angles anticlockwise from e2)",
            "mesh_breaks": np.asarray(fil.mesh.breaks), "mesh_degree": fil.mesh.degree,
            "rtol": rtol, "method": "Galerkin spectral elements (GLL) + Radau IIA(5)",
            "package_version": __version__,
            **{f"stats_{k}": v for k, v in stats.as_dict().items()},
        },
    )
    return ds
