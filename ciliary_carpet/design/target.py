"""Target flows: what a scene's ``[target]`` asks the carpet's mean flow to do.

Geometry
--------
A :class:`Frame` holds what the patterns refer to: the carpet's ``centre`` (centre of the
bounding box of the base points), the straight-flow direction ``d0`` (``flow_direction``: minus
the field direction, where a straight filament pushes the fluid) and the ``spacing``. The
cross-stream axis is ``cross = d0`` rotated by +90 degrees (for the field along +y: d0 = -y,
cross = +x). A deflection ``delta`` (radians, anticlockwise positive) asks for the mean flow
along ``d0`` rotated by ``delta``, i.e. ``cos(delta) d0 + sin(delta) cross``: a positive delta
turns the flow toward +cross. The table's reachable |delta| is
``table.thrust_angle_range()`` (about [0, 0.925] rad for chi_E = 200, eta = 1).

Kinds
-----
:data:`PATTERNS` is the registry of target kinds: each :class:`Pattern` with its formula (``A``
the amplitude in rad, ``w`` the width, ``xi = (x - centre) . cross - line`` the cross-stream
coordinate measured from the line), its deflection function and the geometry keys it reads.
The ``[target]`` section of a scene file is :class:`TargetSpec`, whose fields hold each key's
default, range and the kinds it applies to (:mod:`ciliary_carpet.scenes.schema`); the scene parser, the
key reference of ``designs/README.md`` and the kinds table there are made from these two (a test
checks the README). Adding a pattern means adding a :class:`Pattern` here (and a key to
:class:`TargetSpec` if it needs one). The shear pattern is not antisymmetric about its line
(unlike focus and spread), so the three are distinct; the turn cannot push upstream, so it turns
the flow fully (+-A) where the tangent is across the stream and not at all where it runs with or
against it (a clipped tangent would jump from +A to -A behind the centre, which no superposition
of Stokeslets can follow).

Control points (:func:`control_points`): "cilia" = every base point moved half a spacing
downstream (along d0); "cells" = the centres of the lattice cells: the circumcentres of the
Delaunay triangles of the base points (the Voronoi vertices: the points farthest from every
base), merged where two triangles share one (the cell centres of a square lattice, the triangle
centres of a hexagonal one), and for a carpet whose base points lie on a line (a row) the
"cilia" rule; or an explicit list.

Size: about 690 lines, above the project's 500, because one noun's parts are read together: the
``[target]`` section's documented keys (the README's key table is made from them), the registry,
the frame the patterns refer to, the resolved target and its control points and control file,
all raising the one :class:`TargetError` (the readers of the control file could move to a
module of their own if it grows).
"""
from __future__ import annotations

import csv
import io
import math
import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np

from ciliary_carpet.design.errors import TargetError, UnreachableTargetError
from ciliary_carpet.design.surface_target import surface_directions as _surface_directions
from ciliary_carpet.scenes.schema import Key, SceneError, Section, key, keys_of, reader, section, values

__all__ = ["TargetError", "UnreachableTargetError", "Target", "TargetSpec", "Frame", "Pattern", "PATTERNS",
           "control_points", "reachable_check", "read_target_points", "DEFAULT_ANGLE_FRACTION", "KINDS",
           "ANGLE_KINDS", "SURFACE_KINDS", "KIND_KEYS", "applies_to", "kinds_table"]

DEFAULT_ANGLE_FRACTION = 0.9
"""Without ``target.angle`` the amplitude is this fraction of the table's reachable maximum."""
CSV_SUFFIXES = (".csv", ".txt")
NETCDF_SUFFIXES = (".nc", ".nc4", ".cdf", ".netcdf", ".h5", ".hdf5")




# ------------------------------------------------------------------------------ the kinds
@dataclass(frozen=True)
class Pattern:
    """One target kind of the registry :data:`PATTERNS`.

    Attributes
    ----------
    name : str
        The value of ``target.kind``.
    doc : str
        What it asks, with its formula (README kinds table).
    keys : tuple of str
        The ``[target]`` keys of its own geometry (line, width, centre, file); the keys every
        angle kind or every designed kind takes say so themselves (:class:`TargetSpec`).
    deflection : callable or None
        ``f(target, points (P, 2), frame) -> delta (P,)`` [rad] for the angle kinds; None for
        "none" and "points".
    signed : bool
        ``target.angle`` is a signed deflection in [-180, 180] (else an amplitude in (0, 180]);
        for a surface kind a direction in [-180, 180].
    surface : bool
        A surface-flow kind of standing carpets: the direction of the mean flow on the plane
        z = ``height`` (:mod:`~ciliary_carpet.design.surface_target`), any direction.
    two_sided : bool
        The flow turns toward (or away from) a line from both sides: the design's estimate of
        the reachable amplitude of such a pattern applies
        (:func:`~ciliary_carpet.design.reachability.reachability`).

    A pattern whose ``keys`` hold ``"width"`` has a transition width (:attr:`has_width`): the
    reachability estimates the narrowest width it meets its threshold at.
    """

    name: str
    doc: str
    keys: tuple[str, ...] = ()
    deflection: Callable | None = None
    signed: bool = False
    two_sided: bool = False
    surface: bool = False

    @property
    def has_width(self) -> bool:
        """The pattern has a transition width (the ``[target]`` key ``width`` is one of its keys)."""
        return "width" in self.keys


def _across_line(t: "Target", x: np.ndarray, frame: "Frame") -> np.ndarray:
    """tanh(xi / w), xi the cross-stream coordinate from the line, w the width (one spacing)."""
    w = t.width if t.width is not None else frame.spacing
    xi = frame.cross_coordinate(x) - t.line
    return np.tanh(xi / w)


