"""Cost and accuracy of the carpet flow computations (see benchmarks/README.md).

    python benchmarks/bench_flow.py [--quick] [--sections kernel ...]

Sections (each a function ``bench_<name>(quick, emit)``, each written to
``results/bench_<name>.md``, ``results/bench_<name>_quick.md`` with ``--quick``):

pathlines, longtime
    Time-resolved path lines against fixed-step RK4; the long-time (mean-flow) model against
    time-resolved path lines (docstrings of bench_pathlines and bench_longtime).
kernel
    Throughput of the Stokeslet sum u_i = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j
    (ciliary_carpet.stokes) for M = N random points in the unit cube, standard normal forces:
    - Direct, free space and with a wall (numba, parallel over targets, all cores);
    - the plain-numpy reference (stokeslet_velocity_numpy), up to sizes where one run stays
      below about 20 s;
    - the FMM (fmm3dpy.stfmm3d) at eps = 1e-6 and 1e-12;
    time = best of a few runs after a warm-up (JIT compilation excluded), pairs/s = M N / time,
    error = max_i |u_i - u_i^Direct| / max_i |u_i^Direct| (Direct with wall: against the numpy
    reference with wall where that runs). The crossover size where the FMM becomes faster than
    Direct is measured, or extrapolated from the largest size (Direct ~ (M N), FMM ~ (M + N)).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np

from ciliary_carpet.stokes import FMM, Direct, Wall, stokeslet_velocity, stokeslet_velocity_numpy
from ciliary_carpet.stokes.fmm import fmm_available

RESULTS = Path(__file__).parent / "results"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine_line() -> str:
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    return (f"- machine: {os.cpu_count()} cores, {cpu_model()} ({platform.machine()}), Python "
            f"{platform.python_version()}, numpy {np.__version__}, numba {numba.__version__} "
            f"({numba.get_num_threads()} threads); load average at start {load}")


def best_time(fn, repeat: int = 3, single_above: float = 10.0):
    """(result, best wall time) of ``repeat`` runs; one run only if it takes > single_above s."""
    out, best = None, np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        best = min(best, dt)
        if dt > single_above:
            break
    return out, best


def rel_err(a, b) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def _fmt_t(t):
    return "-" if t is None else (f"{t * 1e3:.1f} ms" if t < 1 else f"{t:.2f} s")


def _fmt_r(x):
    return "-" if x is None else f"{x:.2e}"


def _cpu_seconds():
    """(busy CPU seconds of the whole machine, CPU seconds of this process) so far; None if
    /proc/stat is unavailable."""
    try:
        with open("/proc/stat") as fh:
            v = [int(x) for x in fh.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    t = os.times()
    return (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK"), t.user + t.system


def _others_share(c0, c1, dt):
    """Fraction of the machine's cores used by other processes between two _cpu_seconds()."""
    if c0 is None or c1 is None or dt <= 0:
        return None
    return max(0.0, ((c1[0] - c0[0]) - (c1[1] - c0[1])) / (dt * (os.cpu_count() or 1)))


def _wait_idle(max_wait: float = 120.0, share: float = 0.1) -> float | None:
    """Wait (at most max_wait s) until other processes use < share of the machine over 1 s;
    returns the last measured share."""
    t_end = time.perf_counter() + max_wait
    while True:
        c0, t0 = _cpu_seconds(), time.perf_counter()
        time.sleep(1.0)
        o = _others_share(c0, _cpu_seconds(), time.perf_counter() - t0)
        if o is None or o < share or time.perf_counter() > t_end:
            return o


def _best_time_load(fn, repeat: int = 3, single_above: float = 10.0, clean: float = 0.1,
                    budget: float = 60.0):
    """(result, best wall time, share of the machine used by other processes during that run).

    At least ``repeat`` runs (one if a run takes > single_above s); more, within ``budget``
    seconds, while the best run was disturbed (others' share >= clean)."""
    out, best, other = None, np.inf, None
    t_start = time.perf_counter()
    k = 0
    while True:
        c0 = _cpu_seconds()
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        o = _others_share(c0, _cpu_seconds(), dt)
        k += 1
        if dt < best:
            best, other = dt, o
        done = k >= repeat or dt > single_above
        disturbed = other is not None and other >= clean
        if done and (not disturbed or time.perf_counter() - t_start + dt > budget):
            break
        if disturbed and done:
            _wait_idle(max_wait=min(30.0, budget))
    return out, best, other


