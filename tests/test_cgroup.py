"""The limits of a control group (cilia_runtime.cgroup): read from fake /proc and cgroup trees of
both interface versions, and, where this machine lets a test make groups (root, cgroup v1 memory
and cpu controllers), from real ones in a subprocess."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from cilia_runtime import cgroup


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _v1(tmp_path: Path, *, cpu_mount: str = "cpu", group: str = "/slurm/job_7/step_0") -> Path:
    """A v1 layout like this machine's (a mount per controller) or a combined ``cpu,cpuacct``."""
    fs = tmp_path / "fs"
    proc = tmp_path / "proc"
    ctrl = cpu_mount.split(",")
    _write(proc / "cgroup", f"4:memory:{group}\n3:{','.join(ctrl)}:{group}\n2:cpuset:/\n0::/\n")
    _write(proc / "mountinfo",
           f"31 23 0:28 / {fs} rw,relatime - tmpfs tmpfs rw,mode=755\n"
           f"32 31 0:29 / {fs}/{cpu_mount} rw,relatime - cgroup cgroup rw,{','.join(ctrl)}\n"
           f"35 31 0:32 / {fs}/memory rw,relatime - cgroup cgroup rw,memory\n")
    for d in (fs / cpu_mount, fs / "memory"):
        (d / group.lstrip("/")).mkdir(parents=True)
    return proc


def test_v1_nested_groups_take_the_tightest_limit(tmp_path):
    proc = _v1(tmp_path)
    fs = tmp_path / "fs"
    cpu = fs / "cpu"
    for d in (cpu, cpu / "slurm", cpu / "slurm/job_7", cpu / "slurm/job_7/step_0"):
        _write(d / "cpu.cfs_quota_us", "-1\n")
        _write(d / "cpu.cfs_period_us", "100000\n")
    assert cgroup.cpu_quota(str(proc)) is None  # -1 everywhere: no quota
    _write(cpu / "slurm/job_7/cpu.cfs_quota_us", "250000\n")  # the job: 2.5 CPUs
    assert cgroup.cpu_quota(str(proc)) == pytest.approx(2.5)
    _write(cpu / "slurm/job_7/step_0/cpu.cfs_quota_us", "50000\n")
    _write(cpu / "slurm/job_7/step_0/cpu.cfs_period_us", "50000\n")  # the step: 1 CPU, another period
    assert cgroup.cpu_quota(str(proc)) == pytest.approx(1.0)

    mem = fs / "memory"
    for d in (mem, mem / "slurm", mem / "slurm/job_7", mem / "slurm/job_7/step_0"):
        _write(d / "memory.limit_in_bytes", "9223372036854771712\n")  # v1's "no limit"
        _write(d / "memory.usage_in_bytes", "0\n")
    assert cgroup.memory_headroom(str(proc)) is None
    _write(mem / "slurm/job_7/memory.limit_in_bytes", str(4 << 30))
    _write(mem / "slurm/job_7/memory.usage_in_bytes", str(3 << 30))
    _write(mem / "slurm/job_7/memory.stat", f"cache 100\ninactive_file 5\ntotal_inactive_file {1 << 30}\n")
    # 4 GB less 3 GB used, of which 1 GB inactive file pages the kernel reclaims first
    assert cgroup.memory_headroom(str(proc)) == 2 << 30
    _write(mem / "slurm/job_7/step_0/memory.limit_in_bytes", str(1 << 30))
    _write(mem / "slurm/job_7/step_0/memory.usage_in_bytes", str(1 << 29))
    assert cgroup.memory_headroom(str(proc)) == 1 << 29
    _write(mem / "slurm/job_7/step_0/memory.usage_in_bytes", str(2 << 30))  # over (e.g. cache): none left
    assert cgroup.memory_headroom(str(proc)) == 0


def test_v1_combined_cpu_mount_and_a_container_at_the_mount_root(tmp_path):
    proc = _v1(tmp_path, cpu_mount="cpu,cpuacct", group="/")
    d = tmp_path / "fs" / "cpu,cpuacct"
    _write(d / "cpu.cfs_quota_us", "150000\n")
    _write(d / "cpu.cfs_period_us", "100000\n")
    assert cgroup.cpu_quota(str(proc)) == pytest.approx(1.5)


