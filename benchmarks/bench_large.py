"""Large carpets at the speed of their parts (issue 23): the bundled uniform_deflection scene scaled
to 30 x 30 and 100 x 100 cilia, and the field outputs of a 30 x 30 carpet on a 400 x 400 grid.

Renders (``--sizes 30 100``): ``designs/uniform_deflection.toml`` with ``[carpet] shape = [n, n]``
(every other key as bundled, default outputs) rendered as a user runs it,
``ciliary-carpet render SCENE -o DIR --threads T`` in a fresh process under ``/usr/bin/time -v``
(peak memory: its maximum resident set size). The table gives the render's stage times
(summary.json ``seconds``), its total, the peak memory, the end-point error estimate the summary
reports (``pathline_error``), and a reference error: the end points of the same tracers the
estimate uses, read from the rendered ``pathlines.vtp``, against a check run finer than the
estimate's reference in every setting (flow tolerance :data:`FINE_TOL`, a third of the
reference's, local error test atol :data:`FINE_ATOL` x the spacing and rtol :data:`FINE_RTOL`
as the reference's, the step cap halved), which checks that the estimate holds.

Fields (``--fields``): a 30 x 30 designed carpet, the scene's field box on a 400 x 400 grid: the
mean field and 10 snapshots by the toolkit (``Carpet.evaluate`` at the scene's tolerance), by
the resolved sum (``tol = 0``: every source of every cilium, the plain dense sum) and by the FMM
backend (``fmm3dpy``, the singular Stokeslet, the carpet's regularised one has no FMM: the
resolved sources through :func:`~ciliary_carpet.carpet.traversal.dense_sum`), in the same run.
The resolved sum over 160 000 points (10^11 pairs for the mean field) is evaluated on every
``--stride``-th point and its time scaled to the whole grid (a dense sum's time is linear in
its targets); the errors are measured on those points against it, relative to the field's
largest speed. The FMM runs on those points only (it does not scale linearly: its cost is the
sources' tree), and not for the mean field (:data:`FMM_MEAN`).

Decomposition (``--decompose N``): on the N x N carpet, the estimate's 8 tracers integrated in
one process at several settings (flow tolerance, rtol, atol, step cap), each against the finest
(the check run above: flow tol 1e-5, rtol 1e-10, atol 1e-8 x spacing, the cap halved): where the end-point error comes
from, and what each setting costs (single-threaded runs, one after another).

    python benchmarks/bench_large.py [--sizes 30 100] [--threads 2] [--fields] [--no-reference]
        [--decompose 30] [--cache DIR]

``--cache DIR`` keeps the check runs' end points (``check_N.npy``) and reuses them.

Writes ``benchmarks/results/bench_large.md`` (the sections run).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCENE = ROOT / "designs" / "uniform_deflection.toml"
OUT = ROOT / "benchmarks" / "results" / "bench_large.md"
FINE_TOL = 1e-5
"""Flow tolerance of the check run (the estimate's reference uses the path lines' tenth)."""
FINE_ATOL = 1e-8
"""Local error test of the check run, times the spacing [L] (the estimate's reference's; until
stop 33 the render's 1e-7, which left the check run coarser than the reference there)."""
FINE_RTOL = 1e-10
DECOMPOSE = ((1e-3, 1e-6, 1e-4, 1), (1e-3, 1e-9, 1e-7, 1), (3e-4, 1e-9, 1e-7, 1), (1e-4, 1e-6, 1e-4, 1),
             (1e-4, 1e-8, 1e-6, 1), (1e-4, 1e-9, 1e-7, 1), (3e-5, 1e-10, 1e-8, 1), (1e-3, 1e-6, 1e-4, 2))
"""(flow tol, rtol, atol / spacing, cap divisor) of the decomposition: the settings before (first),
tighter integration, tighter flow, the render's now (1e-4, 1e-9, 1e-7), the estimate's reference."""
FMM_MEAN = ("not run: its 3.7 million sources (64 phase samples) took more than 20 GB in fmm3dpy for 10^4 "
            "targets on this machine (killed); a snapshot's 58 500 took 2.4 GB and 13 s")
STAGES = ("design", "coupling", "mean_field", "snapshots", "frames", "pathlines", "pathline_error", "ftle", "preview",
          "omissions", "total")


def _load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"


def scaled_scene(n: int, folder: Path, field: int | None = None) -> Path:
    """The bundled uniform_deflection scene with ``shape = [n, n]`` (and ``field_shape = [field,
    field]`` if given), written into ``folder``."""
    text = SCENE.read_text()
    text, k = re.subn(r"^shape = \[10, 10\]", f"shape = [{n}, {n}]", text, flags=re.M)
    if field is not None:
        text, k2 = re.subn(r"^field_shape = \[\d+, \d+\]", f"field_shape = [{field}, {field}]", text, flags=re.M)
        k = k * k2
    if k != 1:
        raise RuntimeError(f"{SCENE}: no 'shape = [10, 10]' (or 'field_shape') line to scale")
    text = re.sub(r'^name = "uniform_deflection"', f'name = "uniform_deflection_{n}x{n}"', text, flags=re.M)
    path = folder / f"uniform_deflection_{n}.toml"
    path.write_text(text)
    return path


def render(scene: Path, out: Path, threads: int) -> tuple[dict, float, float]:
    """Render ``scene`` in a fresh process: its summary, wall seconds and peak memory [GB]."""
    exe = Path(sys.executable).with_name("ciliary-carpet")
    cmd = ([str(exe)] if exe.exists() else [sys.executable, "-m", "ciliary_carpet.cli"])
    cmd += ["render", str(scene), "-o", str(out), "--threads", str(threads), "--overwrite", "--json"]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-v"] + cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise RuntimeError(f"render of {scene} failed:\n{p.stderr[-3000:]}")
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    summary = json.loads((out / "summary.json").read_text())
    return summary, wall, (int(rss.group(1)) / 1024 ** 2 if rss else float("nan"))


def _vtp_end_points(path: Path) -> np.ndarray:
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(path))
    r.Update()
    pd = r.GetOutput()
    pts = vtk_to_numpy(pd.GetPoints().GetData())
    lines = pd.GetLines()
    offsets = vtk_to_numpy(lines.GetOffsetsArray())
    conn = vtk_to_numpy(lines.GetConnectivityArray())
    return pts[conn[offsets[1:] - 1]]


