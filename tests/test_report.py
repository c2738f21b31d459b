"""What a render tells, and what it costs (issue 42, items 2, 3, 7): the summary's first lines give
a verdict in a named model, how far that model is from the coupled one, and flag results too
uncertain to use; the terminal gets that head and a line of what will be computed before the wait;
"auto" path lines, their animation and their files are sized to what a scene needs."""
import pytest

from ciliary_carpet.output.report import COUPLING_MATTERS, UNRELIABLE_END_POINTS, _verdict

DESIGN = {"met": True, "residual_rms": 0.02, "residual_threshold": 0.05}


def _first(s):
    return " ".join(_verdict(s, "L"))


def test_an_uncoupled_verdict_says_how_far_the_coupled_model_is():
    far = {"design": DESIGN, "coupling": {"model": "linear drag estimate", "relative_change_median": 1.42}}
    txt = _first(far)
    assert txt.startswith("**Verdict: target met, in the uncoupled model")
    assert "The coupled model differs here" in txt and "142%" in txt and 'coupling = \\"mean\\"' not in txt
    near = {"design": DESIGN, "coupling": {"model": "linear drag estimate",
                                           "relative_change_median": 0.5 * COUPLING_MATTERS}}
    assert "differs here" not in _first(near) and "the verdict stands" in _first(near)


def test_a_coupled_verdict_says_so_with_its_residual():
    s = {"design": {**DESIGN, "met": False}, "coupling": {"model": "mean", "residual": 3e-5, "status": "converged",
                                                       "relative_change_median": 1.4}}
    txt = _first(s)
    assert txt.startswith("**Verdict: target NOT met, in the coupled model") and "3e-05" in txt
    assert "differs here" not in txt


def test_a_standing_verdict_uses_the_measured_push_of_the_neighbours():
    s = {"design": DESIGN, "omissions": {"pushback": {"median": 0.013}}}
    assert "1.3% (median)" in _first(s) and "would change little" in _first(s)
    s["omissions"]["pushback"]["median"] = 0.6
    assert "The coupled model differs here" in _first(s)


def test_unreliable_path_lines_are_flagged_first_in_their_units():
    s = {"pathlines": {"end_point_error": {"max": 8.7}}}
    assert "**Path lines unreliable**" in _first(s) and "8.7 L" in _first(s)
    s["pathlines"]["end_point_error"]["max"] = 0.5 * UNRELIABLE_END_POINTS
    assert "unreliable" not in _first(s)
    # with [units] the error is in m and a cilium is length_m long
    si = {"units": "SI", "scene_resolved": {"units": {"length_m": 1e-4}},
          "pathlines": {"end_point_error": {"max": 5e-5}}}
    assert "unreliable" not in " ".join(_verdict(si, "m"))
    si["pathlines"]["end_point_error"]["max"] = 2e-4
    assert "unreliable" in " ".join(_verdict(si, "m"))


def test_render_prints_the_summarys_head_not_all_of_it(tmp_path, capsys):
    from ciliary_carpet.cli import main

    scene = tmp_path / "tiny.toml"
    scene.write_text('name = "tiny"\n[carpet]\nlattice = "square"\nshape = [2, 2]\nspacing = 2.0\nchi_N = 3.0\n'
                     '[output]\nn_seeds = 4\nperiods = 2.0\nfield_shape = [10, 10]\nsnapshots = 2\nframes = 8\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert ("**The flow shown is the coupled model's** (each cilium beats in the mean flow the others make at it)"
            in out)
    assert "## " not in out and "the whole summary: " in out  # the sections stay in the file
    assert (tmp_path / "out" / "summary.md").read_text().count("\n## ") >= 3


def test_auto_path_lines_follow_the_mean_flow_over_thousands_of_beats_and_say_so():
    from ciliary_carpet.output.plan import RenderPlan, pathline_model
    from ciliary_carpet.transport.flow import AUTO_RESOLVED_BEATS
    from ciliary_carpet.scenes.resources import check_resources
    from ciliary_carpet.scenes.assembly import assemble, render_settings
    from ciliary_carpet.scenes.scene import scene_from_dict

    s = render_settings(scene_from_dict({"carpet": {"shape": [2, 2]}, "tolerance": 1e-3}))
    assert pathline_model(s, 0.5 * AUTO_RESOLVED_BEATS) == ("resolved", "auto")
    model, why = pathline_model(s, 1670)
    assert model == "mean" and "1670 beats" in why and 'pathline_model = \\"resolved\\"' not in why
    resolved = render_settings(scene_from_dict({"output": {"pathline_model": "resolved"}}))
    assert pathline_model(resolved, 1670)[0] == "resolved"
    # a slow carpet whose automatic duration is thousands of beats: the plan picks the mean flow and says so
    slow = scene_from_dict({"carpet": {"shape": [2, 2], "chi_N": 150.0}, "output": {"n_seeds": 4}})
    plan = RenderPlan.decide(render_settings(slow), assemble(slow).carpet(), designed=False,
                             estimate=check_resources(slow))
    line = plan.describe()
    beats = plan.duration / plan.beat.period
    assert line.startswith("render ") and "4 path lines" in line and f"{beats:.0f} beats" in line
    assert beats > AUTO_RESOLVED_BEATS and plan.pathline_model == "mean" and "in the mean flow (auto: " in line