def test_a_group_outside_the_mount_root_is_the_mount(tmp_path):
    """A container without its own cgroup namespace sees the host's group path, but its mount is
    the group itself (mountinfo's root field names it)."""
    fs, proc = tmp_path / "fs", tmp_path / "proc"
    _write(proc / "cgroup", "0::/kubepods/pod1/abc\n")
    _write(proc / "mountinfo", f"40 31 0:38 /kubepods/pod1/abc {fs} rw - cgroup2 cgroup2 rw\n")
    fs.mkdir(parents=True, exist_ok=True)
    _write(fs / "cpu.max", "200000 100000\n")
    _write(fs / "memory.max", str(3 << 30))
    _write(fs / "memory.current", str(1 << 30))
    (h,) = cgroup.hierarchies(str(proc))
    assert (h.version, h.group, h.folders()) == (2, str(fs), [str(fs)])
    assert cgroup.cpu_quota(str(proc)) == pytest.approx(2.0)
    assert cgroup.memory_headroom(str(proc)) == 2 << 30
    _write(proc / "mountinfo", f"40 31 0:38 /other {fs} rw - cgroup2 cgroup2 rw\n")  # not under it
    assert cgroup.hierarchies(str(proc))[0].group == str(fs)


def test_v2_limits_high_and_max(tmp_path):
    fs, proc = tmp_path / "fs", tmp_path / "proc"
    _write(proc / "cgroup", "0::/user.slice/job.scope\n")
    _write(proc / "mountinfo", f"30 23 0:26 / {fs} rw,nosuid - cgroup2 cgroup2 rw,nsdelegate\n")
    leaf = fs / "user.slice/job.scope"
    leaf.mkdir(parents=True)
    for d in (fs, fs / "user.slice", leaf):
        _write(d / "cpu.max", "max 100000\n")
        _write(d / "memory.max", "max\n")
        _write(d / "memory.high", "max\n")
        _write(d / "memory.current", str(1 << 28))
    assert cgroup.cpu_quota(str(proc)) is None and cgroup.memory_headroom(str(proc)) is None
    _write(leaf / "cpu.max", "300000 100000\n")
    _write(fs / "user.slice/cpu.max", "100000 200000\n")  # half a CPU above the leaf's three
    assert cgroup.cpu_quota(str(proc)) == pytest.approx(0.5)
    _write(leaf / "memory.max", str(2 << 30))
    _write(leaf / "memory.high", str(1 << 30))  # throttled hard above it: the tighter counts
    _write(leaf / "memory.stat", f"anon 5\ninactive_file {1 << 27}\n")
    assert cgroup.memory_headroom(str(proc)) == (1 << 30) - (1 << 28) + (1 << 27)


def test_a_group_path_above_the_mount_is_the_mount(tmp_path):
    """``0::/../..`` (a process moved out of its namespace's root) must not climb above the mount,
    nor loop: the mount's own limits count."""
    fs, proc = tmp_path / "fs", tmp_path / "proc"
    _write(proc / "cgroup", "0::/../..\n")
    _write(proc / "mountinfo", f"40 31 0:38 / {fs} rw - cgroup2 cgroup2 rw\n")
    fs.mkdir(parents=True, exist_ok=True)
    _write(fs / "cpu.max", "100000 100000\n")
    (h,) = cgroup.hierarchies(str(proc))
    assert h.folders() == [str(fs)]
    assert cgroup.cpu_quota(str(proc)) == pytest.approx(1.0)
    assert cgroup.Hierarchy(2, frozenset(), str(fs), "/elsewhere").folders() == [str(fs)]


def test_nothing_readable_is_no_limit(tmp_path):
    assert cgroup.hierarchies(str(tmp_path / "nowhere")) == []
    assert cgroup.cpu_quota(str(tmp_path / "nowhere")) is None
    assert cgroup.memory_headroom(str(tmp_path / "nowhere")) is None
    proc = tmp_path / "proc"
    _write(proc / "cgroup", "garbage\n1:cpu:/x\n")
    _write(proc / "mountinfo", "not a mount line\n")
    assert cgroup.hierarchies(str(proc)) == []