def _design(scene_path: Path):
    """The designed carpet, the plan and the spacing of a scene file."""
    from ciliary_carpet.cli import _scene
    from ciliary_carpet.scenes.assembly import design
    from ciliary_carpet.output.plan import RenderPlan
    from ciliary_carpet.scenes.assembly import render_settings
    from ciliary_carpet.scenes.resources import check_resources

    scene = _scene(str(scene_path), False, None)
    _, c = design(scene)
    return c, RenderPlan.decide(render_settings(scene), c, designed=True, estimate=check_resources(scene)), scene.carpet.spacing


def _fine(c, seeds, duration: float, spacing: float, cache: Path | None, n: int) -> tuple[np.ndarray, float]:
    """End points of the check run (module docstring) from ``seeds``, and its seconds (0 when cached)."""
    from ciliary_carpet.transport.flow import ResolvedFlow
    from ciliary_carpet.transport.pathlines import pathlines

    f = cache / f"check_{n}.npy" if cache is not None else None
    if f is not None and f.exists():
        return np.load(f), 0.0
    flow = ResolvedFlow(c, FINE_TOL)
    t = time.perf_counter()
    ref = pathlines(flow, seeds, (0.0, duration), rtol=FINE_RTOL, atol=FINE_ATOL * spacing,
                    samples_per_period=1, max_step=flow.step_cap / 2)
    seconds = time.perf_counter() - t
    if f is not None:
        np.save(f, ref.end_points)
    return ref.end_points, seconds


