"""The main job: a scene file in, a folder of ParaView-ready outputs out.

:func:`render` is a short pipeline: check what the scene needs against the machine
(:func:`~ciliary_carpet.scenes.resources.check_resources`), design the layout (when the scene has a
target), decide the render once from the scene's render settings
(:func:`~ciliary_carpet.scenes.assembly.render_settings`; :class:`~ciliary_carpet.output.plan.RenderPlan`:
the field grid, the beat, the seeds, the path-line model and duration), write each wanted output
of the registry (:data:`~ciliary_carpet.output.outputs.OUTPUTS`, whose docstring lists the files:
VTK files for ParaView, pictures, the ParaView script, ``summary.json`` and ``summary.md``), and
move the finished folder into place. The progress counts the outputs written, and within one
its own steps as they finish (the path lines' tasks: :class:`~ciliary_carpet.output.contract.StageProgress`).
``ciliary-carpet.manifest`` names the files written: what the toolkit wrote (JSON, with sizes and
SHA-256).

Output-folder safety (:mod:`ciliary_carpet.output.folder`, whose docstring states the guarantees).
Everything is first written into a hidden staging folder on the output's own filesystem (next to
a new ``out_dir``, inside an existing one) and swapped in when complete, or removed on failure.
A render holds a lock on ``out_dir`` (a second render of it is refused at once). A non-empty
``out_dir`` is kept unless ``overwrite=True``, and even then only the files the toolkit wrote and
that are unchanged (output names, regular files, the size and SHA-256 its manifest recorded) are
replaced or removed: files someone else put there are never touched, and a render whose output
would replace one of them is refused before any work. The swap is journalled and signals cannot
split it; a folder is complete (:func:`is_complete`) when it has the manifest and
``summary.json`` and no swap is under way, and current for a scene when it was made with the
same settings (``package_version`` and ``scene_resolved`` in ``summary.json``) from inputs with
the same contents (the scene, table and target files, whose SHA-256 the manifest's ``inputs``
record).
``summary.json`` is strict JSON, and a render whose summary would hold a NaN or an infinity is
a :class:`RenderError` (nothing is written). Before any work, :func:`check_resources` compares a
lower bound of the memory and time the scene needs with what the machine has. Times are in units
of tau, lengths in L (SI when the scene has ``[units]``); the path lines and the beat are
described in :mod:`ciliary_carpet.output.plan`. The flow uses the regularised Stokeslets of
``[carpet] blob``: it is bounded everywhere, so the fields are not blanked inside the cilia's
swept regions.
"""
from __future__ import annotations

import logging
import time as _time
from dataclasses import asdict, dataclass
from pathlib import Path

from cilia_runtime.progress import Progress

from ciliary_carpet.output import RenderError
from ciliary_carpet.output.folder import (MANIFEST, PACKAGE_VERSION, OutputFolder, is_complete, only_toolkit_files,
                                         owned_files)
from ciliary_carpet.output.contract import SUMMARY, RenderContext, StageProgress
from ciliary_carpet.output.outputs import OUTPUTS
from ciliary_carpet.output.plan import GEOMETRY_OUTPUTS, RenderPlan
from ciliary_carpet.output.resources import ResourceError
from ciliary_carpet.scenes.assembly import carpet_for, design, load_table, render_settings
from ciliary_carpet.scenes.resources import check_resources
from ciliary_carpet.scenes.scene import Scene, as_scene
from ciliary_carpet.stokes import Auto, backend_named
from cilia_runtime.pool import InProcess

logger = logging.getLogger(__name__)

__all__ = ["render", "RenderResult", "RenderError", "ResourceError", "is_complete", "owned_files", "check_resources",
           "MANIFEST", "SUMMARY"]


@dataclass(frozen=True)
class RenderResult:
    """What a render wrote: the folder, its files, and the summary (also in summary.json)."""

    out_dir: Path
    files: tuple
    summary: dict


