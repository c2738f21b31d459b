"""Scene files: parsing, defaults, validation messages, the table spec, reduced scenes."""
import dataclasses
import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from ciliary_carpet.scenes import scene as scene_mod
from ciliary_carpet.scenes.assembly import assemble, load_table, target_of
from ciliary_carpet.scenes.scene import (
    CarpetSpec,
    OutputSpec,
    Scene,
    SceneError,
    TableBuild,
    TargetSpec,
    load_scene,
    scene_from_dict,
)

DESIGNS = Path(__file__).resolve().parents[1] / "designs"
DESIGN_FILES = sorted(DESIGNS.glob("*.toml"))


def write(tmp_path, text, name="x.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_designs_folder_has_the_five_scenes():
    names = {p.stem for p in DESIGN_FILES}
    assert {"uniform_deflection", "focusing", "spreading", "shear_layer", "vortex_turn"} <= names


@pytest.mark.parametrize("path", DESIGN_FILES, ids=lambda p: p.stem)
def test_every_design_loads(path):
    s = load_scene(path)
    assert s.name == path.stem
    assert s.source == path
    assert path.read_text().lstrip().startswith("#"), "a design starts with a comment block"
    assert "ParaView" in path.read_text()
    assert s.table.file == "default" and s.tolerance == 1e-3
    assert s.carpet.n_cilia == s.carpet.bases().shape[0] <= 200
    # every planar design has a target; a standing one a surface flow, or its layout given (the pump)
    assert s.target.kind != "none" or s.carpet.geometry == "standing" or len(s.states) >= 2
    # the round trip through to_dict
    assert scene_from_dict(s.to_dict(), source=path) == s
    r = s.reduced()
    assert r.carpet.n_cilia <= 16 and r.carpet.lattice == s.carpet.lattice


def test_defaults_filled(tmp_path):
    s = load_scene(write(tmp_path, "", "empty_scene.toml"))
    assert s.name == "empty_scene" and s.description == ""
    assert (s.field.chi_E, s.field.eta, s.field.direction) == (200.0, 1.0, 0.0)
    assert s.table.file == "default" and s.table.build is None
    assert s.carpet == CarpetSpec()
    assert (s.carpet.lattice, s.carpet.shape, s.carpet.spacing, s.carpet.origin) == ("square", (10, 10), 2.0, (0, 0))
    assert (s.carpet.chi_N, s.carpet.phases, s.carpet.seed, s.carpet.wall) == (0.0, "random", 0, None)
    assert s.target == TargetSpec() and s.target.kind == "none" and s.target.angle is None
    assert s.target.control == "cells" and s.target.strict is False and s.target.residual == 0.05
    assert (s.target.speed_floor, s.target.smoothness) == (0.3, 0.0)
    assert s.output == OutputSpec(seeds="line")  # the seeds' default depends on the geometry: the scene resolves it
    assert (s.output.seeds, s.output.n_seeds, s.output.periods, s.output.field_shape) == ("line", 100, None, (80, 80))
    assert (s.output.field_margin, s.output.snapshots, s.output.frames) == (5.0, 4, 40)
    assert s.tolerance == 1e-3 and s.units is None
    d = s.to_dict()
    assert d["carpet"]["shape"] == [10, 10] and d["target"] == {"kind": "none"} and "units" not in d
    assert s.carpet.bases().shape == (100, 2)
    ph = s.carpet.initial_phases()
    assert ph.shape == (100,) and np.all((ph >= 0) & (ph < 1))


def test_full_scene_values(tmp_path):
    s = load_scene(write(tmp_path, """
name = "mine"
tolerance = 1e-4
[field]
chi_E = 150
direction = 90
[carpet]
lattice = "row"
shape = 7
spacing = 3
origin = [1, 2]
phases = "wave"
wave_vector = [0.5, 0]
wall = 1.5
[target]
kind = "uniform"
angle = -20
control = [[1, 2], [3, 4]]
strict = true
speed_floor = 0.2
smoothness = 0.01
[output]
seeds = [[0, 0], [1, 1], [2, 2]]
field_shape = [10, 12]
[units]
length_m = 1e-4
time_s = 2
viscosity_Pa_s = 1e-3
"""))
    assert s.name == "mine" and s.tolerance == 1e-4
    assert s.field.chi_E == 150.0 and isinstance(s.field.chi_E, float)
    assert np.allclose(s.field.flow_direction, [1, 0])  # field along -x (90 deg from +y), flow along +x
    assert math.isclose(s.field.direction_rad, math.pi / 2)
    assert s.carpet.shape == (7,) and s.carpet.wall == 1.5 and s.carpet.wave_vector == (0.5, 0.0)
    assert np.allclose(s.carpet.bases()[:, 1], 2) and np.allclose(s.carpet.bases()[-1], [19, 2])
    assert s.target.angle == -20 and s.target.control == ((1.0, 2.0), (3.0, 4.0)) and s.target.strict
    assert (s.target.speed_floor, s.target.smoothness) == (0.2, 0.01)
    assert s.output.seeds == ((0.0, 0.0), (1.0, 1.0), (2.0, 2.0)) and s.output.field_shape == (10, 12)
    assert s.units.length_m == 1e-4
    assert scene_from_dict(s.to_dict(), s.source) == s


def test_unknown_key_top_level_and_in_section(tmp_path):
    p = write(tmp_path, 'nmae = "a"\n')
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert str(p) in str(e.value) and "'nmae'" in str(e.value) and "did you mean 'name'" in str(e.value)
    p = write(tmp_path, "[carpet]\nspacng = 2\n")
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: [carpet] unknown key 'spacng' (known: ") and "spacing" in msg
    p = write(tmp_path, '[table]\nfile = "t.nc"\n[table.build]\nm = 3\n')
    with pytest.raises(SceneError, match=r"\[table.build\] unknown key 'm'"):
        load_scene(p)
    p = write(tmp_path, "[colour]\nx = 1\n")
    with pytest.raises(SceneError, match="unknown top-level key 'colour'"):
        load_scene(p)


@pytest.mark.parametrize("text, key", [
    ('[carpet]\nspacing = "a"\n', "carpet.spacing must be a number in [1, 1e+06] (L; at least the filament length: closer cilia can touch), got 'a'"),
    ("[carpet]\nspacing = -1\n", "carpet.spacing must be a number in [1, 1e+06]"),
    ("[carpet]\nshape = [10, 2.5]\n", "carpet.shape"),
    ('[carpet]\nlattice = "triangle"\n', "carpet.lattice must be one of"),
    ("[carpet]\nseed = true\n", "carpet.seed must be an integer"),
    ("[field]\neta = 0\n", "field.eta"),
    ("[field]\nchi_E = true\n", "field.chi_E"),
    ("tolerance = 1.0\n", "tolerance must be a number in (0, 1)"),
    ("name = 3\n", "name must be a string"),
    ("[output]\npreview = 1\n", "output.preview must be true or false"),
    ("[output]\nfield_shape = [80]\n", "output.field_shape"),
    ("[output]\nsnapshots = -1\n", "output.snapshots must be an integer in [0, 1000]"),
    ('[output]\nseeds = "circle"\n', "output.seeds"),
    ('[target]\nkind = "focus"\nwidth = 0\n', "target.width must be a positive number"),
    ('[target]\nkind = "focus"\ncentre = [1, 2]\n', 'target.centre does not apply to kind = "focus"'),
    ('[target]\nkind = "turn"\nangle = -10\n', "target.angle must be an amplitude"),
    ('[target]\nkind = "uniform"\ncontrol = [[1, 2, 3]]\n', "target.control[0] must be two numbers"),
    ('[target]\nkind = "points"\n', "target.file is required"),
    ('[target]\nkind = "focus"\nspeed_floor = 1.0\n', "target.speed_floor must be a number in [0, 1)"),
    ('[target]\nkind = "focus"\nsmoothness = -1\n', "target.smoothness"),
    ('[target]\nkind = "points"\nfile = "a.csv"\nspeed_floor = 0.2\n', "target.speed_floor does not apply"),
    ("[carpet]\nwall = 0\n", "carpet.wall must be at least a filament diameter, 2 blob = 0.04 L"),
    ('[target]\nkind = "focus"\nsigma = -0.1\n', "target.sigma must be a number >= 0"),
    ('[target]\nkind = "focus"\nsamples = 0\n', "target.samples must be an integer >= 1"),
    ('[target]\nkind = "points"\nfile = "nope.csv"\n', "target.file 'nope.csv' not found"),
    ('[carpet]\nlattice = "points"\n', "carpet.points is required"),
    ('[carpet]\nlattice = "points"\npoints = [[0, 0]]\nshape = [2, 2]\n', "carpet.shape does not apply"),
    ("[carpet]\npoints = [[0, 0]]\n", "carpet.points applies only to lattice"),
    ("[carpet]\nwave_vector = [1, 0]\n", "carpet.wave_vector applies only to phases"),
    ("[units]\nlength_m = 1e-4\n", "[units] needs all of"),
    ("carpet = 3\n", "carpet must be a table"),
])
def test_wrong_types_and_values_name_the_key(tmp_path, text, key):
    p = write(tmp_path, text)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert str(e.value).startswith(f"{p}: ")
    assert key in str(e.value)


@pytest.mark.parametrize("text, key", [
    ("[carpet]\nspacing = nan\n", "carpet.spacing"),
    ("[field]\nchi_E = inf\n", "field.chi_E"),
    ("[carpet]\norigin = [0, nan]\n", "carpet.origin"),
    ('[target]\nkind = "uniform"\nangle = -inf\n', "target.angle"),
    ('[target]\nkind = "uniform"\nsigma = nan\n', "target.sigma"),
])
def test_nan_and_inf_rejected(tmp_path, text, key):
    with pytest.raises(SceneError, match=key):
        load_scene(write(tmp_path, text))


def test_malformed_toml_names_file_and_position(tmp_path):
    p = write(tmp_path, '[carpet]\nspacing = 2\nlattice = "square\n')
    with pytest.raises(SceneError) as e:
        load_scene(p)
    assert str(p) in str(e.value) and "malformed TOML" in str(e.value) and "line 3" in str(e.value)
    with pytest.raises(SceneError, match="cannot read"):
        load_scene(tmp_path / "missing.toml")


def test_table_default_is_the_shipped_table(tmp_path):
    """file = "default": the shipped table over the background flow for the default coupled
    carpet, the still-fluid one (finer in chi_N) for coupling = "none"."""
    s = load_scene(write(tmp_path, '[table]\nfile = "default"\n'))
    assert s.carpet.coupling == "mean"
    t = load_table(s)
    assert (t.chi_E, t.eta) == (200.0, 1.0)
    assert t.U_range == ((-1.5, 1.5), (-1.5, 1.5))
    assert load_table(s) is t  # cached
    s = load_scene(write(tmp_path, '[table]\nfile = "default"\n[carpet]\ncoupling = "none"\n', "none.toml"))
    t = load_table(s)
    assert t.U_range == ((0.0, 0.0), (0.0, 0.0))
    lo, hi = t.thrust_angle_range()
    assert abs(lo) < 1e-9 and 0.9 < hi < 0.95


def test_table_mismatched_field(tmp_path):
    s = load_scene(write(tmp_path, "[field]\nchi_E = 170\n"))  # no table ships for 170
    with pytest.raises(SceneError) as e:
        load_table(s)
    msg = str(e.value)
    assert str(s.source) in msg and "chi_E = 200" in msg and "chi_E = 170" in msg
    s = load_scene(write(tmp_path, "[field]\neta = 1.000001\n"))
    with pytest.raises(SceneError, match="eta"):
        load_table(s)
    s = load_scene(write(tmp_path, "[field]\neta = 1.0000000000001\n"))  # within 1e-9 relative
    assert load_table(s).eta == 1.0


def test_table_file_relative_to_scene(tmp_path):
    from single_cilium.table import ThrustTable

    sub = tmp_path / "tables"
    sub.mkdir()
    ThrustTable.default().save(sub / "mine.nc")
    s = load_scene(write(tmp_path, '[table]\nfile = "tables/mine.nc"\n'))
    assert s.table.path(s) == sub / "mine.nc"
    assert load_table(s).chi_E == 200.0
    (sub / "bad.nc").write_text("not a table")
    s = load_scene(write(tmp_path, '[table]\nfile = "tables/bad.nc"\n'))
    with pytest.raises(SceneError, match="table.file"):
        load_table(s)


def test_missing_table_without_build_says_add_table_build(tmp_path):
    s = load_scene(write(tmp_path, '[table]\nfile = "nothere.nc"\n'))
    with pytest.raises(SceneError) as e:
        load_table(s)
    assert "[table.build]" in str(e.value) and "nothere.nc" in str(e.value) and str(s.source) in str(e.value)
    with pytest.raises(SceneError, match="needs table.file"):
        load_scene(write(tmp_path, "[table.build]\nn = 5\n"))


def test_missing_table_with_build_builds_it(tmp_path, monkeypatch):
    """The build path (without the minutes of computation): build_table is called with the
    field, a grid over [0, cutoff) plus 1.05 cutoff, the degree and the resolved path."""
    import single_cilium
    import single_cilium.table as table_mod
    from single_cilium.stability import Cutoff

    calls = []
    monkeypatch.setattr(single_cilium, "flutter_cutoff",
                        lambda chi_E, eta, degree: Cutoff(chi_E, eta, 100.0, 1.0, 0.0, "", 0))

    def fake_build(chi_E, eta, grid, degree, path, progress=None):
        calls.append((chi_E, eta, np.asarray(grid), degree, Path(path)))
        table_mod.ThrustTable.default().save(path)

    monkeypatch.setattr(table_mod, "build_table", fake_build)
    s = load_scene(write(tmp_path, '[table]\nfile = "built.nc"\n[table.build]\nn = 5\ndegree = 6\n'
                         '[carpet]\ncoupling = "none"\n'))
    assert s.table.build == TableBuild(n=5, degree=6)
    t = load_table(s)
    assert t.chi_E == 200.0 and (tmp_path / "built.nc").exists()
    (chi_E, eta, grid, degree, path), = calls
    assert (chi_E, eta, degree, path) == (200.0, 1.0, 6, tmp_path / "built.nc")
    assert np.allclose(grid, [0, 25, 50, 75, 105])
    load_table(s)  # exists now: not built again
    assert len(calls) == 1


def test_missing_table_of_a_coupled_scene_is_built_over_the_shipped_flow_grid(tmp_path, monkeypatch):
    """The default coupled carpet and a [table.build] without `flow`: the table is built over the
    shipped flow table's grid (7 x 7 flows in [-1.5, 1.5], 20 chi_N rows up to 1.05 x the largest
    corner cutoff); a still-fluid file with the default coupling is refused, saying what to do."""
    import single_cilium
    import single_cilium.table as table_mod
    from single_cilium.stability import Cutoff

    calls = []
    monkeypatch.setattr(single_cilium, "flutter_cutoff",
                        lambda chi_E, eta, degree, background=(0.0, 0.0): Cutoff(chi_E, eta, 100.0 + background[1],
                                                                                 1.0, 0.0, "", 0))

    def fake_build(chi_E, eta, grid, U_par, U_perp, degree, path, progress=None):
        calls.append((np.asarray(grid), np.asarray(U_par), np.asarray(U_perp)))
        table_mod.ThrustTable.default(flow=True).save(path)

    monkeypatch.setattr(table_mod, "build_table", fake_build)
    s = load_scene(write(tmp_path, '[table]\nfile = "built.nc"\n[table.build]\n'))
    assert s.carpet.coupling == "mean" and s.table.build.flow is None
    t = load_table(s)
    (grid, up, uq), = calls
    assert np.allclose(up, np.linspace(-1.5, 1.5, 7)) and np.allclose(uq, up)
    assert grid.size == 20 and grid[0] == 0.0 and grid[-1] == pytest.approx(1.05 * 101.5)
    assert t.U_range == ((-1.5, 1.5), (-1.5, 1.5))
    still = tmp_path / "still.nc"
    table_mod.ThrustTable.default().save(still)
    s = load_scene(write(tmp_path, '[table]\nfile = "still.nc"\n', "still.toml"))
    with pytest.raises(SceneError, match=r'coupling = "mean" \(the default.*still fluid.*\[table.build\].*coupling = "none"'):
        assemble(s)


def test_reduced_shrinks(tmp_path):
    s = load_scene(DESIGNS / "vortex_turn.toml")
    r = s.reduced()
    assert r.carpet.lattice == "hexagonal" and r.carpet.spacing == s.carpet.spacing
    assert r.carpet.n_cilia <= 16 and r.carpet.shape == (4, 4)
    assert np.allclose(r.carpet.centre, s.carpet.centre)  # same centre: absolute coordinates still fit
    o = r.output
    assert (o.n_seeds, o.field_shape, o.periods, o.snapshots, o.frames) == (10, (16, 16), 2.0, 1, 4)
    assert r.target == s.target and r.field == s.field and r.name == s.name
    # never enlarges; other shapes and lattices
    tiny = s.reduced(max_cilia=1000, n_seeds=1000, field_shape=(500, 500), periods=100, snapshots=9, frames=99)
    assert tiny == dataclasses.replace(s, output=dataclasses.replace(s.output, periods=100.0))  # auto -> bounded
    wide = dataclasses.replace(s, carpet=dataclasses.replace(s.carpet, lattice="square", shape=(20, 5)))
    assert wide.reduced().carpet.shape == (8, 2)
    row = load_scene(write(tmp_path, '[carpet]\nlattice = "row"\nshape = [40]\n')).reduced(max_cilia=5)
    assert row.carpet.shape == (5,) and np.allclose(row.carpet.centre, [39, 0])
    pts = [[float(i), 0.0] for i in range(30)]
    ps = scene_from_dict({"carpet": {"lattice": "points", "points": pts},
                          "output": {"seeds": [[0, float(i)] for i in range(50)]}}).reduced()
    assert ps.carpet.n_cilia == 16 and len(ps.output.seeds) == 10
    assert np.all(np.abs(np.asarray(ps.carpet.points)[:, 0] - 14.5) <= 8)


def test_scene_from_dict_without_file():
    s = scene_from_dict({"carpet": {"shape": [3, 2]}})
    assert s.source is None and s.name == "scene" and s.carpet.n_cilia == 6
    with pytest.raises(SceneError, match="^<scene>: carpet.shape"):
        scene_from_dict({"carpet": {"shape": [0, 2]}})


def test_sections_made_in_code_are_validated():
    c = CarpetSpec(shape=[3, 4], spacing=3, origin=[1, 1])
    assert c.shape == (3, 4) and c.spacing == 3.0 and isinstance(c.spacing, float) and c.origin == (1.0, 1.0)
    with pytest.raises(SceneError, match=r"^<CarpetSpec>: carpet.spacing must be a number in \[1, "):
        dataclasses.replace(c, spacing=-2.0)
    with pytest.raises(SceneError, match="target.angle"):
        TargetSpec(kind="focus", angle=float("nan"))
    with pytest.raises(SceneError, match="output.field_shape"):
        OutputSpec(field_shape=(1, 5))
    with pytest.raises(SceneError, match="tolerance"):
        Scene(name="a", tolerance=2.0)
    with pytest.raises(SceneError, match="carpet must be a CarpetSpec"):
        Scene(name="a", carpet={"shape": [2, 2]})
    s = Scene(name="a", source="designs/x.toml")
    assert s.source == Path("designs/x.toml") and s.carpet == CarpetSpec()


def test_scene_is_frozen():
    s = scene_from_dict({})
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.name = "other"
    assert isinstance(s, Scene) and scene_mod.LATTICES == ("row", "square", "hexagonal", "points")


def test_robust_needs_a_fabrication_tolerance(tmp_path):
    """[target] robust = true without sigma > 0 is a named error; with sigma it reaches the Target."""
    from ciliary_carpet.scenes.scene import SceneError, load_scene
    from ciliary_carpet.design.target import Target

    base = '[carpet]\nshape = [3, 3]\n[target]\nkind = "uniform"\nangle = 10\nrobust = true\n'
    p = tmp_path / "r.toml"
    p.write_text(base)
    with pytest.raises(SceneError, match="robust"):
        load_scene(p)
    p.write_text(base + "sigma = 0.1\n")
    s = load_scene(p)
    assert s.target.robust and target_of(s).robust


# ------------------------------------------------------------------------------ one home per default
RESOLVED = Path(__file__).resolve().parent / "data" / "scene_resolved.json"


def _digest(a) -> list:
    a = np.ascontiguousarray(np.asarray(a, dtype=float))
    return [list(a.shape), hashlib.sha256(a.tobytes()).hexdigest()[:16]]


def resolved_now() -> dict:
    """What the bundled designs resolve to through the one builder (scene keys with defaults
    filled, target, frame, carpet, control points and target deflections), and the defaults of
    an empty scene, of each angle kind and of a Target made in code."""
    from ciliary_carpet.scenes.assembly import assemble
    from ciliary_carpet.design.control import control_points
    from ciliary_carpet.design.patterns import ANGLE_KINDS
    from ciliary_carpet.design.target import Target

    out = {}
    for path in DESIGN_FILES:
        s = load_scene(path)
        if s.states:  # a program: its states' scenes are checked in tests/test_states.py
            continue
        a = assemble(s)
        t, fr, c = a.target, a.frame, a.carpet()
        d = {"scene": s.to_dict(),
             "target": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(t).items()
                        if k not in ("data_points", "data_velocities", "data_uncertainty")},
             "frame": [fr.centre.tolist(), fr.flow_direction.tolist(), fr.spacing],
             "carpet": {"bases": _digest(c.bases), "chi_N": _digest(c.chi_N), "phases": _digest(c.phases),
                        "direction": c.direction, "wall": c.wall, "blob": c.blob, "mu": c.mu,
                        "scales": None if c.scales is None else list(vars(c.scales).values())}}
        if t.is_angle:
            X = control_points(c.bases, fr, t.control)
            d["control"], d["deflection"] = _digest(X), _digest(t.deflection(X, fr))
        out[path.stem] = d
    out["<defaults>"] = {"empty": scene_from_dict({}).to_dict(),
                         "Target": {k: v for k, v in vars(Target("uniform", 0.1)).items() if k != "data_uncertainty"}}
    for k in ANGLE_KINDS:
        out["<defaults>"][k] = scene_from_dict({"target": {"kind": k}}).to_dict()
    return json.loads(json.dumps(out))


def test_designs_and_defaults_resolve_as_recorded():
    """Every default, and every bundled design's carpet, target and frame, is what
    tests/data/scene_resolved.json recorded (made before the defaults got one home each, from
    the separate parsers and scene_carpet): a changed default, range rule or builder step shows
    here. After a deliberate change: ``python tests/test_scene.py`` rewrites the record."""
    want = json.loads(RESOLVED.read_text())
    got = resolved_now()
    assert got.keys() == want.keys()
    for name in want:
        assert got[name] == want[name], name


def test_readme_key_reference_is_the_schema():
    """designs/README.md's key tables and its table of target kinds are what the sections' field
    metadata and target.PATTERNS make (scene.reference()); the section docstrings say the same
    defaults."""
    text = (DESIGNS / "README.md").read_text()
    for heading, table in scene_mod.reference().items():
        assert f"\n### {heading}\n" in text, heading
        section = text.split(f"\n### {heading}\n", 1)[1].split("\n## ", 1)[0].split("\n### ", 1)[0]
        lines = section.split("\n")
        start = next(i for i, ln in enumerate(lines) if ln.startswith("|"))
        end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
        assert "\n".join(lines[start:end]) == table, (
            f"designs/README.md, section {heading}: the table should read\n{table}\n(from scene.reference())")
    assert "spacing : float in [1, 1e+06], default 2.0" in CarpetSpec.__doc__
    assert "speed_floor : float in [0, 1), default 0.3 (kind = uniform, focus" in TargetSpec.__doc__


def test_target_defaults_have_one_home():
    """A Target made in code takes the [target] defaults of TargetSpec; the carpet's blob default
    is the flow model's."""
    from ciliary_carpet.carpet.carpet import BLOB
    from ciliary_carpet.design.target import Target

    t, spec = Target("focus", 0.2), TargetSpec()
    shared = [f.name for f in dataclasses.fields(Target) if f.name in {g.name for g in dataclasses.fields(spec)}]
    assert len(shared) == 17  # kind and the 16 keys a Target takes as they are
    for k in shared[1:]:  # all but kind
        assert getattr(t, k) == getattr(spec, k), k
    assert CarpetSpec().blob == BLOB


def test_one_builder_from_scene_to_table_carpet_and_target(tmp_path):
    """assembly.assemble is the path from a scene to its table, carpet and target: design()
    (and through it render and the command line) builds its carpet there, and a chi_N outside
    the table is refused there, naming the key."""
    from ciliary_carpet.scenes.assembly import assemble, design

    s = scene_from_dict({"carpet": {"shape": [3, 2], "chi_N": 40, "phases": "synchronous"},
                         "field": {"direction": 30}})
    a = assemble(s)
    c = a.carpet()
    assert a.table is load_table(s) and a.target.kind == "none" and c.table is a.table
    assert np.array_equal(c.bases, s.carpet.bases()) and np.all(c.chi_N == 40.0)
    assert c.direction == math.radians(30) and c.blob == s.carpet.blob and c.wall is None
    assert np.allclose(a.carpet([1, 2, 3, 4, 5, 6]).chi_N, [1, 2, 3, 4, 5, 6])
    d, c2 = design(s)
    assert d is None and np.array_equal(c2.bases, c.bases) and np.array_equal(c2.chi_N, c.chi_N)
    assert np.array_equal(c2.phases, c.phases)
    bad = scene_from_dict({"carpet": {"chi_N": 500}}, source=tmp_path / "hot.toml")
    with pytest.raises(SceneError, match=r"hot.toml: carpet.chi_N = 500 is outside the thrust table's range"):
        assemble(bad)
    with pytest.raises(SceneError, match="carpet.chi_N = 500"):
        design(bad)


if __name__ == "__main__":
    RESOLVED.write_text(json.dumps(resolved_now(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {RESOLVED}")


def test_the_package_front_door_exports_what_it_says():
    """``import ciliary_carpet`` is the front door: every exported name is there and its docstring
    names each one (scenes, carpets, flow sums, design, transport, output)."""
    import ciliary_carpet as cc

    assert len(cc.__all__) == len(set(cc.__all__)) >= 25
    for name in cc.__all__:
        assert getattr(cc, name) is not None
        assert name in cc.__doc__, name
    assert cc.load_scene is load_scene and cc.assemble.__module__ == "ciliary_carpet.scenes.assembly"
