"""Scene files: a carpet, its field, its target flow and what to output, in TOML.

:func:`load_scene` reads a scene file (``tomllib``) into a frozen, validated :class:`Scene`.
Every key has one home: a field of its section class below, whose metadata holds its default,
accepted values and meaning (:mod:`ciliary_carpet.scenes.schema`; the ``[target]`` section is
:mod:`ciliary_carpet.scenes.target_spec`, the registry of target kinds
:mod:`ciliary_carpet.design.patterns`). The section docstrings and the
key reference of ``designs/README.md`` (:func:`reference`, checked by the tests) are made from
them. Anything the file gets wrong is a :class:`SceneError` whose message names the file and the
dotted key: unknown keys at any level (with the known ones and a close match), wrong types, NaN
or inf, out-of-range values, keys that do not apply (e.g. ``carpet.wave_vector`` without
``phases = "wave"``), and malformed TOML (with tomllib's line and column).

Conventions (MODEL.md, DESIGN.md): lab frame (x, y) in the plane z = 0, lengths in filament
lengths L. ``carpet.geometry`` says where the cilia beat (:mod:`ciliary_carpet.carpet.geometry`):
``"planar"`` (default: in the plane z = 0, the field in it along ``field.direction``) or
``"standing"`` (clamped on the substrate z = 0, the field along +z, each beat plane turned about
the normal by ``carpet.azimuth``, DEGREES anticlockwise from +x; ``field.direction`` must be 0,
``carpet.wall`` is the wall's distance below the clamps, default 0: the substrate; a standing
scene has no ``[target]`` yet and its cilia are uncoupled). Keys that do not apply to the
scene's geometry are a SceneError. ``field.direction`` is in DEGREES, anticlockwise from +y (the flow model,
:class:`~ciliary_carpet.carpet.carpet.Carpet`, takes radians: use :attr:`FieldSpec.direction_rad`). A
straight filament pushes fluid along ``d0 = -field direction`` (:attr:`FieldSpec.flow_direction`).

Sections (all optional): top level (name, description, tolerance, backend), ``[field]``, ``[table]``
(+ ``[table.build]``), ``[carpet]``, ``[target]``, ``[output]``, ``[units]``, and a program's
states ``[[state]]`` (:class:`StateSpec`: one layout designed for several field strengths, each
state with its ``chi_E``, its ``[state.target]`` and its ``[state.table]``; a program has no
``[target]``, ``[table]`` or ``field.chi_E`` of its own; each state's own scene is
:func:`~ciliary_carpet.scenes.states.state_scenes`).

Values that depend on the thrust table or on the carpet's geometry (the default target angle,
width and centre) are stored as ``None`` here and resolved with the objects (the target
:class:`~ciliary_carpet.design.target.Target` against the table and its frame); the objects a
scene describes (table, carpet, target) are built by :mod:`ciliary_carpet.scenes.assembly`, the
only route from a scene to objects (this module is the file format: it reads and checks, and
builds nothing).

One concept over 500 lines: the scene file's schema, one section per table, and its checks.
"""
from __future__ import annotations

import inspect
import logging
import math
import os
import tomllib
from dataclasses import dataclass, replace
from dataclasses import field as _field
from pathlib import Path

import numpy as np

import single_cilium.table as _table
from single_cilium.lookup import SHIPPED_FIELDS

from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import BLOB, sbt_viscosity
from ciliary_carpet.carpet.coupling import COUPLINGS
from ciliary_carpet.carpet.geometry import GEOMETRIES
from ciliary_carpet.scenes.paths import check_derived, check_input, check_name, check_scene_paths, table_parts
from ciliary_carpet.transport.flow import AUTO_RESOLVED_BEATS, FLOWS, MEAN_MODEL_ERROR
from ciliary_carpet.scenes.schema import SceneError, Section, key, keys_of, markdown_table, read, reader, section, values
from ciliary_carpet.stokes import BACKENDS
from ciliary_carpet.design.patterns import KINDS, STANDING_KINDS, SURFACE_KINDS, kinds_table
from ciliary_carpet.scenes.target_spec import TargetSpec

logger = logging.getLogger(__name__)

__all__ = ["SceneError", "Scene", "FieldSpec", "TableSpec", "TableBuild", "CarpetSpec", "TargetSpec",
           "OutputSpec", "Units", "StateSpec", "load_scene", "scene_from_dict", "as_scene", "reference", "LATTICES",
           "PHASES", "TARGET_KINDS", "MIN_STATES"]

LATTICES = ("row", "square", "hexagonal", "points")
MIN_SPACING = 1.0
"""The smallest distance between base points (L): the filament length, the farthest a cilium's
beat reaches from its base (planar or standing), so cilia at least this far apart cannot touch
(:meth:`Carpet <ciliary_carpet.carpet.carpet.Carpet>` checks its own layout against the reach
of its beat)."""
MAX_LENGTH = 1e6
"""The largest spacing or wall distance (L) a scene takes: beyond it the flow sums lose their
digits (a wall that far is free space: leave it out)."""
MIN_BLOB = 1e-4
"""The smallest filament radius (L): slender-body theory at aspect ratio 5000."""
CHI_E_MAX = 1e4
"""The largest |chi_E|: the equilibrium's boundary layer 1 / chi_E must be resolvable."""
ETA_RANGE = (1e-3, 1e3)
"""The drag-to-bending ratios eta a scene takes."""
VISCOSITY_FACTOR = 100.0
"""How far (a factor) ``carpet.viscosity`` may lie from the filaments' own (slender-body theory of
eta at radius ``blob``): farther, the flow's speed and the filaments' drag disagree by more than
that factor, and the path lines' cost grows with the speed."""
PHASES = ("random", "synchronous", "wave")
TARGET_KINDS = KINDS
SEEDS = ("line", "grid")
SECTIONS = ("field", "table", "carpet", "target", "output", "units")
STATE = "state"
"""The TOML key of a program's states, an array of tables (``[[state]]``)."""
MIN_STATES = 2
"""The fewest states a program has (one field is a plain scene: ``[field]`` and ``[target]``)."""
_SHIPPED = " or ".join(f"{c:g}" for c in SHIPPED_FIELDS)


