"""The render plan: what a render of a scene does, decided once, before any output is written.

:meth:`RenderPlan.decide` takes the scene's render settings (:class:`RenderSettings`: the values
of its ``[output]`` section and the few others a render reads, as plain values) and the designed
carpet and settles what the outputs
(:mod:`ciliary_carpet.output.outputs`) share: the field grid (:class:`FieldGrid`), the cilia's
beat (:class:`Beat`, the time base of what moves), the tracers' seeds (:func:`seed_points`), the
flow they follow (:func:`pathline_model`) and for how long (:func:`pathline_duration`: computed
here once, since it probes the carpet's mean flow), the units of the files and the resource
estimate (:func:`~ciliary_carpet.output.resources.check_resources`, made before the design). It
comes after the design because the path-line duration and the seeds depend on the designed
layout. What the scene's settings make impossible fails here, before any output: seeds inside a
filament (``SeedError``), path lines too large for memory (``PathLineError``), a carpet that makes
no mean flow while the duration is automatic (:class:`~ciliary_carpet.output.RenderError`).

Path lines: unless the scene sets ``[output] periods``, the duration is long enough for a tracer
to cross the whole carpet at the carpet's median mean speed (1.25 times the carpet's extent along
the flow plus three spacings, divided by that speed). The flow they follow is the time-resolved
beat or the long-time mean flow (``[output] pathline_model``; "auto" takes the mean flow when the
scene's tolerance allows its measured error, or when the run is longer than
:data:`~ciliary_carpet.transport.flow.AUTO_RESOLVED_BEATS` beats: following every beat of
thousands costs minutes and files of hundreds of MB for lines whose error the mean flow's
estimate states anyway).
:meth:`RenderPlan.describe` says all this in a line before the work starts. ``[output] periods`` counts periods of the straight
filament, T0 = T(chi_N = 0); the snapshots and frames sample one beat of the cilia themselves
(each beats with its own period T(chi_N): their median, :class:`Beat`).

Standing carpets (``[carpet] geometry = "standing"``): the field grid is the horizontal target
plane z = h (``[output] height``) and a vertical x-z section through the carpet's centre is added
(:meth:`FieldGrid.section`); the seeds lie in the target plane (:func:`seed_points`); the
crossing the automatic duration is made for runs along the carpet's surface flow (the direction
of its summed mean thrust, :func:`standing_flow_direction`) at the median mean speed in that
plane; and the tracers are followed in a box from the substrate up (:func:`standing_domain`).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
import math
from dataclasses import dataclass

import numpy as np

from ciliary_carpet.carpet.carpet import BLOB, Carpet, CycleMean, Scales
from ciliary_carpet.output import RenderError
from ciliary_carpet.output.resources import Estimate
from ciliary_carpet.output.vtkfiles import grid_points
from ciliary_carpet.transport.flow import AUTO_RESOLVED_BEATS, MEAN_MODEL_ERROR
from ciliary_carpet.transport.pathlines import check_output_size, check_seeds

__all__ = ["RenderPlan", "RenderSettings", "FieldGrid", "Beat", "seed_points", "pathline_duration", "pathline_model",
           "standing_flow_direction", "SECTION_TOP", "DOMAIN_MARGIN", "GeometryOutputs", "GEOMETRY_OUTPUTS"]

SECTION_TOP = 2.0
"""A standing carpet's vertical section reaches this many times the target plane's height
(``[output] height``, at least 1 L) above the substrate."""
ANIMATION_STEPS = 10_000
"""Most entries of a looped .pvd (``cilia.pvd``, ``snapshots.pvd``): ParaView's animation has a
step per entry, and tens of thousands (a run over thousands of beats) make it slow to open and
to play."""

DOMAIN_MARGIN = 10.0
"""A standing carpet's tracers are followed within this distance [L] of its bases and seeds
across, and up to this far above the target plane (the planar default domain's margin)."""


@dataclass(frozen=True, eq=False)
class RenderSettings:
    """What a render reads of its scene, as plain values (made from a scene by
    :func:`~ciliary_carpet.scenes.assembly.render_settings`).

    Attributes
    ----------
    name : str
        The scene's name (titles, the progress lines).
    source : str
        What error messages name the scene by (its file).
    output : object
        The ``[output]`` section's values as attributes (``pathlines``, ``seeds``, ``n_seeds``,
        ``periods``, ``pathline_model``, ``samples_per_period``, ``pathline_points``, ``ftle``,
        ``field``, ``field_shape``, ``field_margin``, ``snapshots``, ``frames``, ``preview``,
        ``height``).
    tolerance : float
        The flow's tolerance (the scene's ``tolerance``).
    spacing : float
        The carpet's spacing [L] (``[carpet] spacing``).
    flow_direction : (2,) array
        Where a straight filament pushes the fluid, d0 = -field direction (a planar carpet's
        seeds and automatic duration).
    geometry : str
        "planar" or "standing" (``[carpet] geometry``); :attr:`outputs` is what the render does
        differently for it.
    """

    name: str
    source: str
    output: object
    tolerance: float
    spacing: float
    flow_direction: np.ndarray
    geometry: str

    @property
    def outputs(self) -> "GeometryOutputs":
        """What the render does differently for the carpet's geometry (:data:`GEOMETRY_OUTPUTS`)."""
        return GEOMETRY_OUTPUTS[self.geometry]


@dataclass(frozen=True)
class FieldGrid:
    """The grid of the field outputs, in the plane z = 0 (a standing carpet: the target plane
    z = ``[output] height``): the bounding box of the carpet's bases widened by
    ``[output] field_margin`` + 1 L on each side, with ``[output] field_shape`` points; or a
    standing carpet's vertical section (:meth:`section`).

    Attributes
    ----------
    origin, spacing : tuple of 3 float
        The first point and the steps along x, y (and 1 along z) [L] (a section: along x, 1
        along y, and along z).
    shape : tuple of 3 int
        ``(nx, ny, 1)`` (a section: ``(nx, 1, nz)``): VTK's point order, x fastest
        (:func:`~ciliary_carpet.output.vtkfiles.grid_points`).
    box : tuple of 4 float
        ``(x_min, x_max, y_min, y_max)`` [L], the region the grid covers (a section: ``(x_min,
        x_max, z_min, z_max)``).
    """

    origin: tuple[float, float, float]
    spacing: tuple[float, float, float]
    shape: tuple[int, int, int]
    box: tuple[float, float, float, float]

    @classmethod
    def around(cls, settings: RenderSettings, carpet: Carpet) -> "FieldGrid":
        """The field grid of ``settings`` around ``carpet``'s bases."""
        b = carpet.bases
        m = settings.output.field_margin
        lo, hi = b.min(0) - m - 1.0, b.max(0) + m + 1.0
        nx, ny = settings.output.field_shape
        z = settings.outputs.field_height(settings)
        return cls(origin=(lo[0], lo[1], z),
                   spacing=((hi[0] - lo[0]) / max(nx - 1, 1), (hi[1] - lo[1]) / max(ny - 1, 1), 1.0),
                   shape=(nx, ny, 1), box=(lo[0], hi[0], lo[1], hi[1]))

    @classmethod
    def section(cls, settings: RenderSettings, carpet: Carpet) -> "FieldGrid":
        """A standing carpet's vertical section: the x-z plane through the centre of its bases
        (y = y_c), over the x range of :meth:`around` and from the substrate z = 0 up to
        SECTION_TOP times ``[output] height`` (at least SECTION_TOP L), with about twice as fine
        a step along z as along x (at most twice ``field_shape``'s ny points)."""
        plane = cls.around(settings, carpet)
        b = carpet.bases
        yc = 0.5 * float(b[:, 1].min() + b[:, 1].max())
        top = SECTION_TOP * max(float(settings.output.height), 1.0)
        nx = plane.shape[0]
        dx = plane.spacing[0]
        nz = int(min(max(9, round(2.0 * top / dx) + 1), 2 * settings.output.field_shape[1]))
        return cls(origin=(plane.origin[0], yc, 0.0), spacing=(dx, 1.0, top / (nz - 1)), shape=(nx, 1, nz),
                   box=(plane.box[0], plane.box[1], 0.0, top))

    def points(self) -> np.ndarray:
        """(nx ny nz, 3) the grid's points in VTK order [L]."""
        return grid_points(self.origin, self.spacing, self.shape)

    def lines(self) -> tuple[np.ndarray, np.ndarray]:
        """The grid lines: (nx,) x and (ny,) y [L]."""
        return (self.origin[0] + self.spacing[0] * np.arange(self.shape[0]),
                self.origin[1] + self.spacing[1] * np.arange(self.shape[1]))


@dataclass(frozen=True)
class Beat:
    """The cilia's beat: the median ``period`` of the beating cilia (each beats with the period of
    its own limit cycle, T(chi_N)), their range ``period_min``, ``period_max`` [tau], and how many
    are ``beating``; T0 (the straight filament's period) when none does."""

    period: float
    period_min: float
    period_max: float
    beating: int

    @classmethod
    def of(cls, carpet: Carpet, T0: float) -> "Beat":
        p = carpet.periods
        p = p[np.isfinite(p)]
        if p.size == 0:
            return cls(T0, T0, T0, 0)
        return cls(float(np.median(p)), float(p.min()), float(p.max()), int(p.size))


def seed_points(settings: RenderSettings, carpet: Carpet) -> np.ndarray:
    """(k, 2) the tracers' start points [L] ((k, 3) for a standing carpet: :func:`_standing_seeds`): ``[output] seeds`` as given, or "line" (``n_seeds``
    across the carpet, one spacing upstream of it) or "grid" (about ``n_seeds`` between the
    cilia); a seed inside a filament is nudged across the flow until two blob sizes clear."""
    return GEOMETRY_OUTPUTS[carpet.geometry].seed_points(settings, carpet)


def _planar_seeds(settings: RenderSettings, carpet: Carpet) -> np.ndarray:
    """(k, 2) a planar carpet's seeds (:func:`seed_points`)."""
    o = settings.output
    if not isinstance(o.seeds, str):
        return np.asarray(o.seeds, dtype=float)
    b = carpet.bases
    d0 = settings.flow_direction
    cross = np.array([-d0[1], d0[0]])
    c = 0.5 * (b.min(0) + b.max(0))
    along = (b - c) @ d0
    across = (b - c) @ cross
    if o.seeds == "line":  # across the carpet, one spacing upstream of it
        s = np.linspace(across.min(), across.max(), o.n_seeds)
        seeds = c + (along.min() - settings.spacing) * d0 + s[:, None] * cross
    else:
        n = max(2, int(round(math.sqrt(o.n_seeds))))  # grid: between the cilia
        a = np.linspace(along.min(), along.max(), n) + 0.5 * settings.spacing
        s = np.linspace(across.min(), across.max(), n) + 0.5 * settings.spacing
        A, S = np.meshgrid(a, s)
        seeds = c + A.ravel()[:, None] * d0 + S.ravel()[:, None] * cross
    # never inside a filament: nudge a seed across the flow until it is two blob sizes clear
    clear = 2.0 * (carpet.blob or BLOB)
    for _ in range(100):
        bad = carpet.filament_distance(seeds, 0.0) < clear
        if not bad.any():
            break
        seeds[bad] += clear * cross
    return seeds


def standing_flow_direction(carpet: Carpet) -> np.ndarray:
    """(2,) unit vector: where a standing carpet pushes the fluid along the substrate, the
    direction of the sum of its cilia's mean thrusts in space projected on the plane (+x when
    they cancel)."""
    f = carpet.in_space("mean_thrust")[:, :2].sum(axis=0)
    n = float(np.linalg.norm(f))
    return f / n if n > 1e-12 * max(1.0, float(np.abs(carpet.in_space("mean_thrust")).sum())) else np.array([1.0, 0.0])


def _standing_seeds(settings: RenderSettings, carpet: Carpet) -> np.ndarray:
    """(k, 3) a standing carpet's seeds at the target plane's height h = ``[output] height``:
    explicit points (x, y) lifted to h; "grid": about ``n_seeds`` over the bases' footprint;
    "line": ``n_seeds`` across the carpet's surface flow (:func:`standing_flow_direction`), one
    spacing upstream of its bases. Above the cilia's tips (at most L high) for h > 1; a seed
    within two blob sizes of a filament is lifted until it clears."""
    o = settings.output
    h = float(o.height)
    b = carpet.bases
    if not isinstance(o.seeds, str):
        xy = np.asarray(o.seeds, dtype=float)
    elif o.seeds == "grid":
        n = max(2, int(round(math.sqrt(o.n_seeds))))
        X, Y = np.meshgrid(np.linspace(b[:, 0].min(), b[:, 0].max(), n), np.linspace(b[:, 1].min(), b[:, 1].max(), n))
        xy = np.column_stack([X.ravel(), Y.ravel()])
    else:
        d0 = standing_flow_direction(carpet)
        cross = np.array([-d0[1], d0[0]])
        c = 0.5 * (b.min(0) + b.max(0))
        along, across = (b - c) @ d0, (b - c) @ cross
        s = np.linspace(across.min(), across.max(), o.n_seeds)
        xy = c + (along.min() - settings.spacing) * d0 + s[:, None] * cross
    seeds = np.column_stack([xy, np.full(xy.shape[0], h)])
    clear = 2.0 * (carpet.blob or BLOB)
    for _ in range(100):
        bad = carpet.filament_distance(seeds, 0.0) < clear
        if not bad.any():
            break
        seeds[bad, 2] += clear
    return seeds


def _standing_duration(settings: RenderSettings, carpet: Carpet) -> tuple[float, str]:
    """:func:`pathline_duration` of a standing carpet without ``[output] periods``: the crossing
    of its extent along the surface flow plus three spacings at the median mean speed in the
    target plane over its bases, times 1.25."""
    b = carpet.bases
    d0 = standing_flow_direction(carpet)
    travel = float(np.ptp(b @ d0)) + 3.0 * settings.spacing
    probe = b[:: max(1, b.shape[0] // 200)]
    probe = np.column_stack([probe, np.full(probe.shape[0], float(settings.output.height))])
    u = carpet.velocity(probe, CycleMean(), max(settings.tolerance, 1e-3))
    speed = float(np.median(np.linalg.norm(u[:, :2], axis=1)))
    if not (math.isfinite(speed) and speed > 0):
        raise RenderError(f"{settings.source}: the carpet makes no mean flow at the target plane (median speed "
                          f"{speed:g}): set [output] periods for the path lines")
    return 1.25 * travel / speed, (f"auto: crossing {travel:.3g} L at the median mean speed {speed:.3g} L/tau at "
                                   f"z = {settings.output.height:g} L")


def standing_domain(settings: RenderSettings, carpet: Carpet, seeds: np.ndarray | None) -> tuple:
    """(xmin, xmax, ymin, ymax, zmin, zmax) where a standing carpet's tracers are followed: the
    bases and seeds widened by :data:`DOMAIN_MARGIN` across, from the substrate z = 0 (a tracer
    that reaches the wall ends there, "left the domain") to :data:`DOMAIN_MARGIN` above the
    target plane."""
    pts = carpet.bases if seeds is None else np.concatenate([carpet.bases, seeds[:, :2]])
    lo, hi = pts.min(axis=0) - DOMAIN_MARGIN, pts.max(axis=0) + DOMAIN_MARGIN
    top = max(float(settings.output.height), float(seeds[:, 2].max()) if seeds is not None else 0.0) + DOMAIN_MARGIN
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), 0.0, top)


def pathline_duration(settings: RenderSettings, carpet: Carpet, T0: float) -> tuple[float, str]:
    """Path-line duration and how it was chosen: ``[output] periods * T0`` when the scene sets
    it, else long enough to cross the carpet: 1.25 (extent along the flow + 3 spacings) / U, with
    U the median speed of the mean flow at points between the cilia."""
    o = settings.output
    if o.periods is not None:
        return float(o.periods) * T0, "scene"
    return GEOMETRY_OUTPUTS[carpet.geometry].duration(settings, carpet)


def _planar_duration(settings: RenderSettings, carpet: Carpet) -> tuple[float, str]:
    """:func:`pathline_duration` of a planar carpet without ``[output] periods``: the crossing of
    its extent along the flow direction plus three spacings at the median mean speed between its
    cilia, times 1.25."""
    b = carpet.bases
    d0 = np.asarray(settings.flow_direction, dtype=float)
    sp = settings.spacing
    travel = float(np.ptp(b @ d0)) + 3.0 * sp
    probe = b[:: max(1, b.shape[0] // 200)] + 0.5 * sp * (d0 + np.array([-d0[1], d0[0]]))
    u = carpet.velocity(probe, CycleMean(), max(settings.tolerance, 1e-3))
    speed = float(np.median(np.linalg.norm(u[:, :2], axis=1)))
    if not (math.isfinite(speed) and speed > 0):
        raise RenderError(f"{settings.source}: the carpet makes no mean flow (median speed {speed:g}): set "
                          "[output] periods for the path lines")
    return 1.25 * travel / speed, f"auto: crossing {travel:.3g} L at the median mean speed {speed:.3g} L/tau"


def pathline_model(settings: RenderSettings, beats: float | None = None) -> tuple[str, str]:
    """The flow the tracers follow and why, in words: ``[output] pathline_model``, "auto"
    resolved to "mean" when the scene's tolerance is at least
    :data:`~ciliary_carpet.transport.flow.MEAN_MODEL_ERROR` or the run lasts more than
    :data:`~ciliary_carpet.transport.flow.AUTO_RESOLVED_BEATS` ``beats``, else to "resolved"."""
    m = settings.output.pathline_model
    if m != "auto":
        return m, "scene"
    if settings.tolerance >= MEAN_MODEL_ERROR:
        return "mean", f"auto: the tolerance {settings.tolerance:g} allows the mean flow's error"
    if beats is not None and beats > AUTO_RESOLVED_BEATS:
        return "mean", (f"auto: {beats:.0f} beats, more than {AUTO_RESOLVED_BEATS} to follow one by one; "
                        f"[output] pathline_model = \"resolved\" follows them")
    return "resolved", "auto"


@dataclass(frozen=True, eq=False)
class RenderPlan:
    """What a render of a scene does (see the module docstring); made by :meth:`decide`.

    Attributes
    ----------
    settings : RenderSettings
        The scene's render settings (its ``[output]`` says which outputs are wanted).
    estimate : Estimate
        The resource estimate the render was admitted with.
    designed : bool
        Whether the carpet was designed for a target (the design's outputs).
    T0 : float
        The straight filament's period [tau] (``[output] periods`` counts it).
    beat : Beat
        The cilia's beat: snapshots and frames sample one beat.
    grid : FieldGrid
        The grid of the mean field and the snapshots (and of the long-time flow model).
    scales : Scales or None
        The SI scales of the files (``[units]``), or None for L and tau.
    seeds : (k, 2) array or None
        The tracers' start points (with path lines).
    pathline_model : str or None
        "mean" or "resolved" (with path lines).
    model_from : str or None
        Why that model, in words (:func:`pathline_model`).
    duration : float or None
        The path lines' duration [tau] (with path lines or the FTLE, which runs for a quarter of it).
    duration_from : str or None
        How ``duration`` was chosen, in words.
    section : FieldGrid or None
        A standing carpet's vertical section through its centre (:meth:`FieldGrid.section`);
        None for a planar one.
    domain : tuple of 6 float or None
        Where a standing carpet's tracers are followed (:func:`standing_domain`); None for a
        planar one (the path lines' default domain).
    """

    settings: RenderSettings
    estimate: Estimate
    designed: bool
    T0: float
    beat: Beat
    grid: FieldGrid
    scales: Scales | None
    seeds: np.ndarray | None
    pathline_model: str | None
    duration: float | None
    duration_from: str | None
    section: FieldGrid | None = None
    domain: tuple | None = None
    model_from: str | None = None

    @classmethod
    def decide(cls, settings: RenderSettings, carpet: Carpet, *, designed: bool, estimate: Estimate) -> "RenderPlan":
        """The plan of a render with ``settings`` and the designed ``carpet``; raises what the scene's
        settings make impossible (see the module docstring) before any output."""
        o = settings.output
        seeds = check_seeds(carpet, seed_points(settings, carpet)) if o.pathlines else None  # SeedError
        T0 = float(carpet.table.scalar("period", 0.0))
        duration, how = pathline_duration(settings, carpet, T0) if (o.pathlines or o.ftle) else (None, None)
        if o.pathlines:  # PathLineError (output too large for memory)
            check_output_size(carpet, seeds.shape[0], duration, o.samples_per_period)
        geometry = GEOMETRY_OUTPUTS[carpet.geometry]
        beat = Beat.of(carpet, T0)
        model, why = (pathline_model(settings, duration / beat.period if beat.period > 0 else None) if o.pathlines
                      else (None, None))
        return cls(settings=settings, estimate=estimate, designed=designed, T0=T0, beat=beat,
                   grid=FieldGrid.around(settings, carpet), scales=carpet.scales, seeds=seeds,
                   pathline_model=model, duration=duration,
                   duration_from=how, section=geometry.section(settings, carpet),
                   domain=geometry.domain(settings, carpet, seeds), model_from=why)

    def describe(self) -> str:
        """What the render will compute, in a line, before it starts: the field grid, and the
        path lines' tracers, flow model and duration with how each was chosen."""
        o = self.settings.output
        nx, ny = self.grid.shape[:2]
        parts = [f"mean field on {nx} x {ny} points"]
        if o.pathlines:
            beats = self.duration / self.beat.period if self.beat.period > 0 else math.nan
            flow = "the mean flow" if self.pathline_model == "mean" else "the time-resolved flow"
            why = "as the scene's [output] pathline_model asks" if self.model_from == "scene" else self.model_from
            long = "as the scene's [output] periods asks" if self.duration_from == "scene" else self.duration_from
            parts.append(f"{self.seeds.shape[0]} path lines in {flow} ({why}) for {self.duration:.4g} tau = "
                         f"{beats:.0f} beats ({long})")
        if o.ftle:
            parts.append("the FTLE over a quarter of that" if o.pathlines else "the FTLE")
        return f"render {self.settings.name}: " + "; ".join(parts)

    @property
    def units(self) -> tuple[float, float, float]:
        """The files' (length, time, velocity) units in L, tau, L/tau: the SI scales, or ones."""
        sc = self.scales
        return (sc.length_m, sc.time_s, sc.velocity) if sc is not None else (1.0, 1.0, 1.0)

    @property
    def span(self) -> float:
        """The time range of what moves [tau]: the path lines' duration, or one beat without them.
        The snapshots' and frames' collections repeat one beat until then (one clock)."""
        return self.duration if self.settings.output.pathlines else self.beat.period


class GeometryOutputs(ABC):
    """What a render does differently for a carpet geometry (one object per geometry,
    :data:`GEOMETRY_OUTPUTS` by name; the model's side is the carpet's
    :class:`~ciliary_carpet.carpet.geometry.Geometry`): the field grid's height, the tracers'
    seeds and automatic duration, the vertical section and the tracers' domain, the FTLE's
    options and the summary's keys of the geometry."""

    name: str

    @abstractmethod
    def field_height(self, settings: RenderSettings) -> float:
        """The height z [L] of the field grid's plane (:meth:`FieldGrid.around`)."""

    @abstractmethod
    def seed_points(self, settings: RenderSettings, carpet: Carpet) -> np.ndarray:
        """The tracers' start points [L] (:func:`seed_points`)."""

    @abstractmethod
    def duration(self, settings: RenderSettings, carpet: Carpet) -> tuple[float, str]:
        """The path lines' automatic duration and how it was chosen (:func:`pathline_duration`)."""

    def section(self, settings: RenderSettings, carpet: Carpet) -> FieldGrid | None:
        """The vertical section the field outputs also sample (None: none)."""
        return None

    def domain(self, settings: RenderSettings, carpet: Carpet, seeds: np.ndarray | None) -> tuple | None:
        """Where the tracers are followed (None: the path lines' default domain)."""
        return None

    def ftle_options(self, plan: "RenderPlan") -> dict:
        """The keyword arguments the FTLE field takes for this geometry."""
        return {}

    def summary(self, carpet: Carpet, settings: RenderSettings, length: float) -> dict:
        """The summary's keys of this geometry (``length``: L in the summary's length unit)."""
        return {}


class PlanarOutputs(GeometryOutputs):
    """A planar carpet's render: the field in its plane z = 0, seeds and duration along its flow
    direction; no section, the default domain, no summary keys (a planar summary has no geometry key)."""

    name = "planar"

    def field_height(self, settings):
        return 0.0

    def seed_points(self, settings, carpet):
        return _planar_seeds(settings, carpet)

    def duration(self, settings, carpet):
        return _planar_duration(settings, carpet)


class StandingOutputs(GeometryOutputs):
    """A standing carpet's render: the field in the target plane z = ``[output] height`` and a
    vertical section, seeds and duration along its surface flow, the tracers' domain above the
    substrate; the FTLE in the target plane; the summary's ``geometry`` and ``standing`` keys."""

    name = "standing"

    def field_height(self, settings):
        return float(settings.output.height)

    def seed_points(self, settings, carpet):
        return _standing_seeds(settings, carpet)

    def duration(self, settings, carpet):
        return _standing_duration(settings, carpet)

    def section(self, settings, carpet):
        return FieldGrid.section(settings, carpet)

    def domain(self, settings, carpet, seeds):
        return standing_domain(settings, carpet, seeds)

    def ftle_options(self, plan):
        return {"height": float(plan.grid.origin[2])}

    def summary(self, carpet, settings, length):
        psi = np.round(np.degrees(carpet.azimuth), 9)
        return {"geometry": "standing",
                "standing": {"wall_below_clamps": carpet.wall * length if carpet.wall is not None else None,
                             "azimuth_deg": {"min": float(psi.min()), "max": float(psi.max()),
                                             "median": float(np.median(psi))},
                             "target_height": float(settings.output.height) * length}}


GEOMETRY_OUTPUTS: dict[str, GeometryOutputs] = {g.name: g for g in (PlanarOutputs(), StandingOutputs())}
"""What a render does differently per carpet geometry, by name (the keys of
:data:`~ciliary_carpet.carpet.geometry.GEOMETRIES`)."""
