"""Path lines (ciliary_carpet.transport.pathlines): analytic flows, convergence in the tolerance, dense
output, termination reasons, tracers passing a filament, the long-time model, bad input."""
import math
import warnings

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from ciliary_carpet.carpet.carpet import Carpet, Instant
from ciliary_carpet.transport.flow import FLOWS, MEAN_MODEL_ERROR, Flow, MeanFlow, ResolvedFlow
from ciliary_carpet.transport.pathlines import (
    DOMAIN,
    END,
    REASONS,
    UNDERFLOW,
    PathLineError,
    SeedError,
    _next_step,
    pathlines,
)
from single_cilium.table import ThrustTable


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


@pytest.fixture(scope="module")
def one(table):
    """A single curved cilium at the origin."""
    return Carpet(np.zeros((1, 2)), [4.0], table, phases=[0.3])


class Rotation(Flow):
    """Solid-body rotation u = w (-y, x): circles of period 2 pi / w (beside the carpet ``carpet``)."""

    name = "rotation"

    def __init__(self, carpet, w=1.0):
        self.carpet = carpet
        self.w = w
        self.calls = 0

    def velocity(self, x, t):
        self.calls += 1
        u = np.zeros_like(x)
        u[:, 0] = -self.w * x[:, 1]
        u[:, 1] = self.w * x[:, 0]
        return u


class Oscillating(Flow):
    """u = (cos(2 pi t / P), 0): x(t) = x0 + P sin(2 pi t / P) / (2 pi)."""

    name = "oscillating"

    def __init__(self, carpet, period):
        self.carpet = carpet
        self.P = period

    def velocity(self, x, t):
        u = np.zeros_like(x)
        u[:, 0] = math.cos(2 * math.pi * t / self.P)
        return u


def _rotation_error(one, rtol):
    seeds = np.column_stack([np.linspace(3.0, 6.0, 4), np.zeros(4)])
    t1 = 2.5
    pl = pathlines(Rotation(one), seeds, (0.0, t1), rtol=rtol, atol=rtol, domain=(-20, 20, -20, 20))
    exact = np.column_stack([seeds[:, 0] * math.cos(t1), seeds[:, 0] * math.sin(t1), np.zeros(4)])
    return float(np.abs(pl.end_points - exact).max()), pl


def test_known_flow_and_convergence_in_tolerance(one):
    errs = [_rotation_error(one, r)[0] for r in (1e-4, 1e-6, 1e-8)]
    assert errs[2] < 1e-6
    # the global error follows the tolerance: each factor 100 in rtol gains at least a factor 20
    assert errs[0] / errs[1] > 20 and errs[1] / errs[2] > 20, errs
    _, pl = _rotation_error(one, 1e-8)
    assert pl.status == "success" and np.all(pl.reason == END)
    for p, t in zip(pl.points, pl.times):  # every sample on its circle at its own time
        r0 = np.hypot(*p[0, :2])
        exact = np.column_stack([r0 * np.cos(t), r0 * np.sin(t)])
        assert np.abs(p[:, :2] - exact).max() < 1e-6


def test_dense_output_is_smooth_and_accurate(one):
    P = float(one.periods[0])
    seeds = np.array([[5.0, 0.0], [6.0, 1.0]])
    pl = pathlines(Oscillating(one, P), seeds, (0.0, 3 * P), rtol=1e-9, atol=1e-9, samples_per_period=16)
    for p, t, v in zip(pl.points, pl.times, pl.velocities):
        assert np.diff(t).max() <= P / 16 * (1 + 1e-9)
        assert t.size >= 3 * 16 + 1
        exact = p[0, 0] + P * np.sin(2 * np.pi * t / P) / (2 * np.pi)
        assert np.abs(p[:, 0] - exact).max() < 1e-6 * P  # Hermite samples between the steps
        assert np.abs(v[:, 0] - np.cos(2 * np.pi * t / P)).max() < 1e-3
    assert pl.dt == pytest.approx(P / 16)


