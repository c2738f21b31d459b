"""``ciliary-carpet``: render scenes, design layouts, batch many scenes.

    ciliary-carpet render designs/NAME.toml -o out/NAME [--overwrite] [--reduced] [--json]
    ciliary-carpet design designs/NAME.toml -o layout.nc [--overwrite]
    ciliary-carpet reach designs/PROGRAM.toml [--json]
    ciliary-carpet batch designs/*.toml -o out/ [-j N] [--scheduler ADDRESS [--scheduler-timeout S]] [--overwrite]
                         [--reduced] [--json]

A program scene (``[[state]]``: one layout for several field strengths) renders into a folder per
state with ``program.md`` beside them; ``design`` writes its layout; ``reach`` says, before any
design, what pairs of flows its cilia can make in its fields.

Options before the command: ``--debug`` (show the traceback of a failure), ``--allow-outside-paths``
(let scene files name table and target files outside their own folder), ``--max-hours H`` (the time
a scene may need, default 24), ``--backend NAME`` (the backend of the flow sums, overriding the scenes'
``backend``: auto, direct, fmm, cuda, cuda-fp32, cuda-fp32-acc64), ``-v`` (log progress).

Exit status: 0 success; 1 some scenes of a batch failed (each with its reason), or an internal
error; 2 bad input (scene, table, target file, output folder, resources: the message names the file,
key or value; also an output that cannot be written, e.g. no space left on device); 3 a target the
cilia cannot make; 130 interrupted (Ctrl-C); 143 terminated (SIGTERM: kill, Slurm, systemd, Docker) and
129 hung up (SIGHUP), handled like Ctrl-C: workers stopped, nothing half-written left behind.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from dataclasses import replace
from pathlib import Path

from cilia_runtime.files import strict_json, write_netcdf
from cilia_runtime.pool import pool_for_threads
from cilia_runtime.progress import TqdmProgress
from cilia_runtime.signals import Terminated, exit_status, interrupt_of, terminate_as_interrupt
from cilia_runtime.threads import ThreadBudget

from ciliary_carpet.batch import (BAD_INPUT, CANNOT_MAKE, PRELOAD, batch, one_line, plain_warnings, read_scene,
                                  verdict_text)
from ciliary_carpet.scenes.assembly import design
from ciliary_carpet.output.folder import check_parents
from ciliary_carpet.output.resources import places_that_fit
from ciliary_carpet.render import RenderError, check_resources, render
from ciliary_carpet.scenes.paths import ALLOW_ENV
from ciliary_carpet.scenes.scene import SceneError
from ciliary_carpet.scenes.states import state_scenes
from ciliary_carpet.stokes import BACKENDS, backend_named

logger = logging.getLogger(__name__)

class OutputPathError(RenderError):
    """An output path the command refuses before any work (its message names the path, not the scene)."""


class StdoutError(OSError):
    """Standard output cannot be written (a full disk, a closed pipe); the message says so."""


def _emit(text: str) -> None:
    """Write ``text`` to standard output and flush it: :class:`StdoutError` when it cannot be
    written (later writes, and the interpreter's last flush, then go nowhere)."""
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except OSError as exc:
        try:  # what is left in the buffer must not fail again at exit
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, AttributeError, ValueError):
            pass
        raise StdoutError(exc.errno, f"cannot write to standard output: {exc.strerror or exc}") from None


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return v


def _cmd_render(a) -> int:
    scene = read_scene(a.scene, a.reduced, a.backend)
    budget = ThreadBudget.for_task()  # every core, or this Dask worker's share
    if a.threads is not None:
        budget = replace(budget, numba=a.threads)
    # the path lines on as many processes as numba threads (one: in this process), as memory allows
    pool = pool_for_threads(places_that_fit(scene.needs(), budget.numba), PRELOAD)
    with budget.applied():
        res = render(scene, a.output, overwrite=a.overwrite, progress=TqdmProgress(delay=0.5),
                     max_seconds=a.max_hours * 3600, pool=pool)
    s = res.summary
    try:
        if a.json:
            _emit(strict_json({"out_dir": str(res.out_dir), "files": list(res.files),
                               **({"program": s} if scene.states else {"design": s.get("design")}),
                               "seconds": s["seconds"]}) + "\n")
        elif scene.states:  # a program: its verdict and the states' table; each state's folder has its own
            head = (res.out_dir / "program.md").read_text().split("\n## ", 1)[0].rstrip()
            _emit(head + "\n\n")
            _emit(f"wrote {len(res.files)} files to {res.out_dir} (a folder per state: "
                  f"{', '.join(s.name for s in scene.states)}); the whole summary: {res.out_dir / 'program.md'}\n")
        else:  # the summary's head (title, scene, verdict); the whole of it is one file away
            head = (res.out_dir / "summary.md").read_text().split("\n## ", 1)[0].rstrip()
            _emit(head + "\n\n")
            _emit(f"wrote {len(res.files)} files to {res.out_dir}; the whole summary: "
                  f"{res.out_dir / 'summary.md'}\n")
    except StdoutError as exc:
        raise StdoutError(exc.errno, f"{exc.strerror}; the render in {res.out_dir} is complete (its summary.md "
                                     f"says what it holds)") from None
    return 0


