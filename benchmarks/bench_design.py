"""Cost of the inverse design and of rendering the bundled scenes (see benchmarks/README.md).

    python benchmarks/bench_design.py [--quick] [--cap S] [--out FILE]
                                      [--sections design large velocity reach render targets]
                                      [--sizes 100 1000] [--old-max-n N]

Prints Markdown tables to stdout (progress goes to stderr); ``--out`` also writes them to a file.

1. ``ciliary_carpet.design.inverse.design_layout`` against carpet size: square lattices of N = 100 and
   1000 cilia (nx x ny = N, as square as N allows), spacing 2, random phases (seed 0), the
   shipped table, field along +y. Two angle targets: a uniform 30 degree deflection and the
   bundled focusing pattern, -A tanh(xi / w), A = 20 degrees, w = 4. Control points "cells".
   Each cilium's request is the pattern at its straight force centre; the timed call is
   ``Carpet(...)`` with the local layout (what ``design()`` builds) plus ``design_layout`` with
   its defaults, so the time includes every full-model check. Columns: the local layout's rms
   residual (full model), the design's, its error bound, which layout was returned, cilia near
   the flutter cutoff, iterations, full-model checks, wall time, and the peak resident memory of
   the process (maxrss, in increasing order of size). At N = 10000 (``large``, table 1b) the
   whole focusing design is run once, and its design model's value-and-gradient timed through the
   treecode (:mod:`ciliary_carpet.stokes.treecode`) and through the direct sums, with the treecode's
   error against them.
   The alternative: the design before this version (commit 98c3b54: angle-only objective,
   monopole design model, 4 defect-correction passes at the scene tolerance), run in the same
   process on the same carpets up to N = 1000, capped at ``--cap`` seconds.
2. Velocity targets (kind "points"): a target made by a known smooth layout, chi_N = 90 sin(x/7)
   cos(y/9), measured with the full model; the design starts from chi_N = 0 and must recover the
   flow: 30 x 30 cilia at 400 control points (the 20 x 20 cell centres nearest the carpet's
   centre), free space; 12 x 12 cilia above a wall 0.5 L below the plane.
3. ``ciliary_carpet.render.render`` of every ``designs/*.toml``: the per-stage seconds of
   ``summary["seconds"]`` and the design's figures.
4. (``reach``) ``ciliary_carpet.design.reachability.reachability``'s estimate of the amplitude a two-sided
   pattern can hold against focusing designs at amplitudes 20-40 degrees (width 4 L), on 10 x 10
   and 20 x 12 cilia; (4b) its estimate of the narrowest transition width (``width_min``, and the
   rms residual it expects at a width) against designs at widths 0.5-2 spacings, spacings 2 and
   3, focusing, spreading and shear, on 100, 240 and (two rows) 1024 cilia, with the cost of the
   estimate against the design's.

5. (``targets``, issue 24) velocity targets users have: the mean flow of a smooth known layout
   sampled at scattered points or on a grid through the cilia (points inside swept regions used),
   free space and walls 0.5, 0.1 and 0.05 L below the filaments, 144, 400 and 900 cilia at spacing
   2.5: the rms residual, its error bar (final check at a tolerance picked from the threshold
   0.05) against the resolved sum, and the time. Results: ``results/bench_design_targets.md``.

Timing: wall clock, single run, after a warm-up (numba kernels, table). The machine is shared: the
load average at start and end is printed and inflates every time here; the ratios against the
alternative, run in the same process minutes apart, are the meaningful figures.
"""
from __future__ import annotations

import argparse
import functools
import math
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
import types
import warnings
from pathlib import Path

import numpy as np
import scipy

sys.path.insert(0, str(Path(__file__).parent))
from bench_flow import cpu_model  # one CPU probe for every benchmark

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.design.moments import cycle_moments
from ciliary_carpet.design import DesignModel, design_layout
from ciliary_carpet.render import render
from ciliary_carpet.scenes.scene import load_scene
from ciliary_carpet.design import Frame, control_points
from single_cilium.table import ThrustTable

ROOT = Path(__file__).resolve().parent.parent
SPACING = 2.0
OLD_COMMIT = "98c3b54"


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


