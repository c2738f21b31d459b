"""One render's path-line stage on 1 and 2 cores (issue 23: "at least 1.7x faster on 2 cores").

The path-line stage of a render is its path lines and their end-point error estimate (the
reference run of :func:`~ciliary_carpet.transport.accuracy.pathline_error`); summary.json
``seconds["pathlines"] + seconds["pathline_error"]``. Scenes: ``designs/focusing.toml`` (10 x 10,
bundled) and the bundled uniform_deflection scene scaled to 30 x 30 (``bench_large.scaled_scene``).

Stage (default): each scene designed once in this process, then the render's own stage
(:class:`~ciliary_carpet.output.tracers.PathLinesOutput` ``.write`` into a scratch folder) run,
alternating, ``--repeat`` times each way:

* ``1 core``: in this process, one numba and one BLAS thread (``--threads 1``);
* ``2 threads, in process``: in this process, two numba threads (how a ``--threads 2`` render ran
  before the process pool);
* ``2 cores, pool``: :func:`~cilia_runtime.pool.pool_for_threads` ``(2)``: this
  process and one worker process (what ``--threads 2`` does now);
* ``2 cores, pool, no cores lent``: the same with ``lend_idle=False`` (one numba thread in each
  process throughout).

Same work: on a pool of two places the stage also runs the summary's own computations (what the
model leaves out, the coupling's size: :func:`~ciliary_carpet.output.summary.summary_tasks`)
beside the path lines, where one place makes them with its summary, after the stage. Each table
also gives the stage plus those computations where they ran after it (timed here after the stage;
from summary.json ``omissions`` + ``coupling`` for renders), so that both sides of that ratio do
the same work.

Renders (``--renders``): ``ciliary-carpet render SCENE -o DIR --threads T --overwrite`` in a fresh
process, T = 1, 2, 1, 2, ...; the stage's seconds from summary.json.

Chunks (``--chunks 100 50 25``): the serial work (one thread, in this process) of the 30 x 30
scene's path lines in chunks of these sizes, summed: what each chunk's own per-time overhead
costs.

    python benchmarks/bench_pathlines_parallel.py [--repeat 2] [--renders] [--chunks 100 50 25]
        [--scenes focusing ud30] [--modes 1 2-pool 2-threads 2-pool-nolend] [--no-stage] [--append]

Writes ``benchmarks/results/bench_pathlines_parallel.md``. The machine may be shared: the load
average is printed with each timing.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "bench_pathlines_parallel.md"
sys.path.insert(0, str(ROOT / "benchmarks"))


def _load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3]) if Path("/proc/loadavg").exists() else "?"


def _busy() -> tuple[float, float]:
    """(busy, all) CPU ticks of the whole machine so far (/proc/stat)."""
    try:
        v = [int(x) for x in Path("/proc/stat").read_text().split("\n")[0].split()[1:]]
    except (OSError, ValueError):
        return 0.0, 0.0
    idle = v[3] + (v[4] if len(v) > 4 else 0)
    return float(sum(v) - idle), float(sum(v))


def _cores_busy(before, seconds: float) -> float:
    """Cores the whole machine kept busy since ``before`` (``_busy()``) over ``seconds``."""
    b = _busy()
    return (b[0] - before[0]) / max(seconds, 1e-9) / (os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100)


def _scene_path(key: str, folder: Path) -> Path:
    if key == "focusing":
        return ROOT / "designs" / "focusing.toml"
    if key.startswith("ud"):
        import bench_large

        return bench_large.scaled_scene(int(key[2:]), folder)
    raise SystemExit(f"unknown scene {key!r} (focusing, ud30, ...)")


def _prepared(scene_path: Path):
    """The scene's plan and designed carpet, as a render makes them."""
    from ciliary_carpet.scenes.assembly import design
    from ciliary_carpet.output.plan import RenderPlan
    from ciliary_carpet.scenes.assembly import render_settings
    from ciliary_carpet.scenes.resources import check_resources
    from ciliary_carpet.scenes.scene import load_scene

    scene = load_scene(scene_path)
    d, carpet = design(scene)
    plan = RenderPlan.decide(render_settings(scene), carpet, designed=d is not None, estimate=check_resources(scene, max_seconds=1e9))
    return scene, plan, carpet, d


