"""Cost against error of one limit cycle, beside brute-force time integration (benchmarks/README.md).

    python benchmarks/bench_cycles.py [--quick] [--table]

1. limit_cycle at (chi_E, eta, chi_N) = (200, 1, 16*2pi) over (degree, steps per period): wall time
   and error of the period T, thrust_norm and thrust_angle against degree 12 / 256 steps.
2. Brute force (the baseline): simulate from the Hopf mode (amplitude 0.3) for K periods, then T from
   the last two upward crossings of the tip angle through its mean and the mean force over exactly
   that period (trapezoid on 256 outputs per period); error against the same reference; time to
   reach the shooting's error, as a ratio.
3. (--table) the whole 201-point table chi_N in 0:200:201 on the machine's cores.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy

from single_cilium import CiliumParams, Filament, Mesh, limit_cycle, simulate, stability
from single_cilium.cycle import thrust_angle
from single_cilium.table import build_table


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


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--table", action="store_true")
    args = ap.parse_args(argv)
    lines = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    emit("# bench_cycles")
    emit(f"- machine: {os.cpu_count()} cores, {platform.machine()}, Python {platform.python_version()}, "
         f"numpy {np.__version__}, scipy {scipy.__version__}")
    p = CiliumParams(200.0, 1.0, 16 * 2 * np.pi)
    t0 = time.perf_counter()
    r = limit_cycle(p, degree=10 if args.quick else 12, n_phase=128 if args.quick else 256,
                    floquet=False, error_estimate=False)
    ref = (r.period, r.thrust_norm, r.thrust_angle)
    emit(f"- reference: degree {r.mesh.degree}, {r.data.sizes['phase']} steps per period: T = {ref[0]:.12f}, "
         f"|Fbar| = {ref[1]:.12f}, angle = {ref[2]:.12f} ({time.perf_counter() - t0:.1f} s)")
    emit("")
    emit("## 1. limit_cycle (Newton-Krylov shooting), no Floquet, no error estimate")
    emit("")
    emit("| degree | steps/period | wall [s] | period maps | err T | err abs(Fbar) | err angle [rad] |")
    emit("|---:|---:|---:|---:|---:|---:|---:|")
    rows = [(6, 32), (8, 64)] if args.quick else [(6, 32), (8, 32), (8, 64), (10, 64), (10, 128)]
    best = {}
    for deg, n in rows:
        t0 = time.perf_counter()
        c = limit_cycle(p, degree=deg, n_phase=n, floquet=False, error_estimate=False)
        w = time.perf_counter() - t0
        e = errs((c.period, c.thrust_norm, c.thrust_angle), ref)
        best[(deg, n)] = (w, max(e))
        emit(f"| {deg} | {n} | {w:.2f} | {c.work['period_maps']} | {e[0]:.1e} | {e[1]:.1e} | {e[2]:.1e} |")
    emit("")
    emit("## 2. Brute force: simulate K periods from the Hopf mode (amplitude 0.3), rtol 1e-10, degree 8")
    emit("")
    emit("| K periods | wall [s] | err T | err abs(Fbar) | err angle [rad] |")
    emit("|---:|---:|---:|---:|---:|")
    mesh = Mesh.for_params(p, 8)
    for K in ((10, 20) if args.quick else (10, 20, 40, 80)):
        w, q = brute(p, mesh, ref[0], K)
        e = errs(q, ref)
        emit(f"| {K} | {w:.2f} | {e[0]:.1e} | {e[1]:.1e} | {e[2]:.1e} |")
    emit("")
    emit("## 2b. Near the flutter cutoff: chi_N = 0.995 * cutoff (growth rate ~0.005), degree 8, 64 steps")
    emit("")
    from single_cilium import flutter_cutoff
    pc = CiliumParams(200.0, 1.0, 0.995 * flutter_cutoff(200.0, 1.0, degree=8).chi_N_cutoff)
    t0 = time.perf_counter()
    rc = limit_cycle(pc, degree=8, n_phase=64, floquet=False, error_estimate=False)
    wc = time.perf_counter() - t0
    refc = (rc.period, rc.thrust_norm, rc.thrust_angle)
    emit(f"shooting: {wc:.2f} s ({rc.work['period_maps']} period maps): T = {refc[0]:.10f}, "
         f"|Fbar| = {refc[1]:.10f}, angle = {refc[2]:.10f}")
    emit("")
    emit("| K periods (brute force) | wall [s] | diff T | diff abs(Fbar) | diff angle [rad] |")
    emit("|---:|---:|---:|---:|---:|")
    meshc = Mesh.for_params(pc, 8)
    for K in ((40,) if args.quick else (40, 160)):
        w, q = brute(pc, meshc, refc[0], K)
        e = errs(q, refc)
        emit(f"| {K} | {w:.2f} | {e[0]:.1e} | {e[1]:.1e} | {e[2]:.1e} |")
    emit("")
    if args.table:
        emit("## 3. The 201-point table chi_N = 0:200:201 (degree 8, 64 steps, with error estimates)")
        t0 = time.perf_counter()
        t = build_table(200.0, 1.0, np.linspace(0, 200, 201))
        emit(f"{time.perf_counter() - t0:.0f} s on {os.cpu_count()} processes, {int(t.ds.flutter.sum())} flutter rows")
    out = Path(__file__).parent / "results" / ("bench_cycles_quick.md" if args.quick else "bench_cycles.md")
    out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
