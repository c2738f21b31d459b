"""Cilia that feel the flow: the coupled carpet against the uncoupled one.

    python benchmarks/bench_coupling.py [--table FLOW_TABLE.nc] [--sizes 5 10 20 30 50 100]
                                        [--sections growth scenes large renders] [--large 30 100]
                                        [--renders uniform_deflection focusing standing_pump] [--out FILE]

FLOW_TABLE.nc: a thrust table over the background flow for chi_E = 200, eta = 1; default the
shipped one (``ThrustTable.default(flow=True)``).

1. ``growth``: a uniform square carpet (spacing 2 L, chi_N = 92, random phases seed 0, free
   space) of n x n cilia: the others' mean flow at the cilia (median speed) uncoupled (M(0)) and
   coupled (U, :func:`ciliary_carpet.carpet.coupling.couple`), the linear drag estimate
   (:func:`~ciliary_carpet.carpet.coupling.coupling_estimate`), |A B| (above 1 the plain
   iteration U <- M(U) diverges), Newton steps, full evaluations, residual and wall time.
   The alternative, in the same run: the plain (undamped) fixed-point iteration U <- M(U), its
   residual after as many evaluations as Newton used.
2. ``scenes``: every bundled scene designed uncoupled (``coupling = "none"``) and coupled (the
   default): the design residual and its error bar, the median flow speed at the cilia, the rms
   and largest change of the layout's chi_N, and the residual that the uncoupled layout has in the
   coupled model (what ignoring the coupling costs).
3. ``large``: uniform_deflection at n x n (default 30 and 100), designed coupled (the scene's
   default: design and coupling solve) against uncoupled, each in a fresh process: wall time and
   peak memory (maxrss).
4. ``renders``: bundled scenes rendered coupled (their default) and uncoupled side by side, each
   in a fresh process (the command line a user runs): wall time, the stages' seconds, and the
   path lines' beats (a coupled flow is slower, so its tracers need more beats to cross).
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from single_cilium.table import ThrustTable  # noqa: E402

from ciliary_carpet.carpet import layout  # noqa: E402
from ciliary_carpet.carpet.carpet import Carpet, CycleMean  # noqa: E402
from ciliary_carpet.carpet.coupling import couple, coupling_estimate  # noqa: E402
from ciliary_carpet.scenes.assembly import design  # noqa: E402
from ciliary_carpet.scenes.scene import load_scene  # noqa: E402

OUT: list[str] = []


def say(s: str = "") -> None:
    print(s, flush=True)
    OUT.append(s)


def load() -> str:
    return " / ".join(f"{v:.1f}" for v in os.getloadavg())


def plain_iteration(carpet: Carpet, evaluations: int) -> float:
    """Residual of U <- M(U) after ``evaluations`` evaluations of M (from U = 0)."""
    U = np.zeros((carpet.n, 2))
    res = math.nan
    for _ in range(evaluations):
        try:
            M = replace(carpet, background=U).others_mean_flow(tol=1e-4)[:, :2]
        except Exception:  # the iterate left the table's flow grid: the iteration has diverged
            return math.inf
        res = float(np.abs(U - M).max() / np.abs(M).max())
        U = M
    return res


def growth(table: ThrustTable, sizes) -> None:
    say("## 1. A uniform carpet of n x n cilia (spacing 2 L, chi_N = 92, free space)\n")
    say("Speeds: the others' mean flow at the cilia, median over the cilia (L/tau). 'estimate': the linear drag "
        "estimate without a flow table. 'plain': the residual of the plain iteration U <- M(U) after as many "
        "evaluations as Newton used (inf: it left the table's flow grid, i.e. diverged).\n")
    say("| n x n | uncoupled | coupled | estimate | coupled / uncoupled | abs(A B) | Newton steps | evaluations | "
        "residual | plain | wall [s] | load |")
    say("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for n in sizes:
        c = Carpet(layout.square(n, n, 2.0), 92.0, table, layout.random_phases(n * n, 0))
        est = coupling_estimate(c)
        r = couple(c)
        ch = r.change()
        plain = plain_iteration(c, r.evaluations) if n <= 30 else math.nan
        say(f"| {n} x {n} | {ch['median_speed_uncoupled']:.3f} | {ch['median_speed_coupled']:.3f} | "
            f"{est['median_speed_coupled']:.3f} | {ch['median_speed_coupled'] / ch['median_speed_uncoupled']:.3f} | "
            f"{r.contraction:.2f} | {r.iterations} | {r.evaluations} | {r.residual:.1e} | {plain:.1e} | "
            f"{r.wall_s:.1f} | {load()} |")


def _rms_in(carpet: Carpet, d) -> float:
    """The rms residual of design ``d``'s target in ``carpet``'s mean flow (its weights)."""
    u = carpet.evaluate(d.control, CycleMean(), tol=1e-4).velocity[:, :2]
    if d.kind == "angle":
        t = d.target / np.linalg.norm(d.target, axis=1, keepdims=True)
        r = np.abs(np.arctan2(u[:, 0] * t[:, 1] - u[:, 1] * t[:, 0], (u * t).sum(1)))
    else:
        r = np.linalg.norm(u - d.target, axis=1) / np.sqrt(np.mean((d.target ** 2).sum(1)))
    w = np.ones(r.size) if d.weights is None else d.weights
    return float(np.sqrt(np.sum(w * r ** 2) / np.sum(w)))


def _scaled(scene, shape):
    return replace(scene, carpet=replace(scene.carpet, shape=tuple(shape)))


def scenes(table: ThrustTable, names, sizes=None) -> None:
    for title, items in (("## 2. The bundled scenes, designed uncoupled and coupled", names),
                         ("## 3. uniform_deflection at larger sizes", sizes or [])):
        if not items:
            continue
        say(f"\n{title}\n")
        say("Residual: the design's rms residual (rad for angle targets) +- its error bar; 'in coupled': the uncoupled "
            "layout's residual in the coupled model; speeds: median others' mean flow at the cilia (L/tau); "
            "chi_N change: rms / largest over the cilia.\n")
        say("| scene | cilia | uncoupled residual | coupled residual | uncoupled layout in coupled | speed uncoupled | "
            "speed coupled | chi_N change rms / max | design s uncoupled / coupled | load |")
        say("|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
        for item in items:
            name, shape = (item, None) if isinstance(item, str) else item
            sc = load_scene(ROOT / "designs" / f"{name}.toml")
            if shape is not None:
                sc = _scaled(sc, shape)
            t0 = time.perf_counter()
            d0, c0 = design(replace(sc, carpet=replace(sc.carpet, coupling="none")), table=table)
            t_u = time.perf_counter() - t0
            ccp = replace(c0, coupling="mean")
            in_cpl = _rms_in(ccp, d0) if d0 is not None else math.nan
            ch0 = ccp.coupled.change()
            if shape is not None and shape[0] * shape[1] > 2000:  # the coupled design is not run at this size
                say(f"| {name} {shape[0]}x{shape[1]} | {c0.n} | {d0.residual_rms:.4f} +- {d0.residual_error:.4f} | - | "
                    f"{in_cpl:.4f} | {ch0['median_speed_uncoupled']:.3f} | {ch0['median_speed_coupled']:.3f} | - | "
                    f"{t_u:.0f} / - (coupling {ccp.coupled.wall_s:.0f} s) | {load()} |")
                continue
            scc = replace(sc, carpet=replace(sc.carpet, coupling="mean"))
            t0 = time.perf_counter()
            d1, c1 = design(scc, table=table)
            t_c = time.perf_counter() - t0
            dchi = d1.chi_N - d0.chi_N
            label = name if shape is None else f"{name} {shape[0]}x{shape[1]}"
            say(f"| {label} | {c0.n} | {d0.residual_rms:.4f} +- {d0.residual_error:.4f} | "
                f"{d1.residual_rms:.4f} +- {d1.residual_error:.4f} | {in_cpl:.4f} | "
                f"{ch0['median_speed_uncoupled']:.3f} | {c1.coupled.change()['median_speed_coupled']:.3f} | "
                f"{np.sqrt(np.mean(dchi ** 2)):.2f} / {np.abs(dchi).max():.2f} | {t_u:.0f} / {t_c:.0f} | {load()} |")


def _in_fresh_process(code: str) -> dict:
    """Run python ``code`` (it prints one JSON line last) in a fresh process and return that."""
    import json

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


_LARGE = """
import json, time
from dataclasses import replace


