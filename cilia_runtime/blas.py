"""One BLAS thread for the solvers: the matrices here are small (tens to a few hundred rows),
where a multithreaded BLAS is slower than one thread, and parallelism is process-level."""
from __future__ import annotations

from functools import lru_cache

from threadpoolctl import ThreadpoolController

__all__ = ["single_threaded_blas"]


@lru_cache(maxsize=1)
def _controller() -> ThreadpoolController:
    return ThreadpoolController()  # scans the loaded libraries once


def single_threaded_blas():
    """Context manager limiting BLAS to one thread (cheap to enter repeatedly)."""
    return _controller().limit(limits=1, user_api="blas")
