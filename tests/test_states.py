"""Programs (``[[state]]``): one layout, several field strengths. The scene format and its rules,
each state's own scene (``state_scenes``), and the thrust table shipped per field."""
import dataclasses
import math
import re
from pathlib import Path

import pytest

from ciliary_carpet.scenes.assembly import load_table
from ciliary_carpet.scenes.scene import (
    MIN_STATES,
    Scene,
    SceneError,
    StateSpec,
    TableSpec,
    TargetSpec,
    load_scene,
    scene_from_dict,
)
from ciliary_carpet.scenes.states import state_scenes
from single_cilium.lookup import SHIPPED_FIELDS, SHIPPED_TABLES
from single_cilium.table import TableError, ThrustTable

README = Path(__file__).resolve().parents[1] / "designs" / "README.md"

PROGRAM = """
name = "prog"
[field]
eta = 1.0
[carpet]
shape = [4, 4]
[[state]]
name = "strong"
chi_E = 200
[state.target]
kind = "uniform"
angle = 30
smoothness = 1.0
[[state]]
name = "weak"
chi_E = 150
weight = 2.5
[state.target]
kind = "focus"
angle = 15
"""

STATE = """
[[state]]
name = "{name}"
chi_E = {chi_E}
[state.target]
kind = "uniform"
angle = 10
"""