# ------------------------------------------------------------------------------ sections
@section
@dataclass(frozen=True)
class FieldSpec(Section):
    """``[field]``: the uniform field every cilium feels (0: field along +y; straight filaments
    push the fluid along -y)."""

    SECTION = "field"

    chi_E: float = key(200.0, "stimulus L kappa_E (its boundary layer, 1 / chi_E, must be resolvable by a mesh)",
                       lo=-CHI_E_MAX, hi=CHI_E_MAX)
    eta: float = key(1.0, "drag-to-bending ratio", lo=ETA_RANGE[0], hi=ETA_RANGE[1])
    direction: float = key(0.0, "field direction, anticlockwise from +y (planar carpets; a standing carpet's field is "
                           "along +z: 0 or absent)", shown="float (degrees)")

    @property
    def direction_rad(self) -> float:
        """The field direction in radians (what :class:`~ciliary_carpet.carpet.carpet.Carpet` takes)."""
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


@section
@dataclass(frozen=True)
class TableBuild(Section):
    """``[table.build]``: how to compute the table when ``table.file`` does not exist."""

    SECTION = "table.build"

    n: int = key(41, "only when `file` does not exist: compute the table with `build_table` over chi_N in "
                 "[0, cutoff) with `n` points, plus the flutter-cutoff row and one no-flutter row at 1.05 x "
                 "cutoff, and write it to `file` (minutes; resumable)", "int", lo=3, hi=10_000)
    degree: int = key(inspect.signature(_table.build_table).parameters["degree"].default,  # build_table's own default
                      "mesh degree of that computation (`single_cilium.table.build_table`)", "int", lo=4, hi=32)
    flow: float | None = key(None, "U_max: build the table over a grid of background flows, `U_par` and `U_perp` each "
                             "in [-U_max, U_max] (L/tau) with `flow_points` values and `n` chi_N rows reaching 1.05 x "
                             "the largest cutoff of the grid's corners. Absent: with `carpet.coupling = \"mean\"` (the "
                             "default) the shipped flow table's grid (U_max = 1.5, 7 x 7 flows, 20 chi_N rows: about "
                             "5 minutes on 2 cores), with `coupling = \"none\"` still fluid",
                             lo=0, lo_open=True, hi=100, default_shown="- (see text)")
    flow_points: int = key(5, "values per flow component with `flow` (odd: U = 0 is a flow of the grid)", "int", lo=3,
                           hi=101)

    @classmethod
    def parse(cls, src: str, data, section: str = "table.build") -> dict:
        """The keyword arguments of the ``[table.build]`` table ``data`` (file ``src``; ``section``:
        its dotted name in messages, ``"state[1].table.build"`` for a state's)."""
        return read(src, TableBuild, data, section)[1]


@section
@dataclass(frozen=True)
class TableSpec(Section):
    """``[table]``: which thrust table the carpet uses; ``build`` (a :class:`TableBuild`, given by
    a ``[table.build]`` section): when ``file`` does not exist, the table is computed with
    :func:`~single_cilium.table.build_table` and written there (minutes). Without it a missing
    ``file`` is an error."""

    SECTION = "table"

    file: str = key("default", '`"default"`: the table shipped with single_cilium for the field\'s chi_E '
                    f'({_SHIPPED}; eta = 1; another field is an error): over the background flow for a coupled '
                    'carpet (`carpet.coupling = "mean"`, the default), over chi_N in still fluid for '
                    '`coupling = "none"`; else a NetCDF table path, relative to the scene file. Its (chi_E, eta) must '
                    "match `[field]` (relative 1e-9)", "str")
    build: TableBuild | None = key(None, "the `[table.build]` section", "table")

    @classmethod
    def parse(cls, src: str, data, section: str = "table") -> dict:
        """The keyword arguments of the ``[table]`` table ``data`` (file ``src``; ``section``: its
        dotted name in messages, ``"state[1].table"`` for a state's)."""
        r, kw = read(src, TableSpec, data, section)
        file = kw["file"]
        if not file.strip():
            raise r.fail("file", '"default" or a table path', file)
        kw["build"] = None
        if r.has("build"):
            kw["build"] = TableBuild(**TableBuild.parse(src, r.data["build"], f"{section}.build"))
            if kw["build"].flow is not None and kw["build"].flow_points % 2 == 0:
                raise SceneError(f"{src}: {section}.build.flow_points must be odd (U = 0, still fluid, must be a flow "
                                 f"of the grid), got {kw['build'].flow_points}")
            if file == "default":
                raise SceneError(f'{src}: [{section}.build] needs {section}.file to name where the table is written '
                                 f'(file = "default" is the shipped table)')
        return kw

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