def _turn(t: "Target", x: np.ndarray, frame: "Frame") -> np.ndarray:
    c = frame.centre if t.centre is None else np.asarray(t.centre)
    r = x - c
    tg = np.column_stack([-r[:, 1], r[:, 0]])  # anticlockwise tangent (unnormalised)
    n = np.hypot(tg[:, 0], tg[:, 1])
    return t.amplitude * np.where(n > 0, (tg @ frame.cross) / np.where(n > 0, n, 1.0), 0.0)


PATTERNS: tuple[Pattern, ...] = (
    Pattern("none", "no target: every cilium gets `carpet.chi_N`"),
    Pattern("uniform", "delta = A everywhere (A signed)",
            deflection=lambda t, x, fr: np.full(x.shape[0], t.amplitude), signed=True),
    Pattern("focus", "delta = -A tanh(xi / w): the flow turns toward the line from both sides", ("line", "width"),
            deflection=lambda t, x, fr: -t.amplitude * _across_line(t, x, fr), two_sided=True),
    Pattern("spread", "delta = +A tanh(xi / w): away from the line on both sides", ("line", "width"),
            deflection=lambda t, x, fr: t.amplitude * _across_line(t, x, fr), two_sided=True),
    Pattern("shear", "delta = (A / 2) (1 - tanh(xi / w)): the -cross side (direction 0: the left, x below the "
            "line) turned by A, the other side straight: two streams side by side, a layer of shear",
            ("line", "width"), deflection=lambda t, x, fr: 0.5 * t.amplitude * (1.0 - _across_line(t, x, fr))),
    Pattern("turn", "delta = A times the sine of the angle from d0 to the anticlockwise tangent around `centre`: "
            "full (+-A) upstream and downstream of the centre, zero beside it (the cilia cannot push upstream), "
            "smooth in between; 0 at the centre", ("centre",), deflection=_turn),
    Pattern("points", "target velocities (lab frame, model units L / tau) at control points read from `file` "
            "(a standing carpet: the mean flow on the plane z = `height`)", ("file",)),
    Pattern("pump", "standing carpets: the surface flow along `angle` (degrees anticlockwise from +x) everywhere",
            signed=True, surface=True),
    Pattern("vortex", "standing carpets: the surface flow circling `centre` (`sense`); points within half a "
            "spacing of the centre are left out", ("centre", "sense"), surface=True),
    Pattern("mixer", "standing carpets: two counter-rotating vortices at `centre` -+ (`separation` / 2) along "
            "`angle`, a jet between them; points within half a spacing of either centre are left out",
            ("centre", "separation", "sense"), signed=True, surface=True),
    Pattern("u_turn", "standing carpets: the surface flow comes in along `angle` on one side of the axis through "
            "`centre`, turns about `centre` and goes back on the other side (`sense`)", ("centre", "sense"),
            signed=True, surface=True),
    Pattern("source_sink", "standing carpets: out of a source at `centre` - (`separation` / 2) e and into a sink "
            "at `centre` + (`separation` / 2) e, e along `angle`", ("centre", "separation"), signed=True,
            surface=True),
)
"""The registry of target kinds."""
_PATTERN = {p.name: p for p in PATTERNS}
KINDS = tuple(_PATTERN)
ANGLE_KINDS = tuple(p.name for p in PATTERNS if p.deflection is not None)
SURFACE_KINDS = tuple(p.name for p in PATTERNS if p.surface)
"""The surface-flow kinds of standing carpets (:mod:`~ciliary_carpet.design.surface_target`)."""
_DESIGNED = tuple(k for k in KINDS if k != "none")
_DIRECTION_KINDS = ANGLE_KINDS + SURFACE_KINDS
_STANDING_KINDS = SURFACE_KINDS + ("points",)


def _uses(name: str) -> tuple[str, ...]:
    return tuple(p.name for p in PATTERNS if name in p.keys)