def _v1_root() -> Path | None:
    """Where a test may make real v1 cpu and memory groups (root, both mounted), else None."""
    base = Path("/sys/fs/cgroup")
    if os.geteuid() != 0 or not (base / "cpu" / "cpu.cfs_quota_us").exists() \
            or not (base / "memory" / "memory.limit_in_bytes").exists():
        return None
    return base


def test_real_groups_limit_cores_and_memory(tmp_path):
    """In real v1 groups (1 CPU, 600 MB): cores() is 1, available_memory() below 600 MB and a
    render of 10 x 10 cilia gets one place, in a subprocess moved into them; the groups are
    removed after."""
    scene = tmp_path / "s.toml"
    scene.write_text('[carpet]\nshape = [10, 10]\ncoupling = "none"\n')  # one uncoupled place fits in 600 MB
    base = _v1_root()
    if base is None:
        pytest.skip("needs root and cgroup v1 cpu and memory controllers to make groups")
    name = f"cilia-test-{uuid.uuid4().hex[:8]}"
    cpu, mem = base / "cpu" / name, base / "memory" / name
    try:
        try:
            cpu.mkdir()
            mem.mkdir()
            (cpu / "cpu.cfs_period_us").write_text("100000")
            (cpu / "cpu.cfs_quota_us").write_text("100000")
            (mem / "memory.limit_in_bytes").write_text(str(600 << 20))
        except OSError as exc:
            pytest.skip(f"cannot make cgroups here: {exc}")
        code = ("import os, sys; pid = str(os.getpid());"
                f"open('{cpu}/cgroup.procs', 'w').write(pid); open('{mem}/cgroup.procs', 'w').write(pid);"
                "from cilia_runtime.threads import cores;"
                "from ciliary_carpet.output.resources import available_memory, places_that_fit;"
                "from ciliary_carpet.scenes.scene import load_scene;"
                f"print(cores(), available_memory(), places_that_fit(load_scene({str(scene)!r}).needs(), 2))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        n, avail, places = out.stdout.split()
        assert int(n) == 1
        assert 0 < float(avail) < 600 << 20
        # a 10 x 10 carpet: one place (about 0.46 GB with what the process holds) fits, two (0.70) do not
        assert int(places) == 1 and "instead of 2 processes" in out.stderr
    finally:
        for d in (cpu, mem):
            if d.exists():
                d.rmdir()  # empty again: the subprocess has ended


def _scene(tmp_path, text: str):
    from ciliary_carpet.scenes.scene import load_scene

    p = tmp_path / "s.toml"
    p.write_text(text)
    return load_scene(p)


def test_expected_memory_follows_the_measured_peaks(tmp_path):
    """At the measured sizes the estimate is the largest measured peak times the margin; it grows
    with the cilia and the places; a standing carpet takes more; a coupled carpet adds its table
    and trial carpets (the peaks were measured uncoupled)."""
    from ciliary_carpet.output import resources as r

    mib = 2.0 ** 20
    f = 80 * 80 * r._FIELD_BYTES_PER_POINT * r._PEAK_MARGIN  # the default field grid's part
    for n, one, two in r._PEAK_MIB:
        side = int(round(n ** 0.5))
        s = _scene(tmp_path, f"[carpet]\nshape = [{side}, {side}]\ncoupling = \"none\"\n")
        c = _scene(tmp_path, f"[carpet]\nshape = [{side}, {side}]\n")  # coupled: the default
        here, per_place, per_cilium = r._COUPLED_MIB
        for places in (1, 2, 3):
            assert r.expected_memory(c.needs(), places) - r.expected_memory(s.needs(), places) == pytest.approx(
                (here + (places - 1) * per_place + n * per_cilium) * r._PEAK_MARGIN * mib)
        assert r.expected_memory(s.needs(), 1) == pytest.approx(one * r._PEAK_MARGIN * mib + f)
        assert r.expected_memory(s.needs(), 2) == pytest.approx(two * r._PEAK_MARGIN * mib + f)
        assert r.expected_memory(s.needs(), 3) == pytest.approx((2 * two - one) * r._PEAK_MARGIN * mib + f)
    sizes = [4, 30, 60, 100, 150]
    one = [r.expected_memory(_scene(tmp_path, f"[carpet]\nshape = [{k}, {k}]\ncoupling = \"none\"\n").needs(), 1)
           for k in sizes]
    assert all(a <= b for a, b in zip(one, one[1:]))
    # beyond 10^4 cilia: the last slope, at least linear
    (n1, a1, _), (n2, a2, _) = r._PEAK_MIB[-2:]
    assert one[-1] == pytest.approx((a2 + (22500 - n2) * (a2 - a1) / (n2 - n1)) * r._PEAK_MARGIN * mib + f)
    planar = _scene(tmp_path, '[carpet]\nshape = [12, 12]\ncoupling = "none"\n')
    standing = _scene(tmp_path, '[carpet]\ngeometry = "standing"\nshape = [12, 12]\ncoupling = "none"\n')
    assert r.expected_memory(standing.needs(), 2) == pytest.approx(r._STANDING * (r.expected_memory(planar.needs(), 2) - f) + f)


def test_places_follow_the_memory_available(tmp_path, monkeypatch, caplog):
    from ciliary_carpet.output import resources as r

    s = _scene(tmp_path, "[carpet]\nshape = [10, 10]\n")
    one, two = r.expected_memory(s.needs(), 1), r.expected_memory(s.needs(), 2)
    monkeypatch.setattr(r, "_resident", lambda: 0.0)
    for avail, want in ((math.inf, 4), (two * 1.01, 2), (two * 0.99, 1), (one * 1.01, 1)):
        monkeypatch.setattr(r, "available_memory", lambda a=avail: a)
        caplog.clear()
        assert r.places_that_fit(s.needs(), 4 if math.isinf(avail) else 2) == want
        assert ("instead of 2 processes" in caplog.text) == (want == 1)
    monkeypatch.setattr(r, "available_memory", lambda: one * 0.5)
    caplog.clear()
    assert r.places_that_fit(s.needs(), 2) == 1
    assert "may be killed for want of memory" in caplog.text
    # what this process holds already counts as available: the estimate includes it
    monkeypatch.setattr(r, "available_memory", lambda: two * 0.6)
    monkeypatch.setattr(r, "_resident", lambda: two * 0.5)
    assert r.places_that_fit(s.needs(), 2) == 2


@pytest.mark.slow
def test_a_render_in_a_real_memory_limit_takes_one_place(tmp_path):
    """A render asked for 2 cores in a control group whose limit holds one place of the estimate but
    not two: it runs its path lines in its own process, says so, and finishes (before, it started a
    worker: the bundled focusing scene in a 560 MB group was killed at 17 s)."""
    base = _v1_root()
    if base is None:
        pytest.skip("needs root and cgroup v1 memory controller to make groups")
    from ciliary_carpet.output import resources as r

    name = f"cilia-test-{uuid.uuid4().hex[:8]}"
    mem = base / "memory" / name
    scene = tmp_path / "s.toml"
    scene.write_text("[carpet]\nshape = [3, 3]\n[output]\nn_seeds = 4\nperiods = 1\nfield_shape = [8, 8]\n"
                     "snapshots = 0\nframes = 2\npreview = false\n")
    s = r.expected_memory(_scene(tmp_path, "[carpet]\nshape = [3, 3]\n").needs(), 1)
    limit = int(s + 60 * 2 ** 20)  # one place and a little: two do not fit (two - one is about 240 MB)
    try:
        try:
            mem.mkdir()
            (mem / "memory.limit_in_bytes").write_text(str(limit))
        except OSError as exc:
            pytest.skip(f"cannot make cgroups here: {exc}")
        code = ("import os, sys; open(sys.argv[1], 'w').write(str(os.getpid()));"
                "from ciliary_carpet.cli import main; sys.exit(main(sys.argv[2:]))")
        out = subprocess.run([sys.executable, "-c", code, str(mem / "cgroup.procs"), "render", str(scene), "-o",
                              str(tmp_path / "out"), "--threads", "2", "--json"],
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        assert "path lines in this process alone instead of 2 processes" in out.stderr
        import json

        summ = json.loads((tmp_path / "out" / "summary.json").read_text())
        assert summ["pathlines"]["parallel"]["places"] == 1
        assert summ["threads"]["numba"] == 2  # the other stages keep their threads
    finally:
        if mem.exists():
            mem.rmdir()