def test_termination_reasons(one):
    class Jump(Flow):  # a velocity jump of 1e15 at x = 0.5: no step can resolve it
        name = "jump"
        carpet = one

        def velocity(self, x, t):
            u = np.zeros_like(x)
            u[:, 0] = 1.0 + 1e15 * (x[:, 0] > 0.5)
            return u

    seeds = np.array([[0.45, 3.0], [-50.0, 3.0], [5.0, 3.0]])
    pl = pathlines(Jump(), seeds, (0.0, 1.0), domain=(-100, 10, -10, 10))
    assert list(pl.reason) == [UNDERFLOW, END, DOMAIN]
    assert pl.status == "inaccurate" and "underflow" in pl.message
    assert pl.counts() == {REASONS[END]: 1, REASONS[DOMAIN]: 1, REASONS[UNDERFLOW]: 1}
    # the exit point ends the line: on the boundary x = 10 at the crossing time t = 5e-15 (u = 1e15),
    # not a step beyond it
    assert pl.points[2][-1, 0] == pytest.approx(10.0, abs=1e-10)
    assert pl.times[2][-1] == pytest.approx(5e-15, rel=1e-6)
    assert pl.times[0][-1] == pytest.approx(0.05, abs=1e-3)


def test_exit_point_lies_on_the_boundary_at_the_crossing_time(one):
    """Uniform flow u = (1, 0.5): a tracer from (0, -2) leaves the box x <= 3 at t = 3 exactly, at
    (3, -0.5); the exit is found by bisection on the continuous extension, whatever the steps."""
    class Uniform(Flow):
        name = "uniform"
        carpet = one

        def velocity(self, x, t):
            u = np.zeros_like(x)
            u[:, 0] = 1.0
            u[:, 1] = 0.5
            return u

    for h0 in (0.7, 2.9):
        pl = pathlines(Uniform(), np.array([[0.0, -2.0]]), (0.0, 10.0), domain=(-5, 3, -5, 5), h0=h0)
        assert pl.reason[0] == DOMAIN
        assert pl.times[0][-1] == pytest.approx(3.0, abs=1e-9)
        assert np.allclose(pl.points[0][-1], [3.0, -0.5, 0.0], atol=1e-9)
        assert np.allclose(pl.velocities[0][-1], [1.0, 0.5, 0.0], atol=1e-9)


def test_a_flow_model_is_one_class(one):
    """pathlines asks the flow for its name, domain and step cap: a new model is one subclass of
    Flow (the registry names the bundled ones)."""
    class Drift(Flow):
        name = "drift"
        carpet = one
        domain = np.array([-5.0, 3.0, -5.0, 5.0, -np.inf, np.inf])  # valid only in this box
        step_cap = 0.05

        def velocity(self, x, t):
            u = np.zeros_like(x)
            u[:, 0] = 1.0
            return u

    pl = pathlines(Drift(), np.array([[0.0, -2.0]]), (0.0, 10.0), domain=(-20, 20, -20, 20))
    assert pl.model == "drift" and pl.reason[0] == DOMAIN and "drift flow" in pl.message
    assert pl.points[0][-1, 0] == pytest.approx(3.0, abs=1e-9)  # the flow's domain, not the run's wider one
    assert pl.stats["steps"] >= 3.0 / 0.05 - 1  # its step cap
    assert set(FLOWS) == {"resolved", "mean"} and FLOWS["mean"] is MeanFlow
    assert ResolvedFlow(one).step_cap == pytest.approx(float(one.periods[0]) / 16)
    assert MeanFlow.from_carpet(one, (-2.0, 2.0, -1.0, 3.0), spacing=1.0).domain.tolist() == \
        [-2.0, 2.0, -1.0, 3.0, -np.inf, np.inf]


class FastOnTheRight(Flow):
    """u = (cos(w t), 0, 0) where x > 0, zero elsewhere: x(t) = x0 + sin(w t) / w on the right."""

    name = "fast_on_the_right"

    def __init__(self, carpet, w):
        self.carpet, self.w = carpet, w

    def velocity(self, x, t):
        u = np.zeros_like(x)
        u[:, 0] = np.where(x[:, 0] > 0, math.cos(self.w * t), 0.0)
        return u


def test_smaller_steps_split_what_is_left_equally(one):
    """The tracers that fail a step take smaller steps of equal length, none a short remainder
    (each such step costs a whole instant of a carpet's state), and stay accurate."""
    assert _next_step(1.0, 0.45, equal=True) == pytest.approx(1 / 3)  # not 0.45, 0.45, 0.1
    assert _next_step(1.0, 0.45, equal=False) == 0.45  # the common steps keep the error test's
    assert _next_step(1.0, 0.5, equal=True) == 0.5
    assert _next_step(1.0, 0.6, equal=True) == 0.5
    assert _next_step(1.0, 1.0 - 1e-12, equal=True) == 1.0 and _next_step(1.0, 3.0, equal=False) == 1.0
    # one tracer in a fast flow, one at rest: the common steps (the cap H) suit the second, the
    # first re-integrates each of them in smaller steps
    H, w = 0.05, 60.0
    flow = FastOnTheRight(one, w)
    seeds = np.array([[5.0, 3.0], [-5.0, 3.0]])
    pl = pathlines(flow, seeds, (0.0, 1.0), rtol=1e-10, atol=1e-10, max_step=H, domain=(-9, 9, -9, 9))
    assert pl.stats["substeps"] > 100 and np.all(pl.reason == END)
    assert abs(pl.end_points[0, 0] - (5.0 + math.sin(w) / w)) < 1e-8
    assert np.array_equal(pl.end_points[1], [-5.0, 3.0, 0.0])


