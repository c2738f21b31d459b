"""The objects a scene describes: its thrust table, base points, target frame, target and carpet,
and the carpet designed for its target.

This module is the one route from a :class:`~ciliary_carpet.scenes.scene.Scene` (the file format,
which builds nothing) to objects: :func:`assemble` builds them all, :func:`load_table`,
:func:`frame_of`, :func:`target_of` and :func:`carpet_for` one each, :func:`design` designs
the carpet for the scene's target (the design layer, :mod:`ciliary_carpet.design`, works on the
objects alone), and :func:`render_settings` gives the values a render's plan and outputs read
(:class:`~ciliary_carpet.output.plan.RenderSettings`). The render and the command line build what they need here. The table is the
scene's (:func:`load_table`: the shipped one, a file, or one computed first with
``[table.build]``; cached) and is checked against ``carpet.chi_N``; the target is resolved against
the table (its default angle) and the carpet's frame; the carpet is built on demand with the
curvatures asked for (the design's starting layout, or the scene's own ``carpet.chi_N``).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

import single_cilium.table as _table
from cilia_runtime.progress import Progress
from single_cilium.lookup import SHIPPED_FIELDS, shipped_field
from single_cilium.table import TableError, ThrustTable

from single_cilium.radau import ConvergenceError

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.carpet.coupling import CouplingError
from ciliary_carpet.design.result import Design, DesignError
from ciliary_carpet.scenes.paths import check_derived, inside, table_parts
from ciliary_carpet.scenes.schema import SceneError
from ciliary_carpet.stokes import backend_named
from ciliary_carpet.design.frame import Frame
from ciliary_carpet.design.patterns import ANGLE_KINDS
from ciliary_carpet.design.target import Target
from ciliary_carpet.design.target_design import design_standing_target, design_target
from ciliary_carpet.output.plan import RenderSettings
from ciliary_carpet.scenes.target_spec import resolve_target

if TYPE_CHECKING:
    from ciliary_carpet.scenes.scene import Scene

logger = logging.getLogger(__name__)

__all__ = ["Assembly", "assemble", "carpet_for", "design", "check_table_range", "load_table", "frame_of", "target_of",
           "render_settings", "TableBuildError"]


class TableBuildError(DesignError):
    """A ``[table.build]`` whose computation cannot converge (a computation that cannot be made:
    exit 3 on the command line, as ``single-cilium table``); the message names the scene, the
    failing row and the ``[table.build]`` keys to change."""

_TABLE_CACHE: dict = {}


def render_settings(scene: "Scene") -> RenderSettings:
    """The values a render of ``scene`` reads
    (:class:`~ciliary_carpet.output.plan.RenderSettings`): its name and file, its ``[output]``
    section, tolerance, carpet spacing and geometry, and the flow direction of its field."""
    return RenderSettings(name=scene.name, source=scene.source_name, output=scene.output, tolerance=scene.tolerance,
                          spacing=scene.carpet.spacing, flow_direction=scene.field.flow_direction,
                          geometry=scene.carpet.geometry)


def load_table(scene: "Scene", progress: Progress | None = None) -> ThrustTable:
    """The scene's thrust table (``[table]``): loaded, built first if asked (``[table.build]``), and check that it is for the scene's field.

    ``file = "default"`` is the table shipped for the scene's ``field.chi_E``
    (:data:`~single_cilium.lookup.SHIPPED_FIELDS`, within 1e-9 relative; eta = 1): over the
    background flow for a coupled carpet, over chi_N in still fluid for ``coupling = "none"``
    (:meth:`~single_cilium.table.ThrustTable.default`).

    A build says first, through ``progress`` (:class:`~cilia_runtime.progress.Progress`: its
    ``note``, then a bar over the rows), what it computes and how long that is expected to take
    (:func:`build_estimate`).

    Tables are cached per (file, modification time; a shipped one per field and coupling), so
    repeated loads are free; treat the returned table as read-only.

    Raises
    ------
    SceneError
        If ``file = "default"`` and no table ships for ``field.chi_E``, if the file is missing
        and there is no ``[table.build]``, if it is not a readable table, or if its (chi_E, eta)
        differ from ``[field]`` by more than 1e-9 relative.
    """
    src = scene.source_name
    spec = scene.table
    p = spec.path(scene)
    if p is None:
        flow = scene.carpet.coupling == "mean"
        chi_E = shipped_field(scene.field.chi_E)
        if chi_E is None:
            raise SceneError(
                f"{src}: table.file = \"default\" is a shipped table, and tables ship for {_shipped()} "
                f"(eta = 1), but [field] asks chi_E = {scene.field.chi_E:g}: name a table file with a "
                f"[table.build] section to compute it for this field (takes minutes; the estimate is said first)")
        key = ("default", flow, chi_E)
        table = _TABLE_CACHE.get(key)
        if table is None:
            table = _TABLE_CACHE[key] = ThrustTable.default(flow=flow, chi_E=chi_E)
        where = "the shipped table" + (" over the background flow" if flow else "")
    else:
        if not p.exists():
            if spec.build is None:
                raise SceneError(
                    f"{src}: table.file '{spec.file}' not found (looked for {p.absolute()}); fix the path, "
                    f"use file = \"default\" for the shipped table ({_shipped()}, eta = 1), or add a "
                    f"[table.build] section (n, degree) to compute it there (takes minutes)")
            _check_build_paths(scene, p)
            _build(scene, p, progress)
        st = p.stat()
        key = (str(p.resolve()), st.st_mtime_ns, st.st_size)
        table = _TABLE_CACHE.get(key)
        if table is None:
            try:
                table = ThrustTable.load(p)
            except TableError as exc:
                raise SceneError(f"{src}: table.file: {exc}") from None
            _TABLE_CACHE[key] = table
        where = f"table {p}"
    f = scene.field
    bad = [(k, getattr(table, k), getattr(f, k)) for k in ("chi_E", "eta")
           if abs(getattr(table, k) - getattr(f, k)) > 1e-9 * max(abs(getattr(f, k)), abs(getattr(table, k)))]
    if bad:
        got = ", ".join(f"{k} = {t:g}" for k, t, _ in bad)
        want = ", ".join(f"{k} = {w:g}" for k, _, w in bad)
        raise SceneError(f"{src}: {where} is for {got}, but [field] asks {want}; use a table built "
                         f"for this field (table.file with [table.build]) or change [field]")
    return table


def _shipped() -> str:
    """The shipped fields, as messages say them ("chi_E = 150 or chi_E = 200")."""
    return " or ".join(f"chi_E = {c:g}" for c in SHIPPED_FIELDS)


def _check_build_paths(scene: "Scene", p: Path) -> None:
    """Just before a build: when ``table.file`` lies below the scene's folder, the row folder
    the build derives from it must too (:func:`~ciliary_carpet.scenes.paths.check_derived`; it may
    have become a symbolic link since the scene was read)."""
    if not inside(p, scene.base_dir)[0]:
        return  # table.file itself was allowed outside (allow_outside): so is its row folder
    check_derived(scene.source_name, "table.file", "the table build's row folder", table_parts(p), scene.base_dir)

def _build(scene: "Scene", p: Path, progress: Progress | None = None) -> None:
    """Compute the scene's table into ``p`` (:func:`_build_table`); a computation that does not
    converge is a :class:`TableBuildError` saying which ``[table.build]`` keys to change."""
    b = scene.table.build
    try:
        _build_table(scene, p, progress)
    except ConvergenceError as exc:
        keys = (f"a larger table.build.n (now {b.n}: a finer chi_N grid, each cycle started from its neighbours')"
                + (f", a larger table.build.flow_points (now {b.flow_points}: a finer flow grid), a smaller "
                   f"table.build.flow (now {b.flow:g})" if b.flow is not None else "")
                + f" or a larger table.build.degree (now {b.degree})")
        raise TableBuildError(f"{scene.source_name}: [table.build] could not compute the thrust table {p}: "
                              f"{' '.join(str(exc).split())}; in the scene, try {keys}") from None


ROW_CORE_SECONDS = 0.6
"""CPU seconds one table row takes at the default discretisation (degree 8, 64 phases, error
estimates), pool start included: 525 rows of a table over the flow in 141 s on 2 shared cores
(0.54; benchmarks/results/bench_table_flow.md), 12 rows over chi_N in 3.6 s on 2 (0.61)."""


def build_estimate(rows: int, degree: int, cores: int) -> float:
    """Seconds a table build of ``rows`` rows is expected to take on ``cores`` cores:
    :data:`ROW_CORE_SECONDS` per row, scaled like a cycle's Newton solves with the mesh
    (``(degree / 8)^3``)."""
    return rows * ROW_CORE_SECONDS * (degree / 8.0) ** 3 / max(1, cores)


def _build_table(scene: "Scene", p: Path, progress: Progress | None = None) -> None:
    from single_cilium import flutter_cutoff

    f, b = scene.field, scene.table.build
    cut = flutter_cutoff(f.chi_E, f.eta, degree=b.degree)
    if not math.isfinite(cut.chi_N_cutoff):
        raise SceneError(f"{scene.source_name}: cannot build a thrust table for chi_E = {f.chi_E:g}, "
                         f"eta = {f.eta:g}: {cut.message}")
    c = cut.chi_N_cutoff
    if b.flow is None and scene.carpet.coupling == "mean":  # a coupled carpet: the shipped flow table's grid
        b = replace(b, flow=float(_table.SHIPPED_FLOW[-1]), flow_points=_table.SHIPPED_FLOW.size,
                    n=_table.SHIPPED_FLOW_CHI_N.size)
    if b.flow is None:
        grid = np.concatenate([np.linspace(0.0, c, b.n)[:-1], [1.05 * c]])
        _announce(progress, p, f, grid.size, b.degree, f"{grid.size} rows over chi_N")
        _table.build_table(f.chi_E, f.eta, grid, degree=b.degree, path=p, progress=progress)
        return
    # over the flow: the rows reach past every corner flow's cutoff (each flow's own is added),
    # short of the coiled limit
    U = np.linspace(-b.flow, b.flow, b.flow_points)
    corners = [flutter_cutoff(f.chi_E, f.eta, degree=b.degree, background=(q, u)).chi_N_cutoff
               for u in (-b.flow, b.flow) for q in (-b.flow, b.flow)]
    top = min(1.05 * max([c] + [x for x in corners if math.isfinite(x)]), 0.95 * abs(f.chi_E))
    grid = np.linspace(0.0, top, b.n)
    _announce(progress, p, f, grid.size * U.size ** 2, b.degree,
              f"{grid.size} rows over chi_N x {U.size} x {U.size} background flows")
    _table.build_table(f.chi_E, f.eta, grid, U_par=U, U_perp=U, degree=b.degree, path=p, progress=progress)


def _announce(progress: Progress | None, p: Path, f, rows: int, degree: int, what: str) -> None:
    """Say, before a table build, what it computes and how long it is expected to take."""
    from cilia_runtime.threads import cores

    n = cores()
    eta = build_estimate(rows, degree, n)
    msg = (f"building the thrust table {p} for chi_E = {f.chi_E:g}, eta = {f.eta:g}: {what}, about "
           f"{eta / 60:.1f} min on {n} core{'s' if n > 1 else ''} (the finished rows are kept in {p}.parts/)")
    logger.info(msg)
    if progress is not None:
        progress.note(msg)


def frame_of(scene: "Scene", bases=None) -> Frame:
    """The target :class:`~ciliary_carpet.design.frame.Frame` of ``scene``'s carpet (``bases``
    default: ``scene.carpet.bases()``)."""
    b = scene.carpet.bases() if bases is None else bases
    return Frame.from_bases(b, scene.carpet.spacing, scene.field.direction_rad)


def target_of(scene: "Scene", table: ThrustTable | None = None) -> Target:
    """The resolved target of ``scene`` (``table`` default: :func:`load_table`, needed only for
    the default angle; a control-point file is read relative to the scene's folder)."""
    angle_max = None
    if scene.target.kind in ANGLE_KINDS and scene.target.angle is None:
        table = table if table is not None else load_table(scene)
        angle_max = table.thrust_angle_range()[1]
    return resolve_target(scene.target, scene.base_dir, angle_max)


def check_table_range(scene: "Scene", table: ThrustTable) -> None:
    """SceneError naming ``carpet.chi_N`` when it lies outside ``table``'s range."""
    lo, hi = table.chi_N_range
    c = scene.carpet.chi_N
    if not lo <= abs(c) <= hi:
        raise SceneError(f"{scene.source_name}: carpet.chi_N = {c:g} is outside the thrust table's range "
                         f"[{lo:g}, {hi:g}] (by mirror symmetry also negative; the top is the flutter cutoff)")


def _carpet(scene: "Scene", table: ThrustTable, bases: np.ndarray, chi_N=None) -> Carpet:
    """The carpet of ``scene`` on ``bases`` with curvatures ``chi_N`` (default ``carpet.chi_N``);
    see :meth:`Assembly.carpet`."""
    s = scene
    # a standing carpet: its geometry and the azimuths (the scene's degrees, the carpet's radians)
    standing = {} if s.carpet.geometry == "planar" else dict(
        geometry=s.carpet.geometry, azimuth=np.radians(s.carpet.azimuths(bases.shape[0])))
    c = Carpet(bases, s.carpet.chi_N if chi_N is None else chi_N, table,
               s.carpet.initial_phases(bases), direction=s.field.direction_rad, wall=s.carpet.wall,
               scales=None if s.units is None else s.units.scales(), blob=s.carpet.blob,
               backend=backend_named(s.backend), viscosity=s.carpet.viscosity, coupling=s.carpet.coupling,
               **standing)
    if c.coupled is not None and not c.coupled.converged:  # nothing is drawn from a flow not solved
        h = ", ".join(f"{r:.2g}" for r in c.coupled.history)
        raise CouplingError(f"{s.source_name}: the coupled carpet was not solved: {c.coupled.message} "
                            f"(residual after each Newton step: {h}); nothing was rendered from it. "
                            f'[carpet] coupling = "none" renders the uncoupled model instead (its summary '
                            f"estimates how far that is from the coupled one)")
    return c


@dataclass(frozen=True, eq=False)
class Assembly:
    """What :func:`assemble` builds from ``scene``.

    table : the scene's thrust table; bases : (N, 2) base points; frame : the
    target's :class:`~ciliary_carpet.design.frame.Frame` of those bases; target : the resolved
    :class:`~ciliary_carpet.design.target.Target` (kind "none" without a target).
    """

    scene: "Scene"
    table: ThrustTable
    bases: np.ndarray
    frame: Frame
    target: Target

    def carpet(self, chi_N=None) -> Carpet:
        """The scene's carpet with curvatures ``chi_N`` (scalar or (N,); default the scene's
        ``carpet.chi_N``): its base points, initial phases, field direction, wall, units, blob
        size, the backend of its sums (the scene's ``backend``) and its geometry (a standing
        carpet's azimuths, ``carpet.azimuth`` in degrees, converted to radians). A coupled carpet whose
        solve did not converge raises :class:`~ciliary_carpet.carpet.coupling.CouplingError` (exit 3 on
        the command line) with its residual history."""
        return _carpet(self.scene, self.table, self.bases, chi_N)


def _checked_table(scene: "Scene", table: ThrustTable | None) -> ThrustTable:
    """``table`` (default: :func:`load_table`) checked against ``scene``: ``carpet.chi_N`` in its
    range, and over the background flow for a coupled carpet (else a SceneError)."""
    table = table if table is not None else load_table(scene)
    check_table_range(scene, table)
    (p0, p1), (q0, q1) = table.U_range
    if scene.carpet.coupling == "mean" and p0 == p1 and q0 == q1:
        raise SceneError(f'{scene.source_name}: carpet.coupling = "mean" (the default: each cilium beats in the flow '
                         f"the others make) needs a thrust table over the background flow, but table.file "
                         f"'{scene.table.file}' is for still fluid: name a new table file with a [table.build] "
                         f"section (it is built over the shipped flow grid, U in [-1.5, 1.5] L/tau, about 5 "
                         f"minutes on 2 cores), or set [carpet] coupling = \"none\" for the uncoupled model")
    return table


def assemble(scene: "Scene", table: ThrustTable | None = None) -> Assembly:
    """Build the objects ``scene`` describes (``table`` default: :func:`load_table`).

    Raises SceneError for an unreadable table or one for another field, or ``carpet.chi_N``
    outside the table's range; TargetError for a target that cannot be resolved (an unreadable
    control-point file)."""
    from ciliary_carpet.scenes.scene import as_scene

    scene = as_scene(scene, "assemble()")
    table = _checked_table(scene, table)
    bases = scene.carpet.bases()
    return Assembly(scene, table, bases, frame_of(scene, bases), target_of(scene, table))


def carpet_for(scene: "Scene", table: ThrustTable | None = None) -> Carpet:
    """The carpet ``scene``'s layout describes, with its own ``carpet.chi_N``, with or without a
    target (the target is not resolved, nothing is designed): :meth:`Assembly.carpet` of the
    scene, with the same checks of the table (``table`` default: :func:`load_table`)."""
    from ciliary_carpet.scenes.scene import as_scene

    scene = as_scene(scene, "carpet_for()")
    table = _checked_table(scene, table)
    return _carpet(scene, table, scene.carpet.bases())


def design(scene, table: ThrustTable | None = None) -> tuple[Design | None, Carpet]:
    """Design the scene's carpet for its target: returns (Design, the designed Carpet), or
    (None, the scene's carpet, :func:`carpet_for`) when the scene has no target.

    The objects come from :func:`assemble`; the design is
    :func:`~ciliary_carpet.design.target_design.design_target` (a planar carpet) or
    :func:`~ciliary_carpet.design.target_design.design_standing_target` (a standing one), whose
    docstrings give the verdict: a design whose rms residual exceeds ``[target] residual`` returns
    the closest flow the cilia can make, with a warning naming the worst control points; with
    ``[target] strict = true`` it is a DesignError (exit status 3 of the command line) and
    unreachable angle requests are a TargetError instead of being clipped. ``scene``: a
    :class:`~ciliary_carpet.scenes.scene.Scene` or the path of a scene file (else a TypeError)."""
    from ciliary_carpet.scenes.scene import as_scene

    scene = as_scene(scene, "design()")
    if scene.target.kind == "none":
        return None, carpet_for(scene, table)
    built = assemble(scene, table)
    if scene.carpet.geometry == "standing":  # (the scene's key: a carpet of 10^4 cilia takes seconds to build)
        return design_standing_target(built.target, built.bases, built.frame, built.carpet(),
                                      spacing=scene.carpet.spacing, tol=scene.tolerance, source=scene.source_name)
    return design_target(built.target, built.table, built.bases, built.frame, built.carpet,
                         direction=scene.field.direction_rad, spacing=scene.carpet.spacing, tol=scene.tolerance,
                         source=scene.source_name)