@section
@dataclass(frozen=True)
class CarpetSpec(Section):
    """``[carpet]``: where the cilia stand, their curvature without a target, and their phases
    (lattices: :mod:`ciliary_carpet.carpet.layout`)."""

    SECTION = "carpet"

    lattice: str = key("square", "row along +x; square; hexagonal (odd rows shifted by half a spacing, rows "
                       "sqrt(3)/2 spacing apart); explicit points", "str", choices=LATTICES)
    shape: tuple = key((10, 10), "number of cilia per direction (not with `\"points\"`; a row without it takes "
                       "the first number)", "custom", shown="`[nx, ny]` ints (row: `n` or `[n]`)")
    spacing: float = key(2.0, 'nearest-neighbour distance (L), at least the filament length (closer cilia can touch); '
                         'for `"points"` the typical spacing (control points, pattern widths; the points themselves '
                         "must lie at least 1 L apart)", lo=MIN_SPACING, hi=MAX_LENGTH,
                         what=f"a number in [{MIN_SPACING:g}, {MAX_LENGTH:g}] (L; at least the filament length: "
                              "closer cilia can touch)")
    origin: tuple[float, float] = key((0.0, 0.0), 'the lattice\'s lower-left base point (not with `"points"`)',
                                      "pair")
    points: tuple | None = key(None, 'base points; required iff `lattice = "points"`', "pairs", default_shown="-")
    chi_N: float = key(0.0, "curvature of every cilium when there is no target (with a target: the design's "
                       "starting guess for velocity targets); checked against the table's range")
    phases: str = key("random", "beat phases at t = 0", "str", choices=PHASES)
    seed: int = key(0, "seed of random phases", "int", lo=0)
    wave_vector: tuple[float, float] = key(
        (0.0, 0.0), 'metachronal wave: phase = -(k . x) / 2 pi; only with `phases = "wave"`', "pair",
        what="two numbers [kx, ky] (rad per L)", shown="`[kx, ky]` (rad per L)")
    geometry: str = key("planar", '`"planar"`: the cilia lie and beat in the plane z = 0, the field in it; '
                        '`"standing"`: each cilium is clamped at its base on the substrate z = 0, the field along +z, '
                        "its beat plane turned about the normal by `azimuth`", "str", choices=GEOMETRIES)
    azimuth: float | tuple | None = key(
        None, 'standing carpets only: the beat-plane azimuth psi of every cilium (one number) or of each (a list, '
        "one per cilium in base-point order), degrees anticlockwise from +x; a positive chi_N pushes the fluid "
        "along psi", "custom", shown="float or list (degrees)", default_shown="`0.0` (standing)")
    wall: float | None = key(None, "planar: distance of a no-slip wall below the plane (at least a filament diameter, "
                             "2 `blob`; absent: free space); standing: distance of the wall below the clamps "
                             "(absent: 0, the substrate itself)",
                             lo=0, hi=MAX_LENGTH, default_shown="absent (planar), `0.0` (standing)")
    viscosity: float | None = key(None, "fluid viscosity of the flow (B tau / L^4, the model's unit), within a factor "
                                  f"{VISCOSITY_FACTOR:g} of the one the filaments' drag implies; absent: that one "
                                  "(slender-body theory at radius `blob`: 0.653 eta for the default)",
                                  lo=0, lo_open=True, default_shown="- (from eta)",
                                  shown=f"float, [1/{VISCOSITY_FACTOR:g}, {VISCOSITY_FACTOR:g}] x the filaments'")
    coupling: str = key("mean", '`"mean"`: each cilium beats in the mean flow the others make at it, solved '
                        "self-consistently (the flow a carpet really makes; needs a table over the background flow: "
                        f'the shipped one for chi_E = {_SHIPPED}, eta = 1, else `[table.build]`); `"none"`: each beats as '
                        "in still fluid (the uncoupled model: faster flows than the cilia can sustain)", "str",
                        choices=COUPLINGS)
    blob: float = key(BLOB, "blob size of the regularised Stokeslets in L: the filament radius (the flow stays "
                      "bounded at the filaments)", lo=MIN_BLOB, hi=0.5, hi_open=True,
                      what=f"a length in [{MIN_BLOB:g}, 0.5) L (the filament radius)",
                      shown=f"{MIN_BLOB:g} <= float < spacing / 2")

    @classmethod
    def parse(cls, src: str, data) -> dict:
        r = reader(src, CarpetSpec, data)
        spec = keys_of(CarpetSpec)
        lattice = r.get("lattice", *spec["lattice"])
        if lattice == "points":
            for k in ("shape", "origin"):
                if r.has(k):
                    raise SceneError(f"{src}: carpet.{k} does not apply to lattice = \"points\" "
                                     f"(the base points are carpet.points)")
            if not r.has("points"):
                raise SceneError(f"{src}: carpet.points is required with lattice = \"points\" "
                                 f"(a list of base points [[x, y], ...])")
        elif r.has("points"):
            raise SceneError(f"{src}: carpet.points applies only to lattice = \"points\" (here "
                             f"lattice = \"{lattice}\")")
        geometry = r.get("geometry", *spec["geometry"])
        if geometry != "standing" and r.has("azimuth"):
            raise SceneError(f'{src}: carpet.azimuth applies only to geometry = "standing" (a planar carpet is turned '
                             f'by field.direction)')
        phases = r.get("phases", *spec["phases"])
        if r.has("wave_vector") and phases != "wave":
            raise SceneError(f"{src}: carpet.wave_vector applies only to phases = \"wave\" (here phases = \"{phases}\")")
        kw = values(r, CarpetSpec)
        default = spec["shape"][1]
        if lattice == "points":
            kw["shape"] = ()
        elif lattice == "row":
            v = r.data.get("shape", list(default[:1]))
            if isinstance(v, list) and len(v) == 1:
                v = v[0]
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise r.fail("shape", "a positive integer n or [n] for lattice = \"row\"", r.data.get("shape"))
            kw["shape"] = (v,)
        else:
            v = r.data.get("shape", list(default))
            if (not isinstance(v, list) or len(v) != 2
                    or any(isinstance(x, bool) or not isinstance(x, int) or x < 1 for x in v)):
                raise r.fail("shape", f"two positive integers [nx, ny] for lattice = \"{lattice}\"", v)
            kw["shape"] = (int(v[0]), int(v[1]))
        n = len(kw["points"]) if lattice == "points" else math.prod(kw["shape"])
        kw["azimuth"] = _azimuth(r, n) if geometry == "standing" else None
        if geometry == "standing":
            if kw["wall"] is None:
                kw["wall"] = 0.0
        elif kw["wall"] is not None and kw["wall"] < 2.0 * kw["blob"]:
            raise r.fail("wall", f'at least a filament diameter, 2 blob = {2.0 * kw["blob"]:g} L, for geometry = '
                         '"planar" (the wall lies below the plane of the filaments, which must not cut it; absent: '
                         "free space)", r.data["wall"])
        if lattice == "points":
            _check_points_apart(src, kw["points"])
        if kw["blob"] >= 0.5 * kw["spacing"]:
            raise r.fail("blob", f"less than half the spacing ({0.5 * kw['spacing']:g} L): the blobs of neighbouring "
                         "filaments would overlap", kw["blob"])
        return kw

    def to_dict(self) -> dict:
        """The section as TOML types (keys that do not apply left out)."""
        d = super().to_dict()
        if self.lattice == "points":
            d.pop("shape", None)
            d.pop("origin", None)
        if self.phases != "wave":
            d.pop("wave_vector", None)
        if self.geometry == "planar":
            d.pop("geometry", None)
        return d

    def azimuths(self, n: int | None = None) -> np.ndarray:
        """(N,) the beat-plane azimuths in DEGREES (zeros for a planar carpet, whose cilia take
        none); ``n`` the number of cilia (default :attr:`n_cilia`)."""
        n = self.n_cilia if n is None else int(n)
        if self.azimuth is None:
            return np.zeros(n)
        return np.broadcast_to(np.asarray(self.azimuth, dtype=float), (n,)).copy()

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