def test_tracers_pass_a_single_filament(one):
    """A line of tracers laid across the beating filament's swept region: the filament sweeps
    over them, none is stopped, and the velocity stays bounded on the filament itself."""
    P = float(one.periods[0])
    c, a = one.centres[0], one.radii[0]
    seeds = np.column_stack([np.linspace(c[0] - 0.6 * a, c[0] + 0.6 * a, 9), np.full(9, c[1])])
    seeds = seeds[one.filament_distance(seeds, 0.0) > 2 * one.blob]
    assert len(seeds) >= 6 and all(one.in_swept_region(seeds, 0))
    pl = pathlines(ResolvedFlow(one, 1e-3), seeds, (0.0, P), rtol=1e-5, atol=1e-5)
    assert np.all(pl.reason == END), pl.message
    # the filament passed over the tracers: each is within a few blob sizes of it at some time
    closest = [min(one.filament_distance(p[j:j + 1], t[j])[0] for j in range(len(t)))
               for p, t in zip(pl.points, pl.times)]
    assert sum(d < 0.1 for d in closest) >= 3, closest
    pos, _, _ = one.state(0.37 * P)
    u = one.velocity(pos[0], Instant(0.37 * P))
    assert np.all(np.isfinite(u)) and np.abs(u).max() < 1e3
    singular = Carpet(one.bases, one.chi_N, one.table, one.phases, blob=None)
    near = pos[0, 20] + [1e-7, 0.0]
    assert np.abs(singular.velocity(near[None], Instant(0.37 * P))).max() > \
        100 * np.abs(one.velocity(near[None], Instant(0.37 * P))).max()


