"""Target flows: pattern signs, control points, control files, reachability."""
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from ciliary_carpet.scenes.scene import load_scene, scene_from_dict
from ciliary_carpet.scenes.assembly import frame_of, load_table, target_of
from ciliary_carpet.scenes.target_spec import resolve_target
from ciliary_carpet.design.control import control_points, reachable_check
from ciliary_carpet.design.frame import Frame
from ciliary_carpet.design.target import DEFAULT_ANGLE_FRACTION, Target, TargetError
from ciliary_carpet.design.target_files import read_target_points

DESIGNS = Path(__file__).resolve().parents[1] / "designs"
A = math.radians(40)


def frame(direction_deg=0.0, centre=(0.0, 0.0), spacing=2.0):
    a = math.radians(direction_deg)
    return Frame(np.array(centre), np.array([math.sin(a), -math.cos(a)]), spacing)


def line_points(fr, xis, along=0.0):
    """Points at cross-stream coordinates ``xis`` from the frame's centre."""
    return fr.centre + np.outer(xis, fr.cross) + along * fr.flow_direction


def test_frame_axes():
    fr = frame(0.0)
    assert np.allclose(fr.flow_direction, [0, -1]) and np.allclose(fr.cross, [1, 0])
    fr = Frame.from_bases([[0, 0], [4, 0], [0, 2]], 2.0, math.radians(90))  # field along -x
    assert np.allclose(fr.centre, [2, 1]) and np.allclose(fr.flow_direction, [1, 0])
    assert np.allclose(fr.cross, [0, 1])
    # a positive deflection turns the flow toward +cross
    d = fr.directions([0.3])
    assert d[0] @ fr.cross > 0 and np.isclose(np.linalg.norm(d[0]), 1)
    with pytest.raises(TargetError):
        Frame(np.zeros(2), np.zeros(2), 1.0)


@pytest.mark.parametrize("direction", [0.0, 30.0, 90.0, 200.0])
def test_focus_flows_toward_the_line_and_spread_away(direction):
    fr = frame(direction, centre=(3.0, -1.0))
    line = 0.7
    xis = np.array([-6.0, -2.0, -0.5, 0.5, 2.0, 6.0])
    pts = line_points(fr, xis + line, along=1.3)
    focus = Target("focus", A, line=line, width=1.5)
    spread = Target("spread", A, line=line, width=1.5)
    toward = -np.sign(xis)  # the direction (along cross) from each point to the line
    for tgt, sign in ((focus, 1), (spread, -1)):
        d = tgt.directions(pts, fr)
        assert np.all(sign * toward * (d @ fr.cross) > 0), tgt.kind
        assert np.all(d @ fr.flow_direction > 0)  # still downstream
        assert np.all(np.abs(tgt.deflection(pts, fr)) <= A)
    # on the line: straight; far away: the amplitude
    on = line_points(fr, [line])
    assert abs(focus.deflection(on, fr)[0]) < 1e-12
    far = focus.deflection(line_points(fr, [line - 100.0, line + 100.0]), fr)
    assert np.allclose(far, [A, -A])


def test_uniform_and_shear():
    fr = frame(0.0)
    pts = line_points(fr, [-40.0, 0.0, 40.0])
    assert np.allclose(Target("uniform", -0.3).deflection(pts, fr), -0.3)
    sh = Target("shear", A)  # width None: one spacing
    d = sh.deflection(pts, fr)
    assert np.isclose(d[0], A) and np.isclose(d[1], A / 2) and abs(d[2]) < 1e-6
    # the -cross side (x < 0 here) is turned toward +x, the other side straight down
    dirs = sh.directions(pts, fr)
    assert dirs[0, 0] > 0.5 and np.allclose(dirs[2], [0, -1], atol=1e-6)
    # width defaults to the frame's spacing
    assert np.isclose(Target("focus", A).deflection(line_points(fr, [2.0]), fr)[0], -A * np.tanh(1.0))


