"""Cost against error of one limit cycle for each method, and of the thrust table (benchmarks/README.md).

    python benchmarks/bench_cycles.py [--quick] [--table]

All in the same run, so that the ratios hold under whatever load the machine carries:

1. ``limit_cycle`` with the exact-monodromy shooting (``method="shooting"``, the default) at
   (chi_E, eta, chi_N) = (200, 1, 16*2pi) over (degree, steps per period), no Floquet multipliers and
   no error estimate: wall time, work counters, error of the period T, |Fbar| and the thrust angle
   against degree 12 / 256 steps; then the default call (steps chosen by the solver, Floquet
   multipliers, error estimates) after warm-up, the headline number.
2. The previous method, Newton-Krylov shooting (``method="newton-krylov"``), on the same grid points.
3. Brute force (the obvious alternative): ``simulate`` from the Hopf mode (amplitude 0.3) for K
   periods, T from the last two upward crossings of the tip angle through its mean and the mean
   force over exactly that period (trapezoid on 256 outputs per period).
4. Near the flutter cutoff (0.999 and 0.995 x cutoff): the default call, against brute force.
5. (--table) the 41-row table a scene builds and the 201-row table chi_N = 0:200:201, on a process
   pool over the machine's cores, with Floquet multipliers and error estimates on every row; the
   41-row table against the shipped one (single_cilium/data), computed by the previous method.
"""
from __future__ import annotations

import argparse
import os
import resource
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy

from single_cilium import CiliumParams, Filament, Mesh, flutter_cutoff, limit_cycle, simulate, stability
from single_cilium.cycle import thrust_angle
from single_cilium.table import ThrustTable, build_table


def errs(c, ref):
    return (abs(c[0] - ref[0]) / ref[0], abs(c[1] - ref[1]) / ref[1], abs(c[2] - ref[2]))


def brute(p, mesh, T0, K, per=256):
    st = stability(p, mesh=mesh, n_modes=1, check=False)
    fil = Filament(p, mesh)
    y = fil.equilibrium_state() + 0.3 * np.real(fil.join(st.theta_modes[0], st.kappa_modes[0]))
    th, ka = fil.split(y)
    t0 = time.perf_counter()
    sim = simulate(p, K * T0, state=(th, ka), mesh=mesh, rtol=1e-10, n_out=K * per + 1, error_estimate=False)
    t = sim.data.time.values
    tip = sim.data.theta.values[:, -1]
    last = t > t[-1] - 3 * T0
    d = tip - tip[last].mean()
    up = np.nonzero((d[:-1] < 0) & (d[1:] >= 0))[0]
    c = t[up] - d[up] * (t[up + 1] - t[up]) / (d[up + 1] - d[up])
    a, b = c[-2], c[-1]
    sel = (t >= a) & (t <= b)
    F = sim.force
    tt = np.concatenate([[a], t[sel], [b]])
    Fi = np.stack([np.interp(tt, t, F[:, k]) for k in range(2)], 1)
    Fbar = np.trapezoid(Fi, tt, axis=0) / (b - a)
    return time.perf_counter() - t0, (b - a, float(np.hypot(*Fbar)), thrust_angle(*Fbar))