def _layout_path(given: str, overwrite: bool) -> Path:
    """:func:`_layout_file`, its refusals as :class:`OutputPathError` (naming the path, not the scene)."""
    try:
        return _layout_file(given, overwrite)
    except RenderError as exc:
        raise OutputPathError(str(exc)) from None


def _layout_file(given: str, overwrite: bool) -> Path:
    """The file ``design -o`` writes: ``given``; through it, when it is a symbolic link to a
    regular file and ``overwrite`` (the link is kept, its file replaced). RenderError, before any
    work, for an existing path without ``overwrite``, any other symbolic link (a dangling one
    included: it is the user's, never replaced), a folder, or a ``..`` after a missing folder
    (:func:`~ciliary_carpet.output.folder.check_parents`)."""
    out = Path(given)
    if out.is_symlink():
        to = os.readlink(out)
        if not overwrite:
            raise RenderError(f"{out} is a symbolic link (to {to}); it is kept: pass --overwrite to write the "
                              f"layout into the file it points to, or name another file with -o")
        if not out.is_file():
            raise RenderError(f"{out} is a symbolic link to {to}, which is not an existing file; the link is kept: "
                              f"name the file itself with -o")
        return Path(os.path.realpath(out))
    if os.path.lexists(out) and not overwrite:
        raise RenderError(f"{out} exists; it is kept: pass --overwrite to replace it")
    if out.is_dir():
        raise RenderError(f"{out} is a folder; the layout is a file (.nc)")
    check_parents(out)
    return out


def _cmd_design(a) -> int:
    out = _layout_path(a.output, a.overwrite)
    scene = read_scene(a.scene, a.reduced, a.backend)
    if not scene.states:
        check_resources(scene, max_seconds=a.max_hours * 3600)
    backend_named(scene.backend)  # backend "cuda" without a GPU: CudaUnavailableError before any work
    if scene.states:  # a program: one layout for every state
        from ciliary_carpet.design.program import program_dataset
        from ciliary_carpet.scenes.program import design_program_scene

        for _, sc in state_scenes(scene):
            check_resources(sc, max_seconds=a.max_hours * 3600)
        prog, _ = design_program_scene(scene)
        write_netcdf(program_dataset(prog), out)
        through = f" (the file the symbolic link {a.output} points to)" if str(out) != a.output else ""
        _emit(f"{prog.message}\nwrote {out}{through}\n")
        return 0
    d, carpet = design(scene)
    if d is None:
        raise SceneError(f"{scene.source_name}: the scene has no [target] to design for")
    write_netcdf(d.to_dataset(carpet), out)
    through = f" (the file the symbolic link {a.output} points to)" if str(out) != a.output else ""
    _emit(f"{d.message}\nwrote {out}{through}\n")
    return 0


REACH_FLOW = 0.5
"""The background flow [L/tau] at which ``reach`` says how far a field's cutoff moves: the order of the
others' flow at a coupled carpet's cilia (a uniform carpet at chi_E = 200 levels off at 0.81)."""