def decompose(n: int, cache: Path | None) -> str:
    """Where the end-point error of the estimate's tracers comes from (module docstring)."""
    from ciliary_carpet.transport.accuracy import error_tracers
    from ciliary_carpet.transport.flow import ResolvedFlow
    from ciliary_carpet.transport.pathlines import pathlines
    from numba import set_num_threads

    set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        c, plan, sp = _design(scaled_scene(n, Path(tmp)))
    seeds = plan.seeds[error_tracers(plan.seeds.shape[0])]
    fine, fs = _fine(c, seeds, plan.duration, sp, cache, n)
    cap = ResolvedFlow(c).step_cap
    rows = ["| flow tol | rtol | atol [L] | step cap | max error [L] | median [L] | steps / substeps / rejected "
            "| seconds |", "|---|---|---|---|---|---|---|---|"]
    for tol, rtol, atol, div in DECOMPOSE:
        t = time.perf_counter()
        pl = pathlines(ResolvedFlow(c, tol), seeds, (0.0, plan.duration), rtol=rtol, atol=atol * sp,
                       samples_per_period=1, max_step=cap / div)
        sec = time.perf_counter() - t
        e = np.linalg.norm(pl.end_points - fine, axis=1)
        st = pl.stats
        rows.append(f"| {tol:g} | {rtol:g} | {atol * sp:g} | T/{16 * div:g} | {e.max():.2e} | {np.median(e):.2e} | "
                    f"{st['steps']} / {st['substeps']} / {st['rejected']} | {sec:.1f} |")
        print(rows[-1], flush=True)
    return (f"## Where the end-point error comes from: {n} x {n}, the estimate's {seeds.shape[0]} tracers over "
            f"{plan.duration / plan.beat.period:.0f} beats\n\nAgainst the check run (flow tol {FINE_TOL:g}, rtol "
            f"{FINE_RTOL:g}, atol {FINE_ATOL * sp:g} L, cap T/32{'; %.0f s' % fs if fs else ', cached'}); one thread, "
            f"load average {_load()} at the end (the seconds compare settings only roughly).\n\n"
            + "\n".join(rows) + "\n")


def reference_error(scene_path: Path, out: Path, cache: Path | None, n: int) -> tuple[float, float, float]:
    """The rendered end points of the estimate's tracers against the check run (module docstring):
    max and median distance [L] and the seconds it took."""
    from ciliary_carpet.transport.accuracy import error_tracers

    c, plan, sp = _design(scene_path)
    idx = error_tracers(plan.seeds.shape[0])
    fine, seconds = _fine(c, plan.seeds[idx], plan.duration, sp, cache, n)
    e = np.linalg.norm(_vtp_end_points(out / "pathlines.vtp")[idx] - fine, axis=1)
    return float(e.max()), float(np.median(e)), seconds


