"""The limits a Linux control group puts on this process: its CPU quota and its memory.

A container (``docker run --cpus 2 --memory 4g``, a Kubernetes pod) or a batch job (Slurm with
``--mem``) runs its processes in a control group that caps their CPU time and memory, while the
machine's core count (``os.cpu_count``, the CPU affinity) and ``/proc/meminfo`` still show the
whole host. Sized from the host, a render would run numba's parallel regions on as many threads
as the host has cores, not as the quota allows (each parallel region's barrier waiting for
descheduled threads), and a batch would start as many workers as the host's memory holds,
which the kernel kills (SIGKILL, no message) when the group's memory runs out.

:func:`cpu_quota` and :func:`memory_headroom` read the limits of this process's group and of every
group above it (the tightest counts), for both versions of the interface:

* cgroup v1 (a mount per controller, e.g. ``/sys/fs/cgroup/cpu`` or ``/sys/fs/cgroup/cpu,cpuacct``):
  ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (-1: none), ``memory.limit_in_bytes`` and
  ``memory.usage_in_bytes``;
* cgroup v2 (one ``cgroup2`` mount): ``cpu.max`` (``"max 100000"``: none), ``memory.max`` and
  ``memory.high`` (``"max"``: none; above ``memory.high`` the kernel throttles the group hard, so
  it counts as a limit too) and ``memory.current``.

The group's usage counts the page cache of the files its processes wrote; the kernel reclaims
the inactive part of it before it kills anything, so the headroom is the limit less the usage
less the inactive file pages (``total_inactive_file`` / ``inactive_file`` of ``memory.stat``:
the working set, as Kubernetes counts it). The group paths come from ``/proc/self/cgroup``,
relative to each hierarchy's mount root (``/proc/self/mountinfo``); in a container with its own
cgroup namespace the group is the mount's root. Where nothing can be read (not Linux, no cgroup
mounted, files unreadable) there is no limit: both return None.

dask's ``dask.system.cpu_count`` reads a v2 quota of the process's own group, and a v1 quota only
at the root of a mount named ``cpu,cpuacct``; where the v1 mounts are ``cpu`` and ``cpuacct``
apart, or a job's group is not a mount's root (the usual case), it does not see the v1 quota.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

__all__ = ["Hierarchy", "hierarchies", "cpu_quota", "memory_headroom"]

_NO_LIMIT_V1 = 2 ** 62  # v1 writes "no limit" as a page-rounded 2^63 - 1 (9223372036854771712)


@dataclass(frozen=True)
class Hierarchy:
    """One mounted cgroup hierarchy that this process belongs to: ``version`` 1 or 2, the
    ``controllers`` it carries (v1; empty for v2), where it is mounted (``mount``), and this
    process's group in it, as a folder (``group``, under ``mount``)."""

    version: int
    controllers: frozenset
    mount: str
    group: str

    def folders(self) -> list[str]:
        """The group's folder and those above it, up to the mount's root (innermost first)."""
        mount, d = os.path.normpath(self.mount), os.path.normpath(self.group)
        if os.path.commonpath([mount, d]) != mount:  # not under the mount: the mount alone
            return [self.mount]
        out = [d]
        while d != mount:
            d = os.path.dirname(d)
            out.append(d)
        return out


def _read(path: str) -> str | None:
    try:
        with open(path) as fh:
            return fh.read().strip()
    except (OSError, UnicodeDecodeError):
        return None


def hierarchies(proc: str = "/proc/self") -> list[Hierarchy]:
    """The cgroup hierarchies of this process (``proc``: its ``/proc`` folder; another for tests),
    from ``cgroup`` (``ID:CONTROLLERS:PATH`` lines) and ``mountinfo`` (where each is mounted,
    and the path within the hierarchy of the mount's root). A group outside its mount's root
    (a container that sees the host's paths) is taken to be the mount's root. [] where the files
    cannot be read."""
    groups = _read(os.path.join(proc, "cgroup"))
    mounts = _read(os.path.join(proc, "mountinfo"))
    if groups is None or mounts is None:
        return []
    v1: dict[str, tuple[str, str]] = {}  # controller -> (mount point, mount root)
    v2: tuple[str, str] | None = None
    for line in mounts.splitlines():
        left, sep, right = line.partition(" - ")
        if not sep:
            continue
        f, r = left.split(), right.split()
        if len(f) < 5 or len(r) < 3:
            continue
        root, point = _unescape(f[3]), _unescape(f[4])
        if r[0] == "cgroup2":
            v2 = (point, root)
        elif r[0] == "cgroup":
            for opt in r[2].split(","):
                v1.setdefault(opt, (point, root))
    out = []
    for line in groups.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, ctrl, path = parts
        if ctrl == "":
            if v2 is None:
                continue
            point, root = v2
            out.append(Hierarchy(2, frozenset(), point, _inside(point, root, path)))
        else:
            names = frozenset(c for c in ctrl.split(",") if c)
            where = next((v1[c] for c in names if c in v1), None)
            if where is None:
                continue
            point, root = where
            out.append(Hierarchy(1, names, point, _inside(point, root, path)))
    return out


