"""Scene files: a carpet, its field, its target flow and what to output, in TOML.

:func:`load_scene` reads a scene file (``tomllib``) into a frozen, validated :class:`Scene`.
Every key has a default (the reference table is in ``designs/README.md``; the docstrings of the
section classes below say the same). Anything the file gets wrong is a :class:`SceneError` whose
message names the file and the dotted key: unknown keys at any level (with the known ones and a
close match), wrong types, NaN or inf, out-of-range values, keys that do not apply (e.g.
``carpet.wave_vector`` without ``phases = "wave"``), and malformed TOML (with tomllib's line and
column).

Conventions (MODEL.md, DESIGN.md): lab frame (x, y) in the plane z = 0, lengths in filament
lengths L. ``field.direction`` is in DEGREES, anticlockwise from +y (the flow model,
:class:`~ciliary_carpet.carpet.Carpet`, takes radians: use :attr:`FieldSpec.direction_rad`). A
straight filament pushes fluid along ``d0 = -field direction`` (:attr:`FieldSpec.flow_direction`).

Sections (all optional)::

    name, description, tolerance, backend   top level
    [field]     chi_E, eta, direction
    [table]     file   (+ [table.build] n, degree)
    [carpet]    lattice, shape, spacing, origin, points, chi_N, phases, seed, wave_vector, wall
    [target]    kind, angle, line, width, centre, file, control, residual, strict,
                speed_floor, smoothness, sigma, samples, robust
    [output]    pathlines, seeds, n_seeds, periods, field, field_shape, field_margin,
                snapshots, frames, preview
    [units]     length_m, time_s, viscosity_Pa_s

Values that depend on the thrust table or on the carpet's geometry (the default target angle,
width and centre) are stored as ``None`` here and resolved by :mod:`ciliary_carpet.target`.
"""
from __future__ import annotations

import difflib
import logging
import math
import tomllib
from dataclasses import dataclass, fields, replace
from dataclasses import field as _field
from pathlib import Path

import numpy as np

from single_cilium.table import TableError, ThrustTable

from . import layout
from .paths import check_name, check_scene_paths
from .stokeslet import BACKENDS
from .target import KIND_KEYS, KINDS, applies_to

logger = logging.getLogger(__name__)

__all__ = ["SceneError", "Scene", "FieldSpec", "TableSpec", "TableBuild", "CarpetSpec", "TargetSpec",
           "OutputSpec", "Units", "load_scene", "scene_from_dict", "LATTICES", "PHASES", "TARGET_KINDS"]

LATTICES = ("row", "square", "hexagonal", "points")
PHASES = ("random", "synchronous", "wave")
TARGET_KINDS = KINDS
CONTROLS = ("cells", "cilia")
SEEDS = ("line", "grid")


class SceneError(ValueError):
    """A scene file that cannot be used; the message names the file and the dotted key."""


