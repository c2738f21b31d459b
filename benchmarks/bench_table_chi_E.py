"""Cost and interpolation error of a thrust table over chi_E (benchmarks/README.md).

    python benchmarks/bench_table_chi_E.py

All in the same run (the machine is shared: compare ratios, not absolute times):

1. ``build_table([180, 200, 220], 1, linspace(0, 200, 21))`` (degree 8, 64 steps, Floquet
   multipliers and error estimates on every row) on a process pool over the machine's cores,
   beside the obvious alternative: three one-field tables on the same grid, built one after the
   other (no continuation in chi_E).
2. The interpolation error in chi_E: ``ThrustTable.at(chi_N, chi_E=E)`` at E = 195, 205 against
   fresh cycles (``limit_cycle``, same discretisation) at fractions of the field's cutoff, for the
   grid above (spacing 20) and for five fields 180:220 (spacing 10): the observed order.
3. The cost of serving a new field: the first ``at`` at a new chi_E (the interpolated table is
   built and cached), a cached ``at``, against a fresh one-field table at that field.
"""
from __future__ import annotations

import os
import time

import numpy as np

from single_cilium import CiliumParams
from single_cilium.cycle import limit_cycle
from single_cilium.stability import flutter_cutoff
from single_cilium.table import build_table


def load() -> str:
    return "load average " + " / ".join(f"{v:.1f}" for v in os.getloadavg())


def main() -> None:
    grid = np.linspace(0.0, 200.0, 21)
    print(f"# thrust table over chi_E ({os.cpu_count()} cores; {load()})\n")
    limit_cycle(CiliumParams(200, 1, 50.0), degree=8, n_phase=64)  # warm-up (numba caches)
    t0 = time.perf_counter()
    t3 = build_table([180.0, 200.0, 220.0], 1, grid)
    w3 = time.perf_counter() - t0
    t0 = time.perf_counter()
    for E in (180.0, 200.0, 220.0):
        build_table(E, 1, grid)
    w1 = time.perf_counter() - t0
    ds = t3.ds
    print("## 1. Build (degree 8, 64 steps, Floquet multipliers and error estimates; process pool)\n")
    print("| table | rows | flutter rows | coiled rows | wall [s] |\n|---|---:|---:|---:|---:|")
    print(f"| chi_E = 180, 200, 220 x chi_N = 0:200:21 (+ cutoffs) | {ds.flutter.size} | {int(ds.flutter.sum())} "
          f"| {int(ds.coiled.sum())} | {w3:.1f} |")
    print(f"| three one-field tables, one after the other | {ds.flutter.size} | | | {w1:.1f} |")
    print(f"\nratio (one-field tables / table over chi_E): {w1 / w3:.2f}; {load()}\n")

    t0 = time.perf_counter()
    t5 = build_table([180.0, 190.0, 200.0, 210.0, 220.0], 1, grid)
    w5 = time.perf_counter() - t0
    print(f"five fields 180:220:5 x the same chi_N: {t5.ds.flutter.size} rows, {w5:.1f} s wall\n")
    print("## 2. Interpolation error in chi_E against fresh cycles (same discretisation)\n")
    print("| chi_E | chi_N / cutoff | fields | err cutoff | err T | err abs(Fbar) | err angle [rad] | "
          "max err shape x |\n|---:|---:|---:|---:|---:|---:|---:|---:|")
    for E in (195.0, 205.0):
        cut = flutter_cutoff(E, 1.0, degree=8).chi_N_cutoff
        for frac in (0.0, 0.25, 0.5, 0.75, 0.9, 0.97):
            cN = frac * cut
            f = limit_cycle(CiliumParams(E, 1, cN), degree=8, n_phase=64, error_estimate=False, floquet=False)
            x = f.mesh.interpolate(f.data.x.values.T, ds.s.values).T
            for name, t in (("3", t3), ("5", t5)):
                r = t.at(cN, chi_E=E)
                ec = abs(t._table(E).ds.attrs["chi_N_cutoff"] - cut) / cut
                print(f"| {E:g} | {frac:g} | {name} | {ec:.1e} | {abs(float(r.period) - f.period) / f.period:.1e} | "
                      f"{abs(float(r.thrust_norm) - f.thrust_norm) / f.thrust_norm:.1e} | "
                      f"{abs(float(r.thrust_angle) - f.thrust_angle):.1e} | {np.max(np.abs(r.x.values - x)):.1e} |")
    print(f"\n({load()})\n")
    print("## 3. Serving a new field\n")
    t0 = time.perf_counter()
    t3.at(100.0, chi_E=207.0)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(100):
        t3.at(100.0, chi_E=207.0)
    cached = (time.perf_counter() - t0) / 100
    t0 = time.perf_counter()
    build_table(207.0, 1, grid)
    fresh = time.perf_counter() - t0
    print("| what | wall [s] |\n|---|---:|")
    print(f"| first at(chi_N, chi_E=207) (interpolated table built) | {first:.3f} |")
    print(f"| cached at(chi_N, chi_E=207) | {cached:.4f} |")
    print(f"| fresh one-field table at chi_E = 207 (21 rows + cutoff) | {fresh:.1f} |")
    print(f"\nratio fresh table / first at: {fresh / first:.0f}; {load()}")


if __name__ == "__main__":
    main()
