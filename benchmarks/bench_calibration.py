"""The levels of detail's calibration on every carpet size: the measured error of
``Carpet.evaluate(points, Instant(t), tol)`` against the dense resolved sum (``tol = 0``), in units of
``tol`` times the far-field scale the bound is written in, and whether the rigorous bound
(``FlowSample.error_bound``) held at every point.

The points are those of ``tests/test_carpet.py``'s calibration test: on and between the filaments
and on a grid at distances 0 and 5 L from the carpet. Run from the repository root:
``python benchmarks/bench_calibration.py [--sizes 1 3 10 30 100]``; writes
``benchmarks/results/bench_calibration.md``. The seconds column times the resolved sum and the
three evaluations of each carpet.
"""
import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from test_carpet import _grid, _inside_points, _scale  # noqa: E402

from ciliary_carpet.carpet import layout  # noqa: E402
from ciliary_carpet.carpet.carpet import Carpet, Instant  # noqa: E402
from single_cilium.table import ThrustTable  # noqa: E402

TOLS = (1e-2, 1e-3, 1e-4)


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description="the levels of detail's calibration on every carpet size")
    ap.add_argument("--sizes", type=int, nargs="*", default=[1, 3, 10, 30, 100])
    sizes = ap.parse_args(argv).sizes
    table = ThrustTable.default()
    rows = ["| carpet | wall | points | " + " | ".join(f"max err / (tol scale), tol {t:g}" for t in TOLS)
            + " | bound held | seconds |", "|---|---|---|" + "---|" * len(TOLS) + "---|---|"]
    for n in sizes:
        for wall in (None, 0.5):
            clock = time.perf_counter()
            rng = np.random.default_rng(1)
            c = Carpet(layout.square(n, n, 2.0), rng.uniform(-100, 100, n * n), table,
                       layout.random_phases(n * n, 0), wall=wall)
            p = np.concatenate([_inside_points(c, t=0.81), _grid(c, distances=(0.0, 5.0))])
            ref = c.evaluate(p, Instant(0.81), tol=0)
            scale = _scale(c, p, c.cycles.F_rms)
            ratios, held = [], True
            for tol in TOLS:
                s = c.evaluate(p, Instant(0.81), tol=tol)
                err = np.linalg.norm(s.velocity - ref.velocity, axis=1)
                held &= bool(np.all(err <= s.error_bound * (1 + 1e-9) + 1e-15))
                ratios.append(float(np.max(err / (tol * scale))))
            rows.append(f"| {n} x {n} | {wall if wall is not None else 'none'} | {len(p)} | "
                        + " | ".join(f"{r:.3f}" for r in ratios) + f" | {'yes' if held else 'NO'} | "
                        f"{time.perf_counter() - clock:.0f} |")
            print(rows[-1], flush=True)
    text = ("# Levels of detail: calibration against the resolved sum\n\n"
            f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}; load average at the end {os.getloadavg()[0]:.1f}.\n\n"
            + "\n".join(rows) + "\n")
    out = ROOT / "benchmarks" / "results" / "bench_calibration.md"
    out.write_text(text)
    return text


if __name__ == "__main__":
    main()
