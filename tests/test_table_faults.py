"""Faults of the thrust-table build, the single-cilium command line and numba's cache (issue 43):
no silent wrong or stale number, no "internal error", no file touched that the toolkit did not
write. Temporary folders only; tiny grids."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

_COMPILE = ("import single_cilium\n"
            "from single_cilium._kernels import first_parallel_region\n"
            "first_parallel_region()\n"
            "print('ok')\n")


def _python(code: str, cache: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300,
                          cwd=ROOT)


@pytest.mark.parametrize("damage", ["truncated index", "garbled data"])
def test_a_damaged_numba_cache_file_is_discarded_and_rebuilt(tmp_path, damage):
    """A cache index (``.nbi``) cut short, or a data file (``.nbc``) overwritten with garbage: the
    next run compiles the function anew with one warning naming the file (never an
    UnpicklingError), and the run after it reads a sound cache again (no warning)."""
    cache = tmp_path / "cache"
    first = _python(_COMPILE, cache)
    assert first.returncode == 0 and first.stdout.strip() == "ok", first.stderr[-2000:]
    suffix = ".nbi" if damage == "truncated index" else ".nbc"
    files = sorted(cache.rglob(f"_kernels._one_region-*{suffix}"))
    assert files, sorted(str(p) for p in cache.rglob("*"))
    bad = files[0]
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2] if damage == "truncated index" else b"\x80\x04garbage" * 10)
    second = _python(_COMPILE, cache)
    assert second.returncode == 0 and second.stdout.strip() == "ok", second.stderr[-2000:]
    assert "Traceback" not in second.stderr and "discarded" in second.stderr and bad.name in second.stderr
    assert len(second.stderr.strip().splitlines()) == 1, second.stderr
    third = _python(_COMPILE, cache)
    assert third.returncode == 0 and third.stderr.strip() == "", third.stderr