# ------------------------------------------------------------------------------ value checks
class _Reader:
    """Validates one TOML table: ``get`` pops checked values, ``finish`` rejects what is left."""

    def __init__(self, src: str, data, section: str, known: tuple[str, ...]):
        self.src, self.section, self.known = src, section, known
        if not isinstance(data, dict):
            raise SceneError(f"{src}: {self._where()} must be a table ({self._header()}), got {data!r}")
        unknown = [k for k in data if k not in known]
        if unknown:
            k = unknown[0]
            close = difflib.get_close_matches(k, known, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            where = f"{self._header()} unknown key" if section else "unknown top-level key"
            raise SceneError(f"{src}: {where} '{k}' (known: {', '.join(known)}){hint}")
        self.data = dict(data)

    def _where(self) -> str:
        return self.section or "the scene"

    def _header(self) -> str:
        return f"[{self.section}]" if self.section else "top level"

    def key(self, k: str) -> str:
        return f"{self.section}.{k}" if self.section else k

    def has(self, k: str) -> bool:
        return k in self.data

    def fail(self, k: str, what: str, value) -> SceneError:
        return SceneError(f"{self.src}: {self.key(k)} must be {what}, got {value!r}")

    # typed getters -----------------------------------------------------------
    def number(self, k: str, default, *, lo=None, hi=None, lo_open=False, hi_open=False, what=None):
        if k not in self.data:
            return default
        v = self.data[k]
        desc = what or _describe_range(lo, hi, lo_open, hi_open)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(k, desc, v)
        x = float(v)
        if not math.isfinite(x):
            raise SceneError(f"{self.src}: {self.key(k)} must be a finite number, got {x}")
        if lo is not None and (x < lo or (lo_open and x == lo)):
            raise self.fail(k, desc, v)
        if hi is not None and (x > hi or (hi_open and x == hi)):
            raise self.fail(k, desc, v)
        return x

    def integer(self, k: str, default, *, lo=None):
        if k not in self.data:
            return default
        v = self.data[k]
        if isinstance(v, bool) or not isinstance(v, int) or (lo is not None and v < lo):
            raise self.fail(k, "an integer" + (f" >= {lo}" if lo is not None else ""), v)
        return int(v)

    def boolean(self, k: str, default):
        if k not in self.data:
            return default
        v = self.data[k]
        if not isinstance(v, bool):
            raise self.fail(k, "true or false", v)
        return v

    def string(self, k: str, default, choices=None):
        if k not in self.data:
            return default
        v = self.data[k]
        if not isinstance(v, str) or (choices is not None and v not in choices):
            what = "one of " + ", ".join(repr(c) for c in choices) if choices else "a string"
            raise self.fail(k, what, v)
        return v

    def pair(self, k: str, default, what="two numbers [x, y]"):
        if k not in self.data:
            return default
        return _pair(self.src, self.key(k), self.data[k], what)

    def pairs(self, k: str, default, what="a non-empty list of points [[x, y], ...]"):
        if k not in self.data:
            return default
        return _pairs(self.src, self.key(k), self.data[k], what)

    def table(self, k: str):
        return self.data.get(k)


def _describe_range(lo, hi, lo_open, hi_open) -> str:
    if lo == 0 and lo_open and hi is None:
        return "a positive number"
    if lo == 0 and not lo_open and hi is None:
        return "a number >= 0"
    if lo is not None and hi is not None:
        return f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    return "a number"


def _finite_number(src: str, key: str, v, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{src}: {key} must be {what}, got {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise SceneError(f"{src}: {key} must be {what} (finite), got {x}")
    return x


def _pair(src: str, key: str, v, what: str) -> tuple[float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise SceneError(f"{src}: {key} must be {what}, got {v!r}")
    return (_finite_number(src, key, v[0], what), _finite_number(src, key, v[1], what))


def _pairs(src: str, key: str, v, what: str) -> tuple[tuple[float, float], ...]:
    if not isinstance(v, (list, tuple)) or len(v) == 0:
        raise SceneError(f"{src}: {key} must be {what}, got {v!r}")
    return tuple(_pair(src, f"{key}[{i}]", p, "two numbers [x, y]") for i, p in enumerate(v))


def _plain(v):
    """Tuples to lists, recursively (TOML/JSON-ready)."""
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    return v


def _section_dict(obj) -> dict:
    """The dataclass as a dict of its TOML keys, None values left out."""
    out = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if v is not None:
            out[f.name] = _plain(v)
    return out


def _validate(obj, parse, *args) -> None:
    """``__post_init__`` of a section: read its TOML form with the same checks as a file (so a
    section made in code or by ``dataclasses.replace`` is validated too) and store the
    normalised values (floats, tuples)."""
    for k, v in parse(f"<{type(obj).__name__}>", obj.to_dict(), *args).items():
        object.__setattr__(obj, k, v)


# ------------------------------------------------------------------------------ sections
@dataclass(frozen=True)
class FieldSpec:
    """``[field]``: the uniform field every cilium feels.

    chi_E : float, default 200
        Stimulus ``L kappa_E`` (MODEL.md).
    eta : float > 0, default 1
        Drag-to-bending ratio.
    direction : float, default 0
        Field direction in DEGREES, anticlockwise from +y (0: field along +y; straight filaments
        push the fluid along -y).
    """

    chi_E: float = 200.0
    eta: float = 1.0
    direction: float = 0.0

    def __post_init__(self) -> None:
        _validate(self, _field_kw)

    def to_dict(self) -> dict:
        return _section_dict(self)

    @property
    def direction_rad(self) -> float:
        """The field direction in radians (what :class:`~ciliary_carpet.carpet.Carpet` takes)."""
        return math.radians(self.direction)

    @property
    def field_direction(self) -> np.ndarray:
        """Unit vector along the field, lab frame: (-sin a, cos a)."""
        a = self.direction_rad
        return np.array([-math.sin(a), math.cos(a)])

    @property
    def flow_direction(self) -> np.ndarray:
        """d0 = -field direction: where a straight filament pushes the fluid on average."""
        return -self.field_direction


@dataclass(frozen=True)
class TableBuild:
    """``[table.build]``: how to compute the table when ``table.file`` does not exist.

    n : int >= 3, default 41
        chi_N grid points in [0, cutoff) (the flutter cutoff row is added exactly, plus one
        no-flutter row at 1.05 x cutoff, as in the shipped table).
    degree : int >= 2, default 8
        Polynomial degree of the filament mesh (see single_cilium).
    """

    n: int = 41
    degree: int = 8

    def __post_init__(self) -> None:
        _validate(self, _build_kw)

    def to_dict(self) -> dict:
        return _section_dict(self)


_TABLE_CACHE: dict = {}


@dataclass(frozen=True)
class TableSpec:
    """``[table]``: which thrust table the carpet uses.

    file : str, default "default"
        "default" = the table shipped with single_cilium (chi_E = 200, eta = 1); otherwise a
        NetCDF table path, relative to the scene file.
    build : TableBuild or None
        Given by a ``[table.build]`` section: when ``file`` does not exist, the table is
        computed with :func:`~single_cilium.table.build_table` and written there (minutes).
    """

    file: str = "default"
    build: TableBuild | None = None

    def __post_init__(self) -> None:
        _validate(self, _table_kw)

    def to_dict(self) -> dict:
        d = {"file": self.file}
        if self.build is not None:
            d["build"] = self.build.to_dict() if isinstance(self.build, TableBuild) else self.build
        return d

    def path(self, scene: "Scene") -> Path | None:
        """The table file this spec names, resolved against the scene's folder (None = shipped)."""
        if self.file == "default":
            return None
        p = Path(self.file).expanduser()
        return p if p.is_absolute() else scene.base_dir / p

    def load(self, scene: "Scene") -> ThrustTable:
        """Load the table (building it first if asked), and check that it is for the scene's field.

        Tables are cached per (file, modification time), so repeated loads are free; treat the
        returned table as read-only.

        Raises
        ------
        SceneError
            If the file is missing and there is no ``[table.build]``, if it is not a readable
            table, or if its (chi_E, eta) differ from ``[field]`` by more than 1e-9 relative.
        """
        src = scene.source_name
        p = self.path(scene)
        if p is None:
            key = ("default",)
            table = _TABLE_CACHE.get(key)
            if table is None:
                table = _TABLE_CACHE[key] = ThrustTable.default()
            where = "the shipped default table"
        else:
            if not p.exists():
                if self.build is None:
                    raise SceneError(
                        f"{src}: table.file '{self.file}' not found (looked for {p.absolute()}); fix the path, "
                        f"use file = \"default\" for the shipped table (chi_E = 200, eta = 1), or add a "
                        f"[table.build] section (n, degree) to compute it there (takes minutes)")
                self._build(scene, p)
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

    def _build(self, scene: "Scene", p: Path) -> None:
        from single_cilium import flutter_cutoff
        from single_cilium.table import build_table

        f, b = scene.field, self.build
        cut = flutter_cutoff(f.chi_E, f.eta, degree=b.degree)
        if not math.isfinite(cut.chi_N_cutoff):
            raise SceneError(f"{scene.source_name}: cannot build a thrust table for chi_E = {f.chi_E:g}, "
                             f"eta = {f.eta:g}: {cut.message}")
        c = cut.chi_N_cutoff
        grid = np.concatenate([np.linspace(0.0, c, b.n)[:-1], [1.05 * c]])
        logger.info("building the thrust table %s (chi_E = %g, eta = %g, %d rows)", p, f.chi_E, f.eta, grid.size)
        build_table(f.chi_E, f.eta, grid, degree=b.degree, path=p)


@dataclass(frozen=True)
class CarpetSpec:
    """``[carpet]``: where the cilia stand, their curvature without a target, and their phases.

    lattice : "row" | "square" | "hexagonal" | "points", default "square"
        See :mod:`ciliary_carpet.layout` (row along +x; hexagonal: odd rows shifted by half a
        spacing, rows sqrt(3)/2 spacing apart).
    shape : tuple of int, default (10, 10)
        (nx, ny) for square/hexagonal; (n,) for row (``shape = n`` or ``[n]`` in the file);
        () for points.
    spacing : float > 0, default 2.0
        Nearest-neighbour distance (L). For "points", the typical spacing (used for control
        points and pattern widths).
    origin : (x, y), default (0, 0)
        The lattice's lower-left base point (not used by "points").
    points : tuple of (x, y) or None
        The base points, required iff lattice = "points".
    chi_N : float, default 0.0
        Natural curvature of every cilium when the scene has no target (with a target: the
        design's starting guess for velocity targets). Checked against the table's range when the
        carpet is built.
    phases : "random" | "synchronous" | "wave", default "random"
        Phases at t = 0 (:meth:`initial_phases`).
    seed : int >= 0, default 0
        Random seed of "random" phases (ignored by the others).
    wave_vector : (kx, ky) rad per L, default (0, 0)
        Metachronal wave of "wave" phases (only with phases = "wave").
    wall : float > 0 or None
        Distance of a no-slip wall below the plane (None: free space).
    blob : float > 0, default 0.02
        Blob size of the regularised Stokeslets in L: the filament radius (default: aspect ratio
        25). Less than half the spacing. See :mod:`ciliary_carpet.kernel`.
    """

    lattice: str = "square"
    shape: tuple = (10, 10)
    spacing: float = 2.0
    origin: tuple[float, float] = (0.0, 0.0)
    points: tuple | None = None
    chi_N: float = 0.0
    phases: str = "random"
    seed: int = 0
    wave_vector: tuple[float, float] = (0.0, 0.0)
    wall: float | None = None
    blob: float = 0.02

    def __post_init__(self) -> None:
        _validate(self, _carpet_kw)

    def to_dict(self) -> dict:
        """The section as TOML types (keys that do not apply left out)."""
        d = _section_dict(self)
        if self.lattice == "points":
            d.pop("shape", None)
            d.pop("origin", None)
        if self.phases != "wave":
            d.pop("wave_vector", None)
        return d

    def bases(self) -> np.ndarray:
        """(N, 2) base points in the lab frame."""
        if self.lattice == "row":
            return layout.row(self.shape[0], self.spacing, self.origin)
        if self.lattice == "square":
            return layout.square(*self.shape, spacing=self.spacing, origin=self.origin)
        if self.lattice == "hexagonal":
            return layout.hexagonal(*self.shape, spacing=self.spacing, origin=self.origin)
        return layout.points(self.points)

    @property
    def n_cilia(self) -> int:
        return len(self.points) if self.lattice == "points" else int(np.prod(self.shape))

    @property
    def centre(self) -> np.ndarray:
        """Centre of the bounding box of the base points (the "carpet centre" of the targets)."""
        b = self.bases()
        return 0.5 * (b.min(axis=0) + b.max(axis=0))

    def initial_phases(self, bases=None) -> np.ndarray:
        """(N,) phases at t = 0 in [0, 1) for ``bases`` (default :meth:`bases`)."""
        b = self.bases() if bases is None else np.asarray(bases, dtype=float)
        if self.phases == "random":
            return layout.random_phases(b.shape[0], self.seed)
        if self.phases == "synchronous":
            return layout.synchronous_phases(b.shape[0])
        return layout.wave_phases(b, self.wave_vector)


@dataclass(frozen=True)
class TargetSpec:
    """``[target]``: the flow the carpet is designed for (see :mod:`ciliary_carpet.target`).

    kind : "none" | "uniform" | "focus" | "spread" | "shear" | "turn" | "points", default "none"
        "none": every cilium gets ``carpet.chi_N``; "points": target velocities from ``file``.
    angle : float (DEGREES) or None
        The deflection for "uniform" (signed, anticlockwise from d0), the amplitude (> 0) of
        the patterns. None: 90% of the table's reachable maximum (resolved by the target).
    line : float, default 0
        focus/spread/shear: position of the line, along the cross-stream axis from the carpet's
        centre (L).
    width : float > 0 or None
        focus/spread/shear: transition width (L); None = one carpet spacing.
    centre : (x, y) or None
        turn: the centre of the turn; None = the carpet's centre.
    file : str or None
        points: CSV (columns x, y, u, v) or NetCDF (variables x, y, u, v) of control points and
        target velocities, relative to the scene file. Required for kind = "points".
    control : "cells" | "cilia" | tuple of (x, y), default "cells"
        Where the designed mean flow is compared with the target
        (:func:`~ciliary_carpet.target.control_points`).
    strict : bool, default False
        False: unreachable angle requests are clipped to the reachable range and a design above
        ``residual`` is returned (the closest flow the cilia make), both with a warning naming
        where and by how much; True (batch runs): both are errors (the command line exits 3).
    speed_floor : float in [0, 1), default 0.3
        Angle targets: each control point must keep at least this fraction of the speed the
        straight cilia within 5 spacings make there, along the target direction
        (:func:`~ciliary_carpet.design.floor_reference`).
    smoothness : float >= 0, default 0
        Weight of the neighbour-difference regulariser of the layout (fabrication cost).
    sigma : float >= 0, default 0
        Relative fabrication error of chi_N: with sigma > 0 the design reports the expected
        residual and its spread (:func:`~ciliary_carpet.design.tolerance_study`).
    samples : int >= 1, default 64
        Samples of that study.
    robust : bool, default False
        Design for the expected objective under the error ``sigma`` (a sample average over 16
        fixed samples) instead of the nominal one; needs sigma > 0.
    residual : float > 0, default 0.05
        Acceptance threshold on the overall (rms) residual of the design: radians for angle
        targets, relative to rms |U| for "points".
    """

    kind: str = "none"
    angle: float | None = None
    line: float = 0.0
    width: float | None = None
    centre: tuple[float, float] | None = None
    file: str | None = None
    control: str | tuple = "cells"
    residual: float = 0.05
    strict: bool = False
    speed_floor: float = 0.3
    smoothness: float = 0.0
    sigma: float = 0.0
    samples: int = 64
    robust: bool = False

    def __post_init__(self) -> None:
        _validate(self, _target_kw)

    def to_dict(self) -> dict:
        """The section as TOML types (keys that do not apply to the kind left out)."""
        if self.kind == "none":
            return {"kind": "none"}
        d = _section_dict(self)
        for k, kinds in _TARGET_ONLY.items():
            if self.kind not in kinds:
                d.pop(k, None)
        return d

    @property
    def angle_rad(self) -> float | None:
        return None if self.angle is None else math.radians(self.angle)


@dataclass(frozen=True)
class OutputSpec:
    """``[output]``: what a render writes.

    pathlines : bool, default True
        Path lines of tracers (.vtp).
    seeds : "line" | "grid" | tuple of (x, y), default "line"
        "line": a line of seeds upstream of the carpet, across the flow; "grid": a grid over
        the carpet; or explicit points.
    n_seeds : int >= 1, default 100
        Number of seeds for "line"/"grid" (not used with explicit seeds).
    periods : float > 0 or None (default)
        Path-line duration, in periods of the straight filament; None (key left out): long
        enough for the tracers to cross the whole carpet at its mean speed (see
        :func:`ciliary_carpet.render.render`).
    pathline_model : "auto" | "resolved" | "mean", default "auto"
        Flow the tracers follow: the time-resolved beat, or the long-time model (the mean flow,
        :mod:`ciliary_carpet.pathlines`); "auto" takes the mean flow when the scene's tolerance
        is at least the model's measured error (``pathlines.MEAN_MODEL_ERROR``).
    samples_per_period : int >= 1, default 16
        Path-line points per beat period (dense output).
    ftle : bool, default True
        The finite-time Lyapunov exponent field (ftle.vti) and the mixing number
        (:mod:`ciliary_carpet.ftle`).
    field : bool, default True
        The mean velocity field (.vti).
    field_shape : (nx, ny) ints >= 2, default (80, 80)
        Grid of the velocity field.
    field_margin : float >= 0, default 5.0
        How far the field grid extends beyond the carpet (L).
    snapshots : int >= 0, default 4
        Instantaneous velocity-field snapshots.
    frames : int >= 0, default 40
        Cilia shape frames over one period of the straight filament.
    preview : bool, default True
        A preview image.
    """

    pathlines: bool = True
    seeds: str | tuple = "line"
    n_seeds: int = 100
    periods: float | None = None
    pathline_model: str = "auto"
    samples_per_period: int = 16
    ftle: bool = True
    field: bool = True
    field_shape: tuple[int, int] = (80, 80)
    field_margin: float = 5.0
    snapshots: int = 4
    frames: int = 40
    preview: bool = True

    def __post_init__(self) -> None:
        _validate(self, _output_kw)

    def to_dict(self) -> dict:
        return _section_dict(self)


@dataclass(frozen=True)
class Units:
    """``[units]`` (all three keys required when the section is given; absent: dimensionless
    output): filament length [m], relaxation time [s], fluid viscosity [Pa s]."""

    length_m: float
    time_s: float
    viscosity_Pa_s: float

    def __post_init__(self) -> None:
        _validate(self, _units_kw)

    def to_dict(self) -> dict:
        return _section_dict(self)

    def scales(self):
        """The :class:`~ciliary_carpet.carpet.Scales` of these units."""
        from .carpet import Scales

        return Scales(self.length_m, self.time_s, self.viscosity_Pa_s)


@dataclass(frozen=True)
class Scene:
    """A validated scene (see the module docstring and ``designs/README.md``).

    name : str (default: the file's stem); description : str; field, table, carpet, target,
    output : the sections; tolerance : float in (0, 1), default 1e-3, the flow model's error
    tolerance; backend : one of :data:`~ciliary_carpet.stokeslet.BACKENDS`, default "auto", the
    evaluator of the flow sums (``"cuda"``: the GPU; checked when a render starts, not when the
    file is read, so that a scene for a GPU machine loads anywhere); units : Units or None;
    source : the scene file (None for scenes made in memory), for relative paths and messages.
    """

    name: str
    description: str = ""
    field: FieldSpec = _field(default_factory=FieldSpec)
    table: TableSpec = _field(default_factory=TableSpec)
    carpet: CarpetSpec = _field(default_factory=CarpetSpec)
    target: TargetSpec = _field(default_factory=TargetSpec)
    output: OutputSpec = _field(default_factory=OutputSpec)
    tolerance: float = 1e-3
    units: Units | None = None
    source: Path | None = None
    backend: str = "auto"

    def __post_init__(self) -> None:
        kw = _top_kw("<Scene>", {"name": self.name, "description": self.description, "tolerance": self.tolerance,
                                 "backend": self.backend})
        for k, v in kw.items():
            object.__setattr__(self, k, v)
        for k, cls in (("field", FieldSpec), ("table", TableSpec), ("carpet", CarpetSpec), ("target", TargetSpec),
                       ("output", OutputSpec), ("units", Units)):
            v = getattr(self, k)
            if not isinstance(v, cls) and not (k == "units" and v is None):
                raise SceneError(f"<Scene>: {k} must be a {cls.__name__}, got {type(v).__name__}")
        if self.source is not None:
            object.__setattr__(self, "source", Path(self.source))

    @property
    def base_dir(self) -> Path:
        """The folder relative paths refer to (the scene file's; the working directory without one)."""
        return self.source.parent if self.source is not None else Path.cwd()

    @property
    def source_name(self) -> str:
        return str(self.source) if self.source is not None else f"<scene {self.name}>"

    def load_table(self) -> ThrustTable:
        """``self.table.load(self)``."""
        return self.table.load(self)

    def to_dict(self) -> dict:
        """The resolved scene, defaults filled in, as plain TOML/JSON types (keys that are None,
        i.e. decided later or absent, are left out; ``source`` is not a scene key and is not
        included). ``scene_from_dict(s.to_dict(), s.source)`` gives ``s`` back."""
        d = {"name": self.name, "description": self.description, "tolerance": self.tolerance, "backend": self.backend,
             "field": self.field.to_dict(), "table": self.table.to_dict(), "carpet": self.carpet.to_dict(),
             "target": self.target.to_dict(), "output": self.output.to_dict()}
        if self.units is not None:
            d["units"] = self.units.to_dict()
        return d

    def reduced(self, max_cilia: int = 16, n_seeds: int = 10, field_shape=(16, 16), periods: float = 2,
                snapshots: int = 1, frames: int = 4) -> "Scene":
        """A smaller copy for fast tests: at most ``max_cilia`` cilia (same lattice and spacing,
        shape shrunk in proportion, same carpet centre so that absolute coordinates -- explicit
        control points, seeds, turn centre -- still fall on it; a "points" carpet keeps the
        points nearest its centre), and outputs no larger than the arguments. Never enlarges."""
        c = self.carpet
        m = int(max_cilia)
        if m < 1:
            raise ValueError(f"max_cilia must be >= 1, got {max_cilia!r}")
        if c.n_cilia > m:
            centre = c.centre
            if c.lattice == "points":
                pts = np.asarray(c.points)
                keep = np.sort(np.argsort(np.linalg.norm(pts - centre, axis=1), kind="stable")[:m])
                c = replace(c, points=tuple(tuple(map(float, pts[i])) for i in keep))
            else:
                if c.lattice == "row":
                    shape = (m,)
                else:
                    nx, ny = c.shape
                    f = math.sqrt(m / (nx * ny))
                    sx, sy = max(1, min(nx, int(nx * f))), max(1, min(ny, int(ny * f)))
                    # use the room left by rounding down, on the axis that gains most
                    while True:
                        grow = [(sx + 1) * sy <= m and sx < nx, sx * (sy + 1) <= m and sy < ny]
                        if grow[0] and (not grow[1] or sx / nx <= sy / ny):
                            sx += 1
                        elif grow[1]:
                            sy += 1
                        else:
                            break
                    shape = (sx, sy)
                c = replace(c, shape=shape, origin=(0.0, 0.0))
                shift = centre - c.centre
                c = replace(c, origin=(float(shift[0]), float(shift[1])))
        o = self.output
        seeds = o.seeds
        if not isinstance(seeds, str) and len(seeds) > n_seeds:
            idx = np.unique(np.linspace(0, len(seeds) - 1, max(1, int(n_seeds))).round().astype(int))
            seeds = tuple(seeds[i] for i in idx)
        o = replace(o, seeds=seeds, n_seeds=min(o.n_seeds, int(n_seeds)),
                    field_shape=(min(o.field_shape[0], int(field_shape[0])), min(o.field_shape[1], int(field_shape[1]))),
                    periods=float(periods) if o.periods is None else min(o.periods, float(periods)), snapshots=min(o.snapshots, int(snapshots)),
                    frames=min(o.frames, int(frames)))
        return replace(self, carpet=c, output=o)


# which target keys apply to which kinds (others are an error): from the registry in target.py
_TARGET_ONLY = {k: applies_to(k) for k in sorted({k for keys in KIND_KEYS.values() for k in keys})}


# ------------------------------------------------------------------------------ parsing
def load_scene(path, *, allow_outside: bool = False) -> Scene:
    """Read and validate the scene file ``path`` (TOML). Raises :class:`SceneError` naming the
    file (and the dotted key, or tomllib's line and column). ``table.file`` and ``target.file``
    must lie below the scene's folder unless ``allow_outside`` (:mod:`ciliary_carpet.paths`)."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"{path}: cannot read the scene file ({exc.strerror or exc})") from None
    try:
        data = tomllib.loads(text.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise SceneError(f"{path}: not UTF-8 text ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: malformed TOML: {exc}") from None
    return scene_from_dict(data, source=path, allow_outside=allow_outside)


def scene_from_dict(data: dict, source=None, *, allow_outside: bool = False) -> Scene:
    """A :class:`Scene` from the parsed TOML ``data`` (the same checks as :func:`load_scene`);
    ``source`` is the file it came from (for relative paths and messages), or None."""
    source = None if source is None else Path(source)
    src = str(source) if source is not None else "<scene>"
    if not isinstance(data, dict):
        raise SceneError(f"{src}: a scene must be a table of keys, got {type(data).__name__}")
    sections = ("field", "table", "carpet", "target", "output", "units")
    _Reader(src, data, "", _TOP_KEYS + sections)  # unknown keys
    top = _top_kw(src, {k: v for k, v in data.items() if k not in sections},
                  source.stem if source is not None else "scene")
    base = source.parent if source is not None else Path.cwd()
    check_scene_paths(src, data, base, allow_outside=allow_outside)
    sec = {k: data.get(k, {}) for k in sections}
    return Scene(
        **top,
        field=FieldSpec(**_field_kw(src, sec["field"])),
        table=TableSpec(**_table_kw(src, sec["table"])),
        carpet=CarpetSpec(**_carpet_kw(src, sec["carpet"])),
        target=TargetSpec(**_target_kw(src, sec["target"], base)),
        output=OutputSpec(**_output_kw(src, sec["output"])),
        units=Units(**_units_kw(src, sec["units"])) if "units" in data else None,
        source=source,
    )


_TOP_KEYS = ("name", "description", "tolerance", "backend")


def _top_kw(src, data, default_name="scene") -> dict:
    r = _Reader(src, data, "", _TOP_KEYS)
    name = r.string("name", default_name)
    if not name.strip():
        raise r.fail("name", "a non-empty string", name)
    check_name(src, "name", name)
    return dict(name=name, description=r.string("description", ""),
                tolerance=r.number("tolerance", 1e-3, lo=0, hi=1, lo_open=True, hi_open=True),
                backend=r.string("backend", "auto", BACKENDS))


def _field_kw(src, data) -> dict:
    r = _Reader(src, data, "field", ("chi_E", "eta", "direction"))
    return dict(chi_E=r.number("chi_E", 200.0), eta=r.number("eta", 1.0, lo=0, lo_open=True),
                direction=r.number("direction", 0.0))


def _build_kw(src, data) -> dict:
    b = _Reader(src, data, "table.build", ("n", "degree"))
    return dict(n=b.integer("n", 41, lo=3), degree=b.integer("degree", 8, lo=2))


def _table_kw(src, data) -> dict:
    r = _Reader(src, data, "table", ("file", "build"))
    file = r.string("file", "default")
    if not file.strip():
        raise r.fail("file", '"default" or a table path', file)
    build = None
    if r.has("build"):
        build = TableBuild(**_build_kw(src, r.table("build")))
        if file == "default":
            raise SceneError(f'{src}: [table.build] needs table.file to name where the table is written '
                             f'(file = "default" is the shipped table)')
    return dict(file=file, build=build)


def _carpet_kw(src, data) -> dict:
    r = _Reader(src, data, "carpet", tuple(f.name for f in fields(CarpetSpec)))
    lattice = r.string("lattice", "square", LATTICES)
    spacing = r.number("spacing", 2.0, lo=0, lo_open=True)
    points = None
    if lattice == "points":
        for k in ("shape", "origin"):
            if r.has(k):
                raise SceneError(f"{src}: carpet.{k} does not apply to lattice = \"points\" "
                                 f"(the base points are carpet.points)")
        if not r.has("points"):
            raise SceneError(f"{src}: carpet.points is required with lattice = \"points\" "
                             f"(a list of base points [[x, y], ...])")
        points = r.pairs("points", None)
        shape = ()
    else:
        if r.has("points"):
            raise SceneError(f"{src}: carpet.points applies only to lattice = \"points\" (here "
                             f"lattice = \"{lattice}\")")
        if lattice == "row":
            v = r.data.get("shape", [10])
            if isinstance(v, list) and len(v) == 1:
                v = v[0]
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise r.fail("shape", "a positive integer n or [n] for lattice = \"row\"", r.data.get("shape"))
            shape = (v,)
        else:
            v = r.data.get("shape", [10, 10])
            if (not isinstance(v, list) or len(v) != 2
                    or any(isinstance(x, bool) or not isinstance(x, int) or x < 1 for x in v)):
                raise r.fail("shape", f"two positive integers [nx, ny] for lattice = \"{lattice}\"", v)
            shape = (int(v[0]), int(v[1]))
    phases = r.string("phases", "random", PHASES)
    if r.has("wave_vector") and phases != "wave":
        raise SceneError(f"{src}: carpet.wave_vector applies only to phases = \"wave\" (here phases = \"{phases}\")")
    return dict(
        lattice=lattice, shape=shape, spacing=spacing, origin=r.pair("origin", (0.0, 0.0)), points=points,
        chi_N=r.number("chi_N", 0.0), phases=phases, seed=r.integer("seed", 0, lo=0),
        wave_vector=r.pair("wave_vector", (0.0, 0.0), "two numbers [kx, ky] (rad per L)"),
        wall=r.number("wall", None, lo=0, lo_open=True), blob=_blob(r, spacing))


def _blob(r, spacing) -> float:
    blob = r.number("blob", 0.02, lo=0, lo_open=True, what="a positive length in L (the filament radius)")
    if spacing is not None and blob >= 0.5 * spacing:
        raise r.fail("blob", f"less than half the spacing ({0.5 * spacing:g} L): the blobs of neighbouring "
                     "filaments would overlap", blob)
    return blob


def _target_kw(src, data, base_dir=None) -> dict:
    r = _Reader(src, data, "target", tuple(f.name for f in fields(TargetSpec)))
    kind = r.string("kind", "none", TARGET_KINDS)
    for k, kinds in _TARGET_ONLY.items():
        if r.has(k) and kind not in kinds:
            raise SceneError(f"{src}: target.{k} does not apply to kind = \"{kind}\" (it is used by kind = "
                             f"{', '.join(repr(x) for x in kinds)})")
    if kind == "uniform":
        angle = r.number("angle", None, lo=-180, hi=180, what="a deflection in degrees in [-180, 180]")
    else:
        angle = r.number("angle", None, lo=0, hi=180, lo_open=True,
                         what="an amplitude in degrees in (0, 180]")
    file = r.string("file", None)
    if kind == "points":
        if file is None:
            raise SceneError(f"{src}: target.file is required with kind = \"points\" (a CSV with columns "
                             f"x, y, u, v or a NetCDF file with variables x, y, u, v)")
        if not file.strip():
            raise r.fail("file", "a file path", file)
        p = Path(file).expanduser()
        if base_dir is not None and not (p if p.is_absolute() else base_dir / p).is_file():
            raise SceneError(f"{src}: target.file '{file}' not found (looked for {(base_dir / p).absolute()})")
    control = r.data.get("control", "cells")
    if isinstance(control, str):
        if control not in CONTROLS:
            raise r.fail("control", '"cells", "cilia" or a list of points [[x, y], ...]', control)
    else:
        control = r.pairs("control", None, '"cells", "cilia" or a list of points [[x, y], ...]')
    sigma, robust = r.number("sigma", 0.0, lo=0), r.boolean("robust", False)
    if robust and not sigma > 0:
        raise r.fail("robust", "false unless target.sigma > 0 (it designs for the fabrication tolerance sigma)",
                     robust)
    return dict(
        kind=kind, angle=angle, line=r.number("line", 0.0), width=r.number("width", None, lo=0, lo_open=True),
        centre=r.pair("centre", None), file=file, control=control,
        residual=r.number("residual", 0.05, lo=0, lo_open=True), strict=r.boolean("strict", False),
        speed_floor=r.number("speed_floor", 0.3, lo=0, hi=1, hi_open=True),
        smoothness=r.number("smoothness", 0.0, lo=0), sigma=sigma,
        samples=r.integer("samples", 64, lo=1), robust=robust)


def _output_kw(src, data) -> dict:
    r = _Reader(src, data, "output", tuple(f.name for f in fields(OutputSpec)))
    seeds = r.data.get("seeds", "line")
    if isinstance(seeds, str):
        if seeds not in SEEDS:
            raise r.fail("seeds", '"line", "grid" or a list of points [[x, y], ...]', seeds)
    else:
        seeds = r.pairs("seeds", None, '"line", "grid" or a list of points [[x, y], ...]')
    fs = r.data.get("field_shape", [80, 80])
    if (not isinstance(fs, list) or len(fs) != 2
            or any(isinstance(x, bool) or not isinstance(x, int) or x < 2 for x in fs)):
        raise r.fail("field_shape", "two integers >= 2 [nx, ny]", fs)
    return dict(
        pathlines=r.boolean("pathlines", True), seeds=seeds, n_seeds=r.integer("n_seeds", 100, lo=1),
        periods=r.number("periods", None, lo=0, lo_open=True),
        pathline_model=r.string("pathline_model", "auto", ("auto", "resolved", "mean")),
        samples_per_period=r.integer("samples_per_period", 16, lo=1), ftle=r.boolean("ftle", True),
        field=r.boolean("field", True),
        field_shape=(int(fs[0]), int(fs[1])), field_margin=r.number("field_margin", 5.0, lo=0),
        snapshots=r.integer("snapshots", 4, lo=0), frames=r.integer("frames", 40, lo=0),
        preview=r.boolean("preview", True))


def _units_kw(src, data) -> dict:
    keys = ("length_m", "time_s", "viscosity_Pa_s")
    r = _Reader(src, data, "units", keys)
    missing = [k for k in keys if not r.has(k)]
    if missing:
        raise SceneError(f"{src}: [units] needs all of {', '.join(keys)} (missing: {', '.join(missing)}); "
                         f"leave the section out for dimensionless output")
    return {k: r.number(k, None, lo=0, lo_open=True) for k in keys}