@section
@dataclass(frozen=True)
class OutputSpec(Section):
    """``[output]``: what a render writes (:func:`ciliary_carpet.render.render`)."""

    SECTION = "output"

    pathlines: bool = key(True, "path lines of tracers", "bool")
    seeds: str | tuple | None = key(
        None, "where tracers start: a line upstream of the carpet, across the flow; a grid over it; or explicit "
        "points (standing carpets: at the height `height`)", "pairs", choices=SEEDS,
        default_shown='`"line"` (planar), `"grid"` (standing)')
    n_seeds: int = key(100, "number of seeds (ignored with explicit points)", "int", lo=1)
    periods: float | None = key(
        None, "path-line duration in periods of the straight filament (absent: long enough to cross the carpet at "
        "its median mean speed)", lo=0, lo_open=True)
    pathline_model: str = key(
        "auto", 'the flow tracers follow: time-resolved beat, or the long-time mean flow ("auto": the mean flow '
        f"when `tolerance` >= its measured error, {MEAN_MODEL_ERROR:g}, or the run lasts more than "
        f"{AUTO_RESOLVED_BEATS} beats; the render says which before it starts)", "str",
        choices=("auto", *FLOWS))
    samples_per_period: int = key(16, "path-line points per beat (dense output)", "int", lo=1, hi=1000)
    pathline_points: int = key(10_000, "most points of one tracer's line in `pathlines.vtp` (evenly strided, its end "
                               "kept; the summary says when lines were thinned): files sized for viewing; 0 writes "
                               "every point", "int", lo=0, hi=10_000_000)
    ftle: bool = key(True, "the finite-time Lyapunov exponent field (`ftle.vti`) and the mixing number in the "
                     "summary", "bool")
    field: bool = key(True, "the mean velocity field", "bool")
    field_shape: tuple[int, int] = key((80, 80), "grid of the velocity field", "custom",
                                       shown="`[nx, ny]` ints >= 2")
    field_margin: float = key(5.0, "how far the field grid extends beyond the carpet (L)", lo=0, hi=MAX_LENGTH)
    snapshots: int = key(4, "instantaneous velocity-field snapshots (one file each)", "int", lo=0, hi=1000)
    frames: int = key(40, "cilia shape frames over one period of the straight filament (one file each)", "int", lo=0,
                      hi=10_000)
    preview: bool = key(True, "a preview image", "bool")
    height: float | None = key(None, "standing carpets only: the height z = h of the target plane above the substrate "
                               "(L): the mean field's horizontal slice, the seeds, the FTLE", lo=0, lo_open=True,
                               hi=MAX_LENGTH,
                               default_shown="`target.height` with a target, else `1.5` (standing)")

    @classmethod
    def parse(cls, src: str, data) -> dict:
        r, kw = read(src, OutputSpec, data)
        fs = r.data.get("field_shape", list(keys_of(OutputSpec)["field_shape"][1]))
        if (not isinstance(fs, list) or len(fs) != 2
                or any(isinstance(x, bool) or not isinstance(x, int) or x < 2 for x in fs)):
            raise r.fail("field_shape", "two integers >= 2 [nx, ny]", fs)
        kw["field_shape"] = (int(fs[0]), int(fs[1]))
        return kw


@section
@dataclass(frozen=True)
class Units(Section):
    """``[units]``: absent: dimensionless output; if present, all three keys are required."""

    SECTION = "units"

    length_m: float = key(doc="filament length L in metres", lo=0, lo_open=True)
    time_s: float = key(doc="relaxation time tau in seconds", lo=0, lo_open=True)
    viscosity_Pa_s: float = key(doc="fluid viscosity in Pa s", lo=0, lo_open=True)

    @classmethod
    def parse(cls, src: str, data) -> dict:
        r = reader(src, Units, data)
        names = tuple(keys_of(Units))
        missing = [k for k in names if not r.has(k)]
        if missing:
            raise SceneError(f"{src}: [units] needs all of {', '.join(names)} (missing: {', '.join(missing)}); "
                             f"leave the section out for dimensionless output")
        return values(r, Units)

    def scales(self):
        """The :class:`~ciliary_carpet.carpet.carpet.Scales` of these units."""
        from ciliary_carpet.carpet.carpet import Scales

        return Scales(self.length_m, self.time_s, self.viscosity_Pa_s)


