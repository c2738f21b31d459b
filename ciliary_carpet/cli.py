"""``ciliary-carpet``: render scenes, design layouts, batch many scenes.

    ciliary-carpet render designs/NAME.toml -o out/NAME [--overwrite] [--reduced]
    ciliary-carpet design designs/NAME.toml -o layout.nc [--overwrite]
    ciliary-carpet batch designs/*.toml -o out/ [-j N] [--scheduler ADDRESS] [--overwrite] [--reduced]

Exit status: 0 success; 1 some scenes of a batch failed; 2 bad input (scene, table, target,
output folder); 3 a target the cilia cannot make.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time as _time
from concurrent.futures import Executor, ProcessPoolExecutor, as_completed
from pathlib import Path

from single_cilium._io import write_netcdf
from single_cilium.progress import TqdmProgress
from single_cilium.table import TableError

from .design import DesignError, design
from .render import RenderError, is_complete, render
from .scene import SceneError, load_scene
from .target import TargetError
from .vtkfiles import OutputError

logger = logging.getLogger(__name__)

BAD_INPUT = (SceneError, TargetError, TableError, RenderError, OutputError, FileNotFoundError, ValueError)


def _scene(path: str, reduced: bool):
    s = load_scene(path)
    return s.reduced() if reduced else s


def _cmd_render(a) -> int:
    res = render(_scene(a.scene, a.reduced), a.output, overwrite=a.overwrite, progress=TqdmProgress(delay=0.5))
    s = res.summary
    if a.json:
        print(json.dumps({"out_dir": str(res.out_dir), "files": list(res.files), "design": s.get("design"),
                          "seconds": s["seconds"]}, default=str))
    else:
        print((res.out_dir / "summary.md").read_text(), end="")
        print(f"wrote {len(res.files)} files to {res.out_dir}")
    return 0


def _cmd_design(a) -> int:
    out = Path(a.output)
    if out.exists() and not a.overwrite:
        raise RenderError(f"{out} exists; it is kept: pass --overwrite to replace it")
    scene = _scene(a.scene, a.reduced)
    d, carpet = design(scene)
    if d is None:
        raise SceneError(f"{scene.source_name}: the scene has no [target] to design for")
    write_netcdf(d.to_dataset(carpet), out)
    print(d.message)
    print(f"wrote {out}")
    return 0


def _render_one(scene_path: str, out_root: str, overwrite: bool, reduced: bool) -> dict:
    """One batch task (runs in a worker): never raises, returns a record."""
    clock = _time.perf_counter()
    rec = {"scene": scene_path}
    try:
        scene = _scene(scene_path, reduced)
        out = Path(out_root) / scene.name
        rec["out_dir"] = str(out)
        table = scene.table.path(scene)
        if is_complete(out, [scene_path, table]) and not overwrite:
            rec.update(status="skipped", message="complete and up to date")
        else:
            render(scene, out, overwrite=overwrite or (out.exists() and not is_complete(out)))
            rec.update(status="done", message="rendered")
    except Exception as exc:  # noqa: BLE001 -- one failing scene must not stop the others
        rec.update(status="failed", message=f"{type(exc).__name__}: {exc}")
    rec["seconds"] = _time.perf_counter() - clock
    return rec


def batch(scenes, out_root, *, executor: Executor | None = None, scheduler: str | None = None, jobs: int = 2,
          overwrite: bool = False, reduced: bool = False, progress: bool = True) -> list[dict]:
    """Render many scene files into ``out_root/NAME`` on ``executor`` (default: a local process
    pool of ``jobs`` workers; with ``scheduler``: a Dask distributed cluster, through
    ``Client(scheduler).get_executor()``, the same code path). Resumable: a scene whose folder
    holds a complete render newer than the scene and its table is skipped; an incomplete one
    (an interrupted render leaves only a hidden staging folder) is rendered again; one with
    older results is kept unless ``overwrite``, and reported as failed. Returns one record per
    scene (status done / skipped / failed, message, seconds)."""
    from tqdm.auto import tqdm

    own = client = None
    if executor is None:
        if scheduler is not None:
            from distributed import Client

            client = Client(scheduler)
            executor = client.get_executor()
        else:
            executor = own = ProcessPoolExecutor(max_workers=max(1, int(jobs)))
    recs = []
    try:
        futs = [executor.submit(_render_one, str(s), str(out_root), overwrite, reduced) for s in scenes]
        for f in tqdm(as_completed(futs), total=len(futs), desc="scenes", disable=not progress):
            recs.append(f.result())
    finally:
        if own is not None:
            own.shutdown()
        if client is not None:
            client.close()
    order = {str(s): k for k, s in enumerate(scenes)}
    return sorted(recs, key=lambda r: order[r["scene"]])


def _cmd_batch(a) -> int:
    recs = batch(a.scenes, a.output, scheduler=a.scheduler, jobs=a.jobs, overwrite=a.overwrite, reduced=a.reduced)
    for r in recs:
        print(f"{r['status']:8s} {r['scene']}  ({r['seconds']:.1f} s)  {r['message']}")
    n = {k: sum(r["status"] == k for r in recs) for k in ("done", "skipped", "failed")}
    print(f"{n['done']} rendered, {n['skipped']} up to date, {n['failed']} failed")
    return 1 if n["failed"] else 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("cilia-flow")
    except PackageNotFoundError:
        from single_cilium import __version__

        return __version__


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ciliary-carpet", description=__doc__.split("\n\n")[0])
    ap.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="design (if the scene has a target), run the flow, write VTK/PNG/summary")
    r.add_argument("scene")
    r.add_argument("-o", "--output", required=True, help="output folder")
    r.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    r.add_argument("--reduced", action="store_true", help="a small version of the scene (quick look)")
    r.add_argument("--json", action="store_true", help="print a JSON summary")
    d = sub.add_parser("design", help="write only the designed layout (NetCDF)")
    d.add_argument("scene")
    d.add_argument("-o", "--output", required=True, help="layout file (.nc)")
    d.add_argument("--overwrite", action="store_true")
    d.add_argument("--reduced", action="store_true")
    b = sub.add_parser("batch", help="render many scenes (process pool or Dask cluster), resumable")
    b.add_argument("scenes", nargs="+")
    b.add_argument("-o", "--output", required=True, help="output root; each scene goes to OUTPUT/NAME")
    b.add_argument("-j", "--jobs", type=int, default=2, help="local worker processes (default 2)")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:port)")
    b.add_argument("--overwrite", action="store_true")
    b.add_argument("--reduced", action="store_true")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return {"render": _cmd_render, "design": _cmd_design, "batch": _cmd_batch}[a.cmd](a)
    except DesignError as exc:
        print(f"ciliary-carpet: {exc}", file=sys.stderr)
        return 3
    except BAD_INPUT as exc:
        print(f"ciliary-carpet: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