def render(scene: Scene, out_dir, *, overwrite: bool = False, progress: Progress | None = None,
           max_seconds: float = 86400.0, within=None, pool=None, designed=None, program: dict | None = None
           ) -> RenderResult:
    """Render ``scene`` into ``out_dir`` (see the module docstring for what is written and
    :mod:`ciliary_carpet.output.folder` for the output-folder rules). Raises SceneError, TargetError,
    TableError or DesignError for a scene that cannot be rendered, ResourceError when it
    certainly needs more memory than available or more than ``max_seconds``
    (:func:`check_resources`), and RenderError when ``out_dir`` holds files and ``overwrite`` is
    False, when a file it would replace was not written by a render (or was changed since), when
    another render is writing ``out_dir``, when ``out_dir`` resolves outside ``within`` (a
    batch's output root), or when the result is not finite; nothing in ``out_dir`` is changed
    then. ``pool`` (:mod:`~cilia_runtime.pool`: :class:`InProcess
    <cilia_runtime.pool.InProcess>`, the default, or a :class:`ProcessPool
    <cilia_runtime.pool.ProcessPool>`, e.g. ``pool_for_threads(n)`` for ``n`` cores)
    says where the path lines' chunks and their error estimate's reference run; the numbers are
    the same wherever they run (a pool's workers are made ready while the carpet is designed:
    ``pool.warm()``). ``scene``: a Scene or the path of a scene file (else a TypeError).

    A program scene (``[[state]]``) is :func:`render_program`'s: one folder per state.
    ``designed``: (Design, Carpet) of a layout designed elsewhere (a program's, in this scene's
    field), rendered instead of designing the scene's target; ``program``: the program's record,
    kept in the summary under ``program``."""
    scene = as_scene(scene, "render()")
    if scene.states:
        return render_program(scene, out_dir, overwrite=overwrite, progress=progress, max_seconds=max_seconds,
                              within=within, pool=pool)
    resolved = scene.to_dict()  # the summary's copy of the scene
    with OutputFolder(out_dir, overwrite=overwrite, scene=scene, within=within) as folder:
        estimate = check_resources(scene, max_seconds=max_seconds)
        backend_named(scene.backend)  # backend "cuda" without a GPU: CudaUnavailableError here, before any work
        pool = pool if pool is not None else InProcess()
        pool.warm()  # a process pool's fork server starts while the carpet is designed
        progress = progress if progress is not None else Progress()
        t0 = _time.perf_counter()
        n = scene.carpet.n_cilia
        progress.note(f"render {scene.name}: " + (
            f"the program's layout of {n} cilia in this state's field (chi_E = {scene.field.chi_E:g})"
            if designed is not None else f"designing the curvatures of {n} cilia for the {scene.target.kind} target"
            if scene.target.kind != "none" else f"building the carpet of {n} cilia"))
        table_file = scene.table.path(scene)
        built = table_file is not None and not table_file.exists()
        load_table(scene, progress=progress)  # a [table.build] says what it computes, and shows its rows
        t_table = _time.perf_counter() - t0
        # table (now cached), range check, target and carpet: scenes.assembly
        if designed is not None:
            d, carpet = designed
        else:
            d, carpet = design(scene) if scene.target.kind != "none" else (None, carpet_for(scene))
        clock = {"table": t_table, "design": _time.perf_counter() - t0 - t_table}
        settings = render_settings(scene)
        plan = RenderPlan.decide(settings, carpet, designed=d is not None, estimate=estimate)  # errors before outputs
        progress.note(plan.describe() + f" (design {clock['design']:.1f} s)")
        outputs = [o for o in (cls() for cls in OUTPUTS.values()) if o.wanted(plan)]
        head = _header(scene, plan, carpet)
        if program is not None:
            head["program"] = program
        head["table"] = {"file": "default" if table_file is None else str(table_file), "built": built}
        if built:  # a [table.build] computed it for this render: what it cost
            head["table"].update(build_seconds=t_table, size_bytes=table_file.stat().st_size)
        ctx = RenderContext(plan, carpet, d, folder.stage(), folder.path, head, clock, t0, resolved, pool=pool)
        progress.start(len(outputs), f"render {scene.name}", uniform=False)  # stages of unequal cost
        try:
            for k, o in enumerate(outputs, 1):
                progress.stage(o.name)
                ctx.progress = StageProgress(progress, k - 1)  # e.g. the path lines' tasks as they finish
                o.write(ctx)
                progress.update(k)
            folder.place()  # the manifest (sizes, hashes), then the swap
        finally:
            progress.close()
        files = folder.files()
    logger.info("rendered %s into %s in %.1f s", scene.name, folder.path, clock["total"])
    return RenderResult(out_dir=folder.path, files=files, summary=ctx.summary)


def _header(scene: Scene, plan: RenderPlan, carpet) -> dict:
    """The summary's first keys of a render of ``scene`` with ``plan``: the scene, the settings,
    the units and the beat; a standing carpet's also ``geometry`` ("standing") and ``standing``:
    the wall's distance below the clamps, the azimuths' range [degrees] and the target plane's
    height."""
    _, T, _ = plan.units
    beat = {k: (v * T if k != "beating" else v) for k, v in asdict(plan.beat).items()}
    beat["loop_until"] = plan.span * T
    head = {"scene": scene.name, "source": scene.source_name, "package_version": PACKAGE_VERSION,
            "n_cilia": carpet.n, "tolerance": scene.tolerance, "units": "SI" if plan.scales is not None else "L, tau",
            "T0": plan.T0 * T, "backend": (carpet.backend if carpet.backend is not None else Auto()).describe(),
            "beat": beat}
    head.update(GEOMETRY_OUTPUTS[carpet.geometry].summary(carpet, plan.settings, plan.units[0]))
    return head


