"""Command line: ``single-cilium <command> ...`` (``single-cilium --help`` lists the commands).

Exit status: 0 on success; 2 bad input (the message names the option and value; also an output
file that cannot be written, or not enough memory); 3 a solver that could not continue (the message
says where and what to change); 1 an internal error (a one-line message; ``--debug`` shows the
traceback); 130 interrupted (Ctrl-C); 143 terminated (SIGTERM) and 129 hung up (SIGHUP), handled like
Ctrl-C (a table build's pool workers are stopped, its finished rows kept). ``--json`` output is strict JSON: NaN and infinities are
written as null and listed, with the reason, under ``"non_finite"``.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import numpy as np

from .version import __version__
from cilia_runtime.files import strict_json
from cilia_runtime.signals import Terminated, exit_status, interrupt_of, terminate_as_interrupt
from .equilibrium import NoLimitAngleError, equilibrium, equilibrium_shape, limit_angle
from .dynamics import simulate
from .mesh import Mesh
from .params import CiliumParams
from cilia_runtime.progress import TqdmProgress
from .radau import ConvergenceError
from .stability import flutter_boundary, flutter_cutoff, stability, stability_map
from .cycle import N_PHASE_START, check_cycle_cost, check_degree, check_mesh_size, limit_cycle
from .orbit import METHODS

logger = logging.getLogger(__name__)


def _grid(text: str) -> np.ndarray:
    """``a,b,c`` (a list) or ``start:stop:num`` (inclusive, like numpy.linspace)."""
    try:
        if ":" in text:
            a, b, n = text.split(":")
            return np.linspace(float(a), float(b), int(n))
        return np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 'a,b,c' or 'start:stop:num', got {text!r}") from None


def _params(args) -> CiliumParams:
    return CiliumParams(chi_E=args.chi_E, eta=args.eta, chi_N=args.chi_N)


def _add_params(p: argparse.ArgumentParser, eta_default: float | None = None) -> None:
    p.add_argument("--chi-E", dest="chi_E", type=float, required=True, help="stimulus L kappa_E")
    if eta_default is None:
        p.add_argument("--eta", type=float, required=True, help="drag/bending mu_par L^4/(tau B) > 0")
    else:
        p.add_argument("--eta", type=float, default=eta_default,
                       help=f"drag/bending (does not change the equilibrium; default {eta_default})")
    p.add_argument("--chi-N", dest="chi_N", type=float, default=0.0, help="natural curvature L kappa_N")


def cmd_equilibrium(args) -> dict:
    p = _params(args)
    s = args.s
    theta = equilibrium(p, s, phi=args.phi)
    x, y = equilibrium_shape(p, s, phi=args.phi)
    out = {"chi_E": p.chi_E, "chi_N": p.chi_N, "phi": args.phi, "s": s.tolist(),
           "theta": theta.tolist(), "x": x.tolist(), "y": y.tolist()}
    try:
        out["theta_lim"] = limit_angle(p)
    except NoLimitAngleError as exc:
        out["theta_lim"] = None
        out["theta_lim_note"] = str(exc)
    return out


def cmd_simulate(args) -> dict:
    p = _params(args)
    mesh = Mesh.for_params(p, degree=args.degree)
    progress = None if args.quiet else TqdmProgress()
    sim = simulate(p, args.t_end, mesh=mesh, rtol=args.rtol, n_out=args.n_out,
                   amplitude=args.amplitude, seed=args.seed,
                   error_estimate=not args.no_error_estimate, progress=progress)
    if args.output:
        sim.save(args.output)
    F = sim.force
    return {"chi_E": p.chi_E, "eta": p.eta, "chi_N": p.chi_N, "t_end": args.t_end,
            "output": args.output, "mesh": sim.mesh.describe(), "rtol": args.rtol,
            "F_end": F[-1].tolist(), "F_max": float(np.max(np.hypot(F[:, 0], F[:, 1]))),
            "error_time": sim.error_time, "error_space": sim.error_space,
            "wall_time": sim.wall_time, "status": sim.status, "message": sim.message,
            "stats": sim.stats.as_dict()}


def cmd_stability(args) -> dict:
    res = stability(_params(args), degree=args.degree, n_modes=args.n_modes)
    return res.as_dict()


def cmd_cutoff(args) -> dict:
    return flutter_cutoff(args.chi_E, args.eta, degree=args.degree).as_dict()


def cmd_map(args) -> dict:
    from cilia_runtime.files import write_netcdf

    ds = stability_map(args.chi_N, chi_E=args.chi_E, eta=args.eta, degree=args.degree,
                       progress=None if args.quiet else TqdmProgress(delay=0.5))
    if args.output:
        write_netcdf(ds, args.output)
    out = {"chi_N": args.chi_N, "output": args.output, "png": args.png,
           "points": int(ds.regime.size), "flutter_points": int((ds.regime == 1).sum())}
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from .figures import plot_stability_map

        boundary = None
        if args.boundary:
            boundary = flutter_boundary(args.chi_N, chi_E=(ds.chi_E.values[0], ds.chi_E.values[-1]),
                                        eta=(ds.eta.values[0], ds.eta.values[-1]), degree=args.degree)
            out["boundary_branches"] = len(boundary.branches)
        fig, ax = plt.subplots(figsize=(5, 4))
        m = plot_stability_map(ds, ax, boundary)
        fig.colorbar(m, ax=ax, label=r"flutter frequency $\beta / 2\pi$")
        fig.tight_layout()
        Path(args.png).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.png, dpi=120)
        plt.close(fig)
    return out


def cmd_thrust_curve(args) -> dict:
    """The design curve of one field from a thrust table (the shipped one by default), with its
    error estimates, as a PNG (:func:`single_cilium.figures.plot_thrust_curve`)."""
    from .table import ThrustTable

    table = ThrustTable.default() if args.table is None else ThrustTable.load(args.table)
    if "chi_N_cutoff" not in table.ds.attrs or "phase" not in table.ds.dims or table.ds.chi_N.ndim != 1 \
            or any(d in table.ds.dims for d in ("chi_E", "U_par", "U_perp")):
        raise ValueError(f"--table {args.table}: a table of one field in still fluid is needed (this one is over "
                         "chi_E or the background flow)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .figures import plot_thrust_curve

    fig = plot_thrust_curve(table, n=args.points)
    Path(args.png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.png, dpi=args.dpi)
    plt.close(fig)
    return {"png": args.png, "table": args.table or "default", "chi_E": float(table.ds.attrs["chi_E"]),
            "eta": float(table.ds.attrs["eta"]), "chi_N_cutoff": float(table.ds.attrs["chi_N_cutoff"]),
            "thrust_norm_error_max": float(np.nanmax(table.ds.thrust_norm_error.values)),
            "thrust_angle_error_max": float(np.nanmax(table.ds.thrust_angle_error.values))}


def cmd_cycle(args) -> dict:
    c = limit_cycle(_params(args), degree=args.degree, n_phase=args.n_phase, rtol=args.rtol,
                    method=args.method, error_estimate=not args.no_error_estimate)
    if args.output and c.data is not None:
        from cilia_runtime.files import write_netcdf

        write_netcdf(c.data, args.output)
    out = c.as_dict()
    out["floquet_multipliers"] = [[float(z.real), float(z.imag)] for z in c.floquet_multipliers]
    return out


def _flow_grid(text: str) -> np.ndarray:
    """A background-flow grid: as :func:`_grid`, or ``default`` (``single_cilium.table.DEFAULT_U``)."""
    if text.strip().lower() == "default":
        from .table import DEFAULT_U

        return DEFAULT_U.copy()
    return _grid(text)


def cmd_table(args) -> dict:
    from .table import build_table
    from .tablefile import REGIMES

    # one value: the table of one field; a grid: a table over chi_E (interpolated in chi_E too);
    # a flow grid (--U-par, --U-perp): a table over the background flow
    chi_E = float(args.chi_E[0]) if args.chi_E.size == 1 else args.chi_E
    flow = args.U_par is not None or args.U_perp is not None
    t = build_table(chi_E, args.eta, args.chi_N, U_par=args.U_par, U_perp=args.U_perp, degree=args.degree,
                    n_phase=args.n_phase, scheduler=args.scheduler, scheduler_timeout=args.scheduler_timeout,
                    path=args.output, progress=None if args.quiet else TqdmProgress(delay=0.5),
                    error_estimate=not args.no_error_estimate, tol=args.tol, overwrite=args.overwrite)
    ds = t.ds
    regime = ds.regime.values
    computed = regime != REGIMES.index("not_computed")
    out = {"chi_E": t.chi_E if args.chi_E.size == 1 else ds.chi_E.values.tolist(), "eta": t.eta,
           "output": args.output, "rows": int(computed.sum()), "flutter_rows": int(ds.flutter.sum()),
           "coiled_rows": int(ds.coiled.values[computed].sum())}
    if flow:
        out.update(U_par=ds.U_par.values.tolist(), U_perp=ds.U_perp.values.tolist(),
                   divergence_rows=int((regime == REGIMES.index("divergence")).sum()),
                   no_steady_state_rows=int((regime == REGIMES.index("no_steady_state")).sum()))
    if args.chi_E.size == 1 and not flow:
        out["chi_N_cutoff"] = ds.attrs["chi_N_cutoff"]
    else:
        out["chi_N_cutoff"] = ds.chi_N_cutoff.values.tolist()
    return out


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="single-cilium", description=__doc__.splitlines()[0].replace("``", ""))
    ap.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    ap.add_argument("-v", "--verbose", action="store_true", help="log progress information")
    ap.add_argument("--debug", action="store_true", help="show the traceback of a failure")
    sub = ap.add_subparsers(dest="command", required=True)

    pe = sub.add_parser("equilibrium", help="closed-form equilibrium theta(s), shape and theta_lim")
    _add_params(pe, eta_default=1.0)
    pe.add_argument("--s", type=_grid, default=np.linspace(0, 1, 11),
                    help="arc-length points: 'a,b,c' or 'start:stop:num' (default 0:1:11)")
    pe.add_argument("--phi", type=float, default=0.0, help="clamp angle (default 0)")
    pe.add_argument("--json", action="store_true", help="print JSON (default: a table)")
    pe.set_defaults(func=cmd_equilibrium)

    ps = sub.add_parser("simulate", help="nonlinear dynamics from a perturbed equilibrium")
    _add_params(ps)
    ps.add_argument("--t-end", dest="t_end", type=float, required=True, help="final time (units of tau)")
    ps.add_argument("-o", "--output", help="NetCDF file for the time series (an existing file needs --overwrite)")
    ps.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    ps.add_argument("--rtol", type=float, default=1e-8, help="relative tolerance (default 1e-8)")
    ps.add_argument("--degree", type=int, default=12, help="polynomial degree per element (default 12)")
    ps.add_argument("--n-out", dest="n_out", type=int, default=1001, help="output times (default 1001)")
    ps.add_argument("--amplitude", type=float, default=1e-3, help="initial perturbation of theta")
    ps.add_argument("--seed", type=int, default=0, help="seed of the perturbation shape")
    ps.add_argument("--no-error-estimate", action="store_true", help="skip the two companion runs")
    ps.add_argument("--quiet", action="store_true", help="no progress bar")
    ps.add_argument("--json", action="store_true", help="print a JSON summary")
    ps.set_defaults(func=cmd_simulate)
    pst = sub.add_parser("stability", help="leading eigenvalues of the linearisation (regime, period)")
    _add_params(pst)
    pst.add_argument("--degree", type=int, default=10, help="polynomial degree per element (default 10)")
    pst.add_argument("--n-modes", dest="n_modes", type=int, default=6, help="eigenvalues to report")
    pst.add_argument("--json", action="store_true", help="print JSON")
    pst.set_defaults(func=cmd_stability)

    pc = sub.add_parser("cutoff", help="natural curvature above which flutter stops, at fixed (chi_E, eta)")
    pc.add_argument("--chi-E", dest="chi_E", type=float, required=True)
    pc.add_argument("--eta", type=float, required=True)
    pc.add_argument("--degree", type=int, default=10)
    pc.add_argument("--json", action="store_true")
    pc.set_defaults(func=cmd_cutoff)

    py = sub.add_parser("cycle", help="limit cycle: period, averaged thrust, Floquet multipliers")
    _add_params(py)
    py.add_argument("--degree", type=int, default=10, help="polynomial degree per element (default 10)")
    py.add_argument("--n-phase", dest="n_phase", type=int, default=None,
                    help="steps per period (default: chosen from the time error estimate)")
    py.add_argument("--rtol", type=float, default=1e-6,
                    help="relative accuracy asked of period, |Fbar| and angle (default 1e-6)")
    py.add_argument("--method", choices=sorted(METHODS), default="shooting",
                    help="orbit solver (default shooting: exact-monodromy shooting; newton-krylov: the "
                         "previous solver, kept as a cross-check)")
    py.add_argument("--no-error-estimate", action="store_true")
    py.add_argument("-o", "--output", help="NetCDF file with the cycle over one period (an existing file needs "
                                            "--overwrite)")
    py.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    py.add_argument("--json", action="store_true")
    py.set_defaults(func=cmd_cycle)

    pt = sub.add_parser("table", help="thrust lookup table over chi_N, for one field, a chi_E grid or a grid of "
                                      "background flows (resumable; local pool or Dask)")
    pt.add_argument("--chi-E", dest="chi_E", type=_grid, required=True,
                    help="one field, or a grid 'start:stop:num' or a list (a table over chi_E, interpolated "
                         "in chi_E by ThrustTable)")
    pt.add_argument("--eta", type=float, required=True)
    pt.add_argument("--chi-N", dest="chi_N", type=_grid, required=True, help="'start:stop:num' or a list")
    pt.add_argument("--U-par", dest="U_par", type=_flow_grid, default=None, metavar="GRID",
                    help="background flow along the field (e2, units L/tau): one value, 'start:stop:num', a list "
                         "or 'default' (-2:2:5); a table over the flow (one field; the other component defaults "
                         "to 0). A grid that starts with '-' goes after '=': --U-par=-2:2:5")
    pt.add_argument("--U-perp", dest="U_perp", type=_flow_grid, default=None, metavar="GRID",
                    help="background flow across the field (+e1, units L/tau), as --U-par; give a grid symmetric "
                         "about 0 (negative chi_N are served at -U_perp)")
    pt.add_argument("-o", "--output", required=True,
                    help="NetCDF file (rows kept in OUTPUT.parts/ until done; an existing OUTPUT is refused "
                         "without --overwrite)")
    pt.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    pt.add_argument("--scheduler", help="Dask distributed scheduler address (default: local process pool)")
    pt.add_argument("--scheduler-timeout", dest="scheduler_timeout", type=float, default=None, metavar="SECONDS",
                    help="how long to wait for the scheduler to answer before giving up (default 20, or "
                         "$CILIA_SCHEDULER_TIMEOUT)")
    pt.add_argument("--degree", type=int, default=8)
    pt.add_argument("--n-phase", dest="n_phase", type=int, default=64)
    pt.add_argument("--no-error-estimate", action="store_true")
    pt.add_argument("--tol", type=float, default=1e-8,
                    help="Newton tolerance of each cycle on the scaled shooting residual (default 1e-8)")
    pt.add_argument("--quiet", action="store_true")
    pt.add_argument("--json", action="store_true")
    pt.set_defaults(func=cmd_table)

    pm = sub.add_parser("map", help="stability map over a (chi_E, eta) grid at fixed chi_N")
    pm.add_argument("--chi-N", dest="chi_N", type=float, required=True)
    pm.add_argument("--chi-E", dest="chi_E", type=_grid, required=True, help="'start:stop:num' or a list")
    pm.add_argument("--eta", type=_grid, required=True, help="'start:stop:num' or a list")
    pm.add_argument("--degree", type=int, default=8)
    pm.add_argument("-o", "--output", help="NetCDF file (an existing file needs --overwrite)")
    pm.add_argument("--png", help="PNG figure (flutter coloured by frequency; an existing file needs --overwrite)")
    pm.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT or PNG")
    pm.add_argument("--no-boundary", dest="boundary", action="store_false",
                    help="do not trace the Hopf boundary over the PNG")
    pm.add_argument("--quiet", action="store_true")
    pm.add_argument("--json", action="store_true")
    pm.set_defaults(func=cmd_map)

    pq = sub.add_parser("thrust-curve", help="the design curve: mean thrust and its angle against chi_N, with "
                                             "their error estimates, as a figure (PNG)")
    pq.add_argument("--png", required=True, help="PNG figure (an existing file needs --overwrite)")
    pq.add_argument("--table", default=None,
                    help="a thrust table of one field (NetCDF; default: the shipped chi_E = 200, eta = 1)")
    pq.add_argument("--points", type=int, default=400, help="points along chi_N (default 400)")
    pq.add_argument("--dpi", type=int, default=200, help="resolution of the PNG (default 200)")
    pq.add_argument("--overwrite", action="store_true", help="replace an existing PNG")
    pq.add_argument("--json", action="store_true")
    pq.set_defaults(func=cmd_thrust_curve)
    return ap


def _print_table(out: dict) -> None:
    if "theta" in out:
        print(f"{'s':>10} {'theta':>14} {'x':>14} {'y':>14}")
        for row in zip(out["s"], out["theta"], out["x"], out["y"]):
            print("".join(f"{v:>14.8g}" if i else f"{v:>10.4g}" for i, v in enumerate(row)))
        lim = out["theta_lim"]
        print(f"theta_lim = {lim:.12g}" if lim is not None else out["theta_lim_note"])
    else:
        for k, v in out.items():
            if k != "stats":
                print(f"{k:>12}: {v}")


def _one_line(exc: BaseException) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) not in msg:
        msg = f"{exc.filename}: {exc.strerror or msg}"
    return msg


def _hint(args) -> str:
    """What to change when the discrete equilibrium (the start of stability, cycle, table,
    simulate) cannot be computed."""
    if getattr(args, "chi_E", 1.0) is not None and not isinstance(args.chi_E, np.ndarray) and args.chi_E < 0:
        return ("; here chi_E < 0: the filament folds over where theta leaves 0, away from the clamp, and the "
                "clamp-graded mesh does not resolve that fold at any degree; a larger |chi_N| moves the fold "
                "to the clamp")
    return "; try a higher --degree" if hasattr(args, "degree") else ""


def _check_args(args) -> None:
    """Refuse, before any work, settings out of range or whose cost is beyond reason: a
    ValueError naming the option, its valid range or the largest sensible value."""
    cmd = args.command
    for opt in ("output", "png"):  # an existing file is replaced only with --overwrite
        target = getattr(args, opt, None)
        if target is not None and Path(target).exists():
            flag = "-o" if opt == "output" else "--png"
            if Path(target).is_dir():
                raise ValueError(f"{flag} {target}: is a folder; name a file")
            if not args.overwrite:
                raise ValueError(f"{flag} {target} exists: give --overwrite to replace it, or choose another path")
    for opt, lo in (("points", 2), ("dpi", 20)):
        if getattr(args, opt, lo) < lo:
            raise ValueError(f"--{opt} must be an integer >= {lo}, got {getattr(args, opt)}")
    if not hasattr(args, "degree"):
        return
    with_estimate = cmd in ("cycle", "table") and not args.no_error_estimate
    degree = check_degree(args.degree, with_estimate, "--degree")
    n_phase = getattr(args, "n_phase", None)
    if n_phase is not None and n_phase < 16:
        raise ValueError(f"--n-phase must be an integer >= 16, got {n_phase}")
    if cmd in ("simulate", "stability", "cycle"):
        check_mesh_size(_params(args), degree, "--chi-N", "--degree")
    elif cmd == "map":
        weakest = float(np.min(np.abs(args.chi_E))) if args.chi_E.size else 1.0
        check_mesh_size(CiliumParams(weakest, 1.0, args.chi_N), degree, "--chi-N", "--degree")
    if cmd in ("cycle", "table"):
        chi_E = args.chi_E if cmd == "cycle" else float(np.max(np.abs(args.chi_E))) if args.chi_E.size else 1.0
        p = CiliumParams(chi_E, 1.0, args.chi_N if cmd == "cycle" else 0.0)
        check_cycle_cost(Mesh.for_params(p, degree), N_PHASE_START if n_phase is None else n_phase, "--n-phase",
                         "--degree")


def main(argv: list[str] | None = None) -> int:
    ap = build_parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    name = f"single-cilium {args.command}"
    try:
        with terminate_as_interrupt():  # SIGTERM, SIGHUP: the Ctrl-C cleanup, exit 128 + signum
            _check_args(args)
            try:
                out = args.func(args)
            except SystemError as exc:  # a signal that came back through a compiled function
                stop = interrupt_of(exc)
                if stop is None:
                    raise
                raise stop from None
            text = strict_json(out, indent=1) if getattr(args, "json", False) else None
    except KeyboardInterrupt as exc:
        print(f"{name}: {exc if isinstance(exc, Terminated) else 'interrupted'}", file=sys.stderr)
        return exit_status(exc)
    except ConvergenceError as exc:
        if args.debug:
            raise
        print(f"{name}: did not converge: {_one_line(exc)}", file=sys.stderr)
        return 3
    except RuntimeError as exc:  # a solver that could not continue (e.g. the discrete equilibrium)
        if args.debug:
            raise
        print(f"{name}: could not compute: {_one_line(exc)}{_hint(args)}", file=sys.stderr)
        return 3
    except MemoryError as exc:
        if args.debug:
            raise
        print(f"{name}: error: out of memory ({_one_line(exc)}): ask for a smaller grid or degree", file=sys.stderr)
        return 2
    except (ValueError, TypeError, OSError) as exc:
        if args.debug:
            raise
        print(f"{name}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 -- a bug: one line, the traceback with --debug
        if args.debug:
            raise
        print(f"{name}: internal error: {type(exc).__name__}: {_one_line(exc)} (rerun with --debug for the "
              f"traceback)", file=sys.stderr)
        return 1
    try:
        if text is not None:
            print(text)
        else:
            _print_table(out)
        sys.stdout.flush()
    except OSError as exc:  # a full disk, a closed pipe: the result was computed, stdout could not take it
        try:
            sys.stdout = open(os.devnull, "w")  # nothing more to flush into the broken stream at exit
        except OSError:
            pass
        print(f"{name}: cannot write to standard output: {exc.strerror or exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
