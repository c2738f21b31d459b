"""Scene values that are accepted only where they make sense, numbers in the summary in the units
it states, carpets that own their arrays, and the Python front door."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

import ciliary_carpet as cc
from ciliary_carpet.carpet import layout
from ciliary_carpet.carpet.carpet import Carpet, CycleMean
from ciliary_carpet.scenes.scene import SceneError, load_scene, scene_from_dict
from single_cilium.table import ThrustTable


@pytest.fixture(scope="module")
def table():
    return ThrustTable.default()


# ------------------------------------------------------------------------------ reading
def test_numpy_scalars_read_as_the_numbers_they_hold():
    s = scene_from_dict({"field": {"eta": np.float32(2.0)}, "carpet": {"shape": [np.int64(3), np.int64(2)],
                                                                       "spacing": np.float64(3.0)},
                         "output": {"pathlines": np.bool_(False), "n_seeds": np.int32(5)}})
    assert s.field.eta == 2.0 and s.carpet.shape == (3, 2) and s.output.pathlines is False
    assert s.output.n_seeds == 5 and type(s.output.n_seeds) is int
    with pytest.raises(SceneError, match="output.pathlines must be true or false, got 1"):
        scene_from_dict({"output": {"pathlines": np.int64(1)}})


def test_utf8_byte_order_mark_and_other_encodings(tmp_path):
    p = tmp_path / "bom.toml"
    p.write_bytes(b"\xef\xbb\xbf[carpet]\nspacing = 3.0\n")
    assert load_scene(p).carpet.spacing == 3.0
    q = tmp_path / "latin1.toml"
    q.write_bytes('description = "caf\u00e9"\n'.encode("latin-1"))
    with pytest.raises(SceneError, match=r"latin1.toml: not UTF-8 text \(byte 0xe9 at offset 18\).*save it as UTF-8"):
        load_scene(q)


@pytest.mark.parametrize("text, message", [
    ("[carpet]\nspacing = 0.3\n", r"carpet.spacing must be a number in \[1, 1e\+06\] \(L; at least the filament "
                                  r"length: closer cilia can touch\), got 0.3"),
    ('[carpet]\nlattice = "points"\npoints = [[0, 0], [5, 0], [0.5, 0.2]]\n',
     r"carpet.points\[0\] and carpet.points\[2\] are 0.539 L apart; base points must lie at least 1 L apart"),
    ("[carpet]\nviscosity = 1e-300\n", r"carpet.viscosity must be a number in \[0.00653, 65.3\] \(within a factor "
                                       r"100 of 0.653, .* got 1e-300"),
    ("[field]\neta = 10.0\n[carpet]\nviscosity = 0.05\n", r"carpet.viscosity must be a number in \[0.0653, 653\]"),
    ("[carpet]\nwall = 1e-300\n", r"carpet.wall must be at least a filament diameter, 2 blob = 0.04 L"),
    ("[carpet]\nwall = 1e300\n", r"carpet.wall must be a number in \[0, 1e\+06\], got 1e\+300"),
    ("[carpet]\nblob = 1e-300\n", r"carpet.blob must be a length in \[0.0001, 0.5\) L"),
    ("[field]\neta = 1e-300\n", r"field.eta must be a number in \[0.001, 1000\]"),
    ("[field]\nchi_E = 1e300\n", r"field.chi_E must be a number in \[-10000, 10000\]"),
    ("[carpet]\nshape = [100000, 100000]\n", r"carpet.shape must be at most 1e\+07 cilia in all"),
    ("[output]\nfield_shape = [100000, 100000]\n", r"output.field_shape must be at most 1e\+08 points"),
    ("[output]\nframes = 1000000000\n", r"output.frames must be an integer in \[0, 10000\]"),
    ("[output]\nfield_margin = 1e300\n", r"output.field_margin must be a number in \[0, 1e\+06\]"),
])
def test_values_that_overflow_hang_or_overlap_are_scene_errors(tmp_path, text, message):
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(SceneError, match=f"^{re.escape(str(p))}: {message}"):
        load_scene(p)


def test_bounds_are_not_too_tight():
    """The bounds' edges are scenes: spacing 1 L, the filaments' viscosity times 100, a wall a
    filament diameter below the plane, a standing carpet's wall at its substrate."""
    s = scene_from_dict({"carpet": {"spacing": 1.0, "viscosity": 65.3, "wall": 0.04}})
    assert s.carpet.spacing == 1.0 and s.carpet.viscosity == 65.3 and s.carpet.wall == 0.04
    assert scene_from_dict({"carpet": {"geometry": "standing", "wall": 0.0}}).carpet.wall == 0.0


def test_front_door_takes_a_scene_or_a_path(tmp_path):
    with pytest.raises(TypeError, match=r"design\(\) takes a Scene .* or the path of a scene file, got int"):
        cc.design(3)
    with pytest.raises(TypeError, match=r"render\(\) takes a Scene"):
        cc.render(3.0, tmp_path / "out")
    with pytest.raises(TypeError, match=r"assemble\(\) takes a Scene"):
        cc.assemble(None)
    p = tmp_path / "x.toml"
    p.write_text("[carpet]\nshape = [2, 2]\n")
    d, carpet = cc.design(str(p))
    assert d is None and carpet.n == 4
    with pytest.raises(SceneError, match="cannot read the scene file"):
        cc.design(tmp_path / "missing.toml")


# ------------------------------------------------------------------------------ carpets
def test_carpet_owns_read_only_copies_of_its_arrays(table):
    b, chi, ph = layout.square(3, 3), np.full(9, 30.0), np.linspace(0, 0.8, 9)
    c = Carpet(b, chi, table, ph)
    x = np.array([[1.0, 1.0, 0.5]])
    u = c.velocity(x, CycleMean())
    b += 1.0
    chi[:] = 60.0
    ph[:] = 0.0
    assert np.array_equal(c.velocity(x, CycleMean()), u)
    assert np.all(c.chi_N == 30.0) and c.bases[0, 0] == 0.0 and c.phases[1] > 0
    for name in ("bases", "chi_N", "phases"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(c, name)[0] = 1.0
    s = Carpet(layout.row(2, 2.0), 30.0, table, geometry="standing", wall=0.0, azimuth=np.array([0.1, 0.2]))
    with pytest.raises(ValueError, match="read-only"):
        s.azimuth[0] = 0.0


def test_carpet_refuses_cilia_within_their_reach(table):
    with pytest.raises(ValueError, match=r"cilia 0 and 1 stand 0.3 L apart, within the 0.9\d* L that their beat "
                                         r"reaches.*smallest spacing allowed is 0.9\d* L"):
        Carpet(layout.square(2, 2, spacing=0.3), 30.0, table)
    for geometry, wall in (("planar", None), ("standing", 0.0)):
        c = Carpet(layout.square(2, 2, spacing=1.0), 30.0, table, geometry=geometry, wall=wall)
        assert np.all((c.reach > 0.5) & (c.reach <= 1.0))