def maxrss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def git_state() -> str:
    try:
        h = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, check=True).stdout.strip()
        return f"git {h} ({'modified files in the tree' if dirty else 'clean'})"
    except (OSError, subprocess.CalledProcessError):
        return "git n/a"


def old_design_layout():
    """``design_layout`` of commit OLD_COMMIT, loaded from git into a module of the package."""
    src = subprocess.run(["git", "show", f"{OLD_COMMIT}:ciliary_carpet/design.py"], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    mod = types.ModuleType("ciliary_carpet._design_before")
    mod.__package__ = "ciliary_carpet"
    sys.modules[mod.__name__] = mod
    exec(compile(src, f"{OLD_COMMIT}:ciliary_carpet/design.py", "exec"), mod.__dict__)
    return mod.design_layout


def lattice_shape(n: int) -> tuple[int, int]:
    """nx x ny = n with nx >= ny, as square as n allows (nx along x, the cross-stream axis)."""
    ny = max(d for d in range(1, math.isqrt(n) + 1) if n % d == 0)
    return n // ny, ny


def patterns(frame: Frame):
    return {
        "uniform 30 deg": lambda p: np.full(len(p), math.radians(30.0)),
        "focus 20 deg, w 4": lambda p: -math.radians(20.0) * np.tanh(frame.cross_coordinate(p) / 4.0),
    }


def log(msg: str) -> None:
    print(f"[bench_design {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def f3(x) -> str:
    return f"{x:.3g}"


def local_carpet(table, bases, phases, want):
    chi0 = np.array([table.chi_N_for_angle(a) for a in want])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return Carpet(bases, chi0, table, phases)


def section_design(emit, table: ThrustTable, sizes, cap: float, old_max_n: int):
    emit("## 1. Angle targets against carpet size")
    emit("")
    emit(f"Square lattices nx x ny = N, spacing {SPACING:g}, random phases (seed 0), shipped table, field +y. "
         "Time = `Carpet(...)` of the local layout + `design_layout(...)` (defaults), every full-model check "
         f"included. \"before\": `design_layout` of commit {OLD_COMMIT} on the same carpet (its time excludes the "
         f"Carpet), capped at {cap:g} s. Residuals in rad, measured with the full flow model.")
    emit("")
    emit("Split of the time: the local Carpet, the carpets of the checked layouts, their full-model "
         "evaluations (`evaluate` of the `CycleMean`), the L-BFGS-B solves on the design model; CPU = process CPU time of the "
         "whole row (2 numba threads), less inflated by the other processes on the machine than the wall clock. "
         "\"whole-carpet floor\": the same design with the speed floor relative to the whole straight carpet "
         "(`floor_radius=inf`, the floor of commit b0bebbe), same carpet, same process.")
    emit("")
    emit("| N | target | local rms | design rms (+- bound) | worst | returned | near cutoff | iterations | checks "
         "| time [s] | local Carpet / check carpets / evaluate (mean) / design model [s] | CPU [s] "
         "| peak memory [GB] | whole-carpet floor: rms | near cutoff | time [s] "
         "| before: rms | before: near cutoff | before: time [s] | time before / now |")
    emit("|---:|---|---:|---:|---:|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    old = old_design_layout()
    mom = cycle_moments(table)
    for n in sizes:
        nx, ny = lattice_shape(n)
        bases = layout.square(nx, ny, SPACING)
        phases = layout.random_phases(n, 0)
        frame = Frame.from_bases(bases, SPACING, 0.0)
        X = control_points(bases, frame, "cells")
        centres0 = bases + mom(np.zeros(1))["offset"]
        for name, f in patterns(frame).items():
            log(f"N = {n}, {name}: design")
            want = f(centres0)

            def run():
                t0 = time.perf_counter()
                c = local_carpet(table, bases, phases, want)
                t_c = time.perf_counter() - t0
                return c, t_c, design_layout(c, X, angles=f(X), cilium_angles=want)

            cpu0 = time.process_time()
            out, t_d = timed(run, cap)
            cpu = time.process_time() - cpu0
            if out is None:
                emit(f"| {n} | {name} | stopped after {t_d:.0f} s (> cap) |" + " |" * 17)
                continue
            c, t_c, d = out
            w = d.work
            split = (f"{t_c:.1f} / {w['seconds_carpets']:.1f} / {w['seconds_checks']:.1f} / "
                     f"{w['seconds_model']:.1f}")
            row = [str(n), name, f3(d.local_rms), f"{d.residual_rms:.3g} (+- {d.residual_error:.1g})",
                   f3(float(d.residual.max())), d.returned, str(len(d.near_cutoff)), str(d.work["iterations"]),
                   str(d.work["checks"]), f"{t_d:.1f}", split, f"{cpu:.1f}", f"{maxrss_gb():.2f}"]
            log(f"N = {n}, {name}: design with the whole-carpet floor")
            d_w, t_w = timed(lambda: design_layout(c, X, angles=f(X), cilium_angles=want, floor_radius=math.inf), cap)
            row += ["stopped", "", f"> {cap:g}"] if d_w is None else [
                f3(d_w.residual_rms), str(len(d_w.near_cutoff)), f"{t_w:.1f}"]
            if n <= old_max_n:
                log(f"N = {n}, {name}: design before ({OLD_COMMIT})")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    d_old, t_old = timed(lambda: old(c, X, angles=f(X), cilium_angles=f(c.centres)), cap)
                if d_old is None:
                    row += ["stopped", "", f"> {cap:g}", ""]
                else:
                    b1 = table.flutter_range[1]
                    near = int(np.sum(mom.thrust_norm(d_old.chi_N) < 0.25 * mom.thrust0))
                    row += [f3(d_old.residual_rms), str(near), f"{t_old:.1f}", f"{t_old / t_d:.2f}"]
                    del b1
            else:
                row += ["not run", "", "", ""]
            emit("| " + " | ".join(row) + " |")
    emit("")


def section_large(emit, table: ThrustTable, n: int = 10000):
    """The whole design at N = n (focusing), and its design model through the treecode against
    the direct sums (same carpet, same process)."""
    emit(f"### 1b. N = {n}: the whole design, and the treecode against the direct sums")
    emit("")
    nx, ny = lattice_shape(n)
    bases = layout.square(nx, ny, SPACING)
    frame = Frame.from_bases(bases, SPACING, 0.0)
    X = control_points(bases, frame, "cells")
    f = patterns(frame)["focus 20 deg, w 4"]
    mom = cycle_moments(table)
    want = f(bases + mom(np.zeros(1))["offset"])
    log(f"N = {n}: Carpet(...) + design_layout(...)")
    cpu0, t0 = time.process_time(), time.perf_counter()
    c = local_carpet(table, bases, layout.random_phases(n, 0), want)
    t_c = time.perf_counter() - t0
    d = design_layout(c, X, angles=f(X), cilium_angles=want)
    t_d = time.perf_counter() - t0
    cpu = time.process_time() - cpu0
    w = d.work
    emit("| N | control points | design rms (+- bound) [rad] | returned | near cutoff | iterations | checks | time [s] "
         "| local Carpet / check carpets / evaluate (mean) / design model [s] | CPU [s] | peak memory [GB] |")
    emit("|---:|---:|---:|---|---:|---:|---:|---:|---|---:|---:|")
    emit(f"| {n} | {X.shape[0]} | {d.residual_rms:.3g} (+- {d.residual_error:.1g}) | {d.returned} | "
         f"{len(d.near_cutoff)} | {w['iterations']} | {w['checks']} | {t_d:.1f} | {t_c:.1f} / "
         f"{w['seconds_carpets']:.1f} / {w['seconds_checks']:.1f} / {w['seconds_model']:.1f} | {cpu:.1f} | "
         f"{maxrss_gb():.2f} |")
    emit("")
    log(f"N = {n}: design model, treecode against direct")
    dm = DesignModel(c, X, d.chi_N)
    tree = dm.tree
    rows = []
    for name, tr in (("treecode (theta 0.3)", tree), ("direct sums", None)):
        dm.tree = tr
        u = dm.velocity(d.chi_N)
        ts = []
        for _ in range(3):
            t0 = time.perf_counter()
            u = dm.velocity(d.chi_N)
            dm.gradient(d.chi_N, u)
            ts.append(time.perf_counter() - t0)
        rows.append((name, min(ts), u))
    ud = rows[1][2]
    err = np.linalg.norm(rows[0][2] - ud, axis=1).max() / np.linalg.norm(ud, axis=1).max()
    ang = float(np.abs(np.angle((rows[0][2][:, 0] + 1j * rows[0][2][:, 1]) / (ud[:, 0] + 1j * ud[:, 1]))).max())
    emit("| design model (value + gradient) | time [s] | kernel evaluations per sum | max error vs direct "
         "(relative, angle [rad]) | direct / this |")
    emit("|---|---:|---:|---:|---:|")
    pairs = {"treecode (theta 0.3)": tree.work["pairs"] if tree is not None else 0, "direct sums": X.shape[0] * 3 * n}
    for name, t, _u in rows:
        e = f"{err:.1e}, {ang:.1e}" if name != "direct sums" else "reference"
        emit(f"| {name} | {t:.3f} | {pairs[name]:.3g} | {e} | {rows[1][1] / t:.1f}x |")
    emit("")


def section_velocity(emit, table: ThrustTable, cap: float):
    emit("## 2. Velocity targets made by a known layout (recovery)")
    emit("")
    emit("Target: the full model's mean flow of chi_N = 90 sin(x/7) cos(y/9) at the control points; the design "
         "starts from chi_N = 0. Time = `Carpet(...)` + `design_layout(...)`; rms relative to the rms target speed.")
    emit("")
    emit("| cilia | control points | wall | start rms | design rms (+- bound) | returned | iterations | checks "
         "| time [s] | check carpets / evaluate (mean) / design model [s] | CPU [s] |")
    emit("|---:|---:|---|---:|---:|---|---:|---:|---:|---|---:|")
    for n, wall, n_ctrl in ((30, None, 400), (12, 0.5, None)):
        bases = layout.square(n, n, SPACING)
        phases = layout.random_phases(n * n, 0)
        X = control_points(bases, Frame.from_bases(bases, SPACING, 0.0), "cells")
        if n_ctrl is not None:
            centre = 0.5 * (bases.min(0) + bases.max(0))
            X = X[np.argsort(np.linalg.norm(X - centre, axis=1, ord=np.inf), kind="stable")[:n_ctrl]]
        chi_true = 90 * np.sin(bases[:, 0] / 7) * np.cos(bases[:, 1] / 9)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            U = Carpet(bases, chi_true, table, phases, wall=wall).velocity(X, CycleMean())[:, :2]
        log(f"velocity target: {n * n} cilia, {X.shape[0]} control points, wall {wall}")

        def run():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                c = Carpet(bases, 0.0, table, phases, wall=wall)
            return design_layout(c, X, velocities=U)

        cpu0 = time.process_time()
        d, t_d = timed(run, cap)
        cpu = time.process_time() - cpu0
        if d is None:
            emit(f"| {n * n} | {X.shape[0]} | {wall} | stopped after {t_d:.0f} s |" + " |" * 7)
            continue
        w = d.work
        emit(f"| {n * n} | {X.shape[0]} | {'none' if wall is None else f'{wall} L below'} | {f3(d.local_rms)} | "
             f"{d.residual_rms:.3g} (+- {d.residual_error:.1g}) | {d.returned} | {d.work['iterations']} | "
             f"{d.work['checks']} | {t_d:.1f} | {w['seconds_carpets']:.1f} / {w['seconds_checks']:.1f} / "
             f"{w['seconds_model']:.1f} | {cpu:.1f} |")
    emit("")


def _reachable_target(table, n, spacing, wall, points, seed=1):
    """An n x n carpet at chi_N = 0 and a reachable velocity target: the resolved (tol = 0) mean
    flow of the smooth layout chi_N = 90 sin(2 pi 0.8 x / X + 0.3) cos(2 pi 0.6 y / Y) (X, Y the
    carpet's extent) at "scattered" points (n^2 uniform random points over the bases' box) or on
    a "grid" (the lattice shifted by (0, 0.4 L): every point on a cilium)."""
    b = layout.square(n, n, spacing)
    lo, hi = b.min(axis=0), b.max(axis=0)
    if points == "scattered":
        X = lo + np.random.default_rng(seed).random((n * n, 2)) * (hi - lo)
    else:
        X = b + [0.0, 0.4]
    span = hi - lo
    chi = 90 * np.sin(2 * np.pi * 0.8 * b[:, 0] / span[0] + 0.3) * np.cos(2 * np.pi * 0.6 * b[:, 1] / span[1])
    phases = layout.random_phases(n * n, 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        U = Carpet(b, chi, table, phases, wall=wall).velocity(X, CycleMean(), tol=0.0)[:, :2]
    return b, phases, X, U


def section_targets(emit, table: ThrustTable, cap: float, quick: bool = False):
    """Issue 24: reachable velocity targets at scattered and gridded points (some on cilia), free
    space and walls 0.5, 0.1 and 0.05 L below the filaments, 144 / 400 / 900 cilia."""
    emit("## 5. Velocity targets users have: scattered and gridded points, walls close by (issue 24)")
    emit("")
    emit("Target: the resolved (tol = 0) mean flow of the smooth layout chi_N = 90 sin(2 pi 0.8 x / X + 0.3) "
         "cos(2 pi 0.6 y / Y) (X, Y the carpet's extent) at the control points: `scattered` = as many uniform "
         "random points over the bases' box as cilia (seed 1), `grid` = the lattice moved 0.4 L along +y (every "
         "point on a cilium). Square lattices, spacing 2.5, random phases (seed 0). The design starts from chi_N = "
         "0 with `design_layout(..., threshold=0.05)` (inside points used); time = `Carpet(...)` + "
         "`design_layout`. `+-`: the error bar of the final full-model check (tolerance in brackets, picked from "
         "the threshold); `exact`: the rms residual of the returned layout on the resolved sum (tol = 0, not "
         "timed); `|diff|` its difference from the reported one (the bar must cover it). `near`: the near "
         "field's pairs and seconds; `sweeps`: cilia moved by the sweeps.")
    emit("")
    emit("| cilia | points | P | inside | wall [L] | start rms | rms | +- (final tol) | exact | abs diff | met, bar ok "
         "| time [s] | near pairs / s | iterations | checks | sweeps moved | load avg |")
    emit("|---:|---|---:|---:|---|---:|---:|---|---:|---:|---|---:|---|---:|---:|---:|---|")
    sizes = (12,) if quick else (12, 20, 30)
    walls = (None, 0.5) if quick else (None, 0.5, 0.1, 0.05)
    for n in sizes:
        for wall in walls:
            for points in ("scattered", "grid"):
                b, phases, X, U = _reachable_target(table, n, 2.5, wall, points)
                log(f"targets: {n * n} cilia, {points}, wall {wall}")

                def run():
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore", UserWarning)
                        c = Carpet(b, 0.0, table, phases, wall=wall)
                    return design_layout(c, X, velocities=U, threshold=0.05)

                d, t_d = timed(run, cap)
                if d is None:
                    emit(f"| {n * n} | {points} | {len(X)} | | {wall} | stopped after {t_d:.0f} s |" + " |" * 11)
                    continue
                u = d.carpet.velocity(d.control, CycleMean(), tol=0.0)[:, :2]
                s = math.sqrt(np.mean(np.sum(d.target ** 2, axis=1)))
                exact = math.sqrt(np.mean(np.sum((u - d.target) ** 2, axis=1))) / s
                w = d.work
                emit(f"| {n * n} | {points} | {len(X)} | {d.inside_swept['count']} | "
                     f"{'none' if wall is None else wall} | {f3(d.local_rms)} | {d.residual_rms:.3g} | "
                     f"{d.residual_error:.2g} ({w['final_tol']:.2g}) | {exact:.3g} | {abs(exact - d.residual_rms):.1g} | "
                     f"{'yes' if d.residual_rms <= 0.05 else 'NO'}, {'yes' if d.residual_error <= 0.025 else 'NO'} | "
                     f"{t_d:.1f} | {w['near_pairs']} / {w['seconds_near']:.1f} | {w['iterations']} | {w['checks']} | "
                     f"{w['swept_cilia']} | {loadavg()} |")
    emit("")


def section_reach(emit, table: ThrustTable, quick: bool = False):
    """reachability() against designs: focusing at several amplitudes (4), widths against the
    narrowest-width estimate at spacings 2 and 3 (4b)."""
    from ciliary_carpet.design import reachability
    from ciliary_carpet.design.target import Target

    emit("## 4. Reachability estimate against designs")
    emit("")
    emit("`reachability(carpet, control, frame).pattern_max` (the amplitude a two-sided pattern holds away from "
         "its line) against the focusing design's rms residual (full model; threshold 0.05 rad), square lattices "
         f"of spacing {SPACING:g}, random phases (seed 0), control points \"cells\".")
    emit("")
    emit("| cilia | pattern_max [deg] | amplitude [deg] | width [L] | design rms [rad] | meets 0.05 | "
         "amplitude <= pattern_max |")
    emit("|---:|---:|---:|---:|---:|---|---|")
    mom = cycle_moments(table)
    for nx, ny in ((10, 10),) if quick else ((10, 10), (20, 12)):
        bases = layout.square(nx, ny, SPACING)
        phases = layout.random_phases(nx * ny, 0)
        frame = Frame.from_bases(bases, SPACING, 0.0)
        X = control_points(bases, frame, "cells")
        c0 = local_carpet(table, bases, phases, np.zeros(nx * ny))
        pm = math.degrees(reachability(c0, X, frame).pattern_max)
        centres0 = bases + mom(np.zeros(1))["offset"]
        for amp, w in ((20, 4.0), (25, 4.0), (30, 4.0), (40, 4.0)):
            def f(p, amp=amp, w=w):
                return -math.radians(amp) * np.tanh(frame.cross_coordinate(p) / w)

            want = f(centres0)
            c = local_carpet(table, bases, phases, want)
            d = design_layout(c, X, angles=f(X), cilium_angles=want)
            emit(f"| {nx * ny} | {pm:.1f} | {amp} | {w:g} | {d.residual_rms:.3g} | "
                 f"{'yes' if d.residual_rms <= 0.05 else 'no'} | {'yes' if amp <= pm else 'no'} |")
    emit("")
    emit("### 4b. Narrowest transition width against designs")
    emit("")
    emit("`reachability(carpet, control, frame, target=Target(kind, amplitude, width=w))`: the estimated rms "
         "residual at the width w (the design model across the line on the centre row, one curvature per column: "
         "`width_rms`) and the narrowest width meeting 0.05 rad (`width_min`), against the design's rms residual "
         "(`design_layout` with its defaults, full model) at that width. Square lattices of spacing h, random phases "
         "(seed 0), control points \"cells\", field +y, line through the centre. \"estimate s\": the wall time of "
         "that `reachability` call (width scan included; 2 cores shared with other jobs), \"design s\": the "
         "design's (the obvious alternative: designing to find out), same process.")
    emit("")
    emit("| cilia | h [L] | kind | amplitude [deg] | width [L] | width / h | estimated rms | design rms [rad] | "
         "design meets 0.05 | width_min [L] | estimate: reachable | estimate s | design s |")
    emit("|---:|---:|---|---:|---:|---:|---:|---:|---|---:|---|---:|---:|")
    cases = [((10, 10), 2.0, "focus", 20, (0.5, 0.75, 1.0, 1.5, 2.0)),
             ((10, 10), 3.0, "focus", 20, (0.5, 0.75, 1.0, 1.5, 2.0)),
             ((20, 12), 2.0, "focus", 20, (0.5, 0.75, 1.0, 1.5, 2.0)),
             ((20, 12), 3.0, "focus", 20, (0.5, 0.75, 1.0, 1.5, 2.0)),
             ((10, 10), 2.0, "spread", 20, (0.5, 1.0, 2.0)),
             ((10, 10), 2.0, "shear", 30, (0.5, 1.0, 2.0)),
             ((10, 10), 2.0, "focus", 10, (0.5, 1.0)),
             ((10, 10), 2.0, "focus", 40, (2.0, 6.0)),
             ((32, 32), 2.0, "focus", 20, (1.0, 2.0))]
    if quick:
        cases = cases[:1]
    for (nx, ny), h, kind, amp, grid in cases:
        bases = layout.square(nx, ny, h)
        phases = layout.random_phases(nx * ny, 0)
        frame = Frame.from_bases(bases, h, 0.0)
        X = control_points(bases, frame, "cells")
        c0 = local_carpet(table, bases, phases, np.zeros(nx * ny))
        centres0 = bases + mom(np.zeros(1))["offset"]
        for g in grid:
            tg = Target(kind=kind, amplitude=math.radians(amp), width=g * h)
            t0 = time.perf_counter()
            r = reachability(c0, X, frame, target=tg)
            t_r = time.perf_counter() - t0
            want = tg.deflection(centres0, frame)
            t0 = time.perf_counter()
            c = local_carpet(table, bases, phases, want)
            d = design_layout(c, X, angles=tg.deflection(X, frame), cilium_angles=want, spacing=h)
            t_d = time.perf_counter() - t0
            wm = "none" if not math.isfinite(r.width_min) else f"{r.width_min:.3g}"
            emit(f"| {nx * ny} | {h:g} | {kind} | {amp} | {g * h:g} | {g:g} | {r.width_rms:.3g} | "
                 f"{d.residual_rms:.3g} | {'yes' if d.residual_rms <= 0.05 else 'no'} | {wm} | "
                 f"{'yes' if r.width_reachable else 'no'} | {t_r:.2f} | {t_d:.1f} |")
    emit("")


def warm_up(table: ThrustTable) -> None:
    bases = layout.square(3, 2, SPACING)
    frame = Frame.from_bases(bases, SPACING, 0.0)
    X = control_points(bases, frame, "cells")
    for f in patterns(frame).values():
        c = local_carpet(table, bases, layout.random_phases(6, 0), f(bases))
        design_layout(c, X, angles=f(X), cilium_angles=f(bases), maxiter=5, outer=1)


def section_render(emit, quick: bool, cap: float):
    emit("## 3. render() of the bundled scenes")
    emit("")
    scenes = sorted((ROOT / "designs").glob("*.toml"))
    emit(f"`render(load_scene(path), tmpdir / NAME)` for {len(scenes)} scenes in `designs/`"
         + (" (quick: `Scene.reduced()`)" if quick else "") + "; seconds from `summary[\"seconds\"]`; "
         "fidelity: the fraction of cilium-point pairs of the mean field evaluated at each level of detail.")
    emit("")
    stages = ("design", "mean_field", "snapshots", "frames", "pathlines", "preview", "total")
    emit("| scene | cilia | " + " | ".join(f"{s} [s]" for s in stages)
         + " | design rms [rad] / threshold | worst [rad] | returned | cilia near cutoff | iterations "
         "| mean-field fidelity |")
    emit("|---|---:|" + "---:|" * len(stages) + "---:|---:|---|---:|---:|---|")
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
                 + f" | {rms} / {scene.target.residual:g} | {worst} | {d.get('returned', '-')} | "
                 f"{d.get('cilia_near_cutoff', '-')} | {(d.get('work') or {}).get('iterations', '-')} | {fid} |")
    emit("")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N = 100 and reduced scenes: a smoke test")
    ap.add_argument("--cap", type=float, default=300.0, help="seconds per design / render call (default 300)")
    ap.add_argument("--old-max-n", type=int, default=1000,
                    help="run the design before this version up to this N (default 1000)")
    ap.add_argument("--out", type=Path, default=None, help="also write the tables to this file")
    ap.add_argument("--sections", nargs="+", default=["design", "large", "velocity", "reach", "render"],
                    choices=["design", "large", "velocity", "reach", "render", "targets"],
                    help="the sections to run (default: all)")
    ap.add_argument("--sizes", nargs="+", type=int, default=[100, 1000], help="carpet sizes of section 1")
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
    sizes = (100,) if args.quick else tuple(args.sizes)
    run = set(args.sections)
    t1 = time.perf_counter()
    if "design" in run:
        section_design(emit, table, sizes, args.cap, args.old_max_n)
    if "large" in run and not args.quick:
        section_large(emit, table)
    emit(f"- load average after section 1: {loadavg()}")
    emit("")
    if "velocity" in run and not args.quick:
        section_velocity(emit, table, args.cap)
        emit(f"- load average after section 2: {loadavg()}")
        emit("")
    if "targets" in run:
        section_targets(emit, table, args.cap, args.quick)
        emit(f"- load average after section 5: {loadavg()}")
        emit("")
    t_s1 = time.perf_counter() - t1
    t2 = time.perf_counter()
    if "reach" in run:
        section_reach(emit, table, args.quick)
    if "render" in run:
        section_render(emit, args.quick, args.cap)
    t_s2 = time.perf_counter() - t2
    emit(f"- run time: {time.perf_counter() - t_start:.0f} s (design sections: {t_s1:.0f} s, renders: {t_s2:.0f} s); "
         f"load average at end: {loadavg()}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
