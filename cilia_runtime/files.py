"""Atomic file output (write to a temporary name in the target folder, then rename) and strict JSON.

Files are made in memory first and written with plain :func:`os.write`: a full disk (or quota)
is then an ordinary error naming the file -- :class:`OutputFileError`, "no space left on
device" -- with the temporary removed and an existing file unchanged. (HDF5 writing straight to a
full disk prints pages of tracebacks and may crash the process.)
"""
from __future__ import annotations

import contextlib
import errno as _errno
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

__all__ = ["write_netcdf", "write_bytes", "OutputFileError", "strict_json", "non_finite", "usual_mode"]

_FULL = (_errno.ENOSPC, getattr(_errno, "EDQUOT", _errno.ENOSPC), _errno.EFBIG)


class OutputFileError(OSError):
    """A file that could not be written; ``str()`` is one line naming it and the reason.

    Parameters
    ----------
    path : path-like
        The file that was to be written.
    reason : str
        Why not (``"no space left on device"``, ``"Permission denied"``, ...).
    errno : int, optional
        The operating system's error number.
    """

    def __init__(self, path, reason: str, errno: int | None = None) -> None:
        super().__init__(f"cannot write '{path}': {reason}")
        self.path = Path(path)
        self.reason = str(reason)
        self.errno = errno
        self.filename = str(path)

    def __str__(self) -> str:
        return f"cannot write '{self.path}': {self.reason}"

    def __reduce__(self):  # picklable (raised in pool and Dask workers)
        return (type(self), (self.path, self.reason, self.errno))


def reason(err: OSError) -> str:
    """What went wrong in ``err``, in words: ``"no space left on device"`` for a full disk or
    quota (and a file too large for the file system), else the system's message."""
    if err.errno in _FULL:
        return "no space left on device (free some space, or write elsewhere)"
    return err.strerror or " ".join(str(err).split()) or type(err).__name__


def usual_mode(executable: bool = False) -> int:
    """The permissions a new file (or, ``executable``, folder) gets under the current umask
    (:func:`tempfile.mkstemp` and :func:`tempfile.mkdtemp` make them private: 0600, 0700)."""
    umask = os.umask(0)
    os.umask(umask)
    return (0o777 if executable else 0o666) & ~umask


def write_bytes(path, data) -> Path:
    """Write ``data`` (bytes-like) to ``path`` atomically: to a hidden temporary in the same
    folder with :func:`os.write`, then renamed onto ``path``. Raises :class:`OutputFileError`
    (naming ``path``) when the folder or the file cannot be written -- a full disk included --
    after removing the temporary; an existing ``path`` is then unchanged."""
    path = Path(path)
    view = memoryview(data).cast("B")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    except OSError as err:
        raise OutputFileError(path, reason(err), err.errno) from None
    try:
        try:
            while view.nbytes:
                n = os.write(fd, view)
                view = view[n:]
        finally:
            os.close(fd)
        os.chmod(tmp, usual_mode())  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except OSError as err:
        Path(tmp).unlink(missing_ok=True)
        raise OutputFileError(path, reason(err), err.errno) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_netcdf(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` as NetCDF4/HDF5 (engine h5netcdf) to ``path`` atomically: readers never see
    a half-written file, and an existing file is replaced only once the new one is complete.
    The file is made in memory and written by :func:`write_bytes`: a full disk is an
    :class:`OutputFileError` naming ``path`` ("no space left on device"), never a crash.

    On a Dask worker xarray guards a file it writes with a lock of the cluster named by the file,
    here the in-memory buffer, which the scheduler does not know, so that the write would fail
    ("RuntimeError: Semaphore or Lock `<_io.BytesIO ...>` not known"). Nothing else writes that
    buffer, so the write takes a lock of this process (dask's synchronous scheduler while it
    runs; without dask, xarray takes a lock of this process anyway)."""
    try:
        import dask

        synchronous = dask.config.set(scheduler="synchronous")
    except ImportError:  # dask is an optional extra
        synchronous = contextlib.nullcontext()
    path = Path(path)
    if path.is_dir():
        raise OutputFileError(path, "it is a folder")
    with synchronous:
        data = ds.to_netcdf(engine="h5netcdf")
    return write_bytes(path, data)


def _plain(v, path: str, bad: dict):
    """``v`` as plain JSON types; non-finite floats become None and are noted in ``bad``."""
    if isinstance(v, dict):
        return {str(k): _plain(x, f"{path}.{k}" if path else str(k), bad) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x, f"{path}[{i}]", bad) for i, x in enumerate(v.tolist() if isinstance(v, np.ndarray) else v)]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        x = float(v)
        if not math.isfinite(x):
            bad[path] = "NaN (undefined or not computed)" if math.isnan(x) else ("+inf" if x > 0 else "-inf")
            return None
        return x
    if isinstance(v, (complex, np.complexfloating)):
        return [_plain(v.real, f"{path}.real", bad), _plain(v.imag, f"{path}.imag", bad)]
    if v is None or isinstance(v, str):
        return v
    return str(v)  # paths and other scalars: their text


def non_finite(obj) -> dict:
    """``{dotted.path: what}`` for every NaN or infinity in ``obj`` (nested dicts, lists, arrays)."""
    bad: dict = {}
    _plain(obj, "", bad)
    return bad


def strict_json(obj, **kwargs) -> str:
    """``obj`` as strict JSON (RFC 8259: no NaN or Infinity tokens). Non-finite numbers are
    written as ``null``, and a top-level dict gains ``"non_finite": {path: "NaN (...)" | "+inf"
    | "-inf"}`` saying which values were nulled and why. numpy scalars and arrays become numbers
    and lists, complex numbers ``[re, im]``, anything else its ``str``."""
    bad: dict = {}
    out = _plain(obj, "", bad)
    if bad and isinstance(out, dict):
        out["non_finite"] = bad
    return json.dumps(out, allow_nan=False, **kwargs)