def bench_kernel(quick: bool, emit) -> dict:
    """Kernel throughput table; returns the measurements and the crossover estimate."""
    sizes = (1000, 3000, 10000) if quick else (1000, 3000, 10000, 30000, 100000)
    numpy_budget = 2.0 if quick else 20.0
    fmm = fmm_available()
    emit("## Stokeslet kernel throughput (M = N random points in the unit cube, mu = 1)")
    emit("")
    emit("Direct: numba, parallel over targets; wall: Blake image system, wall z = -0.1. numpy: the "
         "vectorised reference (`stokeslet_velocity_numpy`, chunked over targets). FMM: "
         "`fmm3dpy.stfmm3d` (wheel " + ("installed" if fmm else "NOT installed") + "). "
         "Error: max-norm difference relative to max |u| of Direct (wall: Direct vs the numpy "
         "wall reference). 'others': the share of the machine's CPU that other processes used "
         "during the best Direct runs (free / wall); the machine is shared, rows with a large "
         "share understate the throughput." + ("" if quick else " Each size starts after waiting "
                                                "(at most 2 min) for the machine to be idle."))
    emit("")
    emit("| M = N | Direct [time] | pairs/s | Direct wall | pairs/s | others | wall err | numpy | "
         "pairs/s | numpy err | Direct/numpy | FMM 1e-6 | err | FMM 1e-12 | err |")
    emit("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    rng = np.random.default_rng(0)
    wall = Wall(-0.1)
    # warm-up: JIT compilation (or loading from the cache) of both kernels
    w = rng.random((50, 3))
    stokeslet_velocity(w, w, w, backend=Direct())
    stokeslet_velocity(w, w, w, wall=wall, backend=Direct())
    rows = []
    t_np_prev = t_npw_prev = None
    n_prev = None
    for n in sizes:
        T, S, F = rng.random((n, 3)), rng.random((n, 3)), rng.standard_normal((n, 3))
        pairs = float(n) * n
        rep = 5 if n <= 10000 else (3 if n <= 30000 else 2)
        if not quick:
            _wait_idle()

        def direct(wl, T=T, S=S, F=F):
            return stokeslet_velocity(T, S, F, wall=wl, backend=Direct())

        u, t_d, o_d = _best_time_load(lambda: direct(None), rep)
        uw, t_w, o_w = _best_time_load(lambda: direct(wall), rep)
        row = {"n": n, "t_direct": t_d, "t_wall": t_w, "others": (o_d, o_w), "t_numpy": None,
               "e_numpy": None, "e_wall": None, "t_fmm6": None, "e_fmm6": None, "t_fmm12": None,
               "e_fmm12": None}
        # numpy reference only while the predicted time (quadratic growth) stays in budget
        grow = (n / n_prev) ** 2 if n_prev else 1.0
        if t_np_prev is None or t_np_prev * grow < numpy_budget:
            un, row["t_numpy"] = best_time(lambda T=T, S=S, F=F: stokeslet_velocity_numpy(T, S, F), 2, 2.0)
            row["e_numpy"] = rel_err(un, u)
            t_np_prev = row["t_numpy"]
        if t_npw_prev is None or t_npw_prev * grow < numpy_budget:
            t0 = time.perf_counter()
            unw = stokeslet_velocity_numpy(T, S, F, wall=wall)
            t_npw_prev = time.perf_counter() - t0
            row["e_wall"] = rel_err(uw, unw)
        if fmm:
            for eps, key in ((1e-6, "fmm6"), (1e-12, "fmm12")):
                uf, row["t_" + key] = best_time(
                    lambda T=T, S=S, F=F, eps=eps: stokeslet_velocity(T, S, F, backend=FMM(eps)), 2, 2.0)
                row["e_" + key] = rel_err(uf, u)
        n_prev = n
        rows.append(row)
        ratio = None if row["t_numpy"] is None else row["t_numpy"] / t_d
        np_rate = "-" if row["t_numpy"] is None else f"{pairs / row['t_numpy']:.2e}"
        oth = " / ".join("?" if o is None else f"{o:.0%}" for o in (o_d, o_w))
        emit(f"| {n} | {_fmt_t(t_d)} | {pairs / t_d:.2e} | {_fmt_t(t_w)} | {pairs / t_w:.2e} | {oth} | "
             f"{_fmt_r(row['e_wall'])} | {_fmt_t(row['t_numpy'])} | {np_rate} | "
             f"{_fmt_r(row['e_numpy'])} | {'-' if ratio is None else f'{ratio:.0f}x'} | "
             f"{_fmt_t(row['t_fmm6'])} | {_fmt_r(row['e_fmm6'])} | {_fmt_t(row['t_fmm12'])} | "
             f"{_fmt_r(row['e_fmm12'])} |")
    emit("")
    best = max(float(r["n"]) ** 2 / r["t_direct"] for r in rows)
    best_w = max(float(r["n"]) ** 2 / r["t_wall"] for r in rows)
    emit(f"Peak Direct throughput: {best:.2e} pairs/s free space, {best_w:.2e} pairs/s with the wall "
         f"({best / os.cpu_count():.2e} and {best_w / os.cpu_count():.2e} per core).")
    crossover = {}
    if fmm:
        for key, label in (("fmm6", "1e-6"), ("fmm12", "1e-12")):
            faster = [r["n"] for r in rows if r["t_" + key] < r["t_direct"]]
            if faster:
                n_star = float(faster[0])
                how = "measured (first size where the FMM is faster)"
            else:
                last = rows[-1]
                # Direct ~ n^2, FMM ~ n: equal at n* = n t_fmm / t_direct
                n_star = last["n"] * last["t_" + key] / last["t_direct"]
                how = f"extrapolated from M = N = {last['n']}"
            crossover[key] = n_star
            emit(f"- FMM eps {label} faster than Direct from M = N ~ {n_star:.2g} "
                 f"(M N ~ {n_star ** 2:.2g} pairs; {how}).")
        emit("- fmm3dpy 2.1.0's wheel runs on one thread (no OpenMP); Direct uses all cores.")
    else:
        emit("- fmm3dpy not installed: no FMM columns, no crossover.")
    emit("")
    return {"rows": rows, "crossover": crossover, "peak": best, "peak_wall": best_w}


# ----------------------------------------------------------------------------- carpet sections
def _carpet(n_side=10):
    from ciliary_carpet.carpet import layout
    from ciliary_carpet.carpet.carpet import Carpet
    from single_cilium.table import ThrustTable

    rng = np.random.default_rng(1)
    n = n_side * n_side
    return Carpet(layout.square(n_side, n_side, 2.0), rng.uniform(-100, 100, n), ThrustTable.default(),
                  layout.random_phases(n, 0))


def _rings(carpet, d, n=40):
    lo, hi = carpet.bases.min(0) - 1 - d, carpet.bases.max(0) + 1 + d
    s = np.linspace(0, 1, n, endpoint=False)
    side = [np.column_stack([lo[0] + (hi[0] - lo[0]) * s, np.full(n, lo[1])]),
            np.column_stack([np.full(n, hi[0]), lo[1] + (hi[1] - lo[1]) * s]),
            np.column_stack([hi[0] - (hi[0] - lo[0]) * s, np.full(n, hi[1])]),
            np.column_stack([np.full(n, lo[0]), hi[1] - (hi[1] - lo[1]) * s])]
    return np.concatenate(side)


def bench_levels(quick: bool, emit) -> dict:
    """Levels of detail against the resolved sum on 10 x 10 and 30 x 30 carpets (regularised
    Stokeslets, blob 0.02 L), 1000 random points in and around the carpet (grown by 5 L, none
    inside a filament): time, error relative to |u|, whether the bound holds, and the share of
    the time spent outside the numba kernels."""

    spent = {"kernel": 0.0}

    def timed(fn):
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent["kernel"] += time.perf_counter() - t0
        return wrapper

    import ciliary_carpet.carpet.plan as carpet_module
    from ciliary_carpet.carpet.carpet import CycleMean, Instant
    from ciliary_carpet.stokes import Direct as _Direct

    orig = (_Direct.dense, _Direct.ranged)  # the backend's sums (their structure-of-arrays copies included)
    _Direct.dense, _Direct.ranged = timed(orig[0]), timed(orig[1])
    emit("## Levels of detail vs the resolved sum (1000 points in and around the carpet)\n")
    emit("Error: max over the points of |u - u_resolved| / |u_resolved|. Instantaneous field at t = 0.37 "
         "(levels point/resolved), and the steady mean field (levels mean/resolved; resolved = the 64 phase "
         "samples' average). Resolved time: the plain dense sum of every source (tol = 0; one vectorised "
         "numba sum, the obvious alternative). Sources / point: kernel evaluations per point (FlowSample.work; "
         "the resolved sum: 65 per cilium instantaneous, 64 x 65 mean); monopole / dipole / quadrupole: the cheap pairs "
         "per order (1, 3 and 6 carriers); ranges / point: the source ranges of the sparse sum. Bound holds: the rigorous bound "
         "(error_bound, LOD_SLACK x tol x the far-field sum) holds at every point. Outside kernels: the share "
         "of the evaluation spent outside the numba sums (carriers, moments, filament states, pair lists). "
         "Quadrupoles only: the same evaluation with every cilium that is not resolved summed as six carriers (the "
         "levels before the monopole and dipole orders), and its speed-up over the resolved sum.\n")
    emit("| carpet | field | tol | cheap pairs | monopole / dipole / quadrupole | sources / point | ranges / point | "
         "time | resolved time | speed-up | rel. error | bound holds | outside kernels | quadrupoles only | its speed-up |")
    emit("|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|")
    out = {}
    try:
        for side in ((10,) if quick else (10, 30)):
            c = _carpet(side)
            rng = np.random.default_rng(4)
            lo, hi = c.bases.min(0) - 5, c.bases.max(0) + 5
            pts = lo + (hi - lo) * rng.random((1500, 2))
            pts = pts[c.filament_distance(pts, 0.37) > 2 * c.blob][:1000]
            for field in ("instantaneous", "mean"):
                when = Instant(0.37) if field == "instantaneous" else CycleMean()
                ev = (lambda tol: c.velocity(pts, when, tol=tol))  # noqa: B023
                ref, t_ref = best_time(lambda: ev(0.0), repeat=2)
                for tol in ((1e-3,) if quick else (1e-2, 1e-3, 1e-4)):
                    s = c.evaluate(pts, when, tol=tol)
                    # interleaved with the resolved sum (instantaneous; the mean's takes seconds), best
                    # of 7: the machine is shared, its load changes from second to second
                    t, share, t_q = np.inf, float("nan"), np.inf
                    for _ in range(7):
                        if field == "instantaneous":
                            t_ref = min(t_ref, best_time(lambda: ev(0.0), repeat=1)[1])
                        spent["kernel"] = 0.0
                        _, dt = best_time(lambda: ev(tol), repeat=1)
                        if dt < t:
                            t, share = dt, 1.0 - spent["kernel"] / dt
                        # the alternative: every cilium not resolved as quadrupoles (the far order
                        # the plan takes when classifying a cilium is made prohibitive)
                        price = carpet_module._CLASSIFY
                        carpet_module._CLASSIFY = 1e12
                        c.sums.plans.clear()
                        try:
                            ev(tol)  # the plan is made once per tolerance (not timed, as for the levels)
                            t_q = min(t_q, best_time(lambda: ev(tol), repeat=1)[1])
                        finally:
                            carpet_module._CLASSIFY = price
                            c.sums.plans.clear()
                            ev(tol)
                    err = np.linalg.norm(s.velocity - ref, axis=1)
                    rel = float(np.max(err / np.linalg.norm(ref, axis=1)))
                    frac = 1 - s.fidelity["resolved"]
                    spp = s.work["sources"] / len(pts)
                    o = s.work["orders"]
                    cheap = max(1, sum(o.values()))
                    mix = " / ".join(f"{o[k] / cheap:.0%}" for k in ("monopole", "dipole", "quadrupole"))
                    emit(f"| {side} x {side} | {field} | {tol:g} | {frac:.1%} | {mix} | {spp:.0f} | "
                         f"{s.work['ranges'] / len(pts):.1f} | {_fmt_t(t)} | "
                         f"{_fmt_t(t_ref)} | {t_ref / t:.1f}x | {rel:.1e} | {bool(np.all(err <= s.error_bound * (1 + 1e-9) + 1e-15))} | "
                         f"~{max(share, 0.0):.0%} | {_fmt_t(t_q)} | {t_ref / t_q:.1f}x |")
                    out[(side, field, tol)] = (t_ref / t, rel, spp)
    finally:
        _Direct.dense, _Direct.ranged = orig
    emit("\n(times: best of 7 runs, the instantaneous field's interleaved with the resolved sum's; outside "
         "kernels: in the best run; the machine is shared, so both are approximate)\n")
    return out


def _free_seeds(c, n, rng, pad=2.0):
    """``n`` random seeds over the carpet grown by ``pad``, none within two blob sizes of a filament."""
    lo, hi = c.bases.min(0) - pad, c.bases.max(0) + pad
    seeds = lo + (hi - lo) * rng.random((3 * n, 2))
    return seeds[c.filament_distance(seeds, 0.0) > 2 * (c.blob or 0.02)][:n]


def bench_pathlines(quick: bool, emit) -> dict:
    """Time-resolved path lines in a 10 x 10 carpet: our multirate Dormand-Prince 5(4) with dense
    output against a plain vectorised fixed-step RK4 on the same velocity evaluation (regularised
    Stokeslets, blob 0.02 L, flow tol 1e-3); end-point error against rtol = atol = 1e-8."""
    from ciliary_carpet.carpet.carpet import Instant
    from ciliary_carpet.transport.flow import ResolvedFlow
    from ciliary_carpet.transport.pathlines import pathlines

    c = _carpet()
    T0 = float(np.nanmin(c.periods))
    n_tr, periods = (30, 3) if quick else (100, 20)
    seeds = _free_seeds(c, n_tr, np.random.default_rng(2))
    span = (0.0, periods * T0)
    emit(f"## Path lines: {seeds.shape[0]} tracers over {periods} beats of a 10 x 10 carpet (flow tol 1e-3)\n")
    emit("Seeds at random over the carpet (grown by 2 L), none inside a filament. Error: max end-point distance "
         "[L] over the tracers, against our integrator at rtol = atol = 1e-8 (blob 0.02 L: tracers pass between "
         "and through the beating filaments, none is stopped).\n")
    t0 = time.perf_counter()
    ref = pathlines(ResolvedFlow(c, 1e-3), seeds, span, rtol=1e-8, atol=1e-8)
    t_ref = time.perf_counter() - t0
    emit(f"Reference: {_fmt_t(t_ref)}, {ref.stats['evaluations']} evaluations; outcome {ref.counts()}.\n")
    emit("| integrator | tolerance / step | time | steps (+substeps) | velocity evaluations | points per beat | "
         "end-point error |")
    emit("|---|---:|---:|---:|---:|---:|---:|")
    out = {"reference": (t_ref, ref.counts())}
    runs = [(1e-5, None)] if quick else [(1e-4, None), (1e-6, None), (1e-6, 1e9)]
    for r, cap in runs:
        t0 = time.perf_counter()
        p = pathlines(ResolvedFlow(c, 1e-3), seeds, span, rtol=r, atol=r, max_step=cap)
        t = time.perf_counter() - t0
        err = float(np.max(np.linalg.norm(p.end_points - ref.end_points, axis=1)))
        ppb = float(np.mean([len(q) for q in p.points])) / periods
        how = "steps <= T/16 (default)" if cap is None else "uncapped steps"
        emit(f"| ours: multirate Dormand-Prince 5(4), dense output, {how} | rtol = atol = {r:g} | {_fmt_t(t)} | "
             f"{p.stats['steps']} (+{p.stats['substeps']}) | {p.stats['evaluations']} | {ppb:.0f} | {err:.1e} |")
        out[("dp", r, cap)] = (t, err)
    for per_beat in ((20,) if quick else (20, 40)):
        n_steps = per_beat * periods
        h = (span[1] - span[0]) / n_steps
        x = np.column_stack([seeds, np.zeros(seeds.shape[0])])
        t0 = time.perf_counter()
        tt = 0.0
        for _ in range(n_steps):
            k1 = c.velocity(x, Instant(tt), 1e-3)
            k2 = c.velocity(x + 0.5 * h * k1, Instant(tt + 0.5 * h), 1e-3)
            k3 = c.velocity(x + 0.5 * h * k2, Instant(tt + 0.5 * h), 1e-3)
            k4 = c.velocity(x + h * k3, Instant(tt + h), 1e-3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            tt += h
        t = time.perf_counter() - t0
        err = float(np.max(np.linalg.norm(x - ref.end_points, axis=1)))
        emit(f"| plain vectorised RK4, fixed step | h = T/{per_beat} | {_fmt_t(t)} | {n_steps} | {4 * n_steps} | "
             f"{per_beat} | {err:.1e} |")
        out[("rk4", per_beat)] = (t, err)
    emit("")
    # the case: 1000 tracers over 200 beats, run whole; its error from 100 tracers over the
    # same 200 beats against a reference (the error grows with the beats, as tracers cross the carpet)
    beats = 3 if quick else 200
    runs = ((1e-6, 16),) if quick else ((1e-6, 16), (1e-4, 16), (1e-4, 24))
    seeds = _free_seeds(c, 30 if quick else 100, np.random.default_rng(2))
    span = (0.0, beats * T0)
    t0 = time.perf_counter()
    ref = pathlines(ResolvedFlow(c, 1e-3), seeds, span, rtol=1e-8, atol=1e-8)
    t_ref = time.perf_counter() - t0
    emit(f"### {beats} beats: end-point error ({seeds.shape[0]} tracers) and time (1000 tracers)\n")
    emit(f"Error against our integrator at rtol = atol = 1e-8 ({_fmt_t(t_ref)}, {ref.stats['evaluations']} "
         f"evaluations; outcome {ref.counts()}: the default domain is the carpet grown by 10 L; a tracer that "
         "leaves it ends on its boundary, at the crossing found on the continuous extension). That reference is "
         "itself within 1.5e-5 L (max; median 4e-7) of one at rtol 1e-9 with steps <= T/64 (measured once, "
         "165 s). The step cap sets most of the error: the one-step estimate misses what a tracer passing a "
         "beating filament (a velocity spike shorter than a step) picks up. Time: 1000 tracers (another seed), "
         "flow tol 1e-3, the whole run.\n")
    emit("| rtol = atol | step cap | end-point error max | median | 90th percentile | time, 1000 tracers | "
         "velocity evaluations | ms per evaluation | outcome (1000 tracers) |")
    emit("|---:|---|---:|---:|---:|---:|---:|---:|---|")
    big = _free_seeds(c, 100 if quick else 1000, np.random.default_rng(3))
    for r, cap in runs:
        p = pathlines(ResolvedFlow(c, 1e-3), seeds, span, rtol=r, atol=r, max_step=T0 / cap)
        e = np.linalg.norm(p.end_points - ref.end_points, axis=1)
        t0 = time.perf_counter()
        q = pathlines(ResolvedFlow(c, 1e-3), big, span, rtol=r, atol=r, max_step=T0 / cap)
        t = time.perf_counter() - t0
        emit(f"| {r:g} | T/{cap}{' (default)' if cap == 16 else ''} | {e.max():.1e} | {np.median(e):.1e} | "
             f"{np.percentile(e, 90):.1e} | {_fmt_t(t)} | {q.stats['evaluations']} | "
             f"{1e3 * t / q.stats['evaluations']:.2f} | {q.counts()} |")
        out[("big", r, cap)] = (t, float(e.max()))
    emit("")
    return out


def bench_longtime(quick: bool, emit) -> dict:
    """The long-time model (flow.MeanFlow: the mean Eulerian flow on a grid) against
    time-resolved path lines across the designed uniform_deflection carpet, seeded as the render
    seeds them, for the render's automatic duration."""
    import warnings

    from ciliary_carpet.scenes.assembly import design
    from ciliary_carpet.transport.flow import MeanFlow, ResolvedFlow
    from ciliary_carpet.transport.pathlines import pathlines
    from ciliary_carpet.output.plan import FieldGrid, pathline_duration, seed_points
    from ciliary_carpet.scenes.assembly import render_settings
    from ciliary_carpet.scenes.scene import load_scene

    scene = load_scene(Path(__file__).parent.parent / "designs" / "uniform_deflection.toml")
    if quick:
        scene = scene.reduced()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        _, c = design(scene)
    T0 = float(np.nanmin(c.periods))
    duration, how = pathline_duration(render_settings(scene), c, T0)
    seeds = seed_points(render_settings(scene), c)[:: (1 if quick else 5)]
    box = FieldGrid.around(render_settings(scene), c).box
    emit(f"## Long-time model vs time-resolved path lines ({scene.name}, {c.n} cilia, {seeds.shape[0]} tracers, "
         f"{duration / T0:.0f} beats; {how})\n")
    t0 = time.perf_counter()
    res = pathlines(ResolvedFlow(c, 1e-3), seeds, (0.0, duration), rtol=1e-6, atol=2e-4, domain=box)
    t_res = time.perf_counter() - t0
    out = {"resolved": t_res}
    emit("| flow model | grid spacing | build | integration | end-point error / distance travelled (max, median) "
         "| speed-up |")
    emit("|---|---:|---:|---:|---:|---:|")
    emit(f"| time-resolved (rtol 1e-6, atol 2e-4 L) | - | - | {_fmt_t(t_res)} | reference | 1x |")
    travel = np.linalg.norm(res.end_points - np.column_stack([seeds, np.zeros(len(seeds))]), axis=1)
    for spacing in ((0.5,) if quick else (0.5, 0.25)):
        t0 = time.perf_counter()
        m = MeanFlow.from_carpet(c, box, spacing=spacing, tol=1e-3)
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        p = pathlines(m, seeds, (0.0, duration), rtol=1e-6, atol=2e-4, domain=box)
        t_int = time.perf_counter() - t0
        both = (p.reason == res.reason)
        rel = np.linalg.norm(p.end_points - res.end_points, axis=1)[both] / travel[both]
        emit(f"| mean flow + bicubic grid | {spacing:g} L | {_fmt_t(t_build)} | {_fmt_t(t_int)} | "
             f"{rel.max():.3f}, {np.median(rel):.3f} ({both.sum()} tracers) | {t_res / (t_build + t_int):.0f}x |")
        out[spacing] = (t_build, t_int, float(rel.max()), float(np.median(rel)))
    # the model's integration cost at the size: 1000 tracers over 200 beats
    rng = np.random.default_rng(3)
    many = _free_seeds(c, 1000, rng, pad=0.0)
    t0 = time.perf_counter()
    p = pathlines(m, many, (0.0, 200 * T0), rtol=1e-6, atol=2e-4, domain=box)
    t_many = time.perf_counter() - t0
    emit(f"\nMean-flow path lines of {many.shape[0]} tracers over 200 beats (grid above, built once): "
         f"{_fmt_t(t_many)} ({p.stats['evaluations']} evaluations; outcome {p.counts()}).")
    out["many"] = t_many
    emit("")
    out["drift"] = _stokes_drift(emit, c.table, quick)
    return out


def _stokes_drift(emit, table, quick: bool) -> dict:
    """The size of what the long-time model leaves out: the Stokes drift of one cilium's beat,
    u_S = <(xi . grad) u'> (xi the displacement of the oscillating flow u' = u - ubar, the
    average over one period), against its mean flow ubar, at 16 points on circles around its
    force centre. Time-resolved flow (tol 0) at 64 phases; xi spectrally, grad u' by central
    differences (h = 1e-3 L). Cilia of different periods add no cross terms to the long-time
    average, so in a carpet the drift is this single-cilium drift of the nearest cilia while the
    mean flow adds up over all of them: the ratios below bound the carpet's from above."""
    from ciliary_carpet.carpet.carpet import Carpet, Instant

    emit("### Stokes drift of one cilium's beat against its mean flow (what the long-time model omits)\n")
    emit("| chi_N | distance from the force centre [L] | max |u_S| / |ubar| | median | max |u'| / |ubar| |")
    emit("|---:|---:|---:|---:|---:|")
    n, h = 64, 1e-3
    res = {}
    for chi in ((90.0,) if quick else (0.0, 90.0, 150.0)):
        c = Carpet(np.zeros((1, 2)), np.array([chi]), table)
        T, ctr = float(c.periods[0]), c.centres[0]
        ts = np.arange(n) / n * T
        k = np.fft.fftfreq(n, d=1.0 / n)[:, None, None]
        for d in (1.0, 2.0, 4.0):
            ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
            P = np.c_[ctr[0] + d * np.cos(ang), ctr[1] + d * np.sin(ang), np.zeros(16)]
            offs = [np.zeros(3)] + [s * h * e for e in np.eye(3) for s in (1, -1)]
            U = np.array([[c.velocity(P + o, Instant(tt), tol=0) for o in offs] for tt in ts])  # (phase, offset, point, 3)
            ubar = U[:, 0].mean(0)
            up = U[:, 0] - ubar
            with np.errstate(divide="ignore", invalid="ignore"):
                xi = np.fft.ifft(np.where(k != 0, np.fft.fft(up, axis=0) * T / (2j * np.pi * k), 0), axis=0).real
            grad = np.stack([(U[:, 1 + 2 * i] - U[:, 2 + 2 * i]) / (2 * h) for i in range(3)], axis=2)
            us = np.einsum("npa,npac->pc", xi, grad - grad.mean(0)) / n
            r = np.linalg.norm(us, axis=1) / np.linalg.norm(ubar, axis=1)
            osc = float((np.linalg.norm(up, axis=2).max(0) / np.linalg.norm(ubar, axis=1)).max())
            emit(f"| {chi:g} | {d:g} | {r.max():.1e} | {np.median(r):.1e} | {osc:.0f} |")
            res[(chi, d)] = float(r.max())
    emit("")
    return res


SECTIONS = {"kernel": bench_kernel, "levels": bench_levels, "pathlines": bench_pathlines,
            "longtime": bench_longtime}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only (a smoke test)")
    ap.add_argument("--sections", nargs="+", choices=sorted(SECTIONS), default=list(SECTIONS),
                    help="which sections to run (default: all)")
    args = ap.parse_args(argv)
    RESULTS.mkdir(exist_ok=True)
    for name in args.sections:
        lines: list[str] = []

        def emit(s: str = "") -> None:
            print(s, flush=True)
            lines.append(s)

        emit(f"# bench_flow: {name}" + (" (--quick)" if args.quick else ""))
        emit(machine_line())
        emit("")
        t0 = time.perf_counter()
        SECTIONS[name](args.quick, emit)
        load = ", ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
        emit(f"(section time {time.perf_counter() - t0:.0f} s; load average at end {load})")
        out = RESULTS / (f"bench_{name}_quick.md" if args.quick else f"bench_{name}.md")
        out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
