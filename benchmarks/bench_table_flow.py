"""Cost and interpolation error of a thrust table over the background flow (benchmarks/README.md).

    python benchmarks/bench_table_flow.py            # about 15 minutes on 2 idle cores
    python benchmarks/bench_table_flow.py --quick    # the two coarser grids only

All at chi_E = 200, eta = 1, degree 8, 64 steps per period, Floquet multipliers and error
estimates on every row, on the default process pool over the machine's cores (the machine is
shared: the load average is printed with each timing):

1. Build time against the grid: the flow grid ``U_par x U_perp`` (each ``linspace(-2, 2, m)``,
   spacing 4 / (m - 1)) and the chi_N grid (``linspace(0, 1.05 max cutoff, n)``, the cutoffs
   of all flows added).
2. Interpolation error against fresh cycles (``limit_cycle``, same discretisation) at flows off
   the grid and chi_N at fractions of that flow's cutoff (and just above it, and negative chi_N,
   served by the mirror image): the thrust vector ``|F - F_fresh|``, period (relative), thrust
   angle, shape ``x``; and the table's own estimate (``interpolation_error``): the largest ratio
   of the error to the estimate (below 1: the estimate holds).
3. Continuation in the flow: a flow's cycle at chi_N = 100 started from the neighbouring flow's
   cycle (spacing 1) against the Hopf mode.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from single_cilium import CiliumParams
from single_cilium.cycle import limit_cycle
from single_cilium.stability import flutter_cutoff
from single_cilium.table import build_table

KW = dict(degree=8, n_phase=64)
OFF_GRID = [(-1.3, -0.4), (0.7, 1.6), (-0.2, 0.3), (1.4, -1.7), (0.3, -0.7)]  # off every grid below
FRACTIONS = [0.0, 0.25, 0.5, 0.75, 0.9, 1.04]


def load() -> str:
    return "load average " + " / ".join(f"{v:.1f}" for v in os.getloadavg())


def chi_N_grid(n: int, top: float) -> np.ndarray:
    return np.linspace(0.0, top, n)


def fresh_points():
    """(chi_N, U_par, U_perp, fresh cycle) at the off-grid flows (negative chi_N: the mirror)."""
    pts = []
    for up, uq in OFF_GRID:
        cut = flutter_cutoff(200.0, 1.0, degree=8, background=(uq, up)).chi_N_cutoff
        for f in FRACTIONS:
            cN = f * cut
            c = limit_cycle(CiliumParams(200.0, 1.0, cN, (uq, up)), **KW, error_estimate=False, floquet=False)
            pts.append((cN, up, uq, c))
    for cN, up, uq in [(-60.0, 0.7, 1.6), (-120.0, -1.3, -0.4)]:  # U_perp -> -U_perp under the mirror
        c = limit_cycle(CiliumParams(200.0, 1.0, cN, (uq, up)), **KW, error_estimate=False, floquet=False)
        pts.append((cN, up, uq, c))
    return pts


def errors(t, pts) -> dict:
    out = {"F": 0.0, "F_branch_rel": 0.0, "T": 0.0, "angle": 0.0, "x": 0.0, "ratio": 0.0, "est": 0.0,
           "flutter_mismatch": 0}
    for cN, up, uq, c in pts:
        r = t.at(cN, U_par=up, U_perp=uq)
        F = np.array([float(r.thrust_x), float(r.thrust_y)])
        e = float(np.hypot(*(F - c.thrust)))
        est = float(t.interpolation_error("thrust_norm", cN, U_par=up, U_perp=uq))
        out["F"] = max(out["F"], e)
        out["est"] = max(out["est"], est)
        if e > 1e-7:  # above the rows' Newton tolerance (at a row the estimate is 0)
            out["ratio"] = max(out["ratio"], e / est if est > 0 else np.inf)
        out["flutter_mismatch"] += int(bool(r.flutter) != c.flutter)
        if c.flutter and bool(r.flutter):
            out["F_branch_rel"] = max(out["F_branch_rel"], e / c.thrust_norm)
            out["T"] = max(out["T"], abs(float(r.period) / c.period - 1))
            out["angle"] = max(out["angle"], abs(float(r.thrust_angle) - c.thrust_angle))
            if cN > 0:  # a mirrored cycle starts at the mirror image of phase 0, not a fresh cycle's phase 0
                x = c.mesh.interpolate(c.data.x.values.T, t.ds.s.values).T
                out["x"] = max(out["x"], float(np.max(np.abs(r.x.values - x))))
    return out


def continuation() -> list[str]:
    rows = []
    for up in (-1.0, 0.0, 1.0, 2.0):
        p = CiliumParams(200.0, 1.0, 100.0, (0.0, up))
        nb = limit_cycle(CiliumParams(200.0, 1.0, 100.0, (0.0, up - 1.0)), **KW)
        t0 = time.perf_counter()
        hopf = limit_cycle(p, **KW)
        th = time.perf_counter() - t0
        t0 = time.perf_counter()
        seeded = limit_cycle(p, **KW, seed=nb)
        ts = time.perf_counter() - t0
        rows.append(f"| {up:g} | {hopf.work['newton']} | {th:.2f} | {seeded.work['newton']} | {ts:.2f} | "
                    f"{abs(seeded.period / hopf.period - 1):.1e} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the coarse grids only")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_table_flow.md"))
    args = ap.parse_args()
    lines: list[str] = []

    def say(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    cpu = platform.processor() or platform.machine()
    say(f"# Thrust table over the background flow ({os.cpu_count()} cores; {cpu})\n")
    say(f"- python {sys.version.split()[0]}, code git {rev}; {load()} at start")
    say("- chi_E = 200, eta = 1; degree 8, 64 steps per period, Floquet multipliers and error estimates on every row; "
        "default process pool\n")
    limit_cycle(CiliumParams(200, 1, 50.0), **KW)  # warm-up (numba caches)
    cuts = [flutter_cutoff(200.0, 1.0, degree=8, background=(uq, up)).chi_N_cutoff
            for up in (-2.0, 2.0) for uq in (-2.0, 2.0)]
    top = min(1.05 * max(cuts), 0.95 * 200.0)  # short of the coiled limit, where the steady state turns steep
    cases = [(3, 20), (5, 20)] if args.quick else [(3, 20), (5, 20), (5, 39), (9, 20)]
    t0 = time.perf_counter()
    pts = fresh_points()
    say(f"fresh cycles at {len(pts)} points: {time.perf_counter() - t0:.1f} s ({load()})\n")
    say("## 1-2. Build time and interpolation error against fresh cycles\n")
    say(f"chi_N grid linspace(0, {top:.1f}, n) (1.05 x the largest cutoff over the corners of [-2, 2]^2, at most "
        "0.95 chi_E) plus each "
        "flow's cutoff; flows linspace(-2, 2, m) in each component. Errors: max over the points "
        f"({len(OFF_GRID)} off-grid flows x chi_N / cutoff in {FRACTIONS}, and 2 negative chi_N); F absolute "
        "(|Fbar| is 0.2-3.5 here), the rest on the flutter branch; 'est.' the largest estimate, 'err / est.' the "
        "largest ratio of the error to the table's estimate at the same point; x: the shape at chi_N > 0 (a mirrored "
        "cycle starts at the mirror image of phase 0).\n")
    say("| flows m x m (spacing) | chi_N n (spacing) | rows computed | wall [s] | load | err F | err F / abs(F) | "
        "err T (rel) | err angle [rad] | err x | est. | err / est. |")
    say("|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for m, n in cases:
        U = np.linspace(-2.0, 2.0, m)
        grid = chi_N_grid(n, top)
        t0 = time.perf_counter()
        t = build_table(200.0, 1.0, grid, U_par=U, U_perp=U)
        wall = time.perf_counter() - t0
        rows = int((t.ds.regime.values != 5).sum())
        e = errors(t, pts)
        say(f"| {m} x {m} ({4 / (m - 1):g}) | {n} ({top / (n - 1):.1f}) | {rows} | {wall:.0f} | {load()[13:]} | "
            f"{e['F']:.1e} | {e['F_branch_rel']:.1e} | {e['T']:.1e} | {e['angle']:.1e} | {e['x']:.1e} | "
            f"{e['est']:.1e} | {e['ratio']:.2f} |" + (f" flutter flag differs at {e['flutter_mismatch']} points"
                                                       if e["flutter_mismatch"] else ""))
    say("\n## 3. Continuation in the flow (chi_N = 100, U_perp = 0; seed: the cycle at U_par - 1)\n")
    say("| U_par | Newton steps from the Hopf mode | wall [s] | seeded from U_par - 1 | wall [s] | period change |")
    say("|---:|---:|---:|---:|---:|---:|")
    for r in continuation():
        say(r)
    say(f"\n({load()})")
    Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
