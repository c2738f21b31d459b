import numpy as np
import pytest

from single_cilium import CiliumParams

TWO_PI = 2 * np.pi


@pytest.fixture
def published():
    """The published nonlinear case: chi_E = 200, eta = 1, chi_N = 16 * 2 pi."""
    return CiliumParams(200.0, 1.0, 16 * TWO_PI)


@pytest.fixture
def mount_tmpfs(tmp_path):
    """``mount(name, size)``: a real tmpfs of ``size`` (e.g. "1m") mounted at ``tmp_path / name``,
    unmounted after the test; the test is skipped, saying why, where it cannot be mounted (not
    root, or no mount permission). Used for the cross-device and full-disk cases."""
    import os
    import subprocess

    mounted = []

    def mount(name: str, size: str):
        if not hasattr(os, "geteuid") or os.geteuid() != 0:
            pytest.skip("mounting a tmpfs needs root (CI runs the tests as root)")
        mnt = tmp_path / name
        mnt.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)],
                           capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode})")
        mounted.append(mnt)
        return mnt

    yield mount
    for mnt in mounted:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)