def _cmd_reach(a) -> int:
    """What flows a program's cilia can make in its fields: per state the reachable thrust angles,
    per pair of states the angle pairs one curvature makes, and the curvatures that beat in one
    field only (:func:`~ciliary_carpet.design.program_reach.program_reachability`)."""
    from ciliary_carpet.design.program_reach import program_reachability
    from ciliary_carpet.scenes.assembly import load_table

    scene = read_scene(a.scene, False, a.backend)
    if not scene.states:
        raise SceneError(f"{scene.source_name}: reach compares the field states of a program ([[state]]); this "
                         "scene has one field (its reachable angles are in its render's summary)")
    pairs = state_scenes(scene)
    full = [load_table(sc) for _, sc in pairs]
    r = program_reachability([t.in_still_fluid() for t in full], [spec.name for spec, _ in pairs])
    # a coupled carpet's cilia beat in the others' flow, which moves each field's cutoff
    moved = {}
    for (spec, _), t in zip(pairs, full):
        (p0, p1), (q0, q1) = t.U_range
        if p0 < p1 and q0 < q1:
            u = min(REACH_FLOW, p1, q1)
            cs = [t.cutoff(U_par=p, U_perp=q) for p in (-u, 0.0, u) for q in (-u, 0.0, u)]
            moved[spec.name] = (u, min(cs), max(cs))
    if a.json:
        s = r.summary()
        s["cutoff_in_flow"] = {k: {"flow": u, "min": lo, "max": hi} for k, (u, lo, hi) in moved.items()}
        _emit(strict_json(s) + "\n")
    else:
        lines = [f"In a flow of up to {u:g} L/tau along or across the field (the coupled model: each cilium beats in "
                 f"the others' flow) the flutter cutoff of '{k}' moves between {lo:.1f} and {hi:.1f}: cilia near it may beat or "
                 "rest as the flow decides." for k, (u, lo, hi) in moved.items()]
        _emit(r.describe().rstrip() + "\n" + "".join(x + "\n" for x in lines))
    return 0


def _line(r: dict) -> str:
    """One scene of a batch in words: status, scene, seconds, what happened and the verdict."""
    v = verdict_text(r)
    sec = f"  ({r['seconds']:.1f} s)" if isinstance(r.get("seconds"), (int, float)) else ""
    return f"{r['status']:8s} {r['scene']}{sec}  {r['message']}{'; ' + v if v else ''}"


