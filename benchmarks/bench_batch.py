"""What the batch's fault isolation costs: a fresh worker process per scene (the default of
``ciliary_carpet.batch.batch``: a dead worker fails only its own scene) against the obvious
alternative, one shared process pool (``ProcessPoolExecutor``: one dead worker breaks the pool
and every scene still queued), on the same small scenes; plus the cost of the up-front checks
(``check_resources``) against a render.

    python benchmarks/bench_batch.py [--scenes 6] [--jobs 2] [--repeat 2] [--shape 3] [--field 12] [--out FILE]

Writes ``benchmarks/results/bench_batch.md``.

``--bundled``: the bundled scenes as a default batch against their solo renders, in the same run
and as a user runs them (the command line, each in a fresh process): ``ciliary-carpet render``
of each scene alone (every core for one render), ``ciliary-carpet batch`` of all at the default
settings (each worker its share of the cores: processes), and the same batch with ``--jobs 1``
(one render at a time on every core: threads); each render's stage times and the threads its
summary reports, the machine's load average before and after (issue 23).

    python benchmarks/bench_batch.py --bundled [designs/focusing.toml designs/shear_layer.toml] [--no-serial] [--limit S]

Writes ``benchmarks/results/bench_batch_bundled.md``.

``--dask``: the same scenes as a batch on a local Dask cluster (``--scheduler``), its workers
as ``dask worker`` runs them (processes): one worker of as many threads as cores against as many
workers of one thread each, and threads of the scheduler's own process (what tests use); each
run's wall time, the renders' totals and the threads their summaries report.

    python benchmarks/bench_batch.py --dask [designs/focusing.toml designs/shear_layer.toml] [--repeat 1]

Writes ``benchmarks/results/bench_batch_dask.md``.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

SCENE = ('[carpet]\nshape = [{n}, {n}]\nseed = {k}\n[output]\nn_seeds = 4\nperiods = 1.0\nfield_shape = [{f}, {f}]\n'
         'snapshots = 1\nframes = 2\npreview = false\n')


ROOT = Path(__file__).resolve().parent.parent
BUNDLED = ("designs/focusing.toml", "designs/shear_layer.toml")


def _cli(*args, limit: float | None = None) -> float | None:
    """Run ``ciliary-carpet ARGS`` in a fresh process; its wall time (s), None past ``limit`` s."""
    t = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, "-m", "ciliary_carpet.cli", *map(str, args)], capture_output=True,
                           text=True, cwd=ROOT, timeout=limit)
    except subprocess.TimeoutExpired:
        return None
    took = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"ciliary-carpet {' '.join(map(str, args))} failed ({r.returncode}): {r.stderr[-2000:]}")
    return took


def _summary(folder: Path) -> dict | None:
    f = folder / "summary.json"
    return json.loads(f.read_text()) if f.is_file() else None


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def bundled(scenes: list[str], serial: bool, out: str | None, limit: float | None) -> None:
    """The bundled scenes: the default batch, the solo renders, the batch with --jobs 1; the
    table is rewritten after each run (so a run stopped at ``limit`` s still leaves the others)."""
    from ciliary_carpet.scenes.scene import load_scene
    from cilia_runtime.threads import ThreadBudget, cores

    names = [load_scene(ROOT / s).name for s in scenes]
    root = Path(tempfile.mkdtemp(prefix="bench_batch_bundled."))
    out = out or str(Path(__file__).parent / "results" / "bench_batch_bundled.md")
    load_before = _load()
    b = ThreadBudget.for_batch(len(scenes))
    runs = [("`batch` at the default settings", "batch", [])]
    runs += [(f"`render` {n} alone", "render", [s, n]) for s, n in zip(scenes, names)]
    if serial:
        runs.append(("`batch --jobs 1` (one render at a time, every core)", "batch", ["--jobs", "1"]))
    wall: dict = {}
    stages: list = []

    def write() -> None:
        solo = [wall.get(f"`render` {n} alone") for n in names]
        total = sum(solo) if all(w is not None for w in solo) and len(solo) == len(names) else None
        lines = [f"# bench_batch --bundled: {', '.join(scenes)}", "",
                 f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {cores()} cores "
                 f"({os.cpu_count()} in the machine), load average {load_before} before, {_load()} at the last run's "
                 f"end (1, 5, 15 min; the machine was shared with other jobs while this ran, so absolute times are "
                 f"inflated and noisy); the default batch here: {b.workers} workers x {b.numba} numba threads x "
                 f"{b.blas} BLAS thread; a solo render uses every core.", "",
                 "| run | wall s | ratio to the sum of the solo renders |", "|---|---|---|"]
        for label, _, _ in runs:
            if label not in wall:
                continue
            w = wall[label]
            ws = f"> {limit:.0f} (stopped)" if w is None else f"{w:.1f}"
            ratio = "" if w is None or total is None or label.startswith("`render`") else f"{w / total:.2f}"
            lines.append(f"| {label} | {ws} | {ratio} |")
        if total is not None:
            lines.append(f"| sum of the solo renders | {total:.1f} | 1.00 |")
        keys = sorted({k for _, sec, _ in stages for k in sec if k != "total"})
        lines += ["", "Each render's stages (s, from its summary.json) and the threads it reports:", "",
                  "| render | " + " | ".join(keys) + " | total | threads (numba, BLAS, workers) |",
                  "|---" * (len(keys) + 3) + "|"]
        for label, sec, th in stages:
            t = "" if th is None else f"{th['numba']}, {th['blas']}, {th['workers']}"
            lines.append(f"| {label} | " + " | ".join(f"{sec[k]:.1f}" if k in sec else "" for k in keys)
                         + f" | {sec['total']:.1f} | {t} |")
        text = "\n".join(lines) + "\n"
        print(text, flush=True)
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(text)

    try:
        for k, (label, cmd, extra) in enumerate(runs):
            folder = root / f"run{k}"
            if cmd == "render":
                wall[label] = _cli("render", extra[0], "-o", folder / extra[1], limit=limit)
                done = [extra[1]]
            else:
                wall[label] = _cli("batch", *scenes, "-o", folder, *extra, limit=limit)
                done = names
            for n in done:
                sm = _summary(folder / n)
                if sm is not None:
                    stages.append((f"{label.split('(')[0].strip()}: {n}" if cmd == "batch" else label, sm["seconds"],
                                   sm.get("threads")))
            write()
    finally:
        shutil.rmtree(root, ignore_errors=True)


def dask_runs(scenes: list[str], repeat: int, out: str | None) -> None:
    """The scenes as a batch on local Dask clusters of several shapes, alternating (``--dask``)."""
    import distributed

    from ciliary_carpet.batch import batch
    from cilia_runtime.threads import cores

    c = cores()
    shapes = [(f"1 worker process x {c} threads", dict(n_workers=1, threads_per_worker=c, processes=True)),
              (f"{c} worker processes x 1 thread", dict(n_workers=c, threads_per_worker=1, processes=True)),
              (f"{c} threads of the scheduler's process", dict(n_workers=1, threads_per_worker=c, processes=False))]
    out = out or str(Path(__file__).parent / "results" / "bench_batch_dask.md")
    lines = [f"# bench_batch --dask: {', '.join(scenes)}", "",
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {c} cores; load average {_load()} at the start.",
             "", "| cluster | wall s | renders' totals s | threads (numba, BLAS, workers) | load before |",
             "|---|---|---|---|---|"]
    for r in range(repeat):
        for label, kw in shapes:
            load = _load()
            with tempfile.TemporaryDirectory() as tmp, distributed.LocalCluster(dashboard_address=None, **kw) as cl:
                t = time.perf_counter()
                recs = batch([ROOT / s for s in scenes], Path(tmp) / "out", scheduler=cl.scheduler_address,
                             progress=False)
                wall = time.perf_counter() - t
                bad = [x for x in recs if x["status"] != "done"]
                if bad:
                    raise SystemExit(f"{label}: {bad}")
                sm = [_summary(Path(x["out_dir"])) for x in recs]
            tot = ", ".join(f"{m['seconds']['total']:.1f}" for m in sm)
            th = "; ".join(f"{m['threads']['numba']}, {m['threads']['blas']}, {m['threads']['workers']}" for m in sm)
            lines.append(f"| {label} | {wall:.1f} | {tot} | {th} | {load} |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(text)
    print(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bundled", nargs="*", default=None, metavar="SCENE",
                    help=f"the bundled scenes (default {' '.join(BUNDLED)}) as a default batch against their solo "
                         f"renders")
    ap.add_argument("--dask", nargs="*", default=None, metavar="SCENE",
                    help="the scenes (default: focusing, shear_layer) as a batch on local Dask clusters")
    ap.add_argument("--no-serial", dest="serial", action="store_false", help="with --bundled: skip the --jobs 1 batch")
    ap.add_argument("--limit", type=float, default=None, help="with --bundled: stop a run after this many seconds")
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--shape", type=int, default=3, help="carpet of SHAPE x SHAPE cilia")
    ap.add_argument("--field", type=int, default=12, help="mean and snapshot fields of FIELD x FIELD points")
    ap.add_argument("--out", default=None, help="default results/bench_batch[_SHAPE_FIELD].md")
    a = ap.parse_args()
    if a.dask is not None:
        dask_runs(a.dask or list(BUNDLED), a.repeat, a.out)
        return
    if a.bundled is not None:
        bundled(a.bundled or list(BUNDLED), a.serial, a.out, a.limit)
        return

    from ciliary_carpet.batch import batch
    from ciliary_carpet.render import check_resources, render
    from ciliary_carpet.scenes.scene import load_scene

    root = Path(tempfile.mkdtemp(prefix="bench_batch."))
    try:
        scenes = []
        for k in range(a.scenes):
            p = root / f"s{k}.toml"
            p.write_text(SCENE.format(n=a.shape, k=k, f=a.field))
            scenes.append(p)
        # the shared pool must not fork a process that has run the OpenMP kernels: measure it first
        rows = {"shared ProcessPoolExecutor (fork)": [], "process per scene (default)": []}
        for r in range(a.repeat):
            for label in rows:
                out = root / f"out-{r}-{len(rows[label])}-{label[:5]}"
                t = time.perf_counter()
                if label.startswith("shared"):
                    with ProcessPoolExecutor(a.jobs, mp_context=mp.get_context("fork")) as ex:
                        recs = batch(scenes, out, executor=ex, progress=False)
                else:
                    recs = batch(scenes, out, jobs=a.jobs, progress=False)
                rows[label].append(time.perf_counter() - t)
                assert all(x["status"] == "done" for x in recs), recs
        scene = load_scene(scenes[0])
        t = time.perf_counter()
        n = 200
        for _ in range(n):
            check_resources(scene)
        t_check = (time.perf_counter() - t) / n
        t = time.perf_counter()
        render(scene, root / "single")
        t_render = time.perf_counter() - t
    finally:
        shutil.rmtree(root, ignore_errors=True)

    base = min(rows["shared ProcessPoolExecutor (fork)"])
    lines = [f"# bench_batch: {a.scenes} scenes ({a.shape} x {a.shape} carpet, {a.field} x {a.field} field), -j {a.jobs}, "
             f"{os.cpu_count()} cores (shared with other jobs: absolute times are inflated, the ratio is "
             f"from the same run)", "",
             "| executor | wall s (min of %d) | per scene s | ratio to shared pool |" % a.repeat, "|---|---|---|---|"]
    for label, ts in rows.items():
        w = min(ts)
        lines.append(f"| {label} | {w:.2f} | {w / a.scenes:.2f} | {w / base:.2f} |")
    lines += ["", f"check_resources: {t_check * 1e6:.0f} us per scene; one render of the same scene in this "
              f"process: {t_render:.2f} s (ratio {t_check / t_render:.1e})", ""]
    text = "\n".join(lines)
    if a.out is None:
        tail = "" if (a.shape, a.field) == (3, 12) else f"_{a.shape}_{a.field}"
        a.out = str(Path(__file__).parent / "results" / f"bench_batch{tail}.md")
    print(text)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(text)


if __name__ == "__main__":
    main()