def test_a_long_run_animates_in_a_bounded_number_of_steps_on_the_right_clock():
    from ciliary_carpet.output.fields import _looped
    from ciliary_carpet.output.plan import ANIMATION_STEPS

    files = [f"f{k}" for k in range(40)]
    bundled = _looped(files, 0.25, 27.5)  # 110 beats x 40 frames, as the bundled scenes: every frame of every beat
    assert len(bundled) == 4401 <= ANIMATION_STEPS and bundled[-1] == (27.5, "f0")
    few = _looped(files, 0.25, 2.5)  # 10 beats: looped exactly
    assert len(few) == 401 and few[41] == (0.25 * 41 / 40, "f1")
    long = _looped(files, 0.25, 417.5)  # 1670 beats: 66,800 entries, capped
    assert len(long) == ANIMATION_STEPS and long[-1][0] == 417.5
    t, f = long[7]
    assert f == files[int(round(t / 0.25 * 40)) % 40]  # each step shows the frame of its phase


def test_path_lines_are_thinned_for_viewing_with_their_ends_kept_and_said(tmp_path):
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import scene_from_dict

    tiny = {"name": "tiny", "carpet": {"lattice": "square", "shape": [2, 2], "spacing": 2.0, "chi_N": 3.0},
            "output": {"n_seeds": 4, "periods": 2.0, "field_shape": [10, 10], "snapshots": 1, "frames": 8,
                       "pathline_points": 5, "ftle": False}}
    res = render(scene_from_dict(tiny), tmp_path / "tiny")
    p = res.summary["pathlines"]
    assert p["points"] > p["points_written"] and p["points_written"] <= 5 * p["tracers"]
    r = vtk.vtkXMLPolyDataReader()
    r.SetFileName(str(res.out_dir / "pathlines.vtp"))
    r.Update()
    lines = r.GetOutput()
    assert lines.GetNumberOfPoints() == p["points_written"]
    t = vtk_to_numpy(lines.GetPointData().GetArray("time"))
    assert t.max() == pytest.approx(res.summary["pathlines"]["duration"])  # every line's end is kept
    assert "`pathlines.vtp` holds" in (res.out_dir / "summary.md").read_text()


def test_warnings_print_once_as_plain_lines():
    import subprocess
    import sys

    code = """if True:
        import warnings
        from ciliary_carpet.cli import plain_warnings
        with plain_warnings():
            for where in range(3):  # the same message from three places
                warnings.warn_explicit("the closest flow the cilia make", UserWarning, f"f{where}.py", where)
            warnings.warn_explicit("another\\n  message", UserWarning, "g.py", 1)
        warnings.warn_explicit("after", UserWarning, "h.py", 1)  # the usual format again
    """
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    lines = p.stderr.splitlines()
    assert lines[:2] == ["ciliary-carpet: warning: the closest flow the cilia make",
                         "ciliary-carpet: warning: another message"]
    assert lines[2].startswith("h.py:1: UserWarning: after")


def test_a_standing_carpet_is_clamped_where_its_summary_says():
    from ciliary_carpet.output.report import _clamped

    assert _clamped(0.0, "L") == "clamped on the substrate z = 0 (a no-slip wall)"
    raised = _clamped(0.5, "L")  # on posts: the clamps are not on the substrate
    assert "0.5 L above the substrate" in raised and "z = -0.5 L" in raised and "on the substrate" not in raised
    assert "no wall" in _clamped(None, "m")


def test_a_table_built_for_a_render_is_announced_shown_and_recorded(tmp_path):
    from ciliary_carpet.render import render
    from ciliary_carpet.scenes.scene import load_scene
    from cilia_runtime.progress import Progress

    class Notes(Progress):
        def __init__(self):
            self.notes, self.bars, self.stages = [], [], []

        def note(self, message):
            self.notes.append(message)

        def start(self, total, desc="", uniform=True):
            self.bars.append((desc, uniform))

        def stage(self, name):
            self.stages.append(name)

    scene = tmp_path / "s.toml"
    scene.write_text('[table]\nfile = "t.nc"\n[table.build]\nn = 4\ndegree = 6\n[carpet]\nshape = [2, 2]\n'
                     'coupling = "none"\nchi_N = 40.0\n[output]\nn_seeds = 3\nperiods = 1.0\nfield_shape = [6, 6]\nsnapshots = 1\n'
                     'frames = 4\npreview = false\nftle = false\n')
    seen = Notes()
    res = render(load_scene(scene), tmp_path / "a", progress=seen)
    build = [n for n in seen.notes if n.startswith("building the thrust table")]
    assert len(build) == 1 and "4 rows over chi_N" in build[0] and " min on " in build[0], seen.notes
    assert ("thrust table", True) in seen.bars  # the build's own bar, over its rows: a time remaining
    # the render's bar names each stage and extrapolates no time from stages of unequal cost
    assert [u for d, u in seen.bars if d.startswith("render ")] == [False]
    assert "pathlines" in seen.stages and "summary" in seen.stages
    t = res.summary["table"]
    assert t["built"] and t["build_seconds"] > 0 and t["size_bytes"] == (tmp_path / "t.nc").stat().st_size
    assert "was computed for this render" in (res.out_dir / "summary.md").read_text()
    again = render(load_scene(scene), tmp_path / "b")  # the table is there now: read, not built
    assert again.summary["table"] == {"file": str(tmp_path / "t.nc"), "built": False}
