"""A writable cache folder for numba's compiled functions, checked before anything compiles.

The packages compile with ``cache=True``. numba keeps the cache in the ``__pycache__`` next to the
source, else in the user's cache folder (``~/.cache/numba``), and raises at import time when
neither can be written -- a read-only install (a container image, a shared software tree) run
with an unwritable home, so that even ``--help`` would fail. :func:`ensure_writable_cache` falls
back to a temporary folder (``NUMBA_CACHE_DIR``) with one warning; the compiled functions are
then cached for the run only.

A cache file that cannot be read back (an index ``*.nbi`` or a data file ``*.nbc`` cut short by a
full disk or a killed process, or otherwise damaged) is a cache miss: the function is compiled
anew and numba's next save replaces the file, with one warning naming it. Without this numba
raises at the first call of the function (an ``UnpicklingError``), on every run.
"""
from __future__ import annotations

import atexit
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

__all__ = ["ensure_writable_cache", "tolerate_damaged_cache", "ENV"]

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
    one warning is logged. In every case a damaged cache file is then a cache miss
    (:func:`tolerate_damaged_cache`). Returns the temporary folder, or None.
    """
    try:
        return _ensure_writable(package_dir)
    finally:
        tolerate_damaged_cache()


def _ensure_writable(package_dir) -> Path | None:
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


_WARNED: set[str] = set()


def _discard(what: str, exc: BaseException) -> None:
    """One warning per damaged cache file (or function, when the file is not known)."""
    if what not in _WARNED:
        _WARNED.add(what)
        logger.warning("numba's cache %s could not be read (%s: %s); it is discarded and the function compiled "
                       "anew", what, type(exc).__name__, " ".join(str(exc).split())[:200])


def tolerate_damaged_cache() -> None:
    """Make a cache file numba cannot read back a cache miss instead of an error (idempotent).

    numba reads a function's index (``*.nbi``) and then its data file (``*.nbc``) at the first
    call; an error there (truncated or damaged files: ``UnpicklingError``, ``EOFError``, ...)
    would propagate to the caller on every run. Here a damaged index reads as empty and a damaged
    entry as missing: the function is compiled, and numba's save then replaces the damaged files
    (atomically). One warning per file. Errors of the compiled code itself are not touched.
    """
    from numba.core import caching

    index_file = caching.IndexDataCacheFile
    if getattr(index_file, "_cilia_tolerant", False):
        return
    load_index = index_file._load_index
    load_data = index_file._load_data
    load_overload = caching.Cache._load_overload

    def _load_index(self):
        try:
            return load_index(self)
        except Exception as exc:  # noqa: BLE001 -- any damage: the cache is only a cache
            _discard(str(self._index_path), exc)
            return {}

    def _load_data(self, name):
        try:
            return load_data(self, name)
        except OSError:
            raise  # a file removed meanwhile: numba's own miss
        except Exception as exc:  # noqa: BLE001
            _discard(str(self._data_path(name)), exc)
            raise OSError(f"damaged cache file {self._data_path(name)}") from None  # numba: a miss

    def _load_overload(self, sig, target_context):
        try:
            return load_overload(self, sig, target_context)
        except Exception as exc:  # noqa: BLE001 -- e.g. code that does not rebuild from its entry
            _discard(f"entry of {self._name}", exc)
            return None

    index_file._load_index = _load_index
    index_file._load_data = _load_data
    caching.Cache._load_overload = _load_overload
    index_file._cilia_tolerant = True