def _stage(plan, carpet, d, how: str) -> tuple[float, dict, float]:
    """One run of the render's path-line stage ``how`` ("1", "2-threads", "2-pool"): seconds, summary,
    and the seconds of the same work as a render's: the stage and the summary's own computations
    (:func:`~ciliary_carpet.output.summary.summary_tasks`: what the model leaves out, the coupling's
    size). A pool of two places runs them beside the path lines, inside the stage; in one place a
    render makes them with its summary, after the stage: here they are run and timed after it."""
    from ciliary_carpet.output.contract import RenderContext
    from ciliary_carpet.output.summary import summary_tasks
    from ciliary_carpet.output.tracers import PathLinesOutput
    from cilia_runtime.pool import InProcess, ProcessPool, pool_for_threads
    from cilia_runtime.threads import ThreadBudget
    from ciliary_carpet.batch import PRELOAD

    threads = 1 if how == "1" else 2
    pool = InProcess() if how == "2-threads" else pool_for_threads(threads, PRELOAD)
    if how == "2-pool-nolend":
        pool = ProcessPool(1, parent_works=True, lend_idle=False, preload=PRELOAD)
    pool.warm()  # as a render does before its design: the fork server's start is not the stage's
    with tempfile.TemporaryDirectory() as tmp, ThreadBudget(1, threads, 1).applied():
        ctx = RenderContext(plan, carpet, d, Path(tmp), Path(tmp), {}, {}, time.perf_counter(), pool=pool)
        t = time.perf_counter()
        PathLinesOutput().write(ctx)
        wall = time.perf_counter() - t
        after = [task for name, task in summary_tasks(ctx, pool_only=False) if name not in ctx.beside]
        t = time.perf_counter()
        for task in after:
            task.func(*task.args, **task.kwargs)
        same = wall + time.perf_counter() - t
    return wall, ctx.summary["pathlines"], same


MODES = ("1", "2-pool", "2-threads", "2-pool-nolend")