def test_turn_is_smooth_and_tangential_across_the_stream():
    fr = frame(0.0, centre=(5.0, 5.0))
    tgt = Target("turn", math.radians(50))
    c = np.array([5.0, 5.0])
    phis = np.radians(np.arange(0, 360, 15))
    pts = c + 2.0 * np.column_stack([np.cos(phis), np.sin(phis)])
    delta = tgt.deflection(pts, fr)
    tangent = np.column_stack([-np.sin(phis), np.cos(phis)])  # anticlockwise
    np.testing.assert_allclose(delta, tgt.amplitude * (tangent @ fr.cross), atol=1e-15)
    assert np.all(np.abs(delta) <= tgt.amplitude + 1e-15)
    assert np.all(np.abs(np.diff(delta)) < 0.3 * tgt.amplitude)  # no jump anywhere on the circle
    # the flow's cross-stream component follows the anticlockwise tangent's
    tc_ = tangent @ fr.cross
    dc_ = tgt.directions(pts, fr) @ fr.cross
    assert np.all(np.sign(dc_[np.abs(tc_) > 1e-9]) == np.sign(tc_[np.abs(tc_) > 1e-9]))
    # left of the centre (x < 5) the circle runs down: straight flow
    assert abs(tgt.deflection([[3.0, 5.0]], fr)[0]) < 1e-12
    # below the centre the anticlockwise flow runs toward +x: full positive deflection
    assert tgt.deflection([[5.0, 4.0]], fr)[0] == pytest.approx(tgt.amplitude)
    assert tgt.deflection([[5.0, 5.0]], fr)[0] == 0.0  # the centre itself
    tc = Target("turn", math.radians(50), centre=(0.0, 0.0))
    assert abs(tc.deflection([[-2.0, 0.0]], fr)[0]) < 1e-12


def test_target_from_scene_defaults_and_kinds(tmp_path):
    s = load_scene(DESIGNS / "uniform_deflection.toml")
    t = target_of(s)
    assert t.kind == "uniform" and np.isclose(t.amplitude, math.radians(30))
    table = load_table(s)
    s2 = scene_from_dict({"target": {"kind": "focus"}})
    t2 = target_of(s2, table)
    assert np.isclose(t2.amplitude, DEFAULT_ANGLE_FRACTION * table.thrust_angle_range()[1])
    assert t2.width is None and t2.centre is None and t2.control == "cells"
    with pytest.raises(TargetError, match="angle_max"):
        resolve_target(s2.target)
    none = target_of(scene_from_dict({}))
    with pytest.raises(TargetError):
        none.deflection([[0.0, 0.0]], frame())
    with pytest.raises(TargetError):
        none.velocities()


def test_points_target_from_csv_scene(tmp_path):
    (tmp_path / "ctl.csv").write_text("# target velocities\nx, y, u, v, note\n0, 0, 0.1, -1, a\n"
                                      "1.5, 2, 0, -2, b  # inline comment\n\n3, 4, -0.5, -1, c\n")
    (tmp_path / "s.toml").write_text('[target]\nkind = "points"\nfile = "ctl.csv"\nresidual = 0.1\n')
    s = load_scene(tmp_path / "s.toml")
    t = target_of(s)
    X, U = t.velocities()
    assert np.allclose(X, [[0, 0], [1.5, 2], [3, 4]]) and np.allclose(U, [[0.1, -1], [0, -2], [-0.5, -1]])
    assert t.residual == 0.1 and t.source == str(tmp_path / "ctl.csv")
    X[0, 0] = 99  # a copy
    assert t.velocities()[0][0, 0] == 0
    with pytest.raises(TargetError, match="velocities"):
        t.deflection(X, frame())


def test_csv_errors_name_file_and_row(tmp_path):
    p = tmp_path / "c.csv"
    cases = [
        ("x,y,u,v\n0,0,1,1\n1,nan,1,1\n", "line 3 (data row 2): column 'y' is 'nan'"),
        ("x,y,u,v\n0,0,1,inf\n", "line 2 (data row 1): column 'v' is 'inf'"),
        ("x,y,u,v\n0,0,a,1\n", "column 'u' is not a number: 'a'"),
        ("x,y,u\n0,0,1\n", "lacks column(s) v"),
        ("x,y,u,v\n0,0,1\n", "3 fields, the header has 4"),
        ("x,y,u,v\n", "no data rows"),
        ("", "empty file"),
        ("# only a comment\n\n", "empty file"),
    ]
    for text, msg in cases:
        p.write_text(text)
        with pytest.raises(TargetError) as e:
            read_target_points(p)
        assert str(p) in str(e.value) and msg in str(e.value), (text, str(e.value))
    p.write_text("x y u v\n1 2 3 4\n")  # whitespace-separated is fine
    assert np.allclose(read_target_points(p)[1], [[3, 4]])
    with pytest.raises(TargetError, match="no such"):
        read_target_points(tmp_path / "none.csv")
    (tmp_path / "c.dat").write_text("x,y,u,v\n")
    with pytest.raises(TargetError, match="unknown control-point file type"):
        read_target_points(tmp_path / "c.dat")


