"""A writable cache folder for numba's compiled functions, checked before anything compiles.

The packages compile with ``cache=True``. numba keeps the cache in the ``__pycache__`` next to the
source, else in the user's cache folder (``~/.cache/numba``), and raises at import time when
neither can be written -- a read-only install (a container image, a shared software tree) run
with an unwritable home: even ``--help`` failed. :func:`ensure_writable_cache` falls back to a
temporary folder (``NUMBA_CACHE_DIR``) with one warning; the compiled functions are then cached
for the run only.
"""
from __future__ import annotations

import atexit
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

__all__ = ["ensure_writable_cache", "ENV"]

logger = logging.getLogger(__name__)

ENV = "NUMBA_CACHE_DIR"


def _writable(folder: Path) -> bool:
    """Whether a file can be created in ``folder`` (made if missing) -- numba's own test."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _user_cache() -> Path:
    """numba's per-user cache folder (its ``appdirs`` rule, without importing numba)."""
    if sys.platform == "darwin":
        return Path("~/Library/Caches/numba").expanduser()
    if sys.platform.startswith("win"):
        return Path(os.environ.get("LOCALAPPDATA", "~")).expanduser() / "numba" / "numba" / "Cache"
    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "numba"


def ensure_writable_cache(package_dir) -> Path | None:
    """Make sure numba can cache the functions of the package in ``package_dir``.

    Nothing to do when ``NUMBA_CACHE_DIR`` is set, or ``package_dir/__pycache__`` or numba's
    user cache folder is writable. Otherwise ``NUMBA_CACHE_DIR`` is set (for this process, and
    inherited by its workers) to a new temporary folder, removed when this process exits, and
    one warning is logged. Returns the temporary folder, or None.
    """
    if os.environ.get(ENV):
        return None
    if _writable(Path(package_dir) / "__pycache__") or _writable(_user_cache()):
        return None
    tmp = tempfile.mkdtemp(prefix="cilia-numba-cache-")
    os.environ[ENV] = tmp
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba already imported: it read the environment then
        config.CACHE_DIR = tmp
    owner = os.getpid()
    atexit.register(lambda: os.getpid() == owner and shutil.rmtree(tmp, ignore_errors=True))
    logger.warning("numba cannot cache compiled code in %s nor in %s (read-only); using %s for this run (set %s "
                   "to a writable folder to keep the cache between runs)", Path(package_dir) / "__pycache__",
                   _user_cache(), tmp, ENV)
    return Path(tmp)