def test_long_time_model_against_time_resolved(table):
    """Over 12 beats of a 2 x 2 carpet the mean-flow path lines end within MEAN_MODEL_ERROR of the
    distance travelled from the time-resolved ones. At viscosity 1, where MEAN_MODEL_ERROR was
    measured: the model's relative error grows like 1 / mu (the drift of the oscillating flow is
    quadratic in it, the travel linear), and at the default viscosity 0.653 one tracer of this
    nearly straight 2 x 2 carpet ends 0.16 of its travel off (the render's carpets: 0.030,
    MEAN_MODEL_ERROR's docstring)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        carpet = Carpet(np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0], [2.0, 2.0]]), [3.0, 3.0, 3.0, 3.0], table,
                        phases=[0.0, 0.25, 0.5, 0.75], viscosity=1.0)
    seeds = np.column_stack([np.linspace(-0.5, 2.5, 6), np.full(6, 3.7)])
    span = (0.0, 12 * float(carpet.periods[0]))
    box = (-2.0, 4.0, -2.0, 5.0)
    resolved = pathlines(ResolvedFlow(carpet, 1e-3), seeds, span, rtol=1e-6, atol=1e-5, domain=box)
    mean = pathlines(MeanFlow.from_carpet(carpet, box, spacing=0.25, tol=1e-3), seeds, span, domain=box)
    assert mean.model == "mean" and resolved.model == "resolved"
    ok = (resolved.reason == END) & (mean.reason == END)
    assert ok.sum() >= 4
    travel = np.linalg.norm(resolved.end_points - seeds_3d(seeds), axis=1)
    err = np.linalg.norm(mean.end_points - resolved.end_points, axis=1)
    print("mean model error / travel", err[ok] / travel[ok])
    assert np.all(travel[ok] > 0.3)
    assert np.all(err[ok] <= MEAN_MODEL_ERROR * travel[ok]), (err / travel)[ok]
    assert mean.stats["seconds"] < resolved.stats["seconds"]


def seeds_3d(s):
    return np.column_stack([s, np.zeros(len(s))])


def test_write_pathlines_and_particles(one, tmp_path):
    from ciliary_carpet.output.tracers import particles_to_pvd, pathlines_to_vtp

    P = float(one.periods[0])
    pl = pathlines(Oscillating(one, P), np.array([[5.0, 0.0], [6.0, 1.0]]), (0.0, 2 * P))
    f = pathlines_to_vtp(pl, tmp_path / "p.vtp")
    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(f))
    r.Update()
    out = r.GetOutput()
    assert out.GetNumberOfCells() == 2
    it = vtk_to_numpy(out.GetPointData().GetArray("IntegrationTime"))
    assert it[0] == 0 and it.max() == pytest.approx(2 * P)
    names = out.GetFieldData().GetAbstractArray("TerminationReasonNames")
    assert [names.GetValue(i) for i in range(names.GetNumberOfValues())] == list(REASONS)
    pvd = particles_to_pvd(pl, tmp_path / "particles.pvd", max_frames=10)
    files = sorted(tmp_path.glob("particles_*.vtp"))
    assert 5 <= len(files) <= 10 and pvd.exists()
    rd = vtk.vtkXMLPolyDataReader()
    rd.SetFileName(str(files[-1]))
    rd.Update()
    assert rd.GetOutput().GetNumberOfPoints() == 2


def test_bad_input_named_before_any_work(one, table):
    pos, _, _ = one.state(0.0)
    with pytest.raises(SeedError, match="inside a filament"):
        pathlines(ResolvedFlow(one), pos[0, 30:31] + [0.005, 0.0], (0.0, 1.0))
    with pytest.raises(SeedError, match="shape"):
        pathlines(ResolvedFlow(one), np.zeros((3, 4)), (0.0, 1.0))
    flow = Rotation(one)
    with pytest.raises(PathLineError, match="GiB"):
        pathlines(flow, np.full((1000, 2), 5.0), (0.0, 1e6))
    assert flow.calls == 0
    for bad in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="blob"):
            Carpet(np.zeros((1, 2)), [0.0], table, blob=bad)
    with pytest.raises(ValueError, match="blob = 0.6 is larger than half"):
        Carpet(np.array([[0.0, 0.0], [1.0, 0.0]]), [0.0, 0.0], table, blob=0.6)
    with pytest.raises(TypeError, match="Flow"):
        pathlines("fast", np.array([[5.0, 0.0]]), (0.0, 1.0))
    with pytest.raises(ValueError, match="tol"):
        ResolvedFlow(one, 1.5)


def test_ftle_of_a_linear_hyperbolic_flow(one):
    from ciliary_carpet.transport.ftle import FTLEError, ftle_field

    class Saddle(Flow):  # u = (a x, -a y): stretching rate a everywhere
        name = "saddle"
        carpet = one

        def velocity(self, x, t):
            u = np.zeros_like(x)
            u[:, 0] = 0.7 * (x[:, 0] - 10.0)
            u[:, 1] = -0.7 * x[:, 1]
            return u

    f = ftle_field(Saddle(), (9.0, 11.0, -1.0, 1.0), (7, 5), 2.0, rtol=1e-9, atol=1e-9)
    assert f.ftle.shape == (5, 7) and f.shape == (7, 5)
    assert np.allclose(f.ftle, 0.7, atol=1e-6)
    assert f.mixing_number == pytest.approx(1.4, abs=1e-5)
    rot = ftle_field(Rotation(one), (5.0, 7.0, -1.0, 1.0), (5, 5), 1.0, rtol=1e-9, atol=1e-9)
    assert np.allclose(rot.ftle, 0.0, atol=1e-6)  # a rotation does not stretch
    for shape in ((0, 5), (2, 9)):
        with pytest.raises(FTLEError, match="at least 3 x 3"):
            ftle_field(Saddle(), (9.0, 11.0, -1.0, 1.0), shape, 2.0)
    with pytest.raises(FTLEError, match="box"):
        ftle_field(Saddle(), (9.0, 9.0, -1.0, 1.0), (5, 5), 2.0)
    with pytest.raises(FTLEError, match="duration"):
        ftle_field(Saddle(), (9.0, 11.0, -1.0, 1.0), (5, 5), 0.0)


def test_render_writes_paraview_ready_path_lines(tmp_path):
    import json
    import py_compile

    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import SceneError, scene_from_dict

    data = {"name": "tiny", "carpet": {"lattice": "square", "shape": [2, 2], "spacing": 2.0, "chi_N": 3.0},
            "output": {"n_seeds": 6, "periods": 2.0, "field_shape": [12, 12], "snapshots": 1, "frames": 2}}
    res = render(scene_from_dict(data), tmp_path / "tiny")
    s = json.loads((res.out_dir / "summary.json").read_text())
    p = s["pathlines"]
    assert p["stopped_early"] == 0 and p["model"] == "resolved" and p["duration_from"] == "scene"
    assert p["outcome"]["reached end time"] + p["outcome"]["left the domain"] == 6
    # the path lines at flow tol 1e-4 (tighter than the scene's 1e-3), rtol 1e-9, atol 1e-7 x spacing 2;
    # 6 tracers re-integrated with the flow tolerance / 3 and rtol, atol / 10
    assert (p["flow_tol"], p["rtol"], p["atol"]) == (1e-4, 1e-9, 2e-7)
    e = p["end_point_error"]
    assert e["tracers"] == 6 and "flow tol 3.33e-05, rtol 1e-10, atol 2e-08 L" in e["reference"]
    assert 0 <= e["median"] <= e["max"] < 1e-3
    assert "Their end points are accurate to about" in (res.out_dir / "summary.md").read_text()
    assert {"particles.pvd", "open_in_paraview.py", "ftle.vti", "pathlines.vtp"} <= set(res.files)
    py_compile.compile(str(res.out_dir / "open_in_paraview.py"), doraise=True)
    assert "mixing_number" in s["mixing"] and 0 < s["mixing"]["defined_fraction"] <= 1
    r = vtk.vtkXMLImageDataReader()
    r.SetFileName(str(res.out_dir / "mean_field.vti"))
    r.Update()
    pd = r.GetOutput().GetPointData()
    assert pd.GetVectors().GetName() == "velocity" and pd.GetArray("vorticity").GetNumberOfComponents() == 3
    bad = dict(data, carpet=dict(data["carpet"], blob=1.5))
    with pytest.raises(SceneError, match="blob"):
        scene_from_dict(bad)


def test_render_error_estimate_of_the_long_time_model(table):
    """For the long-time model the render's estimate is its error against the time-resolved flow:
    positive (the models differ), below the distance travelled, and named as the model's error."""
    from ciliary_carpet.transport.flow import MeanFlow
    from ciliary_carpet.transport.accuracy import pathline_error

    c = Carpet(np.array([[0.0, 0.0], [2.0, 0.0]]), [4.0, -4.0], table, phases=[0.3, 0.8])
    T = float(np.nanmin(c.periods))
    seeds = np.array([[-0.5, 1.5], [1.0, 1.4], [2.5, -1.5]])
    flow = MeanFlow.from_carpet(c, (-4.0, 6.0, -4.0, 4.0), tol=1e-3)
    pl = pathlines(flow, seeds, (0.0, 6 * T), domain=(-4.0, 6.0, -4.0, 4.0))
    e = pathline_error(c, seeds, 6 * T, pl, "mean", flow, 1e-3, 2.0)
    travel = np.linalg.norm(pl.end_points[:, :2] - seeds, axis=1)
    assert e["tracers"] == 3 and "long-time model" in e["reference"]
    assert 0 < e["median"] <= e["max"] < travel.max()