@section
@dataclass(frozen=True)
class StateSpec(Section):
    """``[[state]]``: one state of a program, a scene whose one layout of cilia (one chi_N per
    cilium) is designed for several field strengths at once: the state's field strength
    ``chi_E``, the flow the carpet is to make in it (``target``, a :class:`TargetSpec` given by the
    ``[state.target]`` table, with the keys of ``[target]``; every kind but "none"), its weight in
    the joint design, and its thrust table (``table``, a :class:`TableSpec` given by
    ``[state.table]`` and ``[state.table.build]``; default the table shipped for ``chi_E``). The
    program's other sections (``[field]`` without ``chi_E``, ``[carpet]``, ``[output]``, ...)
    hold for every state; :func:`~ciliary_carpet.scenes.states.state_scenes` gives each state's
    own scene. In messages the states are ``state[0]``, ``state[1]``, ... in file order."""

    SECTION = STATE

    name: str = key(doc="the state's name, unique in the program: a file name (the state's scene is named "
                    "`<scene name>_<name>`)", type="str")
    chi_E: float = key(doc="the state's field strength L kappa_E, one per state (two within 1e-9 relative are "
                       "duplicate states); its table is the one shipped for it (chi_E = " + _SHIPPED + ") or "
                       "`[state.table.build]`'s", lo=-CHI_E_MAX, hi=CHI_E_MAX,
                       what=f"a nonzero number in [-{CHI_E_MAX:g}, {CHI_E_MAX:g}]",
                       shown=f"float in [-{CHI_E_MAX:g}, {CHI_E_MAX:g}], not 0")
    weight: float = key(1.0, "the state's weight in the joint design (its share of the objective, relative to the "
                        "other states')", lo=0, lo_open=True)
    target: TargetSpec | None = key(None, "`[state.target]`: the flow the carpet is to make in this state, with the "
                                    "keys of `[target]` (any kind but `\"none\"`: a state without a target is an "
                                    "error)", "custom", shown="table", default_shown="required")
    table: TableSpec = key(TableSpec(), "`[state.table]` (and `[state.table.build]`): the state's thrust table, with "
                           "the keys of `[table]`; its (chi_E, eta) must match the state's chi_E and `field.eta`",
                           "custom", shown="table", default_shown='`file = "default"`')

    @classmethod
    def parse(cls, src: str, data, index: int | None = None, base_dir=None) -> dict:
        """The keyword arguments of one ``[[state]]`` table ``data`` (file ``src``; ``index``: its
        place in the file, for the dotted keys of messages, ``state[index].chi_E``; with
        ``base_dir``, a target's "points" file must exist there); SceneError naming the key
        otherwise."""
        sec = STATE if index is None else f"{STATE}[{index}]"
        r, kw = read(src, StateSpec, data, sec)
        for k in ("name", "chi_E"):
            if not r.has(k):
                raise SceneError(f"{src}: {sec}.{k} is required (each [[state]] gives its name and its field "
                                 f"strength chi_E)")
        if not kw["name"].strip():
            raise r.fail("name", "a non-empty string", kw["name"])
        check_name(src, r.key("name"), kw["name"])
        if kw["chi_E"] == 0.0:
            raise r.fail("chi_E", keys_of(StateSpec)["chi_E"][0].accepted() + " (a state is a field: 0 is none)",
                         r.data["chi_E"])
        if not r.has("target"):
            raise SceneError(f"{src}: {sec}.target is missing: a state without a target; give the state a "
                             f"[state.target] table, with the keys of [target] (kind, angle, ...)")
        kw["target"] = TargetSpec(**TargetSpec.parse(src, r.data["target"], base_dir, f"{sec}.target"))
        if kw["target"].kind == "none":
            raise SceneError(f'{src}: {sec}.target.kind = "none": a state without a target; each state of a '
                             f'program is designed for a flow (a layout without a target is a plain scene)')
        kw["table"] = TableSpec(**TableSpec.parse(src, r.data.get("table", {}), f"{sec}.table"))
        return kw

    def to_dict(self) -> dict:
        """The state as TOML types: its keys, ``target`` and ``table`` as tables."""
        d = {k: getattr(self, k) for k in ("name", "chi_E", "weight") if getattr(self, k) is not None}
        if self.target is not None:
            d["target"] = self.target.to_dict() if isinstance(self.target, TargetSpec) else self.target
        d["table"] = self.table.to_dict() if isinstance(self.table, TableSpec) else self.table
        return d


