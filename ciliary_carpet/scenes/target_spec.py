"""The ``[target]`` section of a scene file: :class:`TargetSpec`, the flow the carpet is designed
for as the file gives it, and its resolution into a design :class:`~ciliary_carpet.design.target.Target`
(:func:`resolve_target`).

The section's keys are the fields of :class:`TargetSpec`: each with its default (a
:class:`~ciliary_carpet.design.target.Target`'s own, where the Target has the key), range and the
target kinds it applies to; the kinds are the registry
:data:`~ciliary_carpet.design.patterns.PATTERNS`. The scene parser, the key reference of
``designs/README.md`` (:func:`~ciliary_carpet.scenes.scene.reference`) and :data:`KIND_KEYS` are
made from them. Every fault of the section is a :class:`~ciliary_carpet.scenes.schema.SceneError`
naming the file and the key.
"""
from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields
from pathlib import Path

from ciliary_carpet.design.errors import TargetError
from ciliary_carpet.design.patterns import (ANGLE_KINDS, DESIGNED_KINDS, DIRECTION_KINDS, KINDS, PATTERN_OF, PATTERNS,
                                            STANDING_KINDS, SURFACE_KINDS, kinds_using)
from ciliary_carpet.design.target import DEFAULT_ANGLE_FRACTION, Target
from ciliary_carpet.design.target_files import read_target_samples
from ciliary_carpet.scenes.schema import Key, SceneError, Section, key, keys_of, reader, section, values

__all__ = ["TargetSpec", "KIND_KEYS", "applies_to", "resolve_target"]

_TARGET_DEFAULTS = {f.name: f.default for f in fields(Target) if f.default is not MISSING}


def _default(name: str):
    """The default of the ``[target]`` key ``name``: the :class:`~ciliary_carpet.design.target.Target`'s."""
    return _TARGET_DEFAULTS[name]