# ------------------------------------------------------------------------------ the [target] section
@section
@dataclass(frozen=True)
class TargetSpec(Section):
    """``[target]``: the flow the carpet is designed for, as the scene file gives it (resolved by
    :meth:`Target.from_spec`; the kinds are :data:`PATTERNS`)."""

    SECTION = "target"

    kind: str = key("none", 'the target kind (table "Target kinds")', "str", choices=KINDS)
    angle: float | None = key(
        None, "uniform: the deflection (signed); patterns: the amplitude A (> 0); standing carpets' pump, mixer, "
        "u_turn, source_sink: the direction or axis, anticlockwise from +x (signed; default 0)", "custom",
        shown="float (degrees)", default_shown=f"{DEFAULT_ANGLE_FRACTION:.0%} of the table's reachable maximum",
        kinds=ANGLE_KINDS + tuple(p.name for p in PATTERNS if p.surface and p.signed))
    line: float = key(0.0, "position of the line along the cross-stream axis, from the carpet's centre (L)",
                      kinds=_uses("line"))
    width: float | None = key(None, "transition width w (L)", lo=0, lo_open=True, default_shown="one spacing",
                              kinds=_uses("width"))
    centre: tuple[float, float] | None = key(None, "the centre of the turn, vortex, mixer, U-turn or source-sink "
                                             "pair", "pair", default_shown="the carpet's centre", kinds=_uses("centre"))
    sense: str = key("anticlockwise", "which way a vortex, the mixer's first vortex or a U-turn circles", "str",
                     choices=("anticlockwise", "clockwise"), kinds=_uses("sense"))
    separation: float | None = key(None, "distance between the mixer's vortices or the source and the sink (L)",
                                   lo=0, lo_open=True, default_shown="half the carpet's width", kinds=_uses("separation"))
    height: float = key(1.5, "standing carpets: the height of the surface-flow plane above the substrate (L), "
                        "above the cilia (which reach at most 1 L)", lo=0, lo_open=True, kinds=_STANDING_KINDS)
    file: str | None = key(
        None, "CSV (header with columns x, y, u, v; `#` comments) or NetCDF (variables x, y, u, v along one "
        "dimension) of control points and target velocities (lab frame, model units L/tau), relative to the "
        "scene file; required. Optional columns (variables) du, dv: each sample's standard uncertainty of u and v "
        "(L/tau, e.g. PIV's): a planar carpet's design then weights each sample by 1 / (du^2 + dv^2), and every "
        "verdict allows for the samples' own noise (`residual`)", "str", default_shown="-", kinds=_uses("file"))
    control: str | tuple = key(
        "cells", 'where the designed mean flow is compared with the target: `"cilia"`: each base point moved '
        'half a spacing downstream; `"cells"`: the cell centres (circumcentres of the Delaunay triangles of the '
        'base points: square cells\' centres, hexagonal triangles\' centres; a row uses the `"cilia"` rule). '
        "Control points more than 2 spacings + 1 L from every base are an error; those inside a cilium's swept "
        "region are used (see `inside_swept`); a standing carpet's are at the same points on the plane z = `height`",
        "pairs", choices=("cells", "cilia"), kinds=_DIRECTION_KINDS)
    residual: float = key(
        0.05, 'acceptance threshold on the design\'s rms residual (rad for angle targets, relative to rms target '
        'speed for `"points"`); the test suite checks it. Samples with uncertainties (`file` columns du, dv) are '
        'met at sqrt(residual^2 + n^2), n their relative rms noise: no design can come closer to noisy samples '
        'than their noise', lo=0, lo_open=True, kinds=_DESIGNED)
    strict: bool = key(
        False, "`false`: clip unreachable angles and return the closest flow when the residual is above "
        "`residual` (with a warning); `true`: both are errors (exit status 3)", "bool", kinds=_DESIGNED)
    speed_floor: float = key(
        0.3, "the speed along the target direction each control point keeps, as a fraction of the speed the "
        "straight cilia within 5 spacings make there (keeps the design from switching cilia off; local, so that "
        "it means the same on every carpet size; standing carpets: of the speed the cilia within 6 L make there "
        "when all pump along the target at the pumping maximum)", lo=0, hi=1, hi_open=True,
        kinds=_DIRECTION_KINDS)
    inside_swept: str = key(
        "use", "control points inside a cilium's swept region (any PIV field, grid or random sample over a carpet "
        "has some): `\"use\"` them like the others (the regularised mean flow is bounded there and resolved "
        "exactly by the design), `\"downweight\"` them (weight 0.1 in the objective and in the rms residual) or "
        "`\"drop\"` them; the design's summary says how many and what was done", "str",
        choices=("use", "downweight", "drop"), kinds=_DESIGNED)
    smoothness: float = key(
        0.0, "weight of the neighbour-difference regulariser (Delaunay neighbours): larger gives layouts with "
        "fewer distinct curvatures", lo=0, kinds=_DESIGNED)
    sigma: float = key(
        0.0, "fabrication tolerance: relative chi_N error of the cilia; > 0 adds the expected residual and its "
        "spread to the design's summary (sampled on the design model with the full model's defect at the "
        "design; the sampling error is reported)", lo=0, kinds=_DESIGNED)
    sigma_psi: float = key(
        0.0, "standing carpets: the azimuth error of the cilia (degrees), sampled with `sigma` in the tolerance "
        "study", lo=0, kinds=_STANDING_KINDS)
    samples: int = key(64, "samples of the tolerance study", "int", lo=1, kinds=_DESIGNED)
    robust: bool = key(
        False, "design for the expected residual under `sigma` instead of the nominal one: the objective is "
        "averaged over 16 fixed samples of chi_N (1 + sigma eps) (a sample average; its error shows in the "
        "tolerance study, whose samples are independent of them); needs `sigma` > 0 (standing carpets: or "
        "`sigma_psi` > 0, both sampled)", "bool", kinds=_DESIGNED)

    @classmethod
    def parse(cls, src: str, data, base_dir=None) -> dict:
        """The keyword arguments of the ``[target]`` table ``data`` (from file ``src``; with
        ``base_dir``, a "points" file must exist there); SceneError naming the key otherwise."""
        r = reader(src, TargetSpec, data)
        spec = keys_of(TargetSpec)
        kind = r.get("kind", *spec["kind"])
        for k, (s, _) in spec.items():  # before the values: the clearer message
            if r.has(k) and s.kinds is not None and kind not in s.kinds:
                raise SceneError(f"{src}: target.{k} does not apply to kind = \"{kind}\" (it is used by kind = "
                                 f"{', '.join(repr(x) for x in s.kinds)})")
        kw = values(r, TargetSpec)
        if _PATTERN[kind].surface:
            angle = Key("float", "", lo=-180, hi=180, what="a direction in degrees in [-180, 180]")
        elif _PATTERN[kind].signed:
            angle = Key("float", "", lo=-180, hi=180, what="a deflection in degrees in [-180, 180]")
        else:
            angle = Key("float", "", lo=0, hi=180, lo_open=True, what="an amplitude in degrees in (0, 180]")
        kw["angle"] = r.get("angle", angle, None)
        file = kw["file"]
        if "file" in _PATTERN[kind].keys:
            if file is None:
                raise SceneError(f"{src}: target.file is required with kind = \"{kind}\" (a CSV with columns "
                                 f"x, y, u, v or a NetCDF file with variables x, y, u, v)")
            if not file.strip():
                raise r.fail("file", "a file path", file)
            p = Path(file).expanduser()
            if base_dir is not None and not (p if p.is_absolute() else base_dir / p).is_file():
                raise SceneError(f"{src}: target.file '{file}' not found (looked for {(base_dir / p).absolute()})")
        if kw["robust"] and not (kw["sigma"] > 0 or kw.get("sigma_psi", 0.0) > 0):
            raise r.fail("robust", "false unless target.sigma > 0 (or, standing carpets, target.sigma_psi > 0: it "
                         "designs for the fabrication tolerance)", kw["robust"])
        return kw

    def to_dict(self) -> dict:
        """The section as TOML types (keys that do not apply to the kind left out)."""
        if self.kind == "none":
            return {"kind": "none"}
        d = super().to_dict()
        for k, (spec, _) in keys_of(TargetSpec).items():
            if spec.kinds is not None and self.kind not in spec.kinds:
                d.pop(k, None)
        return d

    @property
    def angle_rad(self) -> float | None:
        return None if self.angle is None else math.radians(self.angle)