@section
@dataclass(frozen=True)
class Scene:
    """A validated scene (see the module docstring and ``designs/README.md``): the top-level keys
    below, the sections ``field``, ``table``, ``carpet``, ``target``, ``output`` and ``units``
    (None: dimensionless), ``states`` (a program's :class:`StateSpec`, ``[[state]]``; empty for
    a scene of one field) and ``source``: the scene file (None for scenes made in memory), for
    relative paths and messages.

    A program (at least :data:`MIN_STATES` states) has no ``[target]`` and no ``[table]`` of
    its own (its states have them) and its ``[field]`` gives no ``chi_E``: its ``field.chi_E``
    is its first state's, so that what reads ``[field]`` alone sees one of its fields, and a
    standing program's ``output.height``, when not given, is left to each state's scene (the
    height of its target). :func:`~ciliary_carpet.scenes.states.state_scenes` gives the scene of
    each state."""

    SECTION = ""

    name: str = key(doc="the scene's name (outputs are named after it)", type="str",
                    default_shown="file name without `.toml`")
    description: str = key("", "one line for summaries", "str")
    field: FieldSpec = _field(default_factory=FieldSpec)
    table: TableSpec = _field(default_factory=TableSpec)
    carpet: CarpetSpec = _field(default_factory=CarpetSpec)
    target: TargetSpec = _field(default_factory=TargetSpec)
    output: OutputSpec = _field(default_factory=OutputSpec)
    tolerance: float = key(1e-3, "error tolerance of the flow model (levels of detail), relative to the cilia's "
                           "far-field magnitudes", lo=0, hi=1, lo_open=True, hi_open=True)
    backend: str = key("auto", "backend of the flow sums: `\"auto\"` the GPU when one is usable, else the CPU; "
                       "`\"cuda\"` an NVIDIA GPU (`pip install cilia-flow[gpu]`; fp64, or fp32 within the bound of "
                       "`ciliary_carpet.stokes.cuda`), checked when a render starts; `--backend` on the command line "
                       "overrides it", "str", choices=BACKENDS)
    states: tuple[StateSpec, ...] = ()
    units: Units | None = None
    source: Path | None = None

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
        states = tuple(self.states) if isinstance(self.states, (list, tuple)) else self.states
        if not isinstance(states, tuple) or not all(isinstance(x, StateSpec) for x in states):
            raise SceneError(f"<Scene>: states must be a tuple of StateSpec, got {self.states!r}")
        object.__setattr__(self, "states", states)
        self._state_rules()
        self._geometry_rules()
        self._viscosity_rule()

    def _state_rules(self) -> None:
        """The rules of a program (:attr:`states`; none without states): at least
        :data:`MIN_STATES` states, unique names (each giving a valid scene name,
        ``<name>_<state name>``), no two fields within 1e-9 relative, no ``[target]`` or
        ``[table]`` of its own; sets ``field.chi_E`` to the first state's."""
        if not self.states:
            return
        src = self.source_name if self.source is not None else "<scene>"
        _check_state_count(src, len(self.states))
        if self.target.kind != "none":
            raise SceneError(f"{src}: target is ambiguous in a scene with [[state]] (each state has its own "
                             f"target): move [target] into the states, as [state.target]")
        if self.table != TableSpec():
            raise SceneError(f"{src}: table is ambiguous in a scene with [[state]] (each state has its own table): "
                             f"move [table] into the states, as [state.table]")
        for i, st in enumerate(self.states):
            for j, other in enumerate(self.states[:i]):
                if st.name == other.name:
                    raise SceneError(f"{src}: state[{i}].name = {st.name!r} is state[{j}]'s name too: the states' "
                                     f"names must be unique (each state's scene is named after it)")
                if abs(st.chi_E - other.chi_E) <= 1e-9 * max(abs(st.chi_E), abs(other.chi_E)):
                    raise SceneError(f"{src}: state[{i}].chi_E = {st.chi_E:g} is state[{j}]'s field too (within 1e-9 "
                                     f"relative): duplicate states; each state is another field strength")
            check_name(src, f"state[{i}].name", f"{self.name}_{st.name}")
        if self.field.chi_E != self.states[0].chi_E:
            object.__setattr__(self, "field", replace(self.field, chi_E=self.states[0].chi_E))

    def _viscosity_rule(self) -> None:
        """``carpet.viscosity`` within :data:`VISCOSITY_FACTOR` of the filaments' own viscosity
        (:func:`~ciliary_carpet.carpet.carpet.sbt_viscosity` of ``field.eta`` at radius ``carpet.blob``)."""
        mu = self.carpet.viscosity
        if mu is None:
            return
        own = sbt_viscosity(self.field.eta, self.carpet.blob)
        lo, hi = own / VISCOSITY_FACTOR, own * VISCOSITY_FACTOR
        if not lo <= mu <= hi:
            src = self.source_name if self.source is not None else "<scene>"
            raise SceneError(f"{src}: carpet.viscosity must be a number in [{lo:.3g}, {hi:.3g}] (within a factor "
                             f"{VISCOSITY_FACTOR:g} of {own:.3g}, the viscosity the filaments' drag eta = "
                             f"{self.field.eta:g} implies; leave it out to use that one), got {mu:g}")

    def _geometry_rules(self) -> None:
        """The rules between sections that the carpet's geometry sets; resolves the defaults that
        depend on it (``[output] seeds``, ``[output] height``)."""
        src = self.source_name if self.source is not None else "<scene>"
        o = self.output
        if self.carpet.geometry == "standing":
            if self.field.direction != 0.0:
                raise SceneError(f"{src}: field.direction must be 0 (or absent) for carpet.geometry = \"standing\": the "
                                 f"field is along +z, normal to the substrate; turn the cilia with carpet.azimuth "
                                 f"(got field.direction = {self.field.direction:g})")
            for where, t in self._targets():
                if t.kind != "none" and t.kind not in STANDING_KINDS:
                    raise SceneError(f"{src}: {where}.kind = \"{t.kind}\" is a planar carpet's deflection pattern; a "
                                     f"standing carpet's target is a surface flow: {where}.kind = "
                                     f"{', '.join(repr(k) for k in STANDING_KINDS)}")
            # the plane the fields and seeds use is the target's, when there is one (a program's states
            # each have theirs: their scenes resolve it)
            t = self.target
            h = o.height
            if h is None and not self.states:
                h = t.height if t.kind != "none" else 1.5
            o = replace(o, seeds="grid" if o.seeds is None else o.seeds, height=h)
        else:
            if o.height is not None:
                raise SceneError(f"{src}: output.height applies only to carpet.geometry = \"standing\" (a planar "
                                 f"carpet's fields lie in its own plane z = 0)")
            for where, t in self._targets():
                if t.kind in SURFACE_KINDS:
                    raise SceneError(f"{src}: {where}.kind = \"{t.kind}\" is a surface flow of a standing carpet "
                                     f"(carpet.geometry = \"standing\"); a planar carpet's targets are deflections")
            o = replace(o, seeds="line" if o.seeds is None else o.seeds)
        if o is not self.output:
            object.__setattr__(self, "output", o)

    def _targets(self) -> list[tuple[str, TargetSpec]]:
        """(dotted name, target) of the scene's ``[target]`` and of each state's."""
        return [("target", self.target)] + [(f"state[{i}].target", st.target) for i, st in enumerate(self.states)]

    @property
    def base_dir(self) -> Path:
        """The folder relative paths refer to (the scene file's; the working directory without one)."""
        return self.source.parent if self.source is not None else Path.cwd()

    @property
    def source_name(self) -> str:
        return str(self.source) if self.source is not None else f"<scene {self.name}>"

    def needs(self):
        """What a render of the scene's peak memory depends on, as numbers
        (:class:`~ciliary_carpet.output.resources.Needs`, :func:`ciliary_carpet.scenes.resources.needs`):
        what :func:`~ciliary_carpet.output.resources.expected_memory` and
        :func:`~ciliary_carpet.output.resources.places_that_fit` take."""
        from ciliary_carpet.scenes.resources import needs

        return needs(self)

    def to_dict(self) -> dict:
        """The resolved scene, defaults filled in, as plain TOML/JSON types (keys that are None,
        i.e. decided later or absent, are left out; ``source`` is not a scene key and is not
        included). ``scene_from_dict(s.to_dict(), s.source)`` gives ``s`` back. A program's states
        are the list ``"state"`` (``[[state]]``), and it has no ``"target"``, no ``"table"`` and no
        ``field.chi_E`` (its states give them)."""
        d = {"name": self.name, "description": self.description, "tolerance": self.tolerance, "backend": self.backend,
             "field": self.field.to_dict(), "table": self.table.to_dict(), "carpet": self.carpet.to_dict(),
             "target": self.target.to_dict(), "output": self.output.to_dict()}
        if self.units is not None:
            d["units"] = self.units.to_dict()
        if self.states:
            del d["field"]["chi_E"], d["table"], d["target"]
            d[STATE] = [st.to_dict() for st in self.states]
        return d

    def reduced(self, max_cilia: int = 16, n_seeds: int = 10, field_shape=(16, 16), periods: float = 2,
                snapshots: int = 1, frames: int = 4) -> "Scene":
        """A smaller copy for fast tests: at most ``max_cilia`` cilia (same lattice and spacing,
        shape shrunk in proportion, same carpet centre so that absolute coordinates -- explicit
        control points, seeds, turn centre -- still fall on it; a "points" carpet keeps the
        points nearest its centre; per-cilium azimuths go with the original cilium nearest to each
        kept one), and outputs no larger than the arguments. Never enlarges."""
        c = self.carpet
        m = int(max_cilia)
        if m < 1:
            raise ValueError(f"max_cilia must be >= 1, got {max_cilia!r}")
        per_cilium = isinstance(c.azimuth, tuple) and c.n_cilia > m
        if per_cilium:  # one azimuth per cilium: set again below, once the kept cilia are known
            c = replace(c, azimuth=0.0)
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
        if per_cilium:  # each kept cilium takes the azimuth of the original cilium nearest to it
            from scipy.spatial import cKDTree

            near = cKDTree(self.carpet.bases()).query(c.bases())[1]
            c = replace(c, azimuth=tuple(float(self.carpet.azimuth[i]) for i in np.atleast_1d(near)))
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


