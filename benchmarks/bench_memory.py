"""A render's peak memory, all its processes together, against the estimate that sizes batches and
a render's places to a memory limit (``ciliary_carpet.output.resources.expected_memory``).

Each scene is rendered as a user runs it (``ciliary-carpet render SCENE -o DIR --threads T``) on
one place (``--threads 1``: the path lines in the render's process) and on two (``--threads 2``:
and a worker process, started from a fork server), inside a control group of its own made for the
run (cgroup v1 ``memory``; needs root), whose working set -- the group's usage less its inactive
file pages, what the kernel cannot reclaim before it kills -- is polled every 0.1 s: the fork
server and the worker count with the render's process, the shared libraries' pages once. The
group has no limit. Where no group can be made, it says so and stops (a process's peak resident
set would leave out the fork server and the worker).

The scenes: the bundled ones named by ``--scenes`` (default: all of ``designs/``), and the
uniform_deflection scene scaled to N x N cilia for each N of ``--sizes`` (as bench_large.py
makes them). The table gives each peak, the estimate, and their ratio (the estimate must stay
above: it is used to keep renders from being killed, so a ratio below 1 is a failure of the
model, printed as such).

    python benchmarks/bench_memory.py [--scenes focusing shear_layer] [--sizes 30 100] [--no-bundled]

Writes ``benchmarks/results/bench_memory.md``.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "bench_memory.md"
CG = Path("/sys/fs/cgroup/memory")
sys.path.insert(0, str(ROOT / "benchmarks"))


def _working_set(group: Path) -> int:
    usage = int((group / "memory.usage_in_bytes").read_text())
    inactive = 0
    for line in (group / "memory.stat").read_text().splitlines():
        k, _, v = line.partition(" ")
        if k == "total_inactive_file":
            inactive = int(v)
    return max(0, usage - inactive)


def peak(scene: Path, threads: int) -> tuple[int, float, int]:
    """Working-set peak (bytes), wall seconds and exit status of one render in a fresh group."""
    group = CG / f"bench-memory-{uuid.uuid4().hex[:8]}"
    group.mkdir()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            code = ("import os, sys; open(sys.argv[1], 'w').write(str(os.getpid()));"
                    "from ciliary_carpet.cli import main; sys.exit(main(sys.argv[2:]))")
            t0 = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-c", code, str(group / "cgroup.procs"), "render", str(scene),
                                     "-o", str(Path(tmp) / "out"), "--threads", str(threads)],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            top = 0
            while proc.poll() is None:
                try:
                    top = max(top, _working_set(group))
                except OSError:
                    pass
                time.sleep(0.1)
            return top, time.perf_counter() - t0, proc.returncode
    finally:
        for _ in range(50):  # the group empties once its last process is reaped
            try:
                group.rmdir()
                break
            except OSError:
                time.sleep(0.1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="*", default=None, help="bundled scenes (default: all)")
    ap.add_argument("--no-bundled", action="store_true")
    ap.add_argument("--sizes", nargs="*", type=int, default=[30, 100])
    a = ap.parse_args(argv)
    if os.geteuid() != 0 or not (CG / "memory.usage_in_bytes").exists():
        print("bench_memory: needs root and the cgroup v1 memory controller at /sys/fs/cgroup/memory", file=sys.stderr)
        return 2
    from bench_large import scaled_scene

    from ciliary_carpet.output.resources import expected_memory
    from ciliary_carpet.scenes.scene import load_scene

    names = [] if a.no_bundled else (a.scenes if a.scenes is not None else
                                     sorted(p.stem for p in (ROOT / "designs").glob("*.toml")))
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        paths = [ROOT / "designs" / f"{n}.toml" for n in names] + [scaled_scene(n, Path(folder)) for n in a.sizes]
        for path in paths:
            scene = load_scene(path)
            for threads in (1, 2):
                top, wall, rc = peak(path, threads)
                est = expected_memory(scene.needs(), threads)
                rows.append((scene.name, scene.carpet.n_cilia, scene.carpet.geometry, threads, top, est, wall, rc))
                flag = "" if est >= top else "  ** below the peak **"
                print(f"{scene.name} ({scene.carpet.n_cilia} cilia) on {threads}: {top / 2**20:.0f} MiB, estimate "
                      f"{est / 2**20:.0f} MiB (x {est / top:.2f}), {wall:.1f} s, exit {rc}{flag}", flush=True)
    lines = [f"# bench_memory: a render's peak memory against expected_memory", "",
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; {platform.processor() or platform.machine()}, "
             f"{os.cpu_count()} cores; `ciliary-carpet render SCENE --threads T` in a cgroup of its own, its working "
             f"set (usage less inactive file pages) polled every 0.1 s: every process of the render together.", "",
             "| scene | cilia | geometry | places | peak MiB | estimate MiB | estimate / peak | wall s | exit |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, n, geom, t, top, est, wall, rc in rows:
        lines.append(f"| {name} | {n} | {geom} | {t} | {top / 2**20:.0f} | {est / 2**20:.0f} | "
                     f"{est / top:.2f}{' (below!)' if est < top else ''} | {wall:.1f} | {rc} |")
    OUT.write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT}")
    return 0 if all(r[5] >= r[4] and r[7] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