def renders(sizes, threads: int, reference: bool, cache: Path | None) -> str:
    rows = ["| carpet | " + " | ".join(STAGES) + " | wall (process) | peak memory | end-point error estimate "
            "(max / median) | reference error (max / median; check run s) | load before / after |",
            "|---|" + "---|" * len(STAGES) + "---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            scene = scaled_scene(n, Path(tmp))
            out = Path(tmp) / f"out{n}"
            before = _load()
            s, wall, gb = render(scene, out, threads)
            after = _load()
            sec = s["seconds"]
            e = s["pathlines"]["end_point_error"]
            ref = "not run"
            if reference:
                mx, md, rs = reference_error(scene, out, cache, n)
                ref = f"{mx:.2e} / {md:.2e} ({f'{rs:.0f} s' if rs else 'cached'})"
            rows.append(f"| {n} x {n} | " + " | ".join(_stage(sec, k) for k in STAGES)
                        + f" | {wall:.1f} | {gb:.2f} GB | {e['max']:.2e} / {e['median']:.2e} | {ref} | "
                        f"{before} / {after} |")
            print(rows[-1], flush=True)
    return ("## Renders: uniform_deflection scaled (seconds by stage, `--threads "
            f"{threads}`; `(b)`: ran beside the path lines, in a worker of their pool)\n\n" + "\n".join(rows) + "\n")


def _stage(sec: dict, k: str) -> str:
    """A stage's seconds, or those it took beside the path lines (``(b)``: the summary's
    computations that ran in the path lines' pool, ``ciliary_carpet.output.summary.summary_tasks``)."""
    b = sec.get(f"{k}_beside_pathlines")
    return f"{b:.1f} (b)" if b is not None else f"{sec.get(k, float('nan')):.1f}"


def fields(stride: int) -> str:
    """The 400 x 400 mean field and 10 snapshots of a 30 x 30 carpet: toolkit, resolved sum, FMM."""
    from ciliary_carpet.carpet.carpet import CycleMean, Instant
    from ciliary_carpet.carpet.blocks import ResolvedSources
    from ciliary_carpet.carpet.traversal import dense_sum
    from ciliary_carpet.cli import _scene
    from ciliary_carpet.scenes.assembly import design
    from ciliary_carpet.output.plan import RenderPlan
    from ciliary_carpet.scenes.assembly import render_settings
    from ciliary_carpet.scenes.resources import check_resources
    from ciliary_carpet.stokes import FMM, Stokeslet
    from ciliary_carpet.stokes.fmm import fmm_available

    with tempfile.TemporaryDirectory() as tmp:
        scene = _scene(str(scaled_scene(30, Path(tmp), field=400)), False, None)
    _, c = design(scene)
    plan = RenderPlan.decide(render_settings(scene), c, designed=True, estimate=check_resources(scene))
    pts = plan.grid.points()
    sub = np.arange(0, pts.shape[0], stride)
    tol, n_snap, Tb = scene.tolerance, 10, plan.beat.period
    whens = [("mean field", CycleMean())] + [(f"snapshot {k}", Instant(k * Tb / n_snap)) for k in range(n_snap)]
    fmm = FMM(eps=1e-6) if fmm_available() else None
    rows = ["| field | toolkit s (tol %g, 160 000 points) | toolkit max error | resolved sum s (scaled from %d "
            "points) | FMM s (eps 1e-6, on the %d points only) | FMM max error | max speed |" % (tol, sub.size, sub.size),
            "|---|---|---|---|---|---|---|"]
    tot = np.zeros(3)
    for name, when in whens:
        t = time.perf_counter()
        s = c.evaluate(pts, when, tol=tol)
        t_kit = time.perf_counter() - t
        t = time.perf_counter()
        r = c.evaluate(pts[sub], when, tol=0)
        t_res = (time.perf_counter() - t) * pts.shape[0] / sub.size
        vmax = float(np.linalg.norm(r.velocity, axis=1).max())
        e_kit = float(np.linalg.norm(s.velocity[sub] - r.velocity, axis=1).max()) / vmax
        if fmm is not None and isinstance(when, Instant):
            src = ResolvedSources(c.cycles, when.phases(c.cycles))
            js = np.nonzero(when.bounds(c.carriers).S > 0)[0]
            t = time.perf_counter()
            u = dense_sum(pts[sub], js, src, Stokeslet(), fmm, c.mu).velocity
            t_fmm = time.perf_counter() - t
            d = np.linalg.norm(u - r.velocity, axis=1) / vmax
            e_fmm = f"{d.max():.1e} (median {np.median(d):.1e})"
        else:
            t_fmm, e_fmm = float("nan"), ("fmm3dpy not installed" if fmm is None else FMM_MEAN)
        tot += (t_kit, t_res, 0.0 if np.isnan(t_fmm) else t_fmm)
        rows.append(f"| {name} | {t_kit:.2f} | {e_kit:.1e} | {t_res:.1f} | {t_fmm:.1f} | {e_fmm} | {vmax:.3g} |")
        print(rows[-1], flush=True)
    rows.append(f"| **all 11** | **{tot[0]:.1f}** | | **{tot[1]:.0f}** | **{np.nansum(tot[2]):.1f}** (snapshots) "
                "| | |")
    return ("## Fields: 30 x 30 carpet, 400 x 400 grid (the scene's field box)\n\nErrors relative to the "
            "field's largest speed, on the points the resolved sum was evaluated at; the FMM sums the "
            "singular Stokeslet, so its error near the filaments is the regularisation it leaves out.\n\n"
            + "\n".join(rows) + "\n")


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[30, 100])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--fields", action="store_true", help="also the 400 x 400 field comparison")
    ap.add_argument("--stride", type=int, default=64, help="resolved sum on every stride-th grid point")
    ap.add_argument("--no-reference", action="store_true", help="skip the finer check run of the end points")
    ap.add_argument("--decompose", type=int, default=None, help="the error decomposition on this carpet size")
    ap.add_argument("--cache", type=Path, default=None, help="keep and reuse the check runs' end points here")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    parts = [f"# Large carpets (issue 23)\n\nMachine: {platform.processor() or platform.machine()}, "
             f"{os.cpu_count()} cores, Python {platform.python_version()}; load average at the start {_load()}.\n"]
    if a.sizes:
        parts.append(renders(a.sizes, a.threads, not a.no_reference, a.cache))
    if a.decompose:
        parts.append(decompose(a.decompose, a.cache))
    if a.fields:
        parts.append(fields(a.stride))
    text = "\n".join(parts)
    a.out.write_text(text)
    return text


if __name__ == "__main__":
    main()