def reference() -> dict[str, str]:
    """The key reference of ``designs/README.md``: ``{heading: markdown table}``, made from the
    sections' field metadata and the registry of target kinds (the tests check the README)."""
    return {"top level": markdown_table(Scene),
            "`[field]`": markdown_table(FieldSpec),
            "`[table]` and `[table.build]`": markdown_table(TableSpec, ("build.", TableBuild)),
            "`[carpet]`": markdown_table(CarpetSpec),
            "`[target]`": markdown_table(TargetSpec, kinds=True),
            "Target kinds": kinds_table(),
            "`[output]`": markdown_table(OutputSpec),
            "`[units]`": markdown_table(Units),
            "`[[state]]`": markdown_table(StateSpec)}


# ------------------------------------------------------------------------------ parsing
def load_scene(path, *, allow_outside: bool = False) -> Scene:
    """Read and validate the scene file ``path`` (TOML, UTF-8 with or without a byte-order mark).
    Raises :class:`SceneError` naming the file (and the dotted key, or tomllib's line and column). ``table.file`` and ``target.file``
    must lie below the scene's folder unless ``allow_outside`` (:mod:`ciliary_carpet.scenes.paths`)."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise SceneError(f"{path}: cannot read the scene file ({exc.strerror or exc})") from None
    try:
        data = tomllib.loads(text.decode("utf-8-sig"))  # a UTF-8 byte-order mark is not part of the TOML
    except UnicodeDecodeError as exc:
        raise SceneError(f"{path}: not UTF-8 text (byte 0x{text[exc.start]:02x} at offset {exc.start}); a scene "
                         f"file is TOML, which is UTF-8: save it as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{path}: malformed TOML: {exc}") from None
    return scene_from_dict(data, source=path, allow_outside=allow_outside)


def as_scene(scene, what: str) -> Scene:
    """``scene`` itself when it is a :class:`Scene`, else the scene file it names (a ``str`` or
    ``os.PathLike``, read with :func:`load_scene`); a TypeError naming ``what`` (the function
    called) and what it takes for anything else."""
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, (str, os.PathLike)):
        return load_scene(scene)
    raise TypeError(f"{what} takes a Scene (ciliary_carpet.load_scene(path)) or the path of a scene file, "
                    f"got {type(scene).__name__}")


def scene_from_dict(data: dict, source=None, *, allow_outside: bool = False) -> Scene:
    """A :class:`Scene` from the parsed TOML ``data`` (the same checks as :func:`load_scene`);
    ``source`` is the file it came from (for relative paths and messages), or None."""
    source = None if source is None else Path(source)
    src = str(source) if source is not None else "<scene>"
    if not isinstance(data, dict):
        raise SceneError(f"{src}: a scene must be a table of keys, got {type(data).__name__}")
    reader(src, Scene, data, extra=SECTIONS + (STATE,))  # unknown keys
    top = _top_kw(src, {k: v for k, v in data.items() if k not in SECTIONS + (STATE,)},
                  source.stem if source is not None else "scene")
    base = source.parent if source is not None else Path.cwd()
    check_scene_paths(src, data, base, allow_outside=allow_outside)
    states = _states(src, data, base, allow_outside) if STATE in data else ()
    sec = {k: data.get(k, {}) for k in SECTIONS}
    return Scene(
        **top,
        states=states,
        field=FieldSpec(**FieldSpec.parse(src, sec["field"])),
        table=TableSpec(**TableSpec.parse(src, sec["table"])),
        carpet=CarpetSpec(**CarpetSpec.parse(src, sec["carpet"])),
        target=TargetSpec(**TargetSpec.parse(src, sec["target"], base)),
        output=OutputSpec(**OutputSpec.parse(src, sec["output"])),
        units=Units(**Units.parse(src, sec["units"])) if "units" in data else None,
        source=source,
    )


def _check_state_count(src: str, n: int) -> None:
    """SceneError unless a program's ``n`` states are at least :data:`MIN_STATES`."""
    if n < MIN_STATES:
        raise SceneError(f"{src}: state: a program needs at least {MIN_STATES} [[state]] tables (one layout, several "
                         f"fields), got {n}; a single field is a plain scene: chi_E in [field] and its [target]")


