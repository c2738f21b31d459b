"""Cost of the inverse design and of rendering the bundled scenes (see benchmarks/README.md).

    python benchmarks/bench_design.py [--quick] [--cap S] [--out FILE]

Prints Markdown tables to stdout (progress goes to stderr); ``--out`` also writes them to a file.

1. ``ciliary_carpet.design.design_layout`` against carpet size: square lattices of N = 10, 100,
   1000, 10000 cilia (nx x ny = N, as square as N allows), spacing 2, random phases (seed 0), the
   shipped table ``ThrustTable.default()``, field along +y (straight flow along -y). Two angle
   targets: a uniform 30 degree deflection and a focusing pattern, deflection -A tanh(xi / w),
   A = 30 degrees, w = 4, xi the cross-stream (x) coordinate from the carpet's centre. Control
   points: ``control_points(bases, Frame.from_bases(bases, 2, 0), "cells")``; the angles are the
   pattern at the control points and (``cilium_angles``) at ``carpet.centres`` of
   ``Carpet(bases, 0.0, table, phases)``. For each row:
   - the *local* design, ``maxiter=0, outer=1``: every cilium at the chi_N whose own thrust has the
     requested angle, no optimisation (scipy's L-BFGS-B still takes one step with maxiter=0: the
     largest |chi_N - chi_N(local)| it causes is shown), residual measured on the full flow model;
   - the design with the defaults (4 outer passes of L-BFGS-B, at most 500 iterations each).
   Wall times are of ``design_layout`` alone; Carpet construction and one evaluation of the
   design objective (the two P x N Stokeslet sums it costs) are timed separately.
   A design whose projected time exceeds ``--cap`` seconds is not run (the projection: 4 outer
   passes at the cost of the local design, plus the previous size's evaluations at this size's
   cost per evaluation; the local design is one full-model check, the unit cost of an outer pass);
   a design still running after ``--cap`` seconds is stopped. "cilia at the bound": designed
   |chi_N| at the flutter cutoff, where the thrust vanishes.
   Table 1c repeats the designs up to N = ``--threads-max-n`` (default 100) with one BLAS thread
   (threadpoolctl, as ``single_cilium._blas.single_threaded_blas``), then also one numba thread:
   L-BFGS-B's BLAS calls and the numba kernels are tiny there, and their thread start-up and
   synchronisation cost can exceed the work, the more so on a loaded machine.
2. ``ciliary_carpet.render.render`` of every ``designs/*.toml`` into a temporary folder: the
   per-stage seconds of ``summary["seconds"]``, the design residual and the mean-field fidelity.
   A scene that fails (e.g. DesignError: residual above the scene's ``[target] residual``) is
   reported with its error and the time until it failed.

Timing: wall clock, single run (the longest rows take minutes), after a warm-up (numba kernels,
table); numba's and BLAS's default thread counts (the machine's cores) except in table 1c. The
load average is printed at start and end: other processes on the machine change these numbers.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import itertools
import math
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import scipy

sys.path.insert(0, str(Path(__file__).parent))
from bench_flow import cpu_model  # one CPU probe for every benchmark

from ciliary_carpet import layout
from ciliary_carpet.carpet import Carpet
from ciliary_carpet.design import design_layout
from ciliary_carpet.render import render
from ciliary_carpet.scene import load_scene
from ciliary_carpet.stokeslet import stokeslet_velocity
from ciliary_carpet.target import Frame, control_points
from single_cilium._blas import single_threaded_blas
from single_cilium.table import ThrustTable

ROOT = Path(__file__).resolve().parent.parent
A_DEG = 30.0
WIDTH = 4.0
SPACING = 2.0


class _Stopped(Exception):
    pass


def _alarm(signum, frame):
    raise _Stopped()


def timed(fn, cap):
    """(result, seconds) of fn(), or (None, seconds) when it is stopped after ``cap`` seconds."""
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, float(cap))
    t0 = time.perf_counter()
    try:
        out = fn()
    except _Stopped:
        out = None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, old)
    return out, time.perf_counter() - t0


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "n/a"


def git_state() -> str:
    try:
        h = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return f"git {h} ({'modified files in the tree' if dirty else 'clean'})"
    except (OSError, subprocess.CalledProcessError):
        return "git n/a"


def lattice_shape(n: int) -> tuple[int, int]:
    """nx x ny = n with nx >= ny, as square as n allows (nx along x, the cross-stream axis)."""
    ny = max(d for d in range(1, math.isqrt(n) + 1) if n % d == 0)
    return n // ny, ny


def patterns(frame: Frame):
    a = math.radians(A_DEG)
    return {
        "uniform 30 deg": lambda p: np.full(len(p), a),
        "focus 30 deg, w 4": lambda p: -a * np.tanh(frame.cross_coordinate(p) / WIDTH),
    }


def log(msg: str) -> None:
    print(f"[bench_design {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def f3(x) -> str:
    return f"{x:.3g}"


def warm_up(table: ThrustTable) -> None:
    bases = layout.square(3, 2, SPACING)
    carpet = Carpet(bases, 0.0, table, layout.random_phases(6, 0))
    frame = Frame.from_bases(bases, SPACING, 0.0)
    X = control_points(bases, frame, "cells")
    for f in patterns(frame).values():
        design_layout(carpet, X, angles=f(X), cilium_angles=f(carpet.centres), maxiter=5, outer=1)


def pair_time(X3, C3, repeat):
    """Best time of the two Stokeslet sums one objective evaluation costs (model and adjoint)."""
    Fs, Gs = np.ones((C3.shape[0], 3)), np.ones((X3.shape[0], 3))
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        stokeslet_velocity(X3, C3, Fs)
        stokeslet_velocity(C3, X3, Gs)
        best = min(best, time.perf_counter() - t0)
    return best


@contextlib.contextmanager
def one_thread(numba_too: bool = True):
    """One BLAS thread (threadpoolctl) and, if ``numba_too``, one numba thread."""
    import numba

    n0 = numba.get_num_threads()
    with single_threaded_blas():
        if numba_too:
            numba.set_num_threads(1)
        try:
            yield
        finally:
            numba.set_num_threads(n0)


def section_design(emit, table: ThrustTable, sizes, cap: float, threads_max_n: int):
    emit("## 1. design_layout against carpet size")
    emit("")
    emit(f"Square lattices nx x ny = N, spacing {SPACING:g}, random phases (seed 0), `ThrustTable.default()`, "
         "field along +y (straight flow -y). Control points: `control_points(bases, frame, \"cells\")`. "
         f"Targets: uniform {A_DEG:g} deg; focus -A tanh(xi/w), A = {A_DEG:g} deg, w = {WIDTH:g}. "
         f"Cap per design call: {cap:g} s.")
    emit("")
    size_rows, rows, thread_rows = [], [], []
    prev_evals: dict[str, int] = {}
    for n in sizes:
        nx, ny = lattice_shape(n)
        bases = layout.square(nx, ny, SPACING)
        phases = layout.random_phases(n, 0)
        frame = Frame.from_bases(bases, SPACING, 0.0)
        X = control_points(bases, frame, "cells")
        P = X.shape[0]
        log(f"N = {n}: Carpet construction")
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            carpet = Carpet(bases, 0.0, table, phases)
        t_carpet = time.perf_counter() - t0
        # one evaluation of the design objective costs two P x N Stokeslet sums (model + adjoint)
        X3 = np.column_stack([X, np.zeros(P)])
        C3 = np.column_stack([carpet.centres, np.zeros(n)])
        repeat = 3 if n > 1000 else 10
        t_pair = pair_time(X3, C3, repeat)
        with one_thread():
            t_pair1 = pair_time(X3, C3, repeat)
        size_rows.append((n, f"{nx} x {ny}", P, t_carpet, t_pair, t_pair1))
        pats = patterns(frame)
        b1 = table.flutter_range[1]
        size_locals: list[float] = []
        for name, f in pats.items():
            ang_X, ang_c = f(X), f(carpet.centres)
            run = functools.partial(design_layout, carpet, X, angles=ang_X, cilium_angles=ang_c)
            chi_local = np.array([table.chi_N_for_angle(a) for a in ang_c])
            row = {"n": n, "pattern": name}
            # local design (no optimisation)
            proj_local = size_locals[0] if size_locals else None
            if proj_local is not None and proj_local > cap:
                row["local"] = f"not run (projected {proj_local:.0f} s > cap {cap:g} s)"
                d_loc = None
            else:
                log(f"N = {n}, {name}: local design")
                d_loc, t_loc = timed(functools.partial(run, maxiter=0, outer=1), cap)
                if d_loc is None:
                    row["local"] = f"stopped after {t_loc:.0f} s"
                else:
                    size_locals.append(t_loc)
                    row["local"] = (t_loc, d_loc.residual_rms, float(d_loc.residual.max()),
                                    float(np.abs(d_loc.chi_N - chi_local).max()))
            # full design
            t_unit = size_locals[0] if size_locals else None
            evals_guess = prev_evals.get(name, 100)
            proj = None if t_unit is None else 4 * t_unit + evals_guess * t_pair
            if proj is None:
                row["full"] = "not run (no local timing to project from)"
            elif proj > cap:
                row["full"] = (f"not run: projected {proj:.0f} s > cap {cap:g} s (4 outer passes x {t_unit:.0f} s "
                               f"full-model check + ~{evals_guess} evaluations x {t_pair:.2f} s)")
            else:
                log(f"N = {n}, {name}: design (projected {proj:.0f} s)")
                d, t_d = timed(run, cap)
                if d is None:
                    row["full"] = f"stopped after {t_d:.0f} s (> cap)"
                else:
                    prev_evals[name] = int(d.work["evaluations"])
                    row["full"] = (t_d, int(d.work["iterations"]), int(d.work["evaluations"]), d.residual_rms,
                                   float(d.residual.max()), d.status, int(np.sum(np.abs(d.chi_N) >= b1 * (1 - 1e-9))))
                    if n <= threads_max_n:
                        # the same design with one BLAS thread, then also one numba thread
                        for label, numba1 in (("BLAS 1 thread", False), ("BLAS 1 + numba 1 thread", True)):
                            log(f"N = {n}, {name}: design, {label}")
                            with one_thread(numba1):
                                d1, t1 = timed(run, cap)
                            thread_rows.append((n, name, t_d, label, t1, d1 and int(d1.work["evaluations"]),
                                                d1 and float(np.abs(d1.chi_N - d.chi_N).max())))
            rows.append(row)
    emit("### 1a. Per size: setup costs")
    emit("")
    emit("| N | lattice | control points | Carpet(...) [s] | one objective evaluation (2 Stokeslet sums P x N) [ms] "
         "| same, numba 1 thread [ms] |")
    emit("|---:|---:|---:|---:|---:|---:|")
    for n, lat, P, tc, tp, tp1 in size_rows:
        emit(f"| {n} | {lat} | {P} | {tc:.2f} | {tp * 1e3:.3g} | {tp1 * 1e3:.3g} |")
    emit("")
    emit("(min of 10 repeats, 3 for N > 1000; numba's default thread count, then one thread)")
    emit("")
    emit("### 1b. Design time and residual (angles in radians)")
    emit("")
    emit("| N | target | local: wall [s] | local: rms | local: worst | local: max abs(chi - chi_local) "
         "| design: wall [s] | L-BFGS-B iterations | evaluations | design: rms | design: worst | status "
         "| cilia at the bound abs(chi) = cutoff | rms local / design |")
    emit("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        loc, full = r["local"], r["full"]
        lc = [f"{loc[0]:.2f}", f3(loc[1]), f3(loc[2]), f"{loc[3]:.1e}"] if isinstance(loc, tuple) else [loc, "", "", ""]
        if isinstance(full, tuple):
            fc = [f"{full[0]:.2f}", str(full[1]), str(full[2]), f3(full[3]), f3(full[4]),
                  "converged" if full[5] == 0 else "not converged", str(full[6])]
            gain = f"{loc[1] / full[3]:.2f}" if isinstance(loc, tuple) and full[3] > 0 else ""
        else:
            fc, gain = [full, "", "", "", "", "", ""], ""
        emit(f"| {r['n']} | {r['pattern']} | " + " | ".join(lc + fc + [gain]) + " |")
    emit("")
    # scaling exponents between successive sizes
    def exponent(vals):
        out = []
        for (n1, v1), (n2, v2) in itertools.pairwise(vals):
            if v1 > 0 and v2 > 0:
                out.append(f"{n1}->{n2}: {math.log(v2 / v1) / math.log(n2 / n1):.2f}")
        return ", ".join(out) if out else "n/a"

    if thread_rows:
        emit(f"### 1c. The same designs with fewer threads (N <= {threads_max_n})")
        emit("")
        emit("| N | target | default threads [s] | variant | wall [s] | speed-up | evaluations | max abs(chi - default chi) |")
        emit("|---:|---|---:|---|---:|---:|---:|---:|")
        for n, name, t_d, label, t1, ev, dchi in thread_rows:
            emit(f"| {n} | {name} | {t_d:.2f} | {label} | {t1:.2f} | {t_d / t1:.1f}x | {ev} | "
                 f"{'' if dchi is None else f'{dchi:.1e}'} |")
        emit("")
    emit("Scaling exponents d log(time) / d log(N) between successive sizes:")
    emit("")
    emit(f"- Carpet construction: {exponent([(s[0], s[3]) for s in size_rows])}")
    emit(f"- one objective evaluation: {exponent([(s[0], s[4]) for s in size_rows])}; numba 1 thread: "
         f"{exponent([(s[0], s[5]) for s in size_rows])}")
    for name in patterns(Frame(np.zeros(2), np.array([0.0, -1.0]), 1.0)):
        loc = [(r["n"], r["local"][0]) for r in rows if r["pattern"] == name and isinstance(r["local"], tuple)]
        full = [(r["n"], r["full"][0]) for r in rows if r["pattern"] == name and isinstance(r["full"], tuple)]
        emit(f"- {name}: local design {exponent(loc)}; design {exponent(full)}")
    emit("")


def section_render(emit, quick: bool, cap: float):
    emit("## 2. render() of the bundled scenes")
    emit("")
    scenes = sorted((ROOT / "designs").glob("*.toml"))
    emit(f"`render(load_scene(path), tmpdir / NAME)` for {len(scenes)} scenes in `designs/`"
         + (" (quick: `Scene.reduced()`)" if quick else "") + "; seconds from `summary[\"seconds\"]`; "
         "fidelity: the fraction of cilium-point pairs of the mean field evaluated at each level of detail.")
    emit("")
    stages = ("design", "mean_field", "snapshots", "frames", "pathlines", "preview", "total")
    emit("| scene | cilia | " + " | ".join(f"{s} [s]" for s in stages)
         + " | design rms [rad] | design worst [rad] | mean-field fidelity | mean-field points |")
    emit("|---|---:|" + "---:|" * len(stages) + "---:|---:|---|---:|")
    with tempfile.TemporaryDirectory(prefix="bench_design_") as td:
        # warm-up: a reduced render compiles / loads every kernel the renders use
        log("render warm-up (reduced scene)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            render(load_scene(scenes[0]).reduced(), Path(td) / "warmup")
        for path in scenes:
            scene = load_scene(path)
            if quick:
                scene = scene.reduced()
            log(f"render {path.name}")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t_r = time.perf_counter()
                try:
                    res, t = timed(functools.partial(render, scene, Path(td) / path.stem), cap)
                except Exception as e:  # noqa: BLE001 - report and go on
                    msg = str(e).split("; worst")[0].split(": ", 1)[-1]
                    emit(f"| {path.stem} | {scene.carpet.n_cilia} | failed after {time.perf_counter() - t_r:.1f} s: "
                         f"{type(e).__name__}: {msg} |" + " |" * (len(stages) + 3))
                    continue
            if res is None:
                emit(f"| {path.stem} | {scene.carpet.n_cilia} | stopped after {t:.0f} s (> cap) |")
                continue
            s = res.summary
            sec = s.get("seconds", {})
            d = s.get("design") or {}
            m = s.get("mean_field") or {}
            fid = ", ".join(f"{k} {v:.2%}" for k, v in (m.get("fidelity") or {}).items())
            cells = [f"{sec[k]:.2f}" if k in sec else "-" for k in stages]
            rms = f3(d["residual_rms"]) if "residual_rms" in d else "-"
            worst = f3(d["residual_max"]) if "residual_max" in d else "-"
            emit(f"| {path.stem} | {s.get('n_cilia', '')} | " + " | ".join(cells)
                 + f" | {rms} | {worst} | {fid} | {m.get('points', '')} |")
    emit("")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N = 10, 100 and reduced scenes: a smoke test")
    ap.add_argument("--cap", type=float, default=300.0, help="seconds per design / render call (default 300)")
    ap.add_argument("--threads-max-n", type=int, default=100,
                    help="repeat the designs up to this N with one BLAS / numba thread (table 1c; default 100)")
    ap.add_argument("--out", type=Path, default=None, help="also write the tables to this file")
    args = ap.parse_args(argv)
    lines: list[str] = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    t_start = time.perf_counter()
    import numba

    emit("# bench_design" + (" (quick)" if args.quick else ""))
    emit(f"- machine: {os.cpu_count()} cores, {cpu_model()} ({platform.machine()}), Python "
         f"{platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, numba {numba.__version__} "
         f"({numba.get_num_threads()} threads)")
    emit(f"- code: {git_state()}; load average at start: {loadavg()}")
    t0 = time.perf_counter()
    table = ThrustTable.default()
    t_table = time.perf_counter() - t0
    warm_up(table)
    emit(f"- `ThrustTable.default()`: {t_table:.2f} s (not in the times below); warm-up done before timing")
    emit("")
    sizes = (10, 100) if args.quick else (10, 100, 1000, 10000)
    t1 = time.perf_counter()
    section_design(emit, table, sizes, args.cap, args.threads_max_n)
    t_s1 = time.perf_counter() - t1
    t2 = time.perf_counter()
    section_render(emit, args.quick, args.cap)
    t_s2 = time.perf_counter() - t2
    emit(f"- run time: {time.perf_counter() - t_start:.0f} s (section 1: {t_s1:.0f} s, section 2: {t_s2:.0f} s); "
         f"load average at end: {loadavg()}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
