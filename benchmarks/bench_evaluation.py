"""The cost of one evaluation of a carpet's flow at an instant, what path lines pay tens of
thousands of times (issue 23).

The designed uniform_deflection carpet scaled to N x N cilia (``bench_large.scaled_scene``),
evaluated at M random points over it at an instant (flow tol 1e-4, the render's path-line
tolerance), one numba thread, three ways in the same run:

* **moments**: the carriers' forces as before the fused pass (what ``Carpet.evaluate`` still does
  for its reported bound): the moments from their interpolant, the carriers with the bound's
  terms, then stacked (``FlowSums.sum(..., bound=True)``);
* **fused**: ``Carpet.velocity`` at an instant not prepared (``InstantCarriers``: one compiled
  pass from the moments' interpolant, its harmonics cut at ``Carriers.harmonics(tol)``, to the
  stacked forces; where the far cilia are dipoles, the quadrupoles made only for the cilia read);
* **prepared**: ``Carpet.velocity`` after ``Carpet.prepare`` of the five distinct stage times of a
  Dormand-Prince step, as the path lines call it (the cost of the ``prepare`` shared among them).

``--pathlines F``: the render's own path-line call on each carpet (its 100 seeds, flow tol,
rtol and atol: ``PATHLINE_TOL``, ``PATHLINE_RTOL``, ``PATHLINE_ATOL`` x spacing) over the
fraction F of its duration, one thread, with where its time goes: the flow's ``prepare`` (the
carriers of a step's instants) and its evaluations by the number of tracers they carry (the
common steps carry them all, the substeps of tracers near a filament one to a few), twice: the
far cilia's carriers summed in fp64 and in fp32 (``ResolvedFlow(precision=...)``; a render's is
``PATHLINE_PRECISION``), with the largest distance between their end points; then the
same for the error estimate's reference run (8 of the tracers, every tolerance tighter: what runs
beside the path lines on the second core). Run it on two checkouts (``PYTHONPATH``) to compare
code.

Times are per evaluation (median of repeats), with the largest difference of the velocities
from the moments' path relative to the largest speed (the fused and prepared ones equal each
other; they differ from the moments' path by the harmonics cut, at most ``HARMONIC_TAIL`` tol of
the far-field sum). ``--sizes`` carpets, ``--points`` M.

    python benchmarks/bench_evaluation.py [--sizes 30 100] [--points 1 8 100] [--pathlines 0.25]

Writes ``benchmarks/results/bench_evaluation.md``.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
OUT = ROOT / "benchmarks" / "results" / "bench_evaluation.md"
TOL = 1e-4
STAGES = np.array([0.2, 0.3, 0.8, 8 / 9, 1.0])
"""The distinct stage times of a Dormand-Prince step, in steps (the last two stages share 1)."""


def _load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def measure(n: int, points: list[int], repeats: int) -> list[str]:
    import bench_large
    from ciliary_carpet.carpet.carpet import Instant
    from ciliary_carpet.scenes.assembly import design
    from ciliary_carpet.scenes.scene import load_scene

    with tempfile.TemporaryDirectory() as tmp:
        _, c = design(load_scene(bench_large.scaled_scene(n, Path(tmp)), allow_outside=True))
    rng = np.random.default_rng(0)
    lo, hi = c.bases.min(axis=0), c.bases.max(axis=0)
    h = 0.06  # a step of a sixteenth of the beat period, about
    rows = []
    for m in points:
        x = np.column_stack([rng.uniform(lo[0], hi[0], m), rng.uniform(lo[1], hi[1], m), np.zeros(m)])
        c.velocity(x, Instant(0.0), TOL)  # plans and compiled code made
        t0 = [0.0]

        def moments():
            t0[0] += h
            return c.sums.sum(x, Instant(t0[0]), TOL, bound=True)[0].velocity

        def fused():
            t0[0] += h
            return c.velocity(x, Instant(t0[0]), TOL)

        def prepared():
            t0[0] += h
            ts = t0[0] + STAGES * h
            c.prepare(ts, TOL)
            return [c.velocity(x, Instant(t), TOL) for t in ts]

        t_m = _median_time(moments, repeats)
        t_f = _median_time(fused, repeats)
        t_p = _median_time(prepared, max(3, repeats // 5)) / STAGES.size
        t = 12.345
        ref = c.sums.sum(x, Instant(t), TOL, bound=True)[0].velocity
        scale = float(np.abs(ref).max())
        d_f = float(np.abs(c.velocity(x, Instant(t), TOL) - ref).max()) / scale
        c.prepare([t], TOL)
        d_p = float(np.abs(c.velocity(x, Instant(t), TOL) - ref).max()) / scale
        rows.append(f"| {n} x {n} | {m} | {1e3 * t_m:.3f} | {1e3 * t_f:.3f} | {1e3 * t_p:.3f} | "
                    f"{t_m / t_p:.2f} | {d_f:.1e} / {d_p:.1e} | {_load()} |")
        print(rows[-1], flush=True)
    return rows


def pathline_split(n: int, fraction: float) -> list[str]:
    """The render's path-line call on the N x N carpet over ``fraction`` of its duration, one
    thread: its seconds and evaluations, and their split (module docstring); then the same for its
    error estimate's reference run (:func:`~ciliary_carpet.transport.accuracy.error_reference`: 8 of the
    tracers, flow tol, rtol and atol tighter by :data:`~ciliary_carpet.transport.accuracy.REFERENCE_TIGHTER`)."""
    import bench_large
    from ciliary_carpet.transport.accuracy import (
        PATHLINE_ATOL,
        PATHLINE_RTOL,
        PATHLINE_TOL,
        REFERENCE_TIGHTER,
        error_tracers,
    )
    from ciliary_carpet.transport.flow import ResolvedFlow
    from ciliary_carpet.transport.pathlines import pathlines

    with tempfile.TemporaryDirectory() as tmp:
        c, plan, spacing = bench_large._design(bench_large.scaled_scene(n, Path(tmp)))

    class Timed(ResolvedFlow):
        def __post_init__(self) -> None:
            super().__post_init__()
            object.__setattr__(self, "log", {"prepare": [0.0, 0], "evals": []})

        def prepare(self, times) -> None:
            t = time.perf_counter()
            super().prepare(times)
            self.log["prepare"][0] += time.perf_counter() - t
            self.log["prepare"][1] += 1

        def velocity(self, x, t):
            t0 = time.perf_counter()
            u = super().velocity(x, t)
            self.log["evals"].append((x.shape[0], time.perf_counter() - t0))
            return u

    ft, ti = REFERENCE_TIGHTER
    rows = []
    idx = error_tracers(len(plan.seeds))
    ends = {}
    for what, precision, seeds, tol, rtol, atol, spp in (
            ("render", "fp64", plan.seeds, PATHLINE_TOL, PATHLINE_RTOL, PATHLINE_ATOL * spacing, 16),
            ("render", "fp32", plan.seeds, PATHLINE_TOL, PATHLINE_RTOL, PATHLINE_ATOL * spacing, 16),
            ("reference", "fp64", plan.seeds[idx], PATHLINE_TOL / ft, PATHLINE_RTOL / ti,
             PATHLINE_ATOL * spacing / ti, 1)):
        kw = dict(rtol=rtol, atol=atol, samples_per_period=spp)
        pathlines(ResolvedFlow(c, tol, precision=precision), seeds, (0.0, 0.01), **kw)  # compiled, plans made
        flow = Timed(c, tol, precision=precision)
        t = time.perf_counter()
        pl = pathlines(flow, seeds, (0.0, plan.duration * fraction), **kw)
        wall = time.perf_counter() - t
        ends[what, precision] = pl.end_points
        off = ""
        if what == "reference":  # how far each render's run ends from it (its 8 tracers)
            off = " / ".join(f"{np.linalg.norm(ends['render', p][idx] - pl.end_points, axis=1).max():.2g}"
                             for p in ("fp64", "fp32"))
        elif precision == "fp32":
            off = f"{np.linalg.norm(pl.end_points - ends['render', 'fp64'], axis=1).max():.2g} from fp64"
        ev = np.array(flow.log["evals"])
        few = ev[:, 0] < 20
        prep_s, prep_n = flow.log["prepare"]
        rows.append(f"| {n} x {n}, {what} ({len(seeds)} tracers) | {precision} | {fraction:g} | {wall:.2f} | "
                    f"{ev.shape[0]} | {prep_s:.2f} ({prep_n}) | {ev[~few, 1].sum():.2f} ({int((~few).sum())}) | "
                    f"{ev[few, 1].sum():.2f} ({int(few.sum())}) | {wall - prep_s - ev[:, 1].sum():.2f} | "
                    f"{pl.stats['steps']} / {pl.stats['substeps']} / {pl.stats['rejected']} | {off} | {_load()} |")
        print(rows[-1], flush=True)
    return rows


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[30, 100])
    ap.add_argument("--points", type=int, nargs="+", default=[1, 8, 100])
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--pathlines", type=float, default=None, metavar="F",
                    help="also the render's path lines over this fraction of their duration, and their split")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    import numba

    numba.set_num_threads(1)
    head = [f"# One evaluation of a carpet's flow at an instant (issue 23)\n",
            f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one numba thread, "
            f"Python {platform.python_version()}; load average at the start {_load()} (1, 5, 15 min). "
            f"`python benchmarks/bench_evaluation.py --sizes {' '.join(map(str, a.sizes))} --points "
            f"{' '.join(map(str, a.points))}`; flow tol {TOL:g}; ms per evaluation, median of {a.repeats}.\n",
            "| carpet | points | moments (ms) | fused (ms) | prepared (ms) | moments / prepared | "
            "difference fused / prepared (rel.) | load |", "|---|---:|---:|---:|---:|---:|---|---|"]
    rows = []
    for n in a.sizes:
        rows += measure(n, a.points, a.repeats)
    if a.pathlines is not None:
        rows += ["", f"The render's path lines and its error estimate's reference run over a fraction of their "
                 f"duration (`--pathlines {a.pathlines:g}`), one thread: seconds in all, in the flow's prepare "
                 "(calls), in evaluations of 20 tracers or more (the common steps) and of fewer (the substeps), "
                 "and the rest (the integrator). The render's run twice, its far carriers summed in fp64 and in "
                 "fp32 (`PATHLINE_PRECISION`, what a render does), then the reference; end points: the fp32 "
                 "run's largest distance from the fp64 one, and the reference's from each (its 8 tracers, "
                 "fp64 / fp32) [L].", "",
                 "| carpet | far sums | fraction | seconds | evaluations | prepare | evaluations >= 20 tracers | "
                 "evaluations < 20 tracers | rest | steps / substeps / rejected | end points | load |",
                 "|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|---|"]
        for n in a.sizes:
            rows += pathline_split(n, a.pathlines)
    text = "\n".join(head + rows) + "\n"
    a.out.write_text(text)
    return text


if __name__ == "__main__":
    main()