def test_netcdf_read_and_errors(tmp_path):
    p = tmp_path / "c.nc"
    good = xr.Dataset({k: ("point", np.arange(4.0) + i) for i, k in enumerate("xyuv")})
    good.to_netcdf(p, engine="h5netcdf")
    X, U = read_target_points(p)
    assert X.shape == U.shape == (4, 2) and np.allclose(U[:, 1], np.arange(4.0) + 3)
    bad = good.copy(deep=True)
    bad["u"].values[2] = np.nan
    bad.to_netcdf(p, engine="h5netcdf")
    with pytest.raises(TargetError) as e:
        read_target_points(p)
    assert str(p) in str(e.value) and "variable 'u'" in str(e.value) and "index 2" in str(e.value)
    good.drop_vars("v").to_netcdf(p, engine="h5netcdf")
    with pytest.raises(TargetError, match="missing variable.*v"):
        read_target_points(p)
    xr.Dataset({k: ("point", np.zeros(0)) for k in "xyuv"}).to_netcdf(p, engine="h5netcdf")
    with pytest.raises(TargetError, match="no control points"):
        read_target_points(p)
    p.write_text("garbage")
    with pytest.raises(TargetError, match="not a readable NetCDF"):
        read_target_points(p)


def test_control_points():
    from ciliary_carpet.carpet import layout

    b = layout.square(4, 3, spacing=2.0)
    fr = Frame.from_bases(b, 2.0, 0.0)  # d0 = -y, cross = +x
    cil = control_points(b, fr, "cilia")
    assert np.allclose(cil, b + [0, -1])
    cells = control_points(b, fr, "cells")
    assert cells.shape == (3 * 2, 2)  # the cell centres of a 4 x 3 lattice
    assert np.allclose(np.sort(cells[:, 0]), np.sort(np.repeat([1.0, 3.0, 5.0], 2)))
    assert set(np.round(cells[:, 1], 12)) == {1.0, 3.0}
    # field along +x (direction -90 deg): still the cell centres
    assert np.allclose(np.sort(control_points(b, Frame.from_bases(b, 2.0, -math.pi / 2), "cells"), axis=0),
                       np.sort(cells, axis=0))
    row = layout.row(5, spacing=2.0)
    assert np.allclose(control_points(row, Frame.from_bases(row, 2.0, 0.0), "cells"), row + [0, -1])
    explicit = control_points(b, fr, ((0.5, 0.5), (1, 2)))
    assert np.allclose(explicit, [[0.5, 0.5], [1, 2]])
    t = Target("uniform", 0.2, control="cilia")
    assert np.allclose(control_points(b, fr, t), cil)
    hexa = layout.hexagonal(5, 4, spacing=2.0)
    hc = control_points(hexa, Frame.from_bases(hexa, 2.0, 0.0), "cells")
    # the triangle centres of a hexagonal lattice: 2 per rhombus, each 2/sqrt(3) from three bases
    assert hc.shape[0] == 2 * 4 * 3
    from scipy.spatial import cKDTree

    d, _ = cKDTree(hexa).query(hc, k=4)
    assert np.allclose(d[:, :3], 2.0 / math.sqrt(3)) and np.all(d[:, 3] > 2.0 / math.sqrt(3) + 0.5)
    with pytest.raises(TargetError):
        control_points(b, fr, "corners")


def test_reachable_check_lists_and_clips():
    rng = (0.0, 0.9)
    ok, mask = reachable_check([0.1, -0.5, 0.9], rng)
    assert np.allclose(ok, [0.1, -0.5, 0.9]) and not mask.any()
    angles = np.array([0.1, 1.2, -0.3, -1.0])
    pts = np.array([[0, 0], [1, 2], [3, 4], [5, 6.5]])
    with pytest.raises(TargetError) as e:
        reachable_check(angles, rng, points=pts)
    msg = str(e.value)
    assert "2 of 4 control points" in msg and "control point 1 at (1, 2) asks 68.75 deg" in msg
    assert "control point 3 at (5, 6.5) asks -57.30 deg" in msg and "51.57 deg" in msg
    assert "control point 0" not in msg and "control point 2" not in msg and "clip" in msg
    with pytest.warns(UserWarning) as w:
        clipped, mask = reachable_check(angles, rng, clip=True, what="cilium")
    assert "cilium 1 asks 68.75 deg" in str(w[0].message) and "cilium 3" in str(w[0].message)
    assert np.allclose(clipped, [0.1, 0.9, -0.3, -0.9]) and mask.tolist() == [False, True, False, True]
    assert np.allclose(angles, [0.1, 1.2, -0.3, -1.0])  # input untouched
    with pytest.raises(TargetError):
        reachable_check([np.nan], rng)