def q(c):
    return (c.period, c.thrust_norm, c.thrust_angle)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--table", action="store_true")
    args = ap.parse_args(argv)
    lines = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    def load():
        return "load average %.1f / %.1f / %.1f" % os.getloadavg()

    emit("# bench_cycles")
    emit(f"- machine: {os.cpu_count()} cores, {platform.machine()}, Python {platform.python_version()}, "
         f"numpy {np.__version__}, scipy {scipy.__version__}; shared with other jobs: {load()} at the start")
    p = CiliumParams(200.0, 1.0, 16 * 2 * np.pi)
    limit_cycle(p, degree=6)  # warm-up: numba's cached kernels load once per process
    t0 = time.perf_counter()
    r = limit_cycle(p, degree=12, n_phase=256, floquet=False, error_estimate=False)
    ref = q(r)
    emit(f"- reference: degree 12, 256 steps per period: T = {ref[0]:.12f}, |Fbar| = {ref[1]:.12f}, "
         f"angle = {ref[2]:.12f} ({time.perf_counter() - t0:.1f} s)")
    emit("")
    grid = [(6, 32), (8, 64)] if args.quick else [(6, 32), (8, 32), (8, 64), (10, 64), (10, 128)]
    header = ("| method | degree | steps/period | wall [s] | period maps | Newton | factorizations | err T "
              "| err abs(Fbar) | err angle [rad] |")
    emit("## 1-2. Exact-monodromy shooting (new default) and Newton-Krylov shooting (previous), "
         "no Floquet, no error estimate")
    emit("")
    emit(header)
    emit("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    methods = ["shooting", "newton-krylov"]
    for method in methods:
        for deg, n in (grid if method == "shooting" else grid[:2] if args.quick else [(6, 32), (8, 64)]):
            t0 = time.perf_counter()
            c = limit_cycle(p, degree=deg, n_phase=n, floquet=False, error_estimate=False, method=method)
            w = time.perf_counter() - t0
            e = errs(q(c), ref)
            emit(f"| {method} | {deg} | {n} | {w:.2f} | {c.work['period_maps']} | {c.work['newton']} | "
                 f"{c.work['factorizations']} | {e[0]:.1e} | {e[1]:.1e} | {e[2]:.1e} |")
    emit("")
    emit("### The default call: steps chosen by the solver, Floquet multipliers, error estimates")
    emit("")
    emit("| method | degree | wall [s] | cpu [s] | chosen steps | period maps | err T | err abs(Fbar) | err angle | "
         "estimate (max) | floquet |")
    emit("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for method, deg in [("shooting", 10), ("shooting", 8)] + ([] if args.quick else [("newton-krylov", 8)]):
        t0, c0 = time.perf_counter(), time.process_time()
        c = limit_cycle(p, degree=deg, method=method) if method == "shooting" else \
            limit_cycle(p, degree=deg, n_phase=64, method=method)
        w, cpu = time.perf_counter() - t0, time.process_time() - c0
        e = errs(q(c), ref)
        est = max(c.errors[k] for k in ("period", "thrust_norm", "thrust_angle"))
        emit(f"| {method} | {deg} | {w:.2f} | {cpu:.2f} | {c.n_phase}{'' if method == 'shooting' else ' (given)'} | "
             f"{c.work['period_maps']} | {e[0]:.1e} | {e[1]:.1e} | {e[2]:.1e} | {est:.1e} | {c.floquet:.6f} |")
    emit("")
    emit("## 3. Brute force: simulate K periods from the Hopf mode (amplitude 0.3), rtol 1e-10, degree 8")
    emit("")
    emit("| K periods | wall [s] | err T | err abs(Fbar) | err angle [rad] |")
    emit("|---:|---:|---:|---:|---:|")
    mesh = Mesh.for_params(p, 8)
    for K in ((10, 20) if args.quick else (10, 20, 40)):
        w, qq = brute(p, mesh, ref[0], K)
        e = errs(qq, ref)
        emit(f"| {K} | {w:.2f} | {e[0]:.1e} | {e[1]:.1e} | {e[2]:.1e} |")
    emit("")
    emit("## 4. Near the flutter cutoff (default call, degree 10), against brute force (degree 8)")
    emit("")
    cut = flutter_cutoff(200.0, 1.0, degree=8).chi_N_cutoff
    emit("| chi_N / cutoff | method | wall [s] | period maps | T | abs(Fbar) | angle | estimate (max) / "
         "diff from shooting |")
    emit("|---:|---|---:|---:|---:|---:|---:|---:|")
    for frac in (0.999, 0.995):
        pc = CiliumParams(200.0, 1.0, frac * cut)
        t0 = time.perf_counter()
        rc = limit_cycle(pc)
        wc = time.perf_counter() - t0
        est = max(rc.errors[k] for k in ("period", "thrust_norm", "thrust_angle"))
        emit(f"| {frac} | shooting | {wc:.2f} | {rc.work['period_maps']} | {rc.period:.10f} | "
             f"{rc.thrust_norm:.10f} | {rc.thrust_angle:.10f} | {est:.1e} |")
        if frac == 0.995:
            for K in ((40,) if args.quick else (40, 160)):
                w, qq = brute(pc, Mesh.for_params(pc, 8), rc.period, K)
                e = errs(qq, q(rc))
                emit(f"| {frac} | brute force, {K} periods | {w:.2f} | | {qq[0]:.10f} | {qq[1]:.10f} | "
                     f"{qq[2]:.10f} | {max(e):.1e} |")
    emit("")
    emit(f"({load()} at the end of sections 1-4)")
    if args.table:
        emit("")
        emit("## 5. Tables (degree 8, 64 steps, Floquet multipliers and error estimates on every row), "
             f"process pool of {os.cpu_count()}")
        emit("")
        emit("| table | rows | flutter rows | wall [s] | cpu of the workers [s] | load before |")
        emit("|---|---:|---:|---:|---:|---|")
        grid41 = np.concatenate([np.linspace(0.0, cut, 41)[:-1], [1.05 * cut]])
        for name, g in (("41 rows (a scene's [table.build])", grid41),
                        ("201 rows, chi_N = 0:200:201", np.linspace(0, 200, 201))):
            before = load()
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            t = build_table(200.0, 1.0, g)
            w = time.perf_counter() - t0
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the pool's workers, reaped at shutdown
            cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
            emit(f"| {name} | {t.ds.sizes['chi_N']} | {int(t.ds.flutter.sum())} | {w:.1f} | {cpu:.1f} | {before} |")
            if g is grid41:
                t41 = t
        old = ThrustTable.default()
        a, b = old.ds, t41.ds
        idx = [int(np.argmin(np.abs(b.chi_N.values - c))) for c in a.chi_N.values]
        assert np.max(np.abs(b.chi_N.values[idx] - a.chi_N.values)) < 1e-9 * cut
        fl = a.flutter.values.astype(bool) & (a.thrust_norm.values > 0)
        emit("")
        emit("The 41-row table against the shipped one (previous method, same grid), flutter rows:")
        emit("")
        emit("| column | max relative difference | max error estimate in the table |")
        emit("|---|---:|---:|")
        for k, ek in (("period", "period_error"), ("thrust_norm", "thrust_norm_error"),
                      ("thrust_y", "thrust_norm_error"), ("thrust_angle", "thrust_angle_error"),
                      ("floquet", "floquet_trivial_error")):
            x, y = a[k].values[fl], b[k].values[idx][fl]
            m = np.abs(x) > 1e-9
            emit(f"| {k} | {np.max(np.abs(x[m] - y[m]) / np.abs(x[m])):.1e} | {np.nanmax(b[ek].values):.1e} |")
    out = Path(__file__).parent / "results" / ("bench_cycles_quick.md" if args.quick else "bench_cycles.md")
    out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
