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

Patterns (``A`` the amplitude in rad, ``w`` the width, ``xi = (x - centre) . cross - line`` the
cross-stream coordinate measured from the line)
--------------------------------------------------------------------------------
* ``uniform``: delta = A everywhere (A signed).
* ``focus``: delta = -A tanh(xi / w): on both sides the flow is turned toward the line
  (xi < 0: delta > 0, toward +cross; xi > 0: toward -cross), straight on the line.
* ``spread``: delta = +A tanh(xi / w): away from the line on both sides.
* ``shear``: delta = (A / 2) (1 - tanh(xi / w)): the side xi < 0 (the -cross side: for the
  field along +y, the -x half, on the left of a plot) flows at A from d0, the side xi > 0
  straight along d0, with the change over the width w. Two streams side by side whose
  directions differ by A: a layer of shear in the direction of the flow. (Unlike focus and
  spread it is not antisymmetric about the line, so the three are distinct.)
* ``turn``: the flow turns anticlockwise around ``centre``, within what the cilia can do:
  delta = A (t . cross), t the unit anticlockwise tangent ``rot90(x - centre)/|x - centre|``,
  i.e. A times the sine of the angle from d0 to the tangent. The cilia cannot push upstream, so
  the flow is turned fully (+-A) where the tangent is across the stream (upstream and downstream
  of the centre), not at all where it runs with or against it, and smoothly in between (a
  clipped tangent would jump from +A to -A behind the centre, which no superposition of
  Stokeslets can follow). delta = 0 at the centre itself.
* ``points``: target velocities (lab frame, model units L / tau) at given control points, read
  from a file (:func:`read_target_points`).

Control points (:func:`control_points`): "cilia" = every base point moved half a spacing
downstream (along d0); "cells" = the centres of the lattice cells: the circumcentres of the
Delaunay triangles of the base points (the Voronoi vertices: the points farthest from every
base), merged where two triangles share one (the cell centres of a square lattice, the triangle
centres of a hexagonal one), and for a carpet whose base points lie on a line (a row) the
"cilia" rule; or an explicit list.
"""
from __future__ import annotations

import csv
import io
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from single_cilium.table import ThrustTable

    from .scene import Scene, TargetSpec

__all__ = ["TargetError", "UnreachableTargetError", "Target", "Frame", "control_points", "reachable_check",
           "read_target_points", "DEFAULT_ANGLE_FRACTION", "KINDS", "KIND_KEYS", "applies_to"]

_DESIGN_KEYS = ("residual", "strict", "smoothness", "sigma", "samples", "robust")
_ANGLE_KEYS = ("angle", "control", "speed_floor") + _DESIGN_KEYS
KIND_KEYS: dict[str, tuple[str, ...]] = {
    "none": (),
    "uniform": _ANGLE_KEYS,
    "focus": _ANGLE_KEYS + ("line", "width"),
    "spread": _ANGLE_KEYS + ("line", "width"),
    "shear": _ANGLE_KEYS + ("line", "width"),
    "turn": _ANGLE_KEYS + ("centre",),
    "points": ("file",) + _DESIGN_KEYS,
}
"""The registry of target kinds: each kind with the ``[target]`` keys (besides ``kind``) that
apply to it. The scene schema (:mod:`ciliary_carpet.scene`: which keys a kind accepts) and the
key table of ``designs/README.md`` (checked by the tests) derive from it; adding a pattern means
adding it here and to :meth:`Target.deflection`."""
KINDS = tuple(KIND_KEYS)
ANGLE_KINDS = ("uniform", "focus", "spread", "shear", "turn")
DEFAULT_ANGLE_FRACTION = 0.9
"""Without ``target.angle`` the amplitude is this fraction of the table's reachable maximum."""
CSV_SUFFIXES = (".csv", ".txt")
NETCDF_SUFFIXES = (".nc", ".nc4", ".cdf", ".netcdf", ".h5", ".hdf5")


