"""Programs: one layout for two field strengths, designed jointly, against designing each field alone.

    python benchmarks/bench_program.py [--sections bundled sizes] [--sizes 30 100] [--out FILE]

1. ``bundled``: each bundled program (``designs/program_*.toml``, 10 x 10 cilia, coupled) designed
   jointly (:func:`ciliary_carpet.scenes.program.design_program_scene`): wall time and each state's
   rms residual with its error bar. The alternative, in the same run: each state's target designed
   alone in its own field (:func:`ciliary_carpet.scenes.assembly.design` on the state's scene, the
   single-field design), its own residual, and that layout's residual in the OTHER field (the full
   coupled model of that field, at the same tolerance as the program's checks): what a layout made
   for one field does when the field is switched.
2. ``sizes``: program_focus_switch on n x n cilia (default 30 and 100, spacing 2 L), each in a fresh
   process: wall time of the design, peak memory (maxrss) and each state's residual.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ciliary_carpet.carpet.carpet import CycleMean  # noqa: E402
from ciliary_carpet.design.control import control_points  # noqa: E402
from ciliary_carpet.scenes.assembly import assemble, design  # noqa: E402
from ciliary_carpet.scenes.program import design_program_scene  # noqa: E402
from ciliary_carpet.scenes.scene import load_scene  # noqa: E402
from ciliary_carpet.scenes.states import state_scenes  # noqa: E402

OUT: list[str] = []
CHECK_TOL = 3e-2  # the tolerance of the program's (and a single-field design's) full-model checks


def say(s: str = "") -> None:
    print(s, flush=True)
    OUT.append(s)


def load() -> str:
    return " / ".join(f"{v:.1f}" for v in os.getloadavg())


def angle_rms(state_scene, chi) -> float:
    """The rms angle residual [rad] of curvatures ``chi`` in the state's field, at its target's
    control points (the full coupled model)."""
    a = assemble(state_scene)
    X = control_points(a.bases, a.frame, a.target.control)
    c = a.carpet(chi)
    u = c.evaluate(X, CycleMean(), tol=CHECK_TOL).velocity[:, :2]
    d0 = c.rotation @ np.array([0.0, -1.0])
    th = math.atan2(d0[1], d0[0]) + a.target.deflection(X, a.frame)
    err = np.angle((u[:, 0] + 1j * u[:, 1]) * np.exp(-1j * th))
    return float(np.sqrt(np.mean(err ** 2)))


def bundled() -> None:
    say("## 1. The bundled programs (10 x 10 cilia, coupled): joint design against each field designed alone\n")
    say("rms angle residual [rad] of each state's target, measured in the full coupled model of its field; "
        "'+-' the error bar; threshold 0.1 rad.\n")
    say("| scene | layout | seconds | low (chi_E = 150) | high (chi_E = 200) |")
    say("|---|---|---:|---:|---:|")
    for path in sorted((ROOT / "designs").glob("program_*.toml")):
        sc = load_scene(path)
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            prog, _ = design_program_scene(sc)
        tj = time.perf_counter() - t
        cells = [f"{d.residual_rms:.3f} +- {d.residual_error:.3f}" for d in prog.designs]
        say(f"| {sc.name} | joint (one layout) | {tj:.1f} | {cells[0]} | {cells[1]} |")
        pairs = state_scenes(sc)
        for k, (spec, ssc) in enumerate(pairs):
            t = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                d, _ = design(ssc)
            ts = time.perf_counter() - t
            row = ["", ""]
            row[k] = f"{d.residual_rms:.3f} +- {d.residual_error:.3f}"
            other = 1 - k
            row[other] = f"{angle_rms(pairs[other][1], d.chi_N):.3f} (switched)"
            say(f"| {sc.name} | designed for {spec.name} alone | {ts:.1f} | {row[0]} | {row[1]} |")
    say()


_CHILD = r"""
import json, resource, sys, time, warnings
sys.path.insert(0, {root!r})
from ciliary_carpet.scenes.program import design_program_scene
from ciliary_carpet.scenes.scene import load_scene
sc = load_scene({path!r})
t = time.perf_counter()
with warnings.catch_warnings():
    warnings.simplefilter("ignore", UserWarning)
    prog, _ = design_program_scene(sc)
out = {{"seconds": time.perf_counter() - t, "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
       "states": [[n, d.residual_rms, d.residual_error, d.threshold] for n, d in zip(prog.states, prog.designs)],
       "work": prog.work}}
print("RESULT " + json.dumps(out))
"""


def sizes(ns) -> None:
    import json

    say("## 2. program_focus_switch on n x n cilia (spacing 2 L), each in a fresh process\n")
    say("| cilia | design (s) | peak memory (MB) | low: rms +- bar | high: rms +- bar | passes | evaluations |")
    say("|---:|---:|---:|---:|---:|---:|---:|")
    text = (ROOT / "designs" / "program_focus_switch.toml").read_text()
    with tempfile.TemporaryDirectory() as tmp:
        for n in ns:
            p = Path(tmp) / f"focus_switch_{n}.toml"
            p.write_text(re.sub(r"shape = \[10, 10\]", f"shape = [{n}, {n}]", text).replace(
                'name = "program_focus_switch"', f'name = "focus_switch_{n}"'))
            r = subprocess.run([sys.executable, "-c", _CHILD.format(root=str(ROOT), path=str(p))],
                               capture_output=True, text=True, timeout=3600)
            line = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")]
            if r.returncode or not line:
                say(f"| {n * n} | failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode} |")
                continue
            o = json.loads(line[0][7:])
            st = {s[0]: f"{s[1]:.3f} +- {s[2]:.3f}" for s in o["states"]}
            say(f"| {n * n} | {o['seconds']:.1f} | {o['maxrss_mb']:.0f} | {st['low']} | {st['high']} | "
                f"{o['work']['passes']} | {o['work']['evaluations']} |")
    say()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sections", nargs="+", default=["bundled", "sizes"], choices=["bundled", "sizes"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[30, 100])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_program.md"))
    a = ap.parse_args()
    say("# bench_program: one layout for two field strengths\n")
    say(f"Machine: {os.cpu_count()} cores ({platform.machine()}, {platform.processor() or platform.platform()}); "
        f"load average at the start {load()}; `python benchmarks/bench_program.py "
        f"--sections {' '.join(a.sections)} --sizes {' '.join(map(str, a.sizes))}`.\n")
    t0 = time.perf_counter()
    if "bundled" in a.sections:
        bundled()
    if "sizes" in a.sections:
        sizes(a.sizes)
    say(f"Total {time.perf_counter() - t0:.0f} s; load average at the end {load()}.")
    Path(a.out).write_text("\n".join(OUT) + "\n")


if __name__ == "__main__":
    main()
