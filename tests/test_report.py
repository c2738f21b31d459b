"""The summary's first lines (issue 42, item 2): a verdict names the model it is given in and how
far that model is from the coupled one, and flags results too uncertain to use; every sentence is
true of its scene."""
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
    assert "**The flow shown is the uncoupled model's** (each cilium beats as if in still fluid)" in out
    assert "## " not in out and "the whole summary: " in out  # the sections stay in the file
    assert (tmp_path / "out" / "summary.md").read_text().count("\n## ") >= 3