PROGRAM_FILES = ("program.json", "program.md", "program.nc")
"""What a program's render writes next to its states' folders: the program's summary (strict
JSON and Markdown) and its layout (NetCDF, :func:`~ciliary_carpet.design.program.program_dataset`)."""


def render_program(scene: Scene, out_dir, *, overwrite: bool = False, progress: Progress | None = None,
                   max_seconds: float = 86400.0, within=None, pool=None) -> RenderResult:
    """Render a program scene (``[[state]]``): design one layout for every state
    (:func:`~ciliary_carpet.scenes.program.design_program_scene`), then render it in each
    state's field into ``out_dir/<state name>/`` (a complete render folder each, with the
    output-folder rules of :func:`render`; its summary holds the program under ``program``),
    and write :data:`PROGRAM_FILES` into ``out_dir``: the states' residuals with their error
    bars, the limiting state, the switch between states (how many beats the cilia take to settle
    after the field changes, :func:`~ciliary_carpet.design.program_reach.switch_transient`) and the
    layout. ``out_dir`` holding program files from an earlier render is refused unless
    ``overwrite``; nothing else in it is touched."""
    from cilia_runtime.files import strict_json, write_bytes, write_netcdf

    from ciliary_carpet.design.program import program_dataset
    from ciliary_carpet.output.report import program_markdown
    from ciliary_carpet.scenes.program import design_program_scene
    from ciliary_carpet.scenes.states import state_scenes

    out = Path(out_dir)
    if within is not None:
        import os

        root, real = Path(os.path.realpath(within)), Path(os.path.realpath(out))
        if real != root and root not in real.parents:
            raise RenderError(f"{out} resolves to {real}, outside the output folder {root}; nothing was written")
    old = [f for f in PROGRAM_FILES if (out / f).exists()]
    if old and not overwrite:
        raise RenderError(f"{out} already holds a program's render ({', '.join(old)}); pass overwrite to replace "
                          "the files a render wrote there")
    if old and not _program_files_ours(out):
        raise RenderError(f"{out} holds {', '.join(old)} that a program's render did not write (program.json is not "
                          "one); nothing was written: render into another folder")
    for _, sc in state_scenes(scene):  # every state's resources and backend before any work
        check_resources(sc, max_seconds=max_seconds)
        backend_named(sc.backend)
    progress = progress if progress is not None else Progress()
    t0 = _time.perf_counter()
    progress.note(f"render {scene.name}: designing one layout of {scene.carpet.n_cilia} cilia for "
                  f"{len(scene.states)} field states ({', '.join(s.name for s in scene.states)})")
    prog, states = design_program_scene(scene)
    t_design = _time.perf_counter() - t0
    record = prog.summary()
    record["switch"] = _switches(states)
    results = []
    for st in states:
        rec = dict(record, state=st.name)
        # a state's folder left by an interrupted program render (no program files yet) holds only
        # the toolkit's files: replaced as with overwrite (others' files never are)
        again = not old and (out / st.name).is_dir() and only_toolkit_files(out / st.name)
        r = render(st.scene, out / st.name, overwrite=overwrite or again, progress=progress,
                   max_seconds=max_seconds, within=within, pool=pool, designed=(st.design, st.carpet), program=rec)
        results.append(r)
    record["seconds"] = {"design": t_design, "total": _time.perf_counter() - t0}
    record["scene"], record["source"] = scene.name, scene.source_name
    record["folders"] = {st.name: st.name for st in states}
    out.mkdir(parents=True, exist_ok=True)
    write_netcdf(program_dataset(prog), out / "program.nc")
    write_bytes(out / "program.md", program_markdown(record).encode())
    write_bytes(out / "program.json", (strict_json(record, indent=1) + "\n").encode())
    files = tuple(PROGRAM_FILES) + tuple(f"{st.name}/{f}" for st, r in zip(states, results) for f in r.files)
    logger.info("rendered the program %s into %s in %.1f s", scene.name, out, record["seconds"]["total"])
    return RenderResult(out_dir=out, files=files, summary=record)


def _program_files_ours(out: Path) -> bool:
    """Whether ``out/program.json`` is a program render's record (strict JSON with its states)."""
    import json

    try:
        p = json.loads((out / "program.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(p, dict) and isinstance(p.get("states"), list) and "scene" in p


def _switches(states) -> list[dict]:
    """Per state: how long the cilia take to settle after the field switches to it."""
    from ciliary_carpet.design.program_reach import switch_transient

    out = []
    for st in states:
        tr = switch_transient(st.carpet.table.in_still_fluid(), st.design.chi_N)
        out.append({"to": st.name, "chi_E": float(st.carpet.table.chi_E), **tr.summary()})
    return out