def peak_gb():  # this process's peak resident memory: VmHWM (ru_maxrss keeps the forking parent's)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1e6
from ciliary_carpet.scenes.scene import load_scene
from ciliary_carpet.scenes.assembly import design
sc = load_scene("designs/uniform_deflection.toml")
sc = replace(sc, carpet=replace(sc.carpet, shape=({n}, {n}), coupling="{coupling}"))
t0 = time.perf_counter()
d, c = design(sc)
w = time.perf_counter() - t0
cp = c.coupled
print(json.dumps({{"wall": w, "rms": d.residual_rms, "err": d.residual_error, "met": bool(d.residual_rms <= 0.05),
                  "coupling_s": cp.wall_s if cp else None, "steps": cp.iterations if cp else None,
                  "evals": cp.evaluations if cp else None, "residual": cp.residual if cp else None,
                  "peak": peak_gb()}}))
"""


def large(sizes) -> None:
    say("\n## 3. uniform_deflection at larger sizes: designed coupled (the default) against uncoupled\n")
    say("Each run in a fresh process (its import and table load included); 'peak' is its peak resident memory "
        "(VmHWM). 'coupling': "
        "the final carpet's coupled solve (Newton steps, evaluations of M, residual, seconds); the design's "
        "full-model checks each solve it too, from the last solution.\n")
    say("| cilia | model | design wall [s] | peak [GB] | residual +- error [rad] | coupling: steps / evals / residual "
        "/ s | load |")
    say("|---|---|---:|---:|---|---|---|")
    for n in sizes:
        for coupling in ("none", "mean"):
            r = _in_fresh_process(_LARGE.format(n=n, coupling=coupling))
            peak = r["peak"]
            cp = "-" if r["steps"] is None else (f"{r['steps']} / {r['evals']} / {r['residual']:.1e} / "
                                                  f"{r['coupling_s']:.0f}")
            say(f"| {n} x {n} | {'coupled' if coupling == 'mean' else 'uncoupled'} | {r['wall']:.0f} | {peak:.2f} | "
                f"{r['rms']:.4f} +- {r['err']:.4f} | {cp} | {load()} |")


def renders(names) -> None:
    import json
    import tempfile

    say("\n## 4. Bundled renders, coupled (the default) against uncoupled, side by side\n")
    say("`ciliary-carpet render designs/NAME.toml` in a fresh process, the uncoupled one with `[carpet] coupling = "
        "\"none\"` added; wall time of the command, the summary's stage seconds, and the path lines' duration in "
        "beats (chosen to cross the carpet at its mean speed: the coupled flow is slower).\n")
    say("| scene | model | wall [s] | table [s] | design [s] | path lines [s] | beats | s / beat | other [s] | "
        "ratio | load |")
    say("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for name in names:
        text = (ROOT / "designs" / f"{name}.toml").read_text()
        row = {}
        with tempfile.TemporaryDirectory() as tmp:
            for model in ("none", "mean"):
                src = Path(tmp) / f"{name}_{model}.toml"
                src.write_text(text.replace("[carpet]\n", f"[carpet]\ncoupling = \"{model}\"\n", 1))
                out = Path(tmp) / f"out_{model}"
                t0 = time.perf_counter()
                subprocess.run(["ciliary-carpet", "render", str(src), "-o", str(out)], check=True, capture_output=True,
                               cwd=ROOT)
                wall = time.perf_counter() - t0
                s = json.loads((out / "summary.json").read_text())
                sec = s["seconds"]
                beats = s.get("pathlines", {}).get("beats") or float("nan")
                pl = sec.get("pathlines", 0.0)
                other = sec["total"] - sec.get("table", 0.0) - sec.get("design", 0.0) - pl
                row[model] = wall
                ratio = "" if model == "none" else f"{wall / row['none']:.2f}"
                say(f"| {name} | {'coupled' if model == 'mean' else 'uncoupled'} | {wall:.1f} | {sec.get('table', 0):.1f} "
                    f"| {sec.get('design', 0):.1f} | {pl:.1f} | {beats:.0f} | {pl / beats:.3f} | {other:.1f} | {ratio} "
                    f"| {load()} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--table", help="a thrust table over the background flow (chi_E = 200, eta = 1); default the "
                    "shipped one")
    ap.add_argument("--sizes", type=int, nargs="+", default=[5, 10, 20, 30, 50, 100])
    ap.add_argument("--sections", nargs="+", default=["growth", "scenes", "large", "renders"])
    ap.add_argument("--large", type=int, nargs="+", default=[30, 100], help="sizes n of the n x n uniform_deflection")
    ap.add_argument("--renders", nargs="+", default=["uniform_deflection", "focusing", "standing_pump"])
    ap.add_argument("--out", type=Path)
    a = ap.parse_args()
    table = ThrustTable.default(flow=True) if a.table is None else ThrustTable.load(a.table)
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    say(f"# Coupled against uncoupled carpets ({os.cpu_count()} cores; {platform.processor() or platform.machine()})\n")
    (p0, p1), (q0, q1) = table.U_range
    say(f"- python {sys.version.split()[0]}, code git {rev}; load average {load()} at start (1 / 5 / 15 min)")
    say(f"- flow table {'shipped' if a.table is None else Path(a.table).name}: U_par in [{p0:g}, {p1:g}], U_perp in "
        f"[{q0:g}, {q1:g}], {table.ds.sizes['U_par']} x {table.ds.sizes['U_perp']} flows; evaluations at tol 1e-4 "
        "(inexact Newton: loose ones before), rtol 1e-3; the viscosity from the filaments' drag (0.653)\n")
    if "growth" in a.sections:
        growth(table, a.sizes)
    names = [p.stem for p in sorted((ROOT / "designs").glob("*.toml"))
             if "standing" not in p.stem] if "scenes" in a.sections else []
    scenes(table, names)
    if "large" in a.sections:
        large(a.large)
    if "renders" in a.sections:
        renders(a.renders)
    if a.out:
        a.out.write_text("\n".join(OUT) + "\n")


if __name__ == "__main__":
    main()
