"""Atomic file output (write to a temporary name in the target folder, then rename) and strict JSON."""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np
import xarray as xr

__all__ = ["write_netcdf", "strict_json", "non_finite"]


def write_netcdf(ds: xr.Dataset, path) -> Path:
    """Write ``ds`` as NetCDF4/HDF5 (engine h5netcdf) to ``path`` atomically: readers never see
    a half-written file, and an existing file is replaced only once the new one is complete."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    try:
        ds.to_netcdf(tmp, engine="h5netcdf")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


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
