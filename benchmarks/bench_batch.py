"""What the batch's fault isolation costs: a fresh worker process per scene (the default of
``ciliary_carpet.cli.batch``: a dead worker fails only its own scene) against the obvious
alternative, one shared process pool (``ProcessPoolExecutor``: one dead worker breaks the pool
and every scene still queued), on the same small scenes; plus the cost of the up-front checks
(``check_resources``) against a render.

    python benchmarks/bench_batch.py [--scenes 6] [--jobs 2] [--repeat 2] [--shape 3] [--field 12] [--out FILE]

Writes ``benchmarks/results/bench_batch.md``.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

SCENE = ('[carpet]\nshape = [{n}, {n}]\nseed = {k}\n[output]\nn_seeds = 4\nperiods = 1.0\nfield_shape = [{f}, {f}]\n'
         'snapshots = 1\nframes = 2\npreview = false\n')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--shape", type=int, default=3, help="carpet of SHAPE x SHAPE cilia")
    ap.add_argument("--field", type=int, default=12, help="mean and snapshot fields of FIELD x FIELD points")
    ap.add_argument("--out", default=None, help="default results/bench_batch[_SHAPE_FIELD].md")
    a = ap.parse_args()

    from ciliary_carpet.cli import batch
    from ciliary_carpet.render import check_resources, render
    from ciliary_carpet.scene import load_scene

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