KIND_KEYS: dict[str, tuple[str, ...]] = {
    kind: tuple(k for k, (spec, _) in keys_of(TargetSpec).items() if spec.kinds is not None and kind in spec.kinds)
    for kind in KINDS}
"""Each kind with the ``[target]`` keys (besides ``kind``) that apply to it (from :class:`TargetSpec`)."""


def applies_to(name: str) -> tuple[str, ...]:
    """The target kinds the ``[target]`` key ``name`` applies to (every kind for ``kind``; none for
    an unknown key)."""
    spec = keys_of(TargetSpec).get(name)
    if spec is None:
        return ()
    return KINDS if spec[0].kinds is None else spec[0].kinds


def kinds_table() -> str:
    """The "Target kinds" table of ``designs/README.md``: each kind, the keys of its own geometry
    (the others: the kinds column of the key table) and its pattern."""
    rows = ["| kind | its own keys | pattern |", "|---|---|---|"]
    for p in PATTERNS:
        ks = ", ".join(f"`{k}`" for k in p.keys) or "-"
        rows.append(f'| `"{p.name}"` | {ks} | {p.doc} |')
    return "\n".join(rows)


def _xy(name: str, v, shape=None) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if shape is not None and a.shape != shape:
        raise TargetError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TargetError(f"{name} contains NaN or inf")
    return a