def test_design_targets_are_reachable_and_patterns_right():
    """The shipped designs ask only for what the shipped table can do, at their control points
    (those with a target: a standing carpet's layout is given)."""
    from ciliary_carpet.scenes.scene import load_scene

    checked = 0
    for path in sorted(DESIGNS.glob("*.toml")):
        s = load_scene(path)
        if s.target.kind == "none":
            continue
        checked += 1
        table = load_table(s)
        t = target_of(s, table)
        fr = frame_of(s)
        X = control_points(s.carpet.bases(), fr, t.control)
        assert X.shape[0] >= 50
        if t.is_surface:  # any direction is reachable; most control points keep theirs
            A, keep = t.surface_directions(X, fr, s.carpet.bases())
            assert keep.mean() > 0.9 and np.all(np.isfinite(A))
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            reachable_check(t.deflection(X, fr), table.thrust_angle_range(), clip=False, points=X)
    assert checked >= 5


def test_registry_drives_the_schema_and_the_readme():
    """The kinds of [target] are patterns.PATTERNS and the keys each takes come from TargetSpec's
    field metadata: KIND_KEYS covers exactly TargetSpec's keys, a key that does not apply to a
    kind is rejected naming the kinds it is for, and every angle pattern evaluates through its
    registry entry (designs/README.md against both: tests/test_scene.py)."""
    from dataclasses import fields

    from ciliary_carpet.design.patterns import ANGLE_KINDS, KINDS, PATTERNS
    from ciliary_carpet.scenes.scene import SceneError, TargetSpec, scene_from_dict
    from ciliary_carpet.scenes.target_spec import KIND_KEYS, applies_to

    assert KINDS == tuple(p.name for p in PATTERNS) and set(KIND_KEYS) == set(KINDS)
    keys = {k for v in KIND_KEYS.values() for k in v}
    assert {f.name for f in fields(TargetSpec)} == keys | {"kind"}
    for kind, ok in KIND_KEYS.items():
        for k in sorted(keys - set(ok)):
            with pytest.raises(SceneError, match=f"target.{k} does not apply to kind = \"{kind}\" "
                                                 f"\\(it is used by kind = '{applies_to(k)[0]}'"):
                scene_from_dict({"target": {"kind": kind, k: 1}})
    assert applies_to("kind") == KINDS and applies_to("nope") == ()
    fr = Frame(np.zeros(2), np.array([0.0, -1.0]), 2.0)
    pts = np.array([[-3.0, 1.0], [0.5, 0.0], [4.0, -2.0]])
    for p in PATTERNS:
        assert set(p.keys) <= keys
        if p.name in ANGLE_KINDS:
            t = Target(p.name, 0.3)
            assert t.pattern is p and np.allclose(t.deflection(pts, fr), p.deflection(t, pts, fr))
            assert np.all(np.abs(t.deflection(pts, fr)) <= 0.3 + 1e-15)
        else:
            assert p.deflection is None
    assert [p.name for p in PATTERNS if p.two_sided] == ["focus", "spread"]
    assert [p.name for p in PATTERNS if p.signed and not p.surface] == ["uniform"]
    assert [p.name for p in PATTERNS if p.surface] == ["pump", "vortex", "mixer", "u_turn", "source_sink"]
    for p in PATTERNS:
        if p.surface:  # a direction field of the plane: unit directions where it is defined
            t = Target(p.name, 0.4, centre=(0.0, 0.0), separation=3.0)
            A, keep = t.surface_directions(pts, fr)
            assert A.shape == (keep.sum(),) and keep.sum() >= 2 and np.all(np.abs(A) <= np.pi)


def test_sample_uncertainties_come_as_a_pair_of_numbers_at_least_zero(tmp_path):
    from ciliary_carpet.design.target_files import read_target_samples

    p = tmp_path / "c.csv"
    p.write_text("x,y,u,v,du,dv\n0,0,1,2,0.1,0.2\n1,0,1,2,0,0\n")
    X, U, E = read_target_samples(p)
    assert E.tolist() == [[0.1, 0.2], [0.0, 0.0]] and U.shape == (2, 2)
    assert read_target_samples(tmp_path / "c.csv")[2] is not None
    p.write_text("x,y,u,v\n0,0,1,2\n")
    assert read_target_samples(p)[2] is None
    p.write_text("x,y,u,v,du\n0,0,1,2,0.1\n")
    with pytest.raises(TargetError, match="'du' without 'dv'"):
        read_target_samples(p)
    p.write_text("x,y,u,v,du,dv\n0,0,1,2,-0.1,0.1\n")
    with pytest.raises(TargetError, match="du = -0.1 is negative"):
        read_target_samples(p)
