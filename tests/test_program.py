"""Programs: one curvature layout for several field strengths (design.program, scenes.program,
render_program, the command line). Small uncoupled carpets keep these fast; the renders of a
program and the bundled coupled programs (tests/test_render.py) are in the slow set."""
import json
import math
import warnings

import numpy as np
import pytest
import xarray as xr

from ciliary_carpet.cli import main
from ciliary_carpet.design.program import (Program, StateProblem, design_program, mixture_layout, program_bound,
                                           program_dataset, state_problem)
from ciliary_carpet.design.result import DesignError
from ciliary_carpet.render import render
from ciliary_carpet.scenes.assembly import assemble
from ciliary_carpet.scenes.program import design_program_scene
from ciliary_carpet.scenes.scene import load_scene
from ciliary_carpet.scenes.states import state_scenes

STEER = """
name = "steer"
[field]
eta = 1.0
[carpet]
shape = [6, 6]
spacing = 2.0
coupling = "none"
[[state]]
name = "low"
chi_E = 150
[state.target]
kind = "uniform"
angle = {low}
residual = 0.1
speed_floor = 0.1
[[state]]
name = "high"
chi_E = 200
[state.target]
kind = "uniform"
angle = {high}
residual = 0.1
speed_floor = 0.1
{extra}
[output]
pathlines = false
ftle = false
field_shape = [16, 16]
snapshots = 1
frames = 4
preview = false
"""


def scene(tmp_path, low=0.0, high=20.0, extra="", name="steer.toml"):
    p = tmp_path / name
    p.write_text(STEER.format(low=low, high=high, extra=extra))
    return load_scene(p)


def problems(sc):
    out = []
    for spec, s in state_scenes(sc):
        a = assemble(s)
        out.append(state_problem(spec.name, a.target, a.carpet(), a.bases, a.frame, spacing=s.carpet.spacing,
                                 weight=spec.weight))
    return out