def _states(src: str, data: dict, base: Path, allow_outside: bool) -> tuple[StateSpec, ...]:
    """The :class:`StateSpec` of the ``[[state]]`` tables of the parsed TOML ``data`` (file
    ``src``, folder ``base``), after the rules only the file shows: ``state`` an array of
    tables, no ``[target]``, ``[table]`` or ``field.chi_E`` beside it, and each state's
    ``table.file`` and ``target.file`` below the scene's folder (unless ``allow_outside``)."""
    raw = data[STATE]
    if isinstance(raw, dict):
        raise SceneError(f"{src}: state must be an array of tables, one [[state]] per state (double brackets), "
                         f"got a single table [state]")
    if not isinstance(raw, list):
        raise SceneError(f"{src}: state must be an array of tables, one [[state]] per state, got {raw!r}")
    for k in ("target", "table"):
        if k in data:
            raise SceneError(f"{src}: [{k}] is ambiguous in a scene with [[state]] (each state has its own {k}): "
                             f"move it into the states, as [state.{k}]")
    if isinstance(data.get("field"), dict) and "chi_E" in data["field"]:
        raise SceneError(f"{src}: field.chi_E is ambiguous in a scene with [[state]] (each state has its own field "
                         f"strength): move it into the states, as state.chi_E")
    _check_state_count(src, len(raw))
    out = []
    for i, d in enumerate(raw):
        if isinstance(d, dict):
            _check_state_paths(src, f"{STATE}[{i}]", d, base, allow_outside)
        out.append(StateSpec(**StateSpec.parse(src, d, i, base)))
    return tuple(out)


def _check_state_paths(src: str, sec: str, d: dict, base: Path, allow_outside: bool) -> None:
    """The path rules of :func:`~ciliary_carpet.scenes.paths.check_scene_paths` for the state
    ``sec``'s ``table.file`` (unless "default"; with ``build``, its row folder too) and
    ``target.file``, before anything is opened. Values of the wrong type are left to the
    state's own checks."""
    for part, skip in (("table", "default"), ("target", None)):
        t = d.get(part)
        v = t.get("file") if isinstance(t, dict) else None
        if isinstance(v, str) and v.strip() and v != skip:
            full = check_input(src, f"{sec}.{part}.file", v, base, allow_outside=allow_outside)
            if part == "table" and isinstance(t.get("build"), dict):
                check_derived(src, f"{sec}.table.file", "the table build's row folder", table_parts(full), base,
                              allow_outside=allow_outside)


def _top_kw(src, data, default_name="scene") -> dict:
    r, kw = read(src, Scene, data)
    name = kw["name"] if kw["name"] is not None else default_name
    if not name.strip():
        raise r.fail("name", "a non-empty string", name)
    check_name(src, "name", name)
    kw["name"] = name
    return kw


def _check_points_apart(src: str, points) -> None:
    """SceneError naming ``carpet.points`` when two of them lie closer than :data:`MIN_SPACING`."""
    if len(points) < 2:
        return
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=float)
    d, i = cKDTree(pts).query(pts, k=2)
    j = int(np.argmin(d[:, 1]))
    if d[j, 1] < MIN_SPACING:
        k = int(i[j, 1])
        a, b = sorted((j, k))
        raise SceneError(f"{src}: carpet.points[{a}] and carpet.points[{b}] are {d[j, 1]:.3g} L apart; base points "
                         f"must lie at least {MIN_SPACING:g} L apart (the filament length: closer cilia can touch)")


def _azimuth(r, n: int):
    """``carpet.azimuth`` of a standing carpet of ``n`` cilia: one finite number (degrees), or a
    list of ``n`` of them (a tuple); 0.0 when absent."""
    if not r.has("azimuth"):
        return 0.0
    v = r.data["azimuth"]
    what = f"a number of degrees or a list of {n} of them (one per cilium)"

    def one(k, x):
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise SceneError(f"{r.src}: {k} must be {what}, got {x!r}")
        if not math.isfinite(x):
            raise SceneError(f"{r.src}: {k} must be a finite number of degrees, got {float(x)}")
        return float(x)

    if isinstance(v, (list, tuple)):
        if len(v) != n:
            raise SceneError(f"{r.src}: carpet.azimuth must be {what}, got a list of {len(v)}")
        return tuple(one(f"carpet.azimuth[{i}]", x) for i, x in enumerate(v))
    return one("carpet.azimuth", v)