def test_render_error_estimate_is_the_distance_to_a_tighter_run(table):
    """For the time-resolved flow the estimate is the end-point distance of the sampled tracers
    (error_tracers: evenly spread, at most ERROR_SAMPLE) to the same integration with the flow
    tolerance / 3 and rtol, atol / 10 (REFERENCE_TIGHTER), recomputed here by hand."""
    from ciliary_carpet.transport.accuracy import ERROR_SAMPLE, REFERENCE_TIGHTER, error_tracers, pathline_error
    from ciliary_carpet.transport.flow import ResolvedFlow

    assert list(error_tracers(3)) == [0, 1, 2] and list(error_tracers(100)) == [0, 14, 28, 42, 57, 71, 85, 99]
    assert error_tracers(1000).size == ERROR_SAMPLE and REFERENCE_TIGHTER == (3.0, 10.0)
    from ciliary_carpet.carpet import layout

    c = Carpet(layout.square(3, 3, 2.0), np.full(9, 90.0), table, layout.random_phases(9, 0))
    T = float(np.nanmin(c.periods))
    seeds = np.array([[-3.0, 6.0], [2.0, 5.0], [6.0, -1.5]])  # a few L away: the levels of detail matter
    flow = ResolvedFlow(c, 1e-2)
    pl = pathlines(flow, seeds, (0.0, 3 * T), rtol=1e-3, atol=1e-2)
    e = pathline_error(c, seeds, 3 * T, pl, "resolved", flow, 0.5, 2.0)
    ref = pathlines(ResolvedFlow(c, 1e-2 / 3), seeds, (0.0, 3 * T), rtol=1e-4, atol=1e-3, samples_per_period=1)
    d = np.linalg.norm(pl.end_points - ref.end_points, axis=1)
    assert e["tracers"] == 3 and e["max"] == pytest.approx(d.max(), rel=1e-12)
    assert e["median"] == pytest.approx(np.median(d), rel=1e-12) and 1e-6 < e["max"] < 1e-3
    assert "flow tol 0.00333, rtol 0.0001, atol 0.001 L" in e["reference"]


