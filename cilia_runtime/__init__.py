"""The machinery under both packages: nothing here is about cilia or fluids.

``single_cilium`` (the filament) and ``ciliary_carpet`` (arrays of them) import this package; it
imports neither. A new piece of machinery (a scheduler, a way of writing files, a resource limit)
goes here when both layers need it, or when it would otherwise sit in a physics module.

Modules
-------
progress      Progress: the strategy object long computations report to (TqdmProgress draws a bar)
files         files written whole: a temporary name in the same folder, then an atomic rename
threads       ThreadBudget: workers x numba threads x BLAS threads within the cores
pool          where tasks run: this process, or worker processes (shared, or one per task)
blas          single_threaded_blas: one BLAS thread for small dense solves
cgroup        the CPU quota and memory limit of the control group this process runs in
signals       termination signals raised as exceptions, and held around critical sections
scheduler     the Dask scheduler address check and a distributed executor (the dask extra)
numba_cache   a writable cache folder for numba's compiled functions, damaged files discarded
"""
from .numba_cache import ensure_writable_cache as _ensure_writable_cache

_ensure_writable_cache(__path__[0])  # before any module compiles: a read-only install, an unwritable home

from .progress import Progress, TqdmProgress  # noqa: E402

__all__ = ["Progress", "TqdmProgress"]