def write(tmp_path, text, name="prog.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def program(*states, head='name = "prog"\n[carpet]\nshape = [2, 2]\n'):
    """A program's TOML: ``head`` and one plain state per (name, chi_E) of ``states``."""
    return head + "".join(STATE.format(name=n, chi_E=c) for n, c in states)


def fails(tmp_path, text, *fragments):
    """Loading ``text`` is a SceneError naming the file and each of ``fragments``."""
    p = write(tmp_path, text)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert str(p) in msg, msg
    for f in fragments:
        assert f in msg, f"{f!r} not in {msg!r}"
    return msg


# ------------------------------------------------------------------------------ the format
def test_program_loads(tmp_path):
    s = load_scene(write(tmp_path, PROGRAM))
    assert len(s.states) == 2 and all(isinstance(st, StateSpec) for st in s.states)
    strong, weak = s.states
    assert (strong.name, strong.chi_E, strong.weight) == ("strong", 200.0, 1.0)
    assert (weak.name, weak.chi_E, weak.weight) == ("weak", 150.0, 2.5)
    assert isinstance(weak.chi_E, float)
    assert strong.target == TargetSpec(kind="uniform", angle=30.0, smoothness=1.0)
    assert weak.target.kind == "focus" and weak.target.angle == 15.0
    assert strong.table == weak.table == TableSpec()  # file = "default"
    # the program has no target or table of its own; its field.chi_E is its first state's
    assert s.target.kind == "none" and s.table == TableSpec() and s.field.chi_E == 200.0
    assert MIN_STATES == 2


def test_round_trip(tmp_path):
    s = load_scene(write(tmp_path, PROGRAM + '[state.table]\nfile = "t.nc"\n[state.table.build]\nn = 5\n'))
    assert s.states[1].table.file == "t.nc" and s.states[1].table.build.n == 5
    d = s.to_dict()
    assert "target" not in d and "table" not in d and "chi_E" not in d["field"]
    assert [st["name"] for st in d["state"]] == ["strong", "weak"]
    assert d["state"][1]["table"] == {"file": "t.nc", "build": {"n": 5, "degree": 8, "flow_points": 5}}
    assert scene_from_dict(d, s.source) == s
    # a plain scene's dict has no states
    plain = load_scene(write(tmp_path, "", "plain.toml"))
    assert plain.states == () and "state" not in plain.to_dict()


def test_reduced_keeps_the_states(tmp_path):
    s = load_scene(write(tmp_path, PROGRAM.replace("[4, 4]", "[10, 10]")))
    r = s.reduced()
    assert r.carpet.n_cilia <= 16 and r.states == s.states and r.field == s.field


def test_program_made_in_code():
    t = TargetSpec(kind="uniform", angle=10.0)
    s = Scene(name="p", states=[StateSpec("a", 200.0, target=t), StateSpec("b", 150, target=t)])
    assert isinstance(s.states, tuple) and s.states[1].chi_E == 150.0 and s.field.chi_E == 200.0
    assert scene_from_dict(s.to_dict()) == s
    with pytest.raises(SceneError, match="state.chi_E"):
        StateSpec("a", 0.0, target=t)
    with pytest.raises(SceneError, match="a state without a target"):
        StateSpec("a", 150.0)
    with pytest.raises(SceneError, match="target is ambiguous"):
        dataclasses.replace(s, target=t)
    with pytest.raises(SceneError, match="table is ambiguous"):
        dataclasses.replace(s, table=TableSpec(file="t.nc"))
    with pytest.raises(SceneError, match="at least 2"):
        dataclasses.replace(s, states=s.states[:1])
    with pytest.raises(SceneError, match="states must be a tuple of StateSpec"):
        Scene(name="p", states=({"name": "a"},))


# ------------------------------------------------------------------------------ the rules
def test_fewer_than_two_states(tmp_path):
    fails(tmp_path, program(("a", 200)), "state", "at least 2", "[field]", "[target]")
    fails(tmp_path, "state = []\n" + program(), "at least 2")


def test_state_is_an_array_of_tables(tmp_path):
    fails(tmp_path, 'name = "p"\n[state]\nname = "a"\nchi_E = 200\n', "state must be an array of tables", "[[state]]")


def test_duplicate_name(tmp_path):
    fails(tmp_path, program(("a", 200), ("b", 150), ("a", 100)), "state[2].name", "'a'", "state[0]", "unique")


def test_duplicate_chi_E(tmp_path):
    fails(tmp_path, program(("a", 200), ("b", 200.0000000001)), "state[1].chi_E", "state[0]", "duplicate states")
    load_scene(write(tmp_path, program(("a", 200), ("b", 200.001))))  # farther than 1e-9 relative: two states


def test_chi_E_checked(tmp_path):
    fails(tmp_path, program(("a", 200), ("b", 0)), "state[1].chi_E", "nonzero")
    fails(tmp_path, program(("a", 200), ("b", "nan")), "state[1].chi_E", "finite")
    fails(tmp_path, program(("a", 200), ("b", 2e4)), "state[1].chi_E", "[-10000, 10000]")
    fails(tmp_path, program(("a", 200), ("b", '"x"')), "state[1].chi_E")
    load_scene(write(tmp_path, program(("a", 200), ("b", -150))))  # a reversed field is a field


def test_required_keys(tmp_path):
    fails(tmp_path, program(("a", 200)) + '[[state]]\nname = "b"\n[state.target]\nkind = "uniform"\n',
          "state[1].chi_E is required")
    fails(tmp_path, program(("a", 200)) + '[[state]]\nchi_E = 150\n[state.target]\nkind = "uniform"\n',
          "state[1].name is required")


def test_name_checked(tmp_path):
    fails(tmp_path, program(("a", 200), ("x/y", 150)), "state[1].name", "path separator")
    fails(tmp_path, program(("a", 200), ("", 150)), "state[1].name", "non-empty")
    # the state's scene is named <name>_<state name>: that must be a file name too
    fails(tmp_path, program(("a" * 100, 200), ("b", 150), head=f'name = "{"p" * 200}"\n'), "state[0].name",
          "255 bytes")


def test_weight_checked(tmp_path):
    for w in ("0", "-1", "inf", '"1"'):
        fails(tmp_path, program(("a", 200), ("b", 150)).replace("chi_E = 150\n", f"chi_E = 150\nweight = {w}\n"),
              "state[1].weight")


def test_state_without_a_target(tmp_path):
    fails(tmp_path, program(("a", 200)) + '[[state]]\nname = "b"\nchi_E = 150\n', "state[1].target",
          "a state without a target")
    fails(tmp_path, program(("a", 200)) + '[[state]]\nname = "b"\nchi_E = 150\n[state.target]\nkind = "none"\n',
          "state[1].target.kind", "a state without a target")


def test_unknown_keys_with_close_matches(tmp_path):
    msg = fails(tmp_path, program(("a", 200), ("b", 150)).replace("chi_E = 150\n", "chi_E = 150\nwieght = 2\n"),
                "[state[1]] unknown key 'wieght'")
    assert "did you mean 'weight'" in msg
    msg = fails(tmp_path, program(("a", 200), ("b", 150)).replace("angle = 10", "angel = 10"),
                "[state[0].target] unknown key 'angel'")
    assert "did you mean 'angle'" in msg
    fails(tmp_path, program(("a", 200), ("b", 150)) + "[state.table]\nfiel = \"t.nc\"\n",
          "[state[1].table] unknown key 'fiel'", "did you mean 'file'")
    fails(tmp_path, program(("a", 200), ("b", 150)) + '[state.table]\nfile = "t.nc"\n[state.table.build]\nm = 3\n',
          "[state[1].table.build] unknown key 'm'")


def test_state_target_and_table_checked_as_their_sections(tmp_path):
    base = program(("a", 200), ("b", 150))
    fails(tmp_path, base.replace("angle = 10", "angle = 500"), "state[0].target.angle")
    fails(tmp_path, base + "centre = [0, 0]\n", "state[1].target.centre does not apply", 'kind = "uniform"')
    fails(tmp_path, base + "robust = true\n", "state[1].target.robust", "state[1].target.sigma")
    fails(tmp_path, base + '[state.table]\nfile = "default"\n[state.table.build]\nn = 5\n',
          "[state[1].table.build] needs state[1].table.file")
    fails(tmp_path, base + '[state.table]\nfile = "t.nc"\n[state.table.build]\nflow = 1.0\nflow_points = 4\n',
          "state[1].table.build.flow_points must be odd")
    fails(tmp_path, base.replace('kind = "uniform"\nangle = 10', 'kind = "points"', 1), "state[0].target.file",
          "required")


def test_state_paths_stay_in_the_scene_folder(tmp_path):
    sub = tmp_path / "in"
    sub.mkdir()
    base = program(("a", 200), ("b", 150))
    p = write(sub, base + '[state.table]\nfile = "../t.nc"\n[state.table.build]\nn = 5\n')
    with pytest.raises(SceneError, match=re.escape("state[1].table.file = '../t.nc' is outside")):
        load_scene(p)
    assert load_scene(p, allow_outside=True).states[1].table.file == "../t.nc"
    (tmp_path / "pts.csv").write_text("x,y,u,v\n0,0,0,-1\n")
    p = write(sub, base.replace('kind = "uniform"\nangle = 10', 'kind = "points"\nfile = "../pts.csv"', 1))
    with pytest.raises(SceneError, match=re.escape("state[0].target.file = '../pts.csv' is outside")):
        load_scene(p)
    fails(tmp_path, base.replace('kind = "uniform"\nangle = 10', 'kind = "points"\nfile = "none.csv"', 1),
          "state[0].target.file 'none.csv' not found")


@pytest.mark.parametrize("extra, key", [("[target]\nkind = \"uniform\"\n", "[target] is ambiguous"),
                                        ("[target]\n", "[target] is ambiguous"),
                                        ("[table]\nfile = \"default\"\n", "[table] is ambiguous"),
                                        ("[field]\nchi_E = 200\n", "field.chi_E is ambiguous")])
def test_ambiguous_sections(tmp_path, extra, key):
    fails(tmp_path, extra + program(("a", 200), ("b", 150), head='name = "p"\n'), key, "move")


def test_geometry_rules_for_each_state(tmp_path):
    planar = program(("a", 200), ("b", 150))
    fails(tmp_path, planar.replace('kind = "uniform"\nangle = 10', 'kind = "vortex"', 1), "state[0].target.kind",
          "surface flow of a standing carpet")
    head = 'name = "p"\n[carpet]\nshape = [2, 2]\ngeometry = "standing"\n'
    fails(tmp_path, program(("a", 200), ("b", 150), head=head), "state[0].target.kind",
          "planar carpet's deflection pattern")


def test_standing_program(tmp_path):
    text = ('name = "p"\n[carpet]\nshape = [2, 2]\ngeometry = "standing"\n'
            '[[state]]\nname = "a"\nchi_E = 200\n[state.target]\nkind = "pump"\nangle = 30\nheight = 2.0\n'
            '[[state]]\nname = "b"\nchi_E = 150\n[state.target]\nkind = "vortex"\n')
    s = load_scene(write(tmp_path, text))
    assert s.output.height is None and s.output.seeds == "grid"  # each state's scene resolves its height
    assert scene_from_dict(s.to_dict(), s.source) == s
    (_, a), (_, b) = state_scenes(s)
    assert (a.output.height, b.output.height) == (2.0, 1.5)  # the state's target height
    s = load_scene(write(tmp_path, text.replace('geometry = "standing"\n', 'geometry = "standing"\n[output]\nheight = 3.0\n')))
    assert s.output.height == 3.0 and all(one.output.height == 3.0 for _, one in state_scenes(s))


# ------------------------------------------------------------------------------ each state's scene
def test_state_scenes(tmp_path):
    s = load_scene(write(tmp_path, PROGRAM + '[state.table]\nfile = "tables/t150.nc"\n[state.table.build]\nn = 5\n'))
    pairs = state_scenes(s)
    assert [st for st, _ in pairs] == list(s.states)
    for st, one in pairs:
        assert isinstance(one, Scene) and one.states == ()
        assert one.name == f"prog_{st.name}" and one.field.chi_E == st.chi_E
        assert one.target == st.target and one.table == st.table
        assert one.source == s.source and one.carpet == s.carpet and one.output == s.output
        assert one.field.eta == s.field.eta and one.field.direction == s.field.direction
        assert scene_from_dict(one.to_dict(), one.source) == one  # a valid scene of one field
    weak = pairs[1][1]
    assert weak.table.path(weak) == tmp_path / "tables" / "t150.nc"  # relative to the program's folder
    with pytest.raises(SceneError, match="takes a program"):
        state_scenes(load_scene(write(tmp_path, "", "plain.toml")))


def test_readme_example_program_loads(tmp_path):
    text = README.read_text().split("## Programs", 1)[1]
    example = text.split("```toml\n", 1)[1].split("```", 1)[0]
    s = load_scene(write(tmp_path, example, "two_turns.toml"))
    assert [st.chi_E for st in s.states] == [200.0, 150.0]
    assert s.states[0].target.kind == "uniform" and s.states[0].target.angle == 30.0


# ------------------------------------------------------------------------------ tables per field
@pytest.fixture(scope="module")
def t150():
    return ThrustTable.default(chi_E=150)


def test_shipped_fields():
    assert SHIPPED_FIELDS == (150.0, 200.0) and set(SHIPPED_TABLES) == set(SHIPPED_FIELDS)
    data = Path(__file__).resolve().parents[1] / "single_cilium" / "data"
    for still, flow in SHIPPED_TABLES.values():
        assert (data / still).is_file() and (data / flow).is_file()


def test_default_table_at_150(t150):
    assert (t150.chi_E, t150.eta) == (150.0, 1.0)
    assert t150.U_range == ((0.0, 0.0), (0.0, 0.0))  # still fluid: the flow table's U = 0
    assert t150.cutoff() == pytest.approx(94.5938, abs=1e-3)  # flutter_cutoff(150, 1)
    lo, hi = t150.thrust_angle_range()
    assert abs(lo) < 1e-6 and 0.6 < hi < 0.7


def test_unshipped_field_is_an_error():
    with pytest.raises(TableError) as e:
        ThrustTable.default(chi_E=170.0)
    msg = str(e.value)
    assert "chi_E = 170" in msg and "150 or 200" in msg and "[table.build]" in msg


def test_load_table_default_per_field(tmp_path, t150, monkeypatch):
    s = load_scene(write(tmp_path, PROGRAM.replace("[carpet]", '[carpet]\ncoupling = "none"')))
    strong, weak = (one for _, one in state_scenes(s))
    t = load_table(weak)
    assert (t.chi_E, t.eta) == (150.0, 1.0) and t.cutoff() == pytest.approx(t150.cutoff(), rel=1e-12)
    assert load_table(weak) is t  # cached per field
    assert load_table(strong).chi_E == 200.0
    # an unshipped field: the error names the shipped ones and says what to do
    s = load_scene(write(tmp_path, "[field]\nchi_E = 170\n", "f170.toml"))
    with pytest.raises(SceneError) as e:
        load_table(s)
    msg = str(e.value)
    assert str(s.source) in msg and "chi_E = 170" in msg
    assert "chi_E = 150 or chi_E = 200" in msg and "[table.build]" in msg


def test_load_table_default_over_the_flow_at_150(tmp_path):
    """A coupled carpet (the default) at chi_E = 150 reads the shipped table over the flow."""
    s = load_scene(write(tmp_path, "[field]\nchi_E = 150\n", "f150.toml"))
    t = load_table(s)
    assert t.chi_E == 150.0 and t.U_range == ((-1.5, 1.5), (-1.5, 1.5))
    assert math.isclose(t.cutoff(), 94.5938, abs_tol=1e-3)