def test_far_carriers_in_fp32(table):
    """ResolvedFlow(precision="fp32"), as a render's path lines run: the far cilia's carriers summed
    in fp32 (ciliary_carpet.stokes.precision), the rest in fp64. On a 6 x 6 carpet at tol 1e-4 the
    velocities differ from fp64's by far less than the tolerance but more than fp64 rounding; the
    carriers' forces kept for one precision are not read by the other (fp64 after fp32 at the same
    instants gives fp64's numbers to the bit); path lines end within 1e-6 L of fp64's."""
    g = np.arange(6) * 2.0
    bases = np.array([(x, y) for x in g for y in g])
    rng = np.random.default_rng(7)
    c32 = Carpet(bases, rng.uniform(-20, 20, 36), table, phases=rng.uniform(0, 1, 36))
    c64 = Carpet(bases, c32.chi_N, table, phases=c32.phases)
    x = np.column_stack([rng.uniform(-2, 12, 60), rng.uniform(-2, 12, 60), rng.uniform(0.3, 2.0, 60)])
    f32, f64 = ResolvedFlow(c32, 1e-4, precision="fp32"), ResolvedFlow(c64, 1e-4)
    for t in (0.0, 0.37):
        f32.prepare(np.array([t, t + 0.1]))
        u32 = f32.velocity(x, t)
        u64 = f64.velocity(x, t)
        d = np.max(np.abs(u32 - u64)) / np.max(np.abs(u64))
        assert 1e-12 < d < 1e-5, d
        assert np.array_equal(ResolvedFlow(c32, 1e-4).velocity(x, t), u64)  # same carpet, fp64 again
    with pytest.raises(ValueError, match="precision"):
        ResolvedFlow(c32, 1e-4, precision="half")
    with pytest.raises(ValueError, match="precision"):
        c32.velocity(x, Instant(0.0), 1e-4, precision="fp16")
    # with a wall (heights above it: the shift keeps z, Plan.rounded) the same holds
    w32 = Carpet(bases, c32.chi_N, table, phases=c32.phases, wall=0.5)
    w64 = Carpet(bases, c32.chi_N, table, phases=c32.phases, wall=0.5)
    u32 = ResolvedFlow(w32, 1e-4, precision="fp32").velocity(x, 0.2)
    u64 = ResolvedFlow(w64, 1e-4).velocity(x, 0.2)
    d = np.max(np.abs(u32 - u64)) / np.max(np.abs(u64))
    assert 1e-12 < d < 1e-5, d
    # a standing carpet (frames out of the plane; heights above its substrate)
    from ciliary_carpet.carpet import layout

    s32 = Carpet(layout.square(5, 5, 2.0), np.full(25, 30.0), table, geometry="standing")
    s64 = Carpet(layout.square(5, 5, 2.0), np.full(25, 30.0), table, geometry="standing")
    xs = np.column_stack([x[:, :2], x[:, 2] + 1.0])
    u32 = ResolvedFlow(s32, 1e-4, precision="fp32").velocity(xs, 0.3)
    u64 = ResolvedFlow(s64, 1e-4).velocity(xs, 0.3)
    d = np.max(np.abs(u32 - u64)) / np.max(np.abs(u64))
    assert 1e-12 < d < 1e-5, d
    seeds = np.column_stack([np.linspace(1.0, 9.0, 5), np.full(5, 12.5)])
    span = (0.0, 3 * float(c32.periods.min()))
    a = pathlines(f32, seeds, span, rtol=1e-9, atol=1e-8)
    b = pathlines(f64, seeds, span, rtol=1e-9, atol=1e-8)
    assert np.max(np.linalg.norm(a.end_points - b.end_points, axis=1)) < 1e-6
    assert np.min(np.linalg.norm(a.end_points - seeds_3d(seeds), axis=1)) > 0.01  # they moved