def applies_to(key: str) -> tuple[str, ...]:
    """The target kinds a ``[target]`` key applies to (from :data:`KIND_KEYS`)."""
    return tuple(k for k, keys in KIND_KEYS.items() if key in keys)


class TargetError(ValueError):
    """A target that cannot be used: unreadable control file, unreachable angles, bad input."""


class UnreachableTargetError(TargetError):
    """Deflections outside the table's reachable range: a target the cilia cannot make."""


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

    @classmethod
    def from_scene(cls, scene: "Scene", bases=None) -> "Frame":
        """The frame of ``scene``'s carpet (``bases`` default: ``scene.carpet.bases()``)."""
        b = scene.carpet.bases() if bases is None else bases
        return cls.from_bases(b, scene.carpet.spacing, scene.field.direction_rad)

    def cross_coordinate(self, points) -> np.ndarray:
        """(P,) coordinate of ``points`` along the cross-stream axis, from the centre."""
        return (_points("points", points) - self.centre) @ self.cross

    def directions(self, delta) -> np.ndarray:
        """(P, 2) unit flow directions for deflections ``delta`` (P,): cos d d0 + sin d cross."""
        d = np.atleast_1d(np.asarray(delta, dtype=float))
        return np.cos(d)[:, None] * self.flow_direction + np.sin(d)[:, None] * self.cross