def _cmd_batch(a) -> int:
    finished: list = []
    try:
        recs = batch(a.scenes, a.output, scheduler=a.scheduler, jobs=a.jobs, threads=a.threads,
                     overwrite=a.overwrite, reduced=a.reduced, max_seconds=a.max_hours * 3600, backend=a.backend,
                     scheduler_timeout=a.scheduler_timeout, records=finished)
    except KeyboardInterrupt:  # the one line main prints says which scenes finished and which did not
        done = {r["scene"] for r in finished}
        left = [sc for sc in a.scenes if sc not in done]
        fin = ", ".join(f"{r['scene']} ({r['status']}{'; ' + verdict_text(r) if verdict_text(r) else ''})"
                        for r in finished)
        a.note = (f"finished: {fin or 'none'}; not finished: {', '.join(left) or 'none'}"
                  f"{' (run the batch again to render them)' if left else ''}; ")
        raise
    n = {k: sum(r["status"] == k for r in recs) for k in ("done", "skipped", "failed")}
    if a.json:
        _emit(strict_json({"scenes": recs, "done": n["done"], "skipped": n["skipped"], "failed": n["failed"]}) + "\n")
    else:
        _emit("".join(_line(r) + "\n" for r in recs)
              + f"{n['done']} rendered, {n['skipped']} up to date, {n['failed']} failed; index: "
                f"{Path(a.output) / 'batch.md'}\n")
    return 1 if n["failed"] else 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("cilia-flow")
    except PackageNotFoundError:
        from single_cilium import __version__

        return __version__


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="ciliary-carpet", description=__doc__.split("\n\n")[0].replace("``", ""))
    ap.add_argument("-v", "--verbose", action="store_true", help="log progress messages")
    ap.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    ap.add_argument("--debug", action="store_true", help="show the traceback of a failure")
    ap.add_argument("--allow-outside-paths", action="store_true",
                    help="let scene files name table/target files outside their own folder (trusted scenes only)")
    ap.add_argument("--max-hours", type=float, default=24.0,
                    help="refuse scenes estimated to need longer than this (default 24)")
    ap.add_argument("--backend", choices=BACKENDS, default=None,
                    help="backend of the flow sums, overriding the scenes' backend (cuda: an NVIDIA GPU, "
                         "pip install 'cilia-flow[gpu]')")
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("render", help="design (if the scene has a target), run the flow, write VTK/PNG/summary")
    r.add_argument("scene")
    r.add_argument("-o", "--output", required=True, help="output folder")
    r.add_argument("--overwrite", action="store_true",
                   help="replace the files an earlier render wrote there (never other files)")
    r.add_argument("--reduced", action="store_true", help="a small version of the scene (quick look)")
    r.add_argument("--json", action="store_true", help="print a JSON summary (strict JSON)")
    r.add_argument("--threads", type=_positive_int, default=None,
                   help="numba threads of the render, and processes its path lines run in (default: every core "
                        "it may use -- its CPU affinity, a container's CPU quota -- with as many of those processes "
                        "as memory allows; fewer when other jobs share the machine, where many threads wait for "
                        "each other); summary.json says what it used")
    d = sub.add_parser("design", help="write only the designed layout (NetCDF)")
    d.add_argument("scene")
    d.add_argument("-o", "--output", required=True, help="layout file (.nc)")
    d.add_argument("--overwrite", action="store_true")
    d.add_argument("--reduced", action="store_true")
    q = sub.add_parser("reach", help="what pairs of flows a program's cilia can make in its fields (before designing)")
    q.add_argument("scene")
    q.add_argument("--json", action="store_true", help="print the figures as strict JSON")
    b = sub.add_parser("batch", help="render many scenes (a process per scene, or a Dask cluster), resumable")
    b.add_argument("scenes", nargs="+")
    b.add_argument("-o", "--output", required=True, help="output root; each scene goes to OUTPUT/NAME")
    b.add_argument("-j", "--jobs", type=int, default=None,
                   help="local worker processes at once (default: as many as scenes and cores allow, and as fit "
                        "the available memory -- a container's or a batch job's limit where it has one)")
    b.add_argument("--threads", type=int, default=None,
                   help="numba threads per worker (default: the cores divided among the workers; one BLAS thread "
                        "each); each render's summary.json says what it used under \"threads\"")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:port)")
    b.add_argument("--scheduler-timeout", dest="scheduler_timeout", type=float, default=None, metavar="SECONDS",
                   help="how long to wait for the scheduler to answer before giving up (default 20, or "
                        "$CILIA_SCHEDULER_TIMEOUT)")
    b.add_argument("--overwrite", action="store_true")
    b.add_argument("--reduced", action="store_true")
    b.add_argument("--json", action="store_true", help="print the records as strict JSON")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if not (a.max_hours > 0):
        ap.error(f"--max-hours must be > 0, got {a.max_hours}")
    if a.allow_outside_paths:
        os.environ[ALLOW_ENV] = "1"  # inherited by batch workers
    src = getattr(a, "scene", None)
    try:
        # SIGTERM, SIGHUP: the Ctrl-C cleanup, exit 128 + signum; warnings as plain lines, once each
        with terminate_as_interrupt(), plain_warnings():
            return {"render": _cmd_render, "design": _cmd_design, "reach": _cmd_reach, "batch": _cmd_batch}[a.cmd](a)
    except StdoutError as exc:
        print(f"ciliary-carpet: {exc.strerror}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(a, exc)
    except CANNOT_MAKE as exc:
        if a.debug:
            raise
        print(f"ciliary-carpet: {one_line(exc, src)}", file=sys.stderr)
        return 3
    except BAD_INPUT as exc:
        if a.debug:
            raise
        print(f"ciliary-carpet: {one_line(exc, None if isinstance(exc, OutputPathError) else src)}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 -- a bug: one line, the traceback with --debug
        if interrupt_of(exc) is not None:  # a signal handled inside compiled code (a SystemError carries it)
            return _interrupted(a, interrupt_of(exc))
        if a.debug:
            raise
        print(f"ciliary-carpet: internal error: {one_line(exc, src)} (rerun with --debug for the traceback)",
              file=sys.stderr)
        return 1


def _interrupted(a, exc: KeyboardInterrupt) -> int:
    """Ctrl-C or a signal: one line, exit 128 + signum (130 for Ctrl-C)."""
    how = str(exc) if isinstance(exc, Terminated) else "interrupted"
    print(f"ciliary-carpet: {how}; {getattr(a, 'note', '')}nothing half-written was left in the output folder",
          file=sys.stderr)
    return exit_status(exc)


if __name__ == "__main__":
    sys.exit(main())
