"""docs/tutorial.md runs as written: its shell blocks, in order, from a folder holding a copy of
the repository's designs/ and examples/ (issue 42: the eight tasks a newcomer tried)."""
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TUTORIAL = ROOT / "docs" / "tutorial.md"


def bash_blocks() -> list[str]:
    return re.findall(r"^```bash\n(.*?)^```", TUTORIAL.read_text(), re.S | re.M)


def test_the_tutorial_has_its_tasks_as_shell_blocks():
    blocks = bash_blocks()
    assert len(blocks) >= 8 and all(b.strip() for b in blocks)
    assert sum("ciliary-carpet" in b for b in blocks) >= 4 and any("single-cilium" in b for b in blocks)


@pytest.mark.slow
def test_the_tutorial_runs_as_written(tmp_path):
    for folder in ("designs", "examples"):
        shutil.copytree(ROOT / folder, tmp_path / folder)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               MPLBACKEND="Agg")
    for k, block in enumerate(bash_blocks(), 1):
        p = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=600)
        assert p.returncode == 0, f"block {k} exited {p.returncode}:\n{block}\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"
    s = (tmp_path / "out" / "uniform_deflection" / "summary.md").read_text()
    assert "**Verdict: target met, in the coupled model**" in s
    assert (tmp_path / "out" / "my_vortex" / "open_in_paraview.py").is_file()
    assert (tmp_path / "piv_layout.nc").is_file() and (tmp_path / "out" / "batch" / "batch.md").is_file()
    assert (tmp_path / "thrust_curve.png").stat().st_size > 10_000 and (tmp_path / "map.png").is_file()