@pytest.fixture(scope="module")
def steered(tmp_path_factory):
    sc = scene(tmp_path_factory.mktemp("steer"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # met: no warning
        prog, states = design_program_scene(sc)
    return sc, prog, states


def test_a_program_meets_both_states_with_one_layout(steered):
    sc, prog, states = steered
    assert isinstance(prog, Program) and prog.states == ("low", "high")
    assert all(prog.met) and prog.limiting[1] <= 1.0
    for st, d in zip(states, prog.designs):
        # one layout: every state's design holds the program's curvatures
        assert np.array_equal(d.chi_N, prog.chi_N) and np.array_equal(st.carpet.chi_N, prog.chi_N)
        # its residual measured in its own field, with an error bar at most half its threshold
        assert d.residual_rms <= d.threshold and d.residual_error <= 0.5 * d.threshold
        assert st.carpet.table.chi_E == {"low": 150.0, "high": 200.0}[st.name]
    # never worse than the joint local layout
    assert prog.objective <= prog.local_objective * (1 + 1e-12)
    assert np.all(np.abs(prog.chi_N) <= prog.bound + 1e-9)
    s = prog.summary()
    json.dumps(s, allow_nan=False)
    assert [q["name"] for q in s["states"]] == ["low", "high"] and s["limiting"]["state"] in ("low", "high")


def test_the_program_uses_cilia_that_rest_in_the_weaker_field(steered):
    """Straight at 150, turned 20 degrees at 200: no single curvature does both (at 150 every
    beating cilium turns its thrust more than at 200), so some cilia lie beyond the 150 cutoff
    (94.6) and rest there, and they are reported as resting in that state only."""
    sc, prog, states = steered
    low, high = prog.resting
    cut150 = states[0].carpet.table.in_still_fluid().flutter_range[1]
    assert math.isclose(cut150, 94.59, abs_tol=0.01)
    assert len(low) > 0 and len(high) == 0
    assert np.all(np.abs(prog.chi_N[list(low)]) > cut150)


def test_mixture_layout_is_one_curvature_where_one_serves_every_state(tmp_path):
    """Ask each state for exactly the angle one curvature (chi_N = 40) makes in that field: the
    linear program's mixture is that curvature, give or take the neighbouring curvature of the
    grid (the program trades 1/M rad of direction for a unit of speed)."""
    sc = scene(tmp_path)
    probs = problems(sc)
    B = program_bound([p.carpet for p in probs])
    grid = np.linspace(-B, B, 129)
    g40 = grid[np.argmin(np.abs(grid - 40.0))]
    parts = []
    from ciliary_carpet.design.moments import cycle_moments

    for p in probs:
        m = cycle_moments(p.carpet.table)
        F, F0 = m(np.array([g40]))["F"][0], m(np.zeros(1))["F"][0]
        a = math.atan2(F0[0] * F[1] - F0[1] * F[0], F0[0] * F[0] + F0[1] * F[1])

        class _Ob:
            mom = m
        parts.append((p, _Ob(), np.full(p.carpet.n, a)))
    chi = mixture_layout(parts, grid, probs[0].carpet.bases, 2.0)
    step = grid[1] - grid[0]
    assert np.all(np.abs(chi - g40) <= step * (1 + 1e-9)) and np.mean(chi == g40) > 0.9


def test_program_bound_is_the_largest_cutoff_within_every_table(tmp_path):
    probs = problems(scene(tmp_path))
    B = program_bound([p.carpet for p in probs])
    # 200's cutoff 162.77, capped by the 150 table's rows (they reach 132.46)
    assert math.isclose(B, 132.46, abs_tol=0.01)


def test_bad_programs_are_refused_with_the_problem_named(tmp_path):
    probs = problems(scene(tmp_path))
    with pytest.raises(ValueError, match="at least two states"):
        design_program(probs[:1])
    with pytest.raises(ValueError, match="unique"):
        design_program([probs[0], StateProblem(**{**probs[1].__dict__, "name": "low"})])
    with pytest.raises(ValueError, match="duplicate states"):
        design_program([probs[0], StateProblem(**{**probs[0].__dict__, "name": "other"})])
    moved = probs[1].carpet
    from dataclasses import replace

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        other = replace(moved, bases=moved.bases + 0.5)
    with pytest.raises(ValueError, match="same carpet"):
        design_program([probs[0], StateProblem(**{**probs[1].__dict__, "carpet": other})])
    for w in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="weight"):
            StateProblem(**{**probs[0].__dict__, "weight": w})


def test_a_program_the_cilia_cannot_make_warns_or_is_a_design_error(tmp_path):
    """Opposite turns of 35 degrees in the two fields: beyond what the mixture reaches; a
    warning naming the limiting state, and with strict = true a DesignError."""
    sc = scene(tmp_path, low=-35.0, high=35.0)
    with pytest.warns(UserWarning, match="limiting: state"):
        prog, _ = design_program_scene(sc)
    assert not all(prog.met)
    text = (tmp_path / "steer.toml").read_text().replace("residual = 0.1\n", "residual = 0.1\nstrict = true\n", 1)
    (tmp_path / "strict.toml").write_text(text.replace('name = "steer"', 'name = "strict"'))
    with pytest.raises(DesignError, match="cannot make every state"):
        design_program_scene(load_scene(tmp_path / "strict.toml"))


def test_program_dataset_holds_the_layout_and_every_state(steered):
    sc, prog, states = steered
    ds = program_dataset(prog)
    assert ds.sizes["cilium"] == 36 and list(ds.attrs["states"]) == ["low", "high"]
    for n, d in zip(prog.states, prog.designs):
        assert ds[f"{n}_residual"].sizes[f"{n}_control"] == d.control.shape[0]
        assert math.isclose(ds.attrs[f"{n}_residual_rms"], d.residual_rms)
        assert int(ds[f"{n}_resting"].sum()) == len(prog.resting[prog.states.index(n)])
    np.testing.assert_array_equal(ds.chi_N.values, prog.chi_N)


@pytest.mark.slow  # renders (or designs twice): the slow set keeps the default run short
def test_render_of_a_program_writes_a_folder_per_state(tmp_path):
    sc = scene(tmp_path)
    res = render(sc, tmp_path / "out")
    out = tmp_path / "out"
    p = json.loads((out / "program.json").read_text())
    assert [q["name"] for q in p["states"]] == ["low", "high"] and all(q["met"] for q in p["states"])
    assert [q["to"] for q in p["switch"]] == ["low", "high"] and all(q["statement"] for q in p["switch"])
    for name, E in (("low", 150.0), ("high", 200.0)):
        s = json.loads((out / name / "summary.json").read_text())
        assert s["program"]["state"] == name and s["design"]["met"] is True
        assert s["scene_resolved"]["field"]["chi_E"] == E
        assert (out / name / "open_in_paraview.py").is_file()
        assert "State **%s** of a program" % name in (out / name / "summary.md").read_text()
    md = (out / "program.md").read_text()
    assert "**Verdict: every state met" in md and "| low | 150 |" in md and "## The switch" in md
    assert xr.open_dataset(out / "program.nc", engine="h5netcdf").sizes["cilium"] == 36
    assert "program.json" in res.files and "low/summary.json" in res.files
    # a second render without overwrite is refused before any work; with it, replaced
    with pytest.raises(Exception, match="already holds a program"):
        render(sc, out)
    render(sc, out, overwrite=True)


def test_the_command_line_reaches_designs_and_renders_a_program(tmp_path, capsys):
    sc = scene(tmp_path)
    path = str(sc.source)
    assert main(["reach", path]) == 0
    text = capsys.readouterr().out
    assert "'low' chi_E = 150" in text and "beats under 'high', rests under 'low'" in text
    assert main(["reach", path, "--json"]) == 0
    json.loads(capsys.readouterr().out)
    assert main(["design", path, "-o", str(tmp_path / "p.nc")]) == 0
    assert "program of 2 states" in capsys.readouterr().out
    assert xr.open_dataset(tmp_path / "p.nc", engine="h5netcdf").attrs["states"] is not None
    assert main(["render", path, "-o", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "every state met" in out and "a folder per state: low, high" in out


def test_reach_of_a_single_field_scene_is_bad_input(tmp_path, capsys):
    p = tmp_path / "one.toml"
    p.write_text("[target]\nkind = \"uniform\"\nangle = 10\n")
    assert main(["reach", str(p)]) == 2
    assert "compares the field states of a program" in capsys.readouterr().err


def test_a_standing_program_is_refused_by_name(tmp_path):
    text = STEER.format(low=0.0, high=20.0, extra="").replace('coupling = "none"', 'geometry = "standing"\ncoupling = "none"')
    text = text.replace('kind = "uniform"', 'kind = "pump"')
    p = tmp_path / "standing.toml"
    p.write_text(text)
    from ciliary_carpet.scenes.schema import SceneError

    with pytest.raises(SceneError, match="a program .* designs planar carpets"):
        design_program_scene(load_scene(p))


def test_a_state_with_sigma_studies_the_programs_fabrication_tolerance(tmp_path):
    """sigma > 0 in a state's target: that state's design carries the tolerance study of the
    program's layout in its field (how its flow degrades under a relative chi_N scatter)."""
    text = STEER.format(low=0.0, high=20.0, extra="").replace(
        'angle = 20.0\nresidual = 0.1\n', 'angle = 20.0\nresidual = 0.1\nsigma = 0.05\nsamples = 4\n')
    p = tmp_path / "tol.toml"
    p.write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        prog, states = design_program_scene(load_scene(p))
    low, high = prog.designs
    assert low.tolerance is None and high.tolerance is not None
    t = high.tolerance
    json.dumps(t, allow_nan=False)
    assert t["sigma"] == 0.05 and t["samples"] == 4
    # the study's nominal layout is the program's, measured in this state's field
    assert math.isclose(t["nominal_rms"], high.residual_rms, rel_tol=0.05)
    assert t["p90_rms"] >= t["p10_rms"] > 0


@pytest.mark.slow  # renders (or designs twice): the slow set keeps the default run short
def test_a_batch_renders_a_program_and_then_skips_it(tmp_path):
    from ciliary_carpet.batch import batch

    sc = scene(tmp_path)
    recs = batch([str(sc.source)], str(tmp_path / "out"), jobs=1)
    assert recs[0]["status"] == "done" and recs[0]["verdict"] == "met", recs
    assert (tmp_path / "out" / "steer" / "program.json").is_file()
    assert (tmp_path / "out" / "steer" / "high" / "summary.json").is_file()
    recs = batch([str(sc.source)], str(tmp_path / "out"), jobs=1)
    assert recs[0]["status"] == "skipped" and recs[0]["verdict"] == "met", recs


@pytest.mark.slow  # renders (or designs twice): the slow set keeps the default run short
def test_a_states_weight_trades_its_residual_against_the_others(tmp_path):
    """Opposite turns that one layout cannot both meet: weighting a state 4x lowers its residual
    and raises the other's (the weight is its share of the joint objective)."""
    def residuals(w_low):
        text = STEER.format(low=-30.0, high=30.0, extra="").replace(
            'name = "low"\nchi_E = 150\n', f'name = "low"\nchi_E = 150\nweight = {w_low}\n')
        p = tmp_path / f"w{w_low}.toml"
        p.write_text(text.replace('name = "steer"', f'name = "w{int(w_low)}"'))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            prog, _ = design_program_scene(load_scene(p))
        return [d.residual_rms for d in prog.designs]

    even, favour_low = residuals(1.0), residuals(4.0)
    assert favour_low[0] < even[0] and favour_low[1] > even[1]


def test_a_states_table_is_built_on_demand_with_an_estimate_first(tmp_path, monkeypatch):
    """A state whose field has no table yet names one with [state.table.build]: the build is
    announced with its time estimate and computed for that state's chi_E (the computation itself
    is replaced here by a copy of the shipped table of that field: minutes saved)."""
    import shutil
    from importlib import resources
    from pathlib import Path

    import single_cilium.table as table_mod
    from cilia_runtime.progress import Progress
    from ciliary_carpet.scenes.assembly import load_table
    from single_cilium.lookup import SHIPPED_TABLES

    calls = []

    def fake_build(chi_E, eta, chi_N, *, path, **kw):
        calls.append((float(chi_E), float(eta), "U_par" in kw and kw["U_par"] is not None))
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(resources.files("single_cilium") / "data" / SHIPPED_TABLES[150.0][1], path)

    monkeypatch.setattr(table_mod, "build_table", fake_build)
    text = STEER.format(low=0.0, high=20.0, extra="").replace('coupling = "none"\n', "").replace(
        'name = "low"\nchi_E = 150\n',
        'name = "low"\nchi_E = 150\n[state.table]\nfile = "tables/low.nc"\n[state.table.build]\n')
    p = tmp_path / "built.toml"
    p.write_text(text.replace('name = "steer"', 'name = "built"'))
    notes = []

    class Notes(Progress):
        def note(self, msg):
            notes.append(msg)

    (spec, low), _ = state_scenes(load_scene(p))
    t = load_table(low, progress=Notes())
    assert calls == [(150.0, 1.0, True)]  # the coupled default: over the background flow
    assert t.chi_E == 150.0 and (tmp_path / "tables" / "low.nc").is_file()
    assert any("building the thrust table" in n and "chi_E = 150" in n and "min on" in n for n in notes)


@pytest.mark.slow  # renders (or designs twice): the slow set keeps the default run short
def test_a_program_render_never_replaces_files_it_did_not_write_and_resumes_an_interrupted_one(tmp_path):
    sc = scene(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "program.json").write_text("my notes\n")
    with pytest.raises(Exception, match="did not write"):
        render(sc, out, overwrite=True)
    assert (out / "program.json").read_text() == "my notes\n"
    # an interrupted render: a state's folder written, the program files not yet
    out2 = tmp_path / "out2"
    render(sc, out2)
    for f in ("program.json", "program.md", "program.nc"):
        (out2 / f).unlink()
    render(sc, out2)  # no overwrite needed: the state folders hold only the toolkit's files
    assert (out2 / "program.json").is_file()