@section
@dataclass(frozen=True)
class TargetSpec(Section):
    """``[target]``: the flow the carpet is designed for, as the scene file gives it (resolved by
    :func:`resolve_target`; the kinds are :data:`~ciliary_carpet.design.patterns.PATTERNS`)."""

    SECTION = "target"

    kind: str = key("none", 'the target kind (table "Target kinds")', "str", choices=KINDS)
    angle: float | None = key(
        None, "uniform: the deflection (signed); patterns: the amplitude A (> 0); standing carpets' pump, mixer, "
        "u_turn, source_sink: the direction or axis, anticlockwise from +x (signed; default 0)", "custom",
        shown="float (degrees)", default_shown=f"{DEFAULT_ANGLE_FRACTION:.0%} of the table's reachable maximum",
        kinds=ANGLE_KINDS + tuple(p.name for p in PATTERNS if p.surface and p.signed))
    line: float = key(_default("line"), "position of the line along the cross-stream axis, from the carpet's centre (L)",
                      kinds=kinds_using("line"))
    width: float | None = key(_default("width"), "transition width w (L)", lo=0, lo_open=True, default_shown="one spacing",
                              kinds=kinds_using("width"))
    centre: tuple[float, float] | None = key(_default("centre"), "the centre of the turn, vortex, mixer, U-turn or source-sink "
                                             "pair", "pair", default_shown="the carpet's centre", kinds=kinds_using("centre"))
    sense: str = key(_default("sense"), "which way a vortex, the mixer's first vortex or a U-turn circles", "str",
                     choices=("anticlockwise", "clockwise"), kinds=kinds_using("sense"))
    separation: float | None = key(_default("separation"), "distance between the mixer's vortices or the source and the sink (L)",
                                   lo=0, lo_open=True, default_shown="half the carpet's width", kinds=kinds_using("separation"))
    height: float = key(_default("height"), "standing carpets: the height of the surface-flow plane above the substrate (L), "
                        "above the cilia (which reach at most 1 L)", lo=0, lo_open=True, kinds=STANDING_KINDS)
    file: str | None = key(
        None, "CSV (header with columns x, y, u, v; `#` comments) or NetCDF (variables x, y, u, v along one "
        "dimension) of control points and target velocities (lab frame, model units L/tau), relative to the "
        "scene file; required. Optional columns (variables) du, dv: each sample's standard uncertainty of u and v "
        "(L/tau, e.g. PIV's): a planar carpet's design then weights each sample by 1 / (du^2 + dv^2), and every "
        "verdict allows for the samples' own noise (`residual`)", "str", default_shown="-", kinds=kinds_using("file"))
    control: str | tuple = key(
        _default("control"), 'where the designed mean flow is compared with the target: `"cilia"`: each base point moved '
        'half a spacing downstream; `"cells"`: the cell centres (circumcentres of the Delaunay triangles of the '
        'base points: square cells\' centres, hexagonal triangles\' centres; a row uses the `"cilia"` rule). '
        "Control points more than 2 spacings + 1 L from every base are an error; those inside a cilium's swept "
        "region are used (see `inside_swept`); a standing carpet's are at the same points on the plane z = `height`",
        "pairs", choices=("cells", "cilia"), kinds=DIRECTION_KINDS)
    residual: float = key(
        _default("residual"), 'acceptance threshold on the design\'s rms residual (rad for angle targets, relative to rms target '
        'speed for `"points"`); the test suite checks it. Samples with uncertainties (`file` columns du, dv) are '
        'met at sqrt(residual^2 + n^2), n their relative rms noise: no design can come closer to noisy samples '
        'than their noise', lo=0, lo_open=True, kinds=DESIGNED_KINDS)
    strict: bool = key(
        _default("strict"), "`false`: clip unreachable angles and return the closest flow when the residual is above "
        "`residual` (with a warning); `true`: both are errors (exit status 3)", "bool", kinds=DESIGNED_KINDS)
    speed_floor: float = key(
        _default("speed_floor"), "the speed along the target direction each control point keeps, as a fraction of the speed the "
        "straight cilia within 5 spacings make there (keeps the design from switching cilia off; local, so that "
        "it means the same on every carpet size; standing carpets: of the speed the cilia within 6 L make there "
        "when all pump along the target at the pumping maximum)", lo=0, hi=1, hi_open=True,
        kinds=DIRECTION_KINDS)
    inside_swept: str = key(
        _default("inside_swept"), "control points inside a cilium's swept region (any PIV field, grid or random sample over a carpet "
        "has some): `\"use\"` them like the others (the regularised mean flow is bounded there and resolved "
        "exactly by the design), `\"downweight\"` them (weight 0.1 in the objective and in the rms residual) or "
        "`\"drop\"` them; the design's summary says how many and what was done", "str",
        choices=("use", "downweight", "drop"), kinds=DESIGNED_KINDS)
    smoothness: float = key(
        _default("smoothness"), "weight of the neighbour-difference regulariser (Delaunay neighbours): larger gives layouts with "
        "fewer distinct curvatures", lo=0, kinds=DESIGNED_KINDS)
    sigma: float = key(
        _default("sigma"), "fabrication tolerance: relative chi_N error of the cilia; > 0 adds the expected residual and its "
        "spread to the design's summary (sampled on the design model with the full model's defect at the "
        "design; the sampling error is reported)", lo=0, kinds=DESIGNED_KINDS)
    sigma_psi: float = key(
        _default("sigma_psi"), "standing carpets: the azimuth error of the cilia (degrees), sampled with `sigma` in the tolerance "
        "study", lo=0, kinds=STANDING_KINDS)
    samples: int = key(_default("samples"), "samples of the tolerance study", "int", lo=1, kinds=DESIGNED_KINDS)
    robust: bool = key(
        _default("robust"), "design for the expected residual under `sigma` instead of the nominal one: the objective is "
        "averaged over 16 fixed samples of chi_N (1 + sigma eps) (a sample average; its error shows in the "
        "tolerance study, whose samples are independent of them); needs `sigma` > 0 (standing carpets: or "
        "`sigma_psi` > 0, both sampled)", "bool", kinds=DESIGNED_KINDS)

    @classmethod
    def parse(cls, src: str, data, base_dir=None, section: str = "target") -> dict:
        """The keyword arguments of the ``[target]`` table ``data`` (from file ``src``; with
        ``base_dir``, a "points" file must exist there); SceneError naming the key otherwise.
        ``section``: the table's dotted name in messages (``"state[1].target"`` for a state's)."""
        r = reader(src, TargetSpec, data, section)
        spec = keys_of(TargetSpec)
        kind = r.get("kind", *spec["kind"])
        for k, (s, _) in spec.items():  # before the values: the clearer message
            if r.has(k) and s.kinds is not None and kind not in s.kinds:
                raise SceneError(f"{src}: {section}.{k} does not apply to kind = \"{kind}\" (it is used by kind = "
                                 f"{', '.join(repr(x) for x in s.kinds)})")
        kw = values(r, TargetSpec)
        if PATTERN_OF[kind].surface:
            angle = Key("float", "", lo=-180, hi=180, what="a direction in degrees in [-180, 180]")
        elif PATTERN_OF[kind].signed:
            angle = Key("float", "", lo=-180, hi=180, what="a deflection in degrees in [-180, 180]")
        else:
            angle = Key("float", "", lo=0, hi=180, lo_open=True, what="an amplitude in degrees in (0, 180]")
        kw["angle"] = r.get("angle", angle, None)
        file = kw["file"]
        if "file" in PATTERN_OF[kind].keys:
            if file is None:
                raise SceneError(f"{src}: {section}.file is required with kind = \"{kind}\" (a CSV with columns "
                                 f"x, y, u, v or a NetCDF file with variables x, y, u, v)")
            if not file.strip():
                raise r.fail("file", "a file path", file)
            p = Path(file).expanduser()
            if base_dir is not None and not (p if p.is_absolute() else base_dir / p).is_file():
                raise SceneError(f"{src}: {section}.file '{file}' not found (looked for {(base_dir / p).absolute()})")
        if kw["robust"] and not (kw["sigma"] > 0 or kw.get("sigma_psi", 0.0) > 0):
            raise r.fail("robust", f"false unless {section}.sigma > 0 (or, standing carpets, {section}.sigma_psi > 0: "
                         "it designs for the fabrication tolerance)", kw["robust"])
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


def resolve_target(spec: TargetSpec, base_dir=None, angle_max: float | None = None) -> Target:
    """The :class:`~ciliary_carpet.design.target.Target` of a ``[target]`` section: angle in degrees
    -> amplitude in radians (default :data:`~ciliary_carpet.design.target.DEFAULT_ANGLE_FRACTION` x
    ``angle_max``, the table's reachable maximum in radians, which must then be given), and for kind
    "points" the control file read from ``base_dir`` (default: the working directory); the other
    keys are taken as they are."""
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
    return Target(amplitude=amp, data_points=pts, data_velocities=vel, data_uncertainty=unc, source=src,
                  **{k: getattr(spec, k) for k in _FROM_SPEC})


_FROM_SPEC = tuple(f.name for f in fields(Target) if f.name in keys_of(TargetSpec))
"""The fields of :class:`~ciliary_carpet.design.target.Target` that are ``[target]`` keys, taken
from the section as they are."""
