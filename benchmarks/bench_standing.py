"""Standing carpets (issue 26): the surface-flow design at scale, the force-layer check, renders.

    python benchmarks/bench_standing.py [--sizes 10 30 50 100] [--sections design plug render]
                                        [--out benchmarks/results/bench_standing.md]
                                        [--render-sizes 30] [--threads 2 1]

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
3. ``render`` (not by default; its own table, ``benchmarks/results/bench_standing_render.md``): the
   bundled ``designs/standing_vortex.toml`` with ``shape = [n, n]`` (every other key as bundled)
   rendered as a user runs it, ``ciliary-carpet render SCENE -o DIR --threads T`` in a fresh process
   under ``/usr/bin/time -v``, for each ``--threads`` in turn: wall time, the summary's stage times,
   peak memory, the design's residual and the path lines' end-point error estimate.
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
from ciliary_carpet.design.surface import design_surface  # noqa: E402
from ciliary_carpet.design.surface_model import HEIGHT, SurfaceModel, surface_response  # noqa: E402
from ciliary_carpet.design.surface_target import surface_directions  # noqa: E402
from ciliary_carpet.design import Frame, control_points  # noqa: E402

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


RENDER_OUT = ROOT / "benchmarks" / "results" / "bench_standing_render.md"
STAGES = ("design", "mean_field", "snapshots", "frames", "pathlines", "ftle", "ftle_pump", "preview", "total")


def section_render(sizes, threads) -> None:
    """Renders of the bundled standing vortex scaled to n x n (module docstring), own table."""
    import re
    import tempfile

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_large import render

    lines = ["# bench_standing --sections render: the standing vortex scaled, rendered as a user does", "",
             f"Machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, Python "
             f"{platform.python_version()}; load average (1/5/15 min) at the start: {load()}. Seconds; "
             "`pathlines` holds the path lines and their error estimate's reference run (side by side on a "
             "pool with --threads 2).", "",
             "| carpet | --threads | wall | " + " | ".join(STAGES) + " | peak memory | design rms | end-point "
             "estimate (max) | load after |", "|---|---:|---:|" + "---:|" * len(STAGES) + "---:|---|---|---|"]
    text = (ROOT / "designs" / "standing_vortex.toml").read_text()
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            scene = Path(tmp) / f"standing_vortex_{n}.toml"
            t, k = re.subn(r"^shape = \[12, 12\]", f"shape = [{n}, {n}]", text, flags=re.M)
            if k != 1:
                raise RuntimeError("designs/standing_vortex.toml: no 'shape = [12, 12]' line to scale")
            scene.write_text(re.sub(r'^name = "standing_vortex"', f'name = "standing_vortex_{n}x{n}"', t, flags=re.M))
            for T in threads:
                summary, wall, rss = render(scene, Path(tmp) / f"out_{n}_{T}", T)
                sec = summary["seconds"]
                d = summary.get("design") or {}
                ep = summary["pathlines"]["end_point_error"]["max"]
                lines.append(f"| {n} x {n} | {T} | {wall:.1f} | " + " | ".join(f"{sec.get(q, 0.0):.1f}" for q in STAGES)
                             + f" | {rss:.2f} GB | {d.get('residual_rms', float('nan')):.4f} | {ep:.3g} L | {load()} |")
                print(lines[-1], flush=True)
    RENDER_OUT.write_text("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 30, 50, 100])
    ap.add_argument("--sections", nargs="+", default=["design", "plug"], choices=["design", "plug", "render"])
    ap.add_argument("--render-sizes", type=int, nargs="+", default=[30])
    ap.add_argument("--threads", type=int, nargs="+", default=[2, 1])
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
    if "render" in a.sections:
        section_render(a.render_sizes, a.threads)
    if set(a.sections) - {"render"}:
        Path(a.out).write_text("\n".join(OUT) + "\n")


if __name__ == "__main__":
    main()