def _unescape(s: str) -> str:
    """mountinfo's octal escapes (a space is ``\\040``)."""
    return s.replace("\\040", " ").replace("\\011", "\t").replace("\\012", "\n").replace("\\134", "\\")


def _inside(point: str, root: str, path: str) -> str:
    """The folder of group ``path`` under a mount of hierarchy path ``root`` at ``point``."""
    root = root.rstrip("/") or "/"
    if root != "/" and not (path == root or path.startswith(root + "/")):
        return point
    rel = path[len(root):] if root != "/" else path
    rel = rel.lstrip("/")
    folder = os.path.normpath(os.path.join(point, rel)) if rel else point
    # a path such as "/../.." (a process moved out of a namespace's root) would climb above it
    inside = os.path.commonpath([os.path.normpath(point), folder]) == os.path.normpath(point)
    return folder if inside and os.path.isdir(folder) else point


def cpu_quota(proc: str = "/proc/self") -> float | None:
    """The CPUs' worth of time this process's groups allow (quota / period, the tightest along
    the hierarchy; 1.5 for ``--cpus 1.5``), or None where no quota is set or none can be read."""
    best = math.inf
    for h in hierarchies(proc):
        if h.version == 1 and "cpu" not in h.controllers:
            continue
        for d in h.folders():
            if h.version == 1:
                q, p = _int(_read(os.path.join(d, "cpu.cfs_quota_us"))), _int(_read(os.path.join(d, "cpu.cfs_period_us")))
            else:
                text = _read(os.path.join(d, "cpu.max"))
                q = p = None
                if text:
                    w = text.split()
                    q = _int(w[0])
                    p = _int(w[1]) if len(w) > 1 else 100000
            if q is not None and p and q > 0 and p > 0:
                best = min(best, q / p)
    return None if math.isinf(best) else best


def memory_headroom(proc: str = "/proc/self") -> float | None:
    """Bytes this process's groups can still take before the tightest of their limits: per group
    along each hierarchy, the limit less the usage less the inactive file pages (which the kernel
    reclaims first); None where no limit is set or none can be read."""
    best = math.inf
    for h in hierarchies(proc):
        if h.version == 1 and "memory" not in h.controllers:
            continue
        for d in h.folders():
            if h.version == 1:
                limits = [_int(_read(os.path.join(d, "memory.limit_in_bytes")))]
                used = _int(_read(os.path.join(d, "memory.usage_in_bytes")))
                inactive = _stat(d, "total_inactive_file")
                if inactive is None:
                    inactive = _stat(d, "inactive_file")
            else:
                limits = [_int(_read(os.path.join(d, f))) for f in ("memory.max", "memory.high")]
                used = _int(_read(os.path.join(d, "memory.current")))
                inactive = _stat(d, "inactive_file")
            limits = [v for v in limits if v is not None and 0 < v < _NO_LIMIT_V1]
            if not limits:
                continue
            working = max(0, (used or 0) - (inactive or 0))
            best = min(best, max(0.0, float(min(limits) - working)))
    return None if math.isinf(best) else best


def _int(text: str | None) -> int | None:
    if text is None or text == "max":
        return None
    try:
        return int(text.split()[0])
    except (ValueError, IndexError):
        return None


def _stat(folder: str, key: str) -> int | None:
    text = _read(os.path.join(folder, "memory.stat"))
    if not text:
        return None
    for line in text.splitlines():
        k, _, v = line.partition(" ")
        if k == key:
            return _int(v)
    return None