def stage_table(keys, repeat: int, folder: Path, modes=MODES) -> list[str]:
    lines = ["## The render's path-line stage, in one process (stage only)", "",
             "Seconds of `PathLinesOutput.write` (path lines, their files, the error estimate's reference run), "
             "each scene designed once; the ways alternate, minimum of the repeats; with each run the load "
             "average (1, 5, 15 min) before it and the cores the whole machine kept busy during it (this "
             "benchmark's own: 1 for a 1-core run, up to 2 for a pool; more means other jobs ran beside it).", "",
             "On a pool of two places the stage also runs the summary's own computations (what the model "
             "leaves out, the coupling's size: `summary.summary_tasks`) beside the path lines; in one place a "
             "render makes them with its summary. *Same work*: the stage plus those computations where they "
             "ran after it (timed here after the stage), so that both sides of a ratio do the same work.", "",
             "| scene | tracers | 1 core | 2 threads, in process (before) | 2 cores, pool (now) | "
             "2 cores, pool, no cores lent | ratio before | ratio now | ratio no lending | "
             "same work: 1 core | same work: 2 cores, pool | same work: ratio | runs (load) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key in keys:
        scene, plan, carpet, d = _prepared(_scene_path(key, folder))
        best: dict = {}
        same: dict = {}
        runs = []
        for r in range(repeat):
            for how in modes:
                load, b0 = _load(), _busy()
                sec, summ, work = _stage(plan, carpet, d, how)
                busy = _cores_busy(b0, sec)
                best[how] = min(best.get(how, float("inf")), sec)
                same[how] = min(same.get(how, float("inf")), work)
                runs.append(f"{how} {sec:.1f} s, same work {work:.1f} s ({load}; {busy:.1f} cores busy)")
                print(f"{key} {how}: {sec:.1f} s (same work {work:.1f} s)  load {load}  machine busy {busy:.2f} "
                      f"cores  work {summ['work']}  ref {summ['end_point_error'].get('work')}  "
                      f"parallel {summ['parallel']}", flush=True)
        def f(how, ratio=False, d=best):
            if how not in d or (ratio and "1" not in d):
                return "-"
            return f"{d['1'] / d[how]:.2f}" if ratio else f"{d[how]:.1f}"

        lines.append(f"| {key} ({scene.carpet.shape[0]} x {scene.carpet.shape[1]}) | {plan.seeds.shape[0]} | "
                     f"{f('1')} | {f('2-threads')} | {f('2-pool')} | {f('2-pool-nolend')} | {f('2-threads', True)} | "
                     f"{f('2-pool', True)} | {f('2-pool-nolend', True)} | {f('1', d=same)} | {f('2-pool', d=same)} | "
                     f"{f('2-pool', True, d=same)} | {'; '.join(runs)} |")
    return lines


def render_table(keys, repeat: int, folder: Path) -> list[str]:
    exe = Path(sys.executable).with_name("ciliary-carpet")
    base = [str(exe)] if exe.exists() else [sys.executable, "-m", "ciliary_carpet.cli"]
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    lines = ["## Whole renders (`ciliary-carpet render SCENE --threads T`)", "",
             "The path-line stage's seconds (summary.json `pathlines` + `pathline_error`) of fresh renders, "
             "T = 1 and 2 alternating, minimum of the repeats; the render's total in brackets. *Same work*: "
             "also `omissions` + `coupling` (with T = 2 they run beside the path lines, inside `pathlines`, "
             "and are 0; with T = 1 after them).", "",
             "| scene | 1 core | 2 cores | ratio | same work: 1 core | same work: 2 cores | same work: ratio | "
             "runs (load) |", "|---|---|---|---|---|---|---|---|"]
    for key in keys:
        scene = _scene_path(key, folder)
        best: dict = {}
        same: dict = {}
        runs = []
        for r in range(repeat):
            for t in (1, 2):
                out = folder / f"{key}_{t}"
                load = _load()
                p = subprocess.run(base + ["render", str(scene), "-o", str(out), "--threads", str(t), "--overwrite",
                                           "--json"], capture_output=True, text=True, env=env, cwd=ROOT)
                if p.returncode:
                    raise SystemExit(p.stderr)
                s = json.loads((out / "summary.json").read_text())["seconds"]
                sec = s["pathlines"] + s["pathline_error"]
                work = sec + s.get("omissions", 0.0) + s.get("coupling", 0.0)
                best[t] = min(best.get(t, float("inf")), sec)
                same[t] = min(same.get(t, float("inf")), work)
                runs.append(f"T={t} {sec:.1f} s, same work {work:.1f} s [{s['total']:.0f} s] ({load})")
                print(f"render {key} --threads {t}: stage {sec:.1f} s, total {s['total']:.1f} s, load {load}",
                      flush=True)
        lines.append(f"| {key} | {best[1]:.1f} | {best[2]:.1f} | {best[1] / best[2]:.2f} | {same[1]:.1f} | "
                     f"{same[2]:.1f} | {same[1] / same[2]:.2f} | {'; '.join(runs)} |")
    return lines


def chunk_table(sizes, folder: Path) -> list[str]:
    import numba
    from threadpoolctl import threadpool_limits

    from ciliary_carpet.transport.accuracy import PATHLINE_ATOL, PATHLINE_RTOL, PATHLINE_TOL
    from ciliary_carpet.transport.flow import ResolvedFlow
    from ciliary_carpet.transport.pathlines import pathlines

    scene, plan, carpet, d = _prepared(_scene_path("ud30", folder))
    flow = ResolvedFlow(carpet, min(scene.tolerance, PATHLINE_TOL))
    kw = dict(rtol=PATHLINE_RTOL, atol=PATHLINE_ATOL * scene.carpet.spacing,
              samples_per_period=scene.output.samples_per_period, domain=plan.domain)
    lines = ["## Serial work of the 30 x 30 path lines in chunks", "",
             f"{plan.seeds.shape[0]} tracers over {plan.duration:.1f} time units, one numba and one BLAS thread, "
             "in this process; each chunk its own integration (`pathlines(..., chunk_size=n)`); work = the "
             "chunks' seconds summed.", "",
             "| chunk size | chunks | work [s] | x one chunk | evaluations | steps (substeps) | load |",
             "|---|---|---|---|---|---|---|"]
    first = None
    numba.set_num_threads(1)
    with threadpool_limits(1, user_api="blas"):
        for size in sizes:
            load = _load()
            pl = pathlines(flow, plan.seeds, (0.0, plan.duration), chunk_size=size, **kw)
            st = pl.stats
            first = first or st["seconds"]
            lines.append(f"| {size} | {st['chunks']} | {st['seconds']:.1f} | {st['seconds'] / first:.2f} | "
                         f"{st['evaluations']} | {st['steps']} ({st['substeps']}) | {load} |")
            print(lines[-1], flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["focusing", "ud30"])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES, help="ways of the stage table")
    ap.add_argument("--renders", action="store_true", help="also whole renders in fresh processes")
    ap.add_argument("--no-stage", action="store_true", help="skip the stage-only table")
    ap.add_argument("--chunks", nargs="*", type=int, default=[], help="chunk sizes of the serial-work table")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--append", action="store_true", help="add the tables to --out (after a header line)")
    a = ap.parse_args()
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True,
                           cwd=ROOT).stdout.strip()
    head = ["# Path-line stage on 1 and 2 cores (bench_pathlines_parallel.py)", "",
            f"- machine: {os.cpu_count()} cores, {platform.processor() or platform.machine()}, {platform.platform()}",
            f"- python {platform.python_version()}; code: git {rev}{' (modified)' if dirty else ''}",
            f"- load average at start: {_load()} (the machine may be shared: see each run's)", ""]
    body: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if not a.no_stage:
            body += stage_table(a.scenes, a.repeat, folder, a.modes) + [""]
        if a.renders:
            body += render_table(a.scenes, a.repeat, folder) + [""]
        if a.chunks:
            body += chunk_table(a.chunks, folder) + [""]
    text = "\n".join(head + body)
    print(text)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if a.append and a.out.exists():
        text = a.out.read_text().rstrip("\n") + "\n\n" + "\n".join(
            [f"(appended: git {rev}{' (modified)' if dirty else ''}, load average at start {_load()})", ""] + body)
    a.out.write_text(text)


if __name__ == "__main__":
    main()