def _points(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.ndim == 1 and a.shape == (2,):
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 2:
        raise TargetError(f"{name} must have shape (P, 2), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise TargetError(f"{name} contain NaN or inf")
    return a


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


# ------------------------------------------------------------------------------ frame
@dataclass(frozen=True, eq=False)
class Frame:
    """The carpet geometry the patterns refer to.

    centre (2,): the carpet's centre; flow_direction (2,): the unit vector d0 (normalised here);
    spacing: the lattice spacing (the default pattern width)."""

    centre: np.ndarray
    flow_direction: np.ndarray
    spacing: float

    def __post_init__(self) -> None:
        c = _xy("Frame.centre", self.centre, (2,))
        d = _xy("Frame.flow_direction", self.flow_direction, (2,))
        n = float(np.hypot(*d))
        if n == 0:
            raise TargetError("Frame.flow_direction must be a non-zero vector")
        s = float(self.spacing)
        if not (math.isfinite(s) and s > 0):
            raise TargetError(f"Frame.spacing must be a positive number, got {self.spacing!r}")
        object.__setattr__(self, "centre", _readonly(c))
        object.__setattr__(self, "flow_direction", _readonly(d / n))
        object.__setattr__(self, "spacing", s)

    @property
    def cross(self) -> np.ndarray:
        """The cross-stream axis: d0 rotated by +90 degrees."""
        d = self.flow_direction
        return np.array([-d[1], d[0]])

    @classmethod
    def from_bases(cls, bases, spacing: float, direction_rad: float) -> "Frame":
        """The frame of a carpet with base points ``bases`` (N, 2) under a field at
        ``direction_rad`` (RADIANS anticlockwise from +y, as :class:`Carpet` takes it):
        centre = centre of the bases' bounding box, d0 = (sin a, -cos a)."""
        b = _points("bases", bases)
        a = float(direction_rad)
        return cls(0.5 * (b.min(axis=0) + b.max(axis=0)), np.array([math.sin(a), -math.cos(a)]), spacing)

    def cross_coordinate(self, points) -> np.ndarray:
        """(P,) coordinate of ``points`` along the cross-stream axis, from the centre."""
        return (_points("points", points) - self.centre) @ self.cross

    def directions(self, delta) -> np.ndarray:
        """(P, 2) unit flow directions for deflections ``delta`` (P,): cos d d0 + sin d cross."""
        d = np.atleast_1d(np.asarray(delta, dtype=float))
        return np.cos(d)[:, None] * self.flow_direction + np.sin(d)[:, None] * self.cross


# ------------------------------------------------------------------------------ target
def spec_default(name: str):
    """The default of the ``[target]`` key ``name`` (its one home is :class:`TargetSpec`)."""
    return keys_of(TargetSpec)[name][1]


@dataclass(frozen=True, eq=False)
class Target:
    """A resolved target (from a scene's ``[target]`` by :meth:`from_spec`; for a scene: :func:`~ciliary_carpet.scenes.assembly.target_of`).

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    amplitude : float or None
        RADIANS: the deflection (uniform, signed) or the pattern amplitude (> 0); for the surface
        kinds the direction or axis (default 0); None for "none" and "points".
    line, width, centre, control, residual, strict, speed_floor, inside_swept, smoothness, sigma, samples, robust,
    sense, separation, height, sigma_psi :
        as the keys of :class:`TargetSpec` (same defaults): width None = ``frame.spacing``,
        centre None = ``frame.centre``, separation None = half the carpet's width along the axis
        (:meth:`surface_directions`); sigma_psi in DEGREES; ``control`` see :func:`control_points`; the design
        settings go to :func:`~ciliary_carpet.design.inverse.design_layout` (``robust``: its
        ``robust_sigma``) and :func:`~ciliary_carpet.design.tolerance.tolerance_study`.
    data_points, data_velocities : ndarray or None
        (P, 2) arrays for kind "points" (else None); see :meth:`velocities`.
    data_uncertainty : ndarray or None
        (P, 2) standard uncertainties of the target velocities' components (L/tau, >= 0), for kind
        "points" when the file gives them (columns du, dv); see :meth:`sample_weights`.
    source : str or None
        The control-point file for kind "points" (for messages).
    """

    kind: str
    amplitude: float | None = None
    line: float = spec_default("line")
    width: float | None = spec_default("width")
    centre: tuple | None = spec_default("centre")
    control: object = spec_default("control")
    residual: float = spec_default("residual")
    strict: bool = spec_default("strict")
    speed_floor: float = spec_default("speed_floor")
    inside_swept: str = spec_default("inside_swept")
    smoothness: float = spec_default("smoothness")
    sigma: float = spec_default("sigma")
    samples: int = spec_default("samples")
    robust: bool = spec_default("robust")
    sense: str = spec_default("sense")
    separation: float | None = spec_default("separation")
    height: float = spec_default("height")
    sigma_psi: float = spec_default("sigma_psi")
    data_points: np.ndarray | None = None
    data_velocities: np.ndarray | None = None
    data_uncertainty: np.ndarray | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise TargetError(f"target kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.is_angle:
            if self.amplitude is None or not math.isfinite(self.amplitude):
                raise TargetError(f"target kind {self.kind!r} needs a finite amplitude (rad), got {self.amplitude!r}")
            if not self.pattern.signed and self.amplitude <= 0:
                raise TargetError(f"the amplitude of a {self.kind!r} target must be > 0, got {self.amplitude!r}")
            object.__setattr__(self, "amplitude", float(self.amplitude))
        if self.is_surface:
            a = 0.0 if self.amplitude is None else float(self.amplitude)
            if not math.isfinite(a):
                raise TargetError(f"target kind {self.kind!r} needs a finite direction (rad), got {self.amplitude!r}")
            object.__setattr__(self, "amplitude", a)
        if self.sense not in ("anticlockwise", "clockwise"):
            raise TargetError(f"target sense must be \"anticlockwise\" or \"clockwise\", got {self.sense!r}")
        if self.separation is not None and not (math.isfinite(self.separation) and self.separation > 0):
            raise TargetError(f"target separation must be a positive number, got {self.separation!r}")
        if not (math.isfinite(self.height) and self.height > 0):
            raise TargetError(f"target height must be a positive number, got {self.height!r}")
        if not (math.isfinite(self.sigma_psi) and self.sigma_psi >= 0):
            raise TargetError(f"target sigma_psi must be a number >= 0 (degrees), got {self.sigma_psi!r}")
        if self.inside_swept not in ("use", "downweight", "drop"):
            raise TargetError(f"target inside_swept must be \"use\", \"downweight\" or \"drop\", got "
                              f"{self.inside_swept!r}")
        if self.robust and not (self.sigma > 0 or self.sigma_psi > 0):
            raise TargetError(f"target robust = true designs for the fabrication tolerance sigma (or sigma_psi), which "
                              f"must then be > 0, got sigma = {self.sigma!r}")
        if self.width is not None and not (math.isfinite(self.width) and self.width > 0):
            raise TargetError(f"target width must be a positive number, got {self.width!r}")
        if not math.isfinite(self.line):
            raise TargetError(f"target line must be finite, got {self.line!r}")
        if self.centre is not None:
            object.__setattr__(self, "centre", tuple(map(float, _xy("target centre", self.centre, (2,)))))
        if self.kind == "points":
            if self.data_points is None or self.data_velocities is None:
                raise TargetError("a 'points' target needs data_points and data_velocities (P, 2)")
            p = _points("target data_points", self.data_points)
            v = _points("target data_velocities", self.data_velocities)
            if p.shape != v.shape or p.shape[0] == 0:
                raise TargetError(f"target data_points {p.shape} and data_velocities {v.shape} must match")
            object.__setattr__(self, "data_points", _readonly(p))
            object.__setattr__(self, "data_velocities", _readonly(v))
            if self.data_uncertainty is not None:
                e = _points("target data_uncertainty", self.data_uncertainty)
                if e.shape != p.shape or np.any(e < 0):
                    raise TargetError(f"target data_uncertainty must be (P, 2) = {p.shape} numbers >= 0, got shape "
                                      f"{e.shape}")
                object.__setattr__(self, "data_uncertainty", _readonly(e))

    # -------------------------------------------------------------------- construction
    @classmethod
    def from_spec(cls, spec: TargetSpec, base_dir=None, angle_max: float | None = None) -> "Target":
        """Resolve a :class:`TargetSpec`: angle in degrees -> amplitude in radians (default
        :data:`DEFAULT_ANGLE_FRACTION` x ``angle_max``, the table's reachable maximum in radians,
        which must then be given), and for kind "points" the control file read from ``base_dir``
        (default: the working directory); the other keys are taken as they are."""
        amp = None
        if spec.kind in SURFACE_KINDS:
            amp = math.radians(spec.angle) if spec.angle is not None else 0.0
        elif spec.kind in ANGLE_KINDS:
            if spec.angle is not None:
                amp = math.radians(spec.angle)
            elif angle_max is None:
                raise TargetError(f"target kind {spec.kind!r} without target.angle needs the table's reachable "
                                  f"maximum (angle_max) for its default")
            else:
                amp = DEFAULT_ANGLE_FRACTION * float(angle_max)
        pts = vel = unc = src = None
        if spec.kind == "points":
            p = Path(spec.file).expanduser()
            if not p.is_absolute():
                p = Path(base_dir if base_dir is not None else Path.cwd()) / p
            pts, vel, unc = read_target_samples(p)
            src = str(p)
        return cls(amplitude=amp, data_points=pts, data_velocities=vel, data_uncertainty=unc, source=src,
                   **{k: getattr(spec, k) for k in _FROM_SPEC})

    # -------------------------------------------------------------------- evaluation
    @property
    def pattern(self) -> Pattern:
        """This kind's entry of :data:`PATTERNS`."""
        return _PATTERN[self.kind]

    @property
    def is_angle(self) -> bool:
        """True for deflection targets (uniform and the patterns)."""
        return self.pattern.deflection is not None

    @property
    def is_surface(self) -> bool:
        """True for the surface-flow kinds of standing carpets."""
        return self.pattern.surface

    def surface_directions(self, points, frame: Frame, bases=None) -> tuple[np.ndarray, np.ndarray]:
        """(directions (P',) [rad, anticlockwise from +x], keep (P,) bool) of a surface kind at
        ``points`` (P, 2): the direction of its model field
        (:func:`~ciliary_carpet.design.surface_target.surface_directions`) at the points kept (those
        not within half a spacing of the pattern's singular points). ``centre`` None: the frame's;
        ``separation`` None: half the extent of ``bases`` (default the points) along the axis."""
        if not self.is_surface:
            raise TargetError(f"a {self.kind!r} target is not a surface flow (kinds {', '.join(SURFACE_KINDS)})")
        x = _points("points", points)
        c = frame.centre if self.centre is None else np.asarray(self.centre)
        d = self.separation
        if d is None:
            b = x if bases is None else _points("bases", bases)
            e = np.array([math.cos(self.amplitude), math.sin(self.amplitude)])
            d = 0.5 * float(np.ptp(b @ e)) or frame.spacing
        return _surface_directions(self.kind, x, c, frame.spacing, self.amplitude, d,
                                  1 if self.sense == "anticlockwise" else -1)

    def deflection(self, points, frame: Frame) -> np.ndarray:
        """(P,) target deflection delta [rad] at ``points`` (P, 2) for the angle kinds (the
        formulas: :data:`PATTERNS`)."""
        if not self.is_angle:
            raise TargetError(f"a {self.kind!r} target has no deflection angles"
                              + (" (use velocities())" if self.kind == "points" else ""))
        return self.pattern.deflection(self, _points("points", points), frame)

    def directions(self, points, frame: Frame) -> np.ndarray:
        """(P, 2) unit target flow directions at ``points`` (d0 rotated by the deflection)."""
        return frame.directions(self.deflection(points, frame))

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """For kind "points": control points (P, 2) and target velocities (P, 2), lab frame
        (copies)."""
        if self.kind != "points":
            raise TargetError(f"a {self.kind!r} target has no target velocities (only kind 'points')")
        return np.array(self.data_points), np.array(self.data_velocities)

    def sample_weights(self) -> np.ndarray | None:
        """For kind "points" with uncertainties: (P,) weights of the samples in the design's
        objective and rms residual, ``1 / (s_k^2 + s_0^2)`` scaled to mean 1, with ``s_k^2 = du_k^2 +
        dv_k^2`` and ``s_0`` a tenth of the rms ``s`` (a sample given as exact does not outweigh
        the others without bound); None without uncertainties (all weights 1)."""
        if self.kind != "points" or self.data_uncertainty is None:
            return None
        s2 = np.sum(np.asarray(self.data_uncertainty) ** 2, axis=1)
        s0 = 0.01 * float(np.mean(s2))
        if s0 == 0.0:  # every sample given as exact
            return None
        w = 1.0 / (s2 + s0)
        return w / w.mean()

    def noise(self) -> float:
        """For kind "points" with uncertainties: the samples' relative rms noise ``n`` =
        sqrt(sum w_k s_k^2 / sum w_k |U_k|^2) (weights :meth:`sample_weights`), the rms residual a
        design that makes the true flow exactly has against the samples, in the units of the
        velocity residual (relative to the rms target speed); 0 without uncertainties."""
        w = self.sample_weights()
        if w is None:
            return 0.0
        s2 = np.sum(np.asarray(self.data_uncertainty) ** 2, axis=1)
        u2 = np.sum(np.asarray(self.data_velocities) ** 2, axis=1)
        return float(math.sqrt(np.sum(w * s2) / max(float(np.sum(w * u2)), 1e-300)))

    def threshold(self) -> float:
        """The rms residual at which the target counts as met: ``residual``, combined with the
        samples' own noise for sampled velocities with uncertainties, sqrt(residual^2 + noise^2)."""
        return float(math.hypot(self.residual, self.noise()))


_FROM_SPEC = tuple(f.name for f in fields(Target) if f.name in keys_of(TargetSpec))
"""The fields of :class:`Target` that are ``[target]`` keys, taken from the spec as they are."""


# ------------------------------------------------------------------------------ control points
def control_points(bases, frame: Frame, control="cells") -> np.ndarray:
    """(P, 2) points where the designed mean flow is compared with the target.

    ``control``: "cilia" (each base point moved half a spacing along d0, just downstream of its
    cilium), "cells" (the circumcentres of the Delaunay triangles of the base points, duplicates
    merged: the cell centres; for collinear base points, a row, the "cilia" rule), a list
    of points (P, 2), or anything with a ``control`` attribute holding one of these (a Target or
    a TargetSpec)."""
    if hasattr(control, "control"):
        control = control.control
    b = _points("bases", bases)
    h, d0, cr = frame.spacing, frame.flow_direction, frame.cross
    if not isinstance(control, str):
        return _points("control points", control).copy()
    if control not in ("cells", "cilia"):
        raise TargetError(f"control must be 'cells', 'cilia' or a list of points, got {control!r}")
    down = b + 0.5 * h * d0
    if control == "cilia" or b.shape[0] < 3:
        return down
    sv = np.linalg.svd(b - b.mean(axis=0), compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], h):  # collinear: a row
        return down
    from scipy.spatial import ConvexHull, Delaunay

    tri = Delaunay(b)
    cand = _circumcentres(b[tri.simplices])
    # the two triangles of a square cell share their circumcentre: keep one
    key = np.round((cand - b.min(axis=0)) / (1e-6 * h)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    cand = cand[np.sort(first)]
    # inside the triangulation = inside the bases' convex hull (its unit-normal half-planes; a
    # point search in a square lattice's degenerate triangulation took 2 s for 100 x 100 cilia)
    eq = ConvexHull(b).equations
    inside = np.all(cand @ eq[:, :2].T + eq[:, 2] <= 1e-9 * h, axis=1)
    if not np.any(inside):
        raise TargetError("no cell centre lies inside the carpet (too few cilia for control = \"cells\"); "
                          "use control = \"cilia\" or a list of points")
    cand = cand[inside]
    return cand[np.lexsort((cand[:, 0], cand[:, 1]))]


def _circumcentres(t: np.ndarray) -> np.ndarray:
    """(T, 2) circumcentres of the triangles t (T, 3, 2)."""
    a, bb, c = t[:, 0], t[:, 1], t[:, 2]
    d = 2.0 * (a[:, 0] * (bb[:, 1] - c[:, 1]) + bb[:, 0] * (c[:, 1] - a[:, 1]) + c[:, 0] * (a[:, 1] - bb[:, 1]))
    sa, sb, sc = (a ** 2).sum(1), (bb ** 2).sum(1), (c ** 2).sum(1)
    ux = (sa * (bb[:, 1] - c[:, 1]) + sb * (c[:, 1] - a[:, 1]) + sc * (a[:, 1] - bb[:, 1])) / d
    uy = (sa * (c[:, 0] - bb[:, 0]) + sb * (a[:, 0] - c[:, 0]) + sc * (bb[:, 0] - a[:, 0])) / d
    return np.column_stack([ux, uy])


# ------------------------------------------------------------------------------ reachability
def reachable_check(angles, angle_range, clip: bool = False, *, what: str = "control point",
                    points=None) -> tuple[np.ndarray, np.ndarray]:
    """Check requested deflections against the table's reachable range.

    ``angles`` (P,) rad; ``angle_range`` = ``table.thrust_angle_range()`` (only its maximum is
    used: |delta| <= max, negative angles by mirror symmetry); ``what`` names the items in the
    message ("control point", "cilium") and ``points`` (P, 2), if given, their positions.

    Returns ``(angles, unreachable)``: a copy of the angles (clipped to [-max, max] with
    ``clip=True``) and the (P,) boolean mask of the unreachable ones. Without ``clip`` any
    unreachable angle is a :class:`TargetError` listing the indices, positions and requested
    angles (the first 10) and the reachable range; with ``clip`` the same list is a
    ``UserWarning``."""
    a = np.atleast_1d(np.asarray(angles, dtype=float)).copy()
    if not np.all(np.isfinite(a)):
        raise TargetError("target angles contain NaN or inf")
    hi = float(angle_range[1])
    bad = np.abs(a) > hi * (1 + 1e-12)
    if np.any(bad):
        idx = np.nonzero(bad)[0]
        pts = None if points is None else _points("points", points)
        items = []
        for i in idx[:10]:
            at = f" at ({pts[i, 0]:.4g}, {pts[i, 1]:.4g})" if pts is not None else ""
            items.append(f"{what} {i}{at} asks {math.degrees(a[i]):.2f} deg")
        more = f" (and {idx.size - 10} more)" if idx.size > 10 else ""
        items_name = "cilia" if what == "cilium" else f"{what}s"
        msg = (f"{idx.size} of {a.size} {items_name} ask for a deflection outside the reachable range "
               f"|angle| <= {math.degrees(hi):.2f} deg ({hi:.4f} rad) of this field: {'; '.join(items)}{more}")
        if not clip:
            raise UnreachableTargetError(msg + "; lower target.angle, or set target.strict = false to clip them")
        warnings.warn(msg + "; clipped to the reachable range", UserWarning, stacklevel=2)
        a = np.clip(a, -hi, hi)
    return a, bad


# ------------------------------------------------------------------------------ control files
def read_target_points(path) -> tuple[np.ndarray, np.ndarray]:
    """Control points (P, 2) and target velocities (P, 2) from a file (:func:`read_target_samples`
    without the uncertainties)."""
    xy, uv, _ = read_target_samples(path)
    return xy, uv


def read_target_samples(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Control points (P, 2), target velocities (P, 2) and, when the file gives them (columns or
    variables ``du`` and ``dv``, both), the velocities' standard uncertainties (P, 2) (else None)
    from a file: CSV (``.csv``/``.txt``:
    a header naming the columns x, y, u, v in any order, extra columns ignored, comma- or
    whitespace-separated, ``#`` starts a comment) or NetCDF (``.nc``, ``.nc4``, ``.cdf``, ``.h5``:
    variables x, y, u, v along one common dimension). Positions in L, velocities in model units
    (L / tau), lab frame; uncertainties in L / tau, >= 0. Missing columns, one of du, dv without
    the other, non-numbers, NaN/inf, negative uncertainties and empty files are a
    :class:`TargetError` naming the file and the line or variable."""
    p = Path(path)
    if not p.is_file():
        raise TargetError(f"{p}: no such control-point file")
    suf = p.suffix.lower()
    if suf in CSV_SUFFIXES or suf in NETCDF_SUFFIXES:
        cols = (_read_csv if suf in CSV_SUFFIXES else _read_netcdf)(p)
        big = np.abs(cols) > 1e150  # squares and sums of these stay finite
        if np.any(big):
            i, j = (int(k[0]) for k in np.nonzero(big))
            raise TargetError(f"{p}: control point {i} (data row {i + 1}): {_ALL_COLS[j]} = {cols[i, j]:g}"
                              f" is beyond +-1e150; positions are in L, velocities in L / tau")
        if cols.shape[1] > 4:
            neg = np.nonzero(cols[:, 4:] < 0)
            if neg[0].size:
                i, j = int(neg[0][0]), int(neg[1][0])
                raise TargetError(f"{p}: control point {i} (data row {i + 1}): {_UNC_COLS[j]} = {cols[i, 4 + j]:g} "
                                  f"is negative; an uncertainty is >= 0 (L / tau)")
        return cols[:, :2].copy(), cols[:, 2:4].copy(), (cols[:, 4:6].copy() if cols.shape[1] > 4 else None)
    raise TargetError(f"{p}: unknown control-point file type {suf!r} (CSV: {', '.join(CSV_SUFFIXES)}; "
                      f"NetCDF: {', '.join(NETCDF_SUFFIXES)})")


_COLS = ("x", "y", "u", "v")
_UNC_COLS = ("du", "dv")
_ALL_COLS = _COLS + _UNC_COLS


def _optional_pair(p: Path, present: list) -> tuple:
    """The columns to read: x, y, u, v, and du, dv when both are ``present`` (one alone is an
    error naming the other)."""
    has = [c in present for c in _UNC_COLS]
    if any(has) and not all(has):
        there, missing = (_UNC_COLS if has[0] else _UNC_COLS[::-1])
        raise TargetError(f"{p}: column {there!r} without {missing!r}: the uncertainties of u and v come as a pair")
    return _ALL_COLS if all(has) else _COLS


def _read_csv(p: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TargetError(f"{p}: cannot read ({exc})") from None
    lines = [(n, ln.split("#", 1)[0].strip()) for n, ln in enumerate(text.splitlines(), start=1)]
    lines = [(n, ln) for n, ln in lines if ln]
    if not lines:
        raise TargetError(f"{p}: empty file (expected a header with columns x, y, u, v and data rows)")

    def split(s: str) -> list[str]:
        if "," in s:
            return [c.strip() for c in next(csv.reader(io.StringIO(s)))]
        return s.split()

    n0, head = lines[0]
    names = [c.lower() for c in split(head)]
    missing = [c for c in _COLS if c not in names]
    if missing:
        raise TargetError(f"{p}: line {n0}: header {head!r} lacks column(s) {', '.join(missing)} "
                          f"(needs x, y, u, v)")
    want = _optional_pair(p, names)
    dup = [c for c in want if names.count(c) > 1]
    if dup:
        raise TargetError(f"{p}: line {n0}: column(s) {', '.join(dup)} appear twice in the header")
    col = {c: names.index(c) for c in want}
    rows = []
    for k, (n, ln) in enumerate(lines[1:], start=1):
        cells = split(ln)
        if len(cells) != len(names):
            raise TargetError(f"{p}: line {n} (data row {k}): {len(cells)} fields, the header has {len(names)}")
        vals = []
        for c in want:
            s = cells[col[c]]
            try:
                x = float(s)
            except ValueError:
                raise TargetError(f"{p}: line {n} (data row {k}): column {c!r} is not a number: {s!r}") from None
            if not math.isfinite(x):
                raise TargetError(f"{p}: line {n} (data row {k}): column {c!r} is {s!r}; every value must be finite")
            vals.append(x)
        rows.append(vals)
    if not rows:
        raise TargetError(f"{p}: no data rows after the header")
    return np.array(rows)


def _read_netcdf(p: Path) -> tuple[np.ndarray, np.ndarray]:
    import xarray as xr

    try:
        with xr.open_dataset(p) as ds:
            ds = ds.load()
    except Exception as exc:  # h5netcdf/scipy raise OSError, ValueError, KeyError, ...
        raise TargetError(f"{p}: not a readable NetCDF file ({type(exc).__name__}: {exc})") from None
    missing = [c for c in _COLS if c not in ds.variables]
    if missing:
        raise TargetError(f"{p}: missing variable(s) {', '.join(missing)} (needs x, y, u, v along one dimension)")
    arrs = {}
    want = _optional_pair(p, list(ds.variables))
    dims = {c: ds[c].dims for c in want}
    for c in want:
        if len(dims[c]) != 1:
            raise TargetError(f"{p}: variable {c!r} must be 1-d, has dims {dims[c]}")
    if len({dims[c] for c in want}) != 1:
        raise TargetError(f"{p}: variables {', '.join(want)} must share one dimension, have "
                          f"{', '.join(f'{c}{dims[c]}' for c in want)}")
    for c in want:
        try:
            v = np.asarray(ds[c].values, dtype=float)
        except (TypeError, ValueError):
            raise TargetError(f"{p}: variable {c!r} is not numeric (dtype {ds[c].dtype})") from None
        bad = np.nonzero(~np.isfinite(v))[0]
        if bad.size:
            raise TargetError(f"{p}: variable {c!r} is not finite at index {int(bad[0])} (along "
                              f"'{dims[c][0]}'; {bad.size} such values); x, y, u, v must be finite")
        arrs[c] = v
    if arrs["x"].size == 0:
        raise TargetError(f"{p}: no control points (dimension '{dims['x'][0]}' is empty)")
    return np.column_stack([arrs[c] for c in want])