# ------------------------------------------------------------------------------ target
@dataclass(frozen=True, eq=False)
class Target:
    """A resolved target (from a scene's ``[target]`` by :meth:`from_spec` / :meth:`from_scene`).

    kind : one of :data:`KINDS`.
    amplitude : float or None
        RADIANS: the deflection (uniform, signed) or the pattern amplitude (> 0); None for
        "none" and "points".
    line : cross-stream offset of the line from the centre (focus/spread/shear), L.
    width : transition width (L), or None = ``frame.spacing``.
    centre : (x, y) of the turn, or None = ``frame.centre``.
    control : "cells" | "cilia" | tuple of (x, y): see :func:`control_points`.
    strict : unreachable angles and a residual above ``residual`` are errors (else: clipped /
        the closest flow, with a warning).
    speed_floor, smoothness : design settings (:func:`~ciliary_carpet.design.design_layout`).
    sigma, samples : the fabrication-tolerance study (:func:`~ciliary_carpet.design.tolerance_study`).
    robust : design for the expected objective under the relative chi_N error ``sigma`` (needs
        sigma > 0; ``robust_sigma`` of :func:`~ciliary_carpet.design.design_layout`).
    residual : acceptance threshold on the design's rms residual.
    data_points, data_velocities : (P, 2) arrays for kind "points" (else None); see
        :meth:`velocities`.
    source : the control-point file for kind "points" (for messages).
    """

    kind: str
    amplitude: float | None = None
    line: float = 0.0
    width: float | None = None
    centre: tuple | None = None
    control: object = "cells"
    residual: float = 0.05
    strict: bool = False
    speed_floor: float = 0.3
    smoothness: float = 0.0
    sigma: float = 0.0
    samples: int = 64
    robust: bool = False
    data_points: np.ndarray | None = None
    data_velocities: np.ndarray | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise TargetError(f"target kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.kind in ANGLE_KINDS:
            if self.amplitude is None or not math.isfinite(self.amplitude):
                raise TargetError(f"target kind {self.kind!r} needs a finite amplitude (rad), got {self.amplitude!r}")
            if self.kind != "uniform" and self.amplitude <= 0:
                raise TargetError(f"the amplitude of a {self.kind!r} target must be > 0, got {self.amplitude!r}")
            object.__setattr__(self, "amplitude", float(self.amplitude))
        if self.robust and not self.sigma > 0:
            raise TargetError(f"target robust = true designs for the fabrication tolerance sigma, which must then be "
                              f"> 0, got sigma = {self.sigma!r}")
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

    # -------------------------------------------------------------------- construction
    @classmethod
    def from_spec(cls, spec: "TargetSpec", base_dir=None, angle_max: float | None = None) -> "Target":
        """Resolve a :class:`~ciliary_carpet.scene.TargetSpec`: angle in degrees -> amplitude in
        radians (default :data:`DEFAULT_ANGLE_FRACTION` x ``angle_max``, the table's reachable
        maximum in radians, which must then be given), and for kind "points" the control file
        read from ``base_dir`` (default: the working directory)."""
        amp = None
        if spec.kind in ANGLE_KINDS:
            if spec.angle is not None:
                amp = math.radians(spec.angle)
            elif angle_max is None:
                raise TargetError(f"target kind {spec.kind!r} without target.angle needs the table's reachable "
                                  f"maximum (angle_max) for its default")
            else:
                amp = DEFAULT_ANGLE_FRACTION * float(angle_max)
        pts = vel = src = None
        if spec.kind == "points":
            p = Path(spec.file).expanduser()
            if not p.is_absolute():
                p = Path(base_dir if base_dir is not None else Path.cwd()) / p
            pts, vel = read_target_points(p)
            src = str(p)
        return cls(kind=spec.kind, amplitude=amp, line=spec.line, width=spec.width, centre=spec.centre,
                   control=spec.control, residual=spec.residual, strict=spec.strict,
                   speed_floor=spec.speed_floor, smoothness=spec.smoothness, sigma=spec.sigma,
                   samples=spec.samples, robust=spec.robust, data_points=pts,
                   data_velocities=vel, source=src)

    @classmethod
    def from_scene(cls, scene: "Scene", table: "ThrustTable | None" = None) -> "Target":
        """The target of ``scene`` (``table`` default: ``scene.load_table()``, needed only for
        the default angle)."""
        angle_max = None
        if scene.target.kind in ANGLE_KINDS and scene.target.angle is None:
            table = table if table is not None else scene.load_table()
            angle_max = table.thrust_angle_range()[1]
        return cls.from_spec(scene.target, scene.base_dir, angle_max)

    # -------------------------------------------------------------------- evaluation
    @property
    def is_angle(self) -> bool:
        """True for deflection targets (uniform and the patterns)."""
        return self.kind in ANGLE_KINDS

    def deflection(self, points, frame: Frame) -> np.ndarray:
        """(P,) target deflection delta [rad] at ``points`` (P, 2) for the angle kinds (uniform,
        focus, spread, shear, turn); see the module docstring for the formulas."""
        if not self.is_angle:
            raise TargetError(f"a {self.kind!r} target has no deflection angles"
                              + (" (use velocities())" if self.kind == "points" else ""))
        x = _points("points", points)
        A = self.amplitude
        if self.kind == "uniform":
            return np.full(x.shape[0], A)
        if self.kind == "turn":
            c = frame.centre if self.centre is None else np.asarray(self.centre)
            r = x - c
            t = np.column_stack([-r[:, 1], r[:, 0]])  # anticlockwise tangent (unnormalised)
            n = np.hypot(t[:, 0], t[:, 1])
            return A * np.where(n > 0, (t @ frame.cross) / np.where(n > 0, n, 1.0), 0.0)
        w = self.width if self.width is not None else frame.spacing
        xi = frame.cross_coordinate(x) - self.line
        th = np.tanh(xi / w)
        if self.kind == "focus":
            return -A * th
        if self.kind == "spread":
            return A * th
        return 0.5 * A * (1.0 - th)  # shear

    def directions(self, points, frame: Frame) -> np.ndarray:
        """(P, 2) unit target flow directions at ``points`` (d0 rotated by the deflection)."""
        return frame.directions(self.deflection(points, frame))

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """For kind "points": control points (P, 2) and target velocities (P, 2), lab frame
        (copies)."""
        if self.kind != "points":
            raise TargetError(f"a {self.kind!r} target has no target velocities (only kind 'points')")
        return np.array(self.data_points), np.array(self.data_velocities)


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
    from scipy.spatial import Delaunay

    tri = Delaunay(b)
    cand = _circumcentres(b[tri.simplices])
    # the two triangles of a square cell share their circumcentre: keep one
    key = np.round((cand - b.min(axis=0)) / (1e-6 * h)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    cand = cand[np.sort(first)]
    inside = tri.find_simplex(cand, tol=1e-9 * h) >= 0
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
        msg = (f"{idx.size} of {a.size} {what}s ask for a deflection outside the reachable range "
               f"|angle| <= {math.degrees(hi):.2f} deg ({hi:.4f} rad) of this field: {'; '.join(items)}{more}")
        if not clip:
            raise UnreachableTargetError(msg + "; lower target.angle, or set target.strict = false to clip them")
        warnings.warn(msg + "; clipped to the reachable range", UserWarning, stacklevel=2)
        a = np.clip(a, -hi, hi)
    return a, bad


# ------------------------------------------------------------------------------ control files
def read_target_points(path) -> tuple[np.ndarray, np.ndarray]:
    """Control points (P, 2) and target velocities (P, 2) from a file: CSV (``.csv``/``.txt``:
    a header naming the columns x, y, u, v in any order, extra columns ignored, comma- or
    whitespace-separated, ``#`` starts a comment) or NetCDF (``.nc``, ``.nc4``, ``.cdf``, ``.h5``:
    variables x, y, u, v along one common dimension). Positions in L, velocities in model units
    (L / tau), lab frame. Missing columns, non-numbers, NaN/inf and empty files are a
    :class:`TargetError` naming the file and the line or variable."""
    p = Path(path)
    if not p.is_file():
        raise TargetError(f"{p}: no such control-point file")
    suf = p.suffix.lower()
    if suf in CSV_SUFFIXES:
        return _read_csv(p)
    if suf in NETCDF_SUFFIXES:
        return _read_netcdf(p)
    raise TargetError(f"{p}: unknown control-point file type {suf!r} (CSV: {', '.join(CSV_SUFFIXES)}; "
                      f"NetCDF: {', '.join(NETCDF_SUFFIXES)})")


_COLS = ("x", "y", "u", "v")


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
    dup = [c for c in _COLS if names.count(c) > 1]
    if dup:
        raise TargetError(f"{p}: line {n0}: column(s) {', '.join(dup)} appear twice in the header")
    col = {c: names.index(c) for c in _COLS}
    rows = []
    for k, (n, ln) in enumerate(lines[1:], start=1):
        cells = split(ln)
        if len(cells) != len(names):
            raise TargetError(f"{p}: line {n} (data row {k}): {len(cells)} fields, the header has {len(names)}")
        vals = []
        for c in _COLS:
            s = cells[col[c]]
            try:
                x = float(s)
            except ValueError:
                raise TargetError(f"{p}: line {n} (data row {k}): column {c!r} is not a number: {s!r}") from None
            if not math.isfinite(x):
                raise TargetError(f"{p}: line {n} (data row {k}): column {c!r} is {s!r}; x, y, u, v must be finite")
            vals.append(x)
        rows.append(vals)
    if not rows:
        raise TargetError(f"{p}: no data rows after the header")
    a = np.array(rows)
    return a[:, :2].copy(), a[:, 2:].copy()


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
    dims = {c: ds[c].dims for c in _COLS}
    for c in _COLS:
        if len(dims[c]) != 1:
            raise TargetError(f"{p}: variable {c!r} must be 1-d, has dims {dims[c]}")
    if len({dims[c] for c in _COLS}) != 1:
        raise TargetError(f"{p}: variables x, y, u, v must share one dimension, have "
                          f"{', '.join(f'{c}{dims[c]}' for c in _COLS)}")
    for c in _COLS:
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
    return np.column_stack([arrs["x"], arrs["y"]]), np.column_stack([arrs["u"], arrs["v"]])
