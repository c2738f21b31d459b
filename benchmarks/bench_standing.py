"""Standing carpets (issue 26): the surface-flow design at scale, and the force-layer check.

    python benchmarks/bench_standing.py [--sizes 10 30 50 100] [--sections design plug]
                                        [--out benchmarks/results/bench_standing.md]

1. ``design``: square standing carpets of n x n cilia (spacing 2 L, wall at the clamps, random
   phases seed 0), a vortex about the carpet's centre on the plane z = 1.5 L, control points at the
   cell centres, threshold 0.05 rad (:func:`ciliary_carpet.design.surface.design_surface`): the
   design's total time including every full-model check (and the checks' share), the residual with
   its error bar, the local layout's residual (every cilium pumping along the target at its
   nearest control point, no optimisation: the obvious alternative), L-BFGS-B iterations. Beside
   it, in the same run, one evaluation of the design model against one full-model evaluation
   (levels of detail at tol 1e-2) at the same control points, and their ratio.
2. ``plug``: a uniform standing carpet (chi_N = 92, psi = 0.3 rad, spacing 1.5 L) of width W:
   its mean flow at z = 2 and 3 L above the middle over the force-layer plug U = n (F_t c_z + D_zt)
   / mu (MODEL.md section 6), for W = 30, 60, 90 L, and the extrapolation in 1/W.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from single_cilium.table import ThrustTable  # noqa: E402

from ciliary_carpet.carpet import layout  # noqa: E402
from ciliary_carpet.carpet.carpet import Carpet, CycleMean  # noqa: E402
from ciliary_carpet.design.surface import HEIGHT, SurfaceModel, design_surface, surface_response  # noqa: E402
from ciliary_carpet.design.surface_target import surface_directions  # noqa: E402
from ciliary_carpet.design.target import Frame, control_points  # noqa: E402

OUT: list[str] = []


def say(s: str = "") -> None:
    print(s, flush=True)
    OUT.append(s)


def load() -> str:
    return " / ".join(f"{v:.1f}" for v in os.getloadavg())


def section_design(table, sizes) -> None:
    say("## 1. Surface-flow design: a vortex on n x n standing cilia")
    say()
    say("| cilia | control points | design s (checks s) | residual (rad) | local layout | L-BFGS-B iterations "
        "| model eval s | full eval s (tol 1e-2) | full / model | load |")
    say("|---|---:|---:|---|---:|---:|---:|---:|---:|---|")
    for n in sizes:
        b = layout.square(n, n, 2.0)
        b = b - b.mean(axis=0)
        c = Carpet(b, 50.0, table, layout.random_phases(n * n, 0), wall=0.0, geometry="standing")
        surface_response(c, HEIGHT)  # built once per table and height (its time is in the design's work)
        X = control_points(b, Frame(np.zeros(2), np.array([0.0, -1.0]), 2.0), "cells")
        A, keep = surface_directions("vortex", X, (0.0, 0.0), 2.0)
        t0 = time.perf_counter()
        d = design_surface(c, X[keep], directions=A, threshold=0.05)
        total = time.perf_counter() - t0
        m = SurfaceModel(d.carpet, X[keep], HEIGHT)
        t0 = time.perf_counter()
        m.flow(d.chi_N, d.azimuth)
        t_model = time.perf_counter() - t0
        t0 = time.perf_counter()
        d.carpet.evaluate(m.X3, CycleMean(), 1e-2)
        t_full = time.perf_counter() - t0
        say(f"| {n}x{n} | {keep.sum()} | {total:.1f} ({d.work['seconds_checks']:.1f}) | {d.residual_rms:.4f} +- "
            f"{d.residual_error:.4f} | {d.local_rms:.4f} | {d.work['iterations']} | {t_model:.3f} | {t_full:.3f} | "
            f"{t_full / t_model:.1f} | {load()} |")
    say()


def section_plug(table) -> None:
    say("## 2. The force-layer plug above a uniform standing carpet")
    say()
    say("| width W (L) | cilia | u / U at z = 2 L | u / U at z = 3 L | error bound / U | s |")
    say("|---:|---:|---:|---:|---:|---:|")
    psi, sp = 0.3, 1.5
    e = np.array([math.cos(psi), math.sin(psi), 0.0])
    rows = []
    for n in (20, 40, 60):
        b = layout.square(n, n, sp)
        b = b - b.mean(axis=0)
        t0 = time.perf_counter()
        c = Carpet(b, 92.0, table, wall=0.0, geometry="standing", azimuth=psi)
        F, D, cz = c.cycles.F_mean[0], c.cycles.D_mean[0], c.cycles.centre[0, 1]
        U = (F[0] * cz + D[1, 0]) / sp ** 2 / c.mu
        s = c.evaluate(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]]), CycleMean(), 1e-5)
        r = s.velocity @ e / U
        rows.append((n * sp, r))
        say(f"| {n * sp:g} | {n * n} | {r[0]:.4f} | {r[1]:.4f} | {s.error_bound.max() / U:.1e} | "
            f"{time.perf_counter() - t0:.1f} |")
    (w1, r1), (w2, r2) = rows[-2:]
    ext = r2 + (r2 - r1) * (1 / w2) / (1 / w1 - 1 / w2)
    say(f"| extrapolated (1/W, from {w1:g} and {w2:g}) | | {ext[0]:.4f} | {ext[1]:.4f} | | |")
    say()
    say(f"U = n (F_t c_z + D_zt) / mu = {U:.5f} L/tau (n = 1/{sp ** 2:g} per L^2, mu = {c.mu:.4f}).")
    say()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 30, 50, 100])
    ap.add_argument("--sections", nargs="+", default=["design", "plug"], choices=["design", "plug"])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_standing.md"))
    a = ap.parse_args()
    table = ThrustTable.default()
    say("# bench_standing: standing carpets")
    say()
    say(f"Machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}; load average (1/5/15 min) at the start: {load()}.")
    say()
    if "design" in a.sections:
        section_design(table, a.sizes)
    if "plug" in a.sections:
        section_plug(table)
    Path(a.out).write_text("\n".join(OUT) + "\n")


if __name__ == "__main__":
    main()
