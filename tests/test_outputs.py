"""The render as a pipeline over the output registry (issue 25, point 3): the registry names every
file a render writes (the manifest and the folder's ownership come from it), the plan decides
the path-line duration once, and the carpet layer imports no private module of single_cilium."""
import ast
import json
import re
from pathlib import Path

import pytest

import ciliary_carpet
import ciliary_carpet.output.plan as plan_module
from ciliary_carpet.output import RenderError
from ciliary_carpet.output.folder import MANIFEST, owned_files
from ciliary_carpet.output.contract import Output
from ciliary_carpet.output.outputs import OUTPUTS
from ciliary_carpet.render import render
from ciliary_carpet.scenes.scene import load_scene
from cilia_runtime.progress import Progress

SCENE = ('[carpet]\nshape = [3, 3]\n[target]\nkind = "uniform"\nangle = 20.0\n[output]\nn_seeds = 4\n'
         'field_shape = [8, 8]\nsnapshots = 2\nframes = 2\n')


def test_registry_follows_the_contract():
    assert list(OUTPUTS)[-1] == "summary"  # written last: it holds every other output's section
    for name, cls in OUTPUTS.items():
        assert issubclass(cls, Output) and cls.name == name and cls.__doc__ and cls.files
        for f in cls.files:
            re.compile(f)


def test_every_file_comes_from_one_registered_output(tmp_path, monkeypatch):
    """A render with every output on: each file it wrote is named by exactly one output, each
    output wrote a file, and the duration was worked out once (it probes the mean flow). Its
    progress moves within the path lines' stage as their tasks finish."""
    calls = []
    real = plan_module.pathline_duration

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(plan_module, "pathline_duration", counted)
    p = tmp_path / "s.toml"
    p.write_text(SCENE)
    out = tmp_path / "out"
    seen = []

    class Recorded(Progress):
        def stage(self, name):
            seen.append(name)

        def update(self, done):
            seen.append(done)

    res = render(load_scene(p), out, progress=Recorded())
    assert len(calls) == 1
    k = seen.index("pathlines")  # the stage's number: the updates before it count the outputs done
    before = max(x for x in seen[:k] if not isinstance(x, str))
    within = [x for x in seen[k + 1:seen.index(before + 1)] if not isinstance(x, str)]
    assert within and all(before < x < before + 1 for x in within) and within == sorted(within)
    names = set(json.loads((out / MANIFEST).read_text())["files"]) - {MANIFEST}
    assert names == set(res.files) - {MANIFEST}
    by_output = {n: [o for o, cls in OUTPUTS.items() if any(re.fullmatch(f, n) for f in cls.files)] for n in names}
    assert all(len(v) == 1 for v in by_output.values()), by_output
    assert {v[0] for v in by_output.values()} == set(OUTPUTS)
    assert owned_files(out) == names | {MANIFEST}
    s = res.summary
    assert s["pathlines"]["duration"] > 0
    assert s["mixing"]["duration"] == pytest.approx(0.25 * s["pathlines"]["duration"])
    assert {"design", "mean_field", "pathlines", "pathline_error", "ftle", "omissions", "total"} <= set(s["seconds"])


def test_an_unregistered_file_is_not_placed(tmp_path, monkeypatch):
    """A file no output names would be the user's for ever after: the render fails, nothing is placed."""
    import ciliary_carpet.output.outputs as outputs
    from ciliary_carpet.output.views import ParaViewOutput

    class Stray(ParaViewOutput):
        def write(self, ctx):
            super().write(ctx)
            (ctx.stage / "stray.txt").write_text("x")

    monkeypatch.setitem(outputs.OUTPUTS, "paraview", Stray)
    p = tmp_path / "s.toml"
    p.write_text('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 2\nperiods = 1.0\nfield_shape = [8, 8]\n'
                 'snapshots = 0\nframes = 0\npreview = false\nftle = false\n')
    with pytest.raises(RenderError, match="stray.txt"):
        render(load_scene(p), tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_frames_written_by_the_render_threads(tmp_path, monkeypatch):
    """The cilia frames are written by as many threads as the render's numba threads, each file
    complete and listed in order in cilia.pvd; a write that fails in a thread fails the render
    with its error (the file named), and nothing is placed."""
    import threading
    import xml.etree.ElementTree as ET

    import ciliary_carpet.output.fields as fields
    from ciliary_carpet.output.vtkfiles import OutputError

    p = tmp_path / "s.toml"
    p.write_text('[carpet]\nshape = [2, 2]\n[output]\nn_seeds = 2\nperiods = 1.0\nfield_shape = [6, 6]\n'
                 'snapshots = 0\nframes = 6\npreview = false\nftle = false\npathlines = false\n')
    real, seen = fields.write_cilia, set()

    def spy(path, *a, **k):
        seen.add(threading.get_ident())
        return real(path, *a, **k)

    monkeypatch.setattr(fields, "write_cilia", spy)
    monkeypatch.setattr(fields, "threads_in_use", lambda: {"numba": 2, "blas": 1, "workers": 1})
    res = render(load_scene(p), tmp_path / "out")
    pvd = ET.parse(tmp_path / "out" / "cilia.pvd").getroot()
    files = [d.get("file") for d in pvd.iter("DataSet")]
    assert files[:6] == [f"cilia_{k:03d}.vtp" for k in range(6)]
    assert all((tmp_path / "out" / f).stat().st_size > 0 for f in set(files))
    assert threading.get_ident() not in seen and len(seen) <= 2  # the writers, not the render's thread
    assert res.summary["seconds"]["frames"] > 0

    def broken(path, *a, **k):
        if path.name == "cilia_003.vtp":
            raise OutputError(path, "no space left on device")
        return real(path, *a, **k)

    monkeypatch.setattr(fields, "write_cilia", broken)
    with pytest.raises(OutputError, match="cilia_003.vtp.*no space left"):
        render(load_scene(p), tmp_path / "out2")
    assert not (tmp_path / "out2").exists()


def test_carpet_layer_imports_no_private_module_of_single_cilium():
    root = Path(ciliary_carpet.__file__).parent
    bad = []
    for f in root.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            mods = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                    [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            bad += [f"{f.relative_to(root)}: {m}" for m in mods
                    if m.startswith("single_cilium.") and any(part.startswith("_") for part in m.split(".")[1:])]
    assert bad == []
