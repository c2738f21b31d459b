"""The carpet's outputs as VTK XML files for ParaView, written atomically.

Plain numpy arrays in, files out: path lines of tracers and cilium centre lines as PolyData
(``.vtp``), velocity fields on regular grids as ImageData (``.vti``), point clouds such as the
carpet layout as PolyData of vertices, and ParaView collections (``.pvd``) that put a series of
files on a time axis.

Conventions
-----------
* Coordinates are (x, y, z) with the carpet in the plane z = 0; units are whatever the caller
  uses (dimensionless or SI), the files do not record them.
* Geometry (points, grid origin and spacing) and path line times must be finite: a ``NaN``
  there raises :class:`ValueError` naming the argument. Data arrays (velocities, drag, any
  field array) may hold ``NaN`` (e.g. to blank grid points inside a cilium's swept region);
  VTK stores them as they are.
* A single file carrying a time stores it as the one-value float64 field data array
  ``"TimeValue"``, which VTK's XML readers (and so ParaView) report as the file's time.
* Grid point order is VTK's: x fastest, then y, then z; the point ``(i, j, k)`` of a grid of
  ``shape = (nx, ny, nz)`` points has index ``i + nx * (j + ny * k)``. :func:`grid_points`
  returns the coordinates in that order, so that ``u(grid_points(...))`` is ready to write.

Every writer validates its input, makes the file in memory (VTK's writers write to a string),
creates the parent folder if needed, writes the bytes with :func:`os.write` to a hidden temporary
file in the target folder and renames it onto the target with :func:`os.replace`: readers never
see a half-written file, and on any failure the temporary is removed and an existing target is
left untouched. A folder or file that cannot be written -- a full disk included -- raises
:class:`OutputError`, one line naming the file and the reason ("no space left on device").

One concept over 500 lines: the VTK writers, one per kind of data set, sharing the checks and the
atomic write above.
"""
from __future__ import annotations

import io
import logging
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyvista as pv
from vtkmodules.vtkIOXML import vtkXMLImageDataWriter, vtkXMLPolyDataWriter, vtkXMLWriterBase

from single_cilium.checks import finite
from cilia_runtime.files import OutputFileError, write_bytes

logger = logging.getLogger(__name__)

__all__ = [
    "OutputError",
    "PvdEntry",
    "grid_points",
    "write_pathlines",
    "write_field",
    "write_cilia",
    "write_points",
    "write_pvd",
]

_INT32 = np.iinfo(np.int32)


class OutputError(OutputFileError):
    """An output path that cannot be written: :class:`cilia_runtime.files.OutputFileError` (one line
    naming the file and the reason; ``path``, ``reason``, ``errno``; picklable) under the name the
    carpet layer's callers catch."""


@dataclass(frozen=True)
class PvdEntry:
    """One data set of a ParaView collection.

    Parameters
    ----------
    time : float
        The time step (finite).
    file : str or Path
        The data set's file; must exist inside the ``.pvd``'s folder (or a subfolder).
    part : int, default 0
        The part index (several files at one time step, e.g. cilia and path lines).
    """

    time: float
    file: str | Path
    part: int = 0

    def __post_init__(self) -> None:
        t = finite("time", self.time)
        part = _int_scalar("part", self.part)
        if part < 0:
            raise ValueError(f"part must be >= 0, got {part}")
        object.__setattr__(self, "time", t)
        object.__setattr__(self, "file", Path(self.file))
        object.__setattr__(self, "part", part)


# --------------------------------------------------------------------------------------------
# validation


def _int_scalar(name: str, value) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    return int(value)


def _float_array(name: str, value, shape: tuple, *, finite: bool) -> np.ndarray:
    """``value`` as float64 of ``shape`` (``None`` entries: any length >= 1)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an array of real numbers") from None
    want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
    if a.ndim != len(shape) or any(s is not None and d != s for d, s in zip(a.shape, shape)):
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if any(s is None and d < 1 for d, s in zip(a.shape, shape)):
        raise ValueError(f"{name} must not be empty, got shape {a.shape}")
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite ({int(np.sum(~np.isfinite(a)))} values are not)")
    return a


def _int32_array(name: str, value, n: int) -> np.ndarray:
    a = np.asarray(value)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    if a.dtype.kind not in "iu":
        if a.dtype.kind == "f" and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
            pass  # integral floats are accepted
        else:
            raise ValueError(f"{name} must hold integers, got dtype {a.dtype}")
    if n and (a.min() < _INT32.min or a.max() > _INT32.max):
        raise ValueError(f"{name} must fit in 32-bit integers")
    return a.astype(np.int32)


def _data_array(name: str, value, n: int) -> np.ndarray:
    """A point data array: (n,) or (n, k), numeric (bool stored as uint8)."""
    a = np.asarray(value)
    if a.ndim not in (1, 2) or a.shape[0] != n or (a.ndim == 2 and a.shape[1] < 1):
        raise ValueError(f"array {name!r} must have shape ({n},) or ({n}, k), got {a.shape}")
    kind = a.dtype.kind
    if kind == "b":
        return a.astype(np.uint8)
    if kind == "f" and a.dtype.itemsize < 4:
        return a.astype(np.float32)
    if kind not in "iuf":
        raise ValueError(f"array {name!r} must be real numbers, got dtype {a.dtype}")
    return np.ascontiguousarray(a)


def _data_arrays(arrays: Mapping[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    if not isinstance(arrays, Mapping):
        raise ValueError(f"arrays must be a mapping name -> array, got {type(arrays).__name__}")
    out = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"arrays: names must be non-empty strings, got {name!r}")
        out[name] = _data_array(name, value, n)
    return out


def _grid(origin, spacing, shape) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    o = _float_array("origin", origin, (3,), finite=True)
    h = _float_array("spacing", spacing, (3,), finite=True)
    if np.any(h <= 0):
        raise ValueError(f"spacing must be > 0, got {h.tolist()}")
    try:
        dims = tuple(shape)
    except TypeError:
        raise ValueError(f"shape must be three point counts (nx, ny, nz), got {shape!r}") from None
    if len(dims) != 3:
        raise ValueError(f"shape must be three point counts (nx, ny, nz), got {shape!r}")
    dims = tuple(_int_scalar("shape", d) for d in dims)
    if min(dims) < 1:
        raise ValueError(f"shape must be >= 1 along every axis, got {dims}")
    return o, h, dims  # type: ignore[return-value]


def _time_value(time) -> float | None:
    return None if time is None else finite("time", time)


def _check_suffix(path, ext: str) -> Path:
    path = Path(path)
    if path.suffix.lower() != ext:
        raise ValueError(f"path must end in {ext}, got '{path}'")
    return path


# --------------------------------------------------------------------------------------------
# atomic output


def _atomic_write(path: Path, make: Callable[[], bytes]) -> Path:
    """Write the bytes ``make()`` returns to ``path`` atomically
    (:func:`cilia_runtime.files.write_bytes`: a hidden temporary in ``path``'s folder, plain
    :func:`os.write`, then a rename).

    Raises OutputError (naming ``path``) when the folder or the file cannot be written (a full
    disk: "no space left on device") or VTK cannot make the file; any other exception from
    ``make`` propagates. Either way no temporary is left and an existing ``path`` is unchanged.
    """
    try:
        data = make()
    except pv.VTKExecutionError as err:
        lines = [ln.strip() for ln in str(err).splitlines() if "): " in ln]  # "vtkX (0x..): msg"
        detail = "; ".join(ln.split("): ", 1)[1] for ln in lines[:2]) or " ".join(str(err).split())
        raise OutputError(path, f"VTK could not write the file ({detail})") from None
    if not data:
        raise OutputError(path, "the writer produced an empty file")
    try:
        write_bytes(path, data)
    except OSError as err:
        raise OutputError(path, getattr(err, "reason", None) or err.strerror or str(err), err.errno) from None
    logger.debug("wrote %s", path)
    return path


COMPRESSION = vtkXMLWriterBase.LZ4
"""The compressor of the VTK XML files: VTK's LZ4 (VTK >= 8.1; Debian's ParaView 5.11 opens every
file of a render, tests/test_paraview.py). Measured on a 30 x 30 carpet's cilia frame (58 500 points,
the data then base64-encoded), 19 ms and 3.2 MB against zlib's 67 ms and 2.6 MB (uncompressed 23 ms,
5.0 MB)."""


_XML_WRITERS = {".vtp": vtkXMLPolyDataWriter, ".vti": vtkXMLImageDataWriter}
"""VTK's XML writer of each file extension the writers make (PolyData, ImageData)."""


def _mesh_bytes(mesh: pv.DataObject, path: Path) -> bytes:
    """The VTK XML file of ``mesh`` (binary, :data:`COMPRESSION`, the appended data raw), made in
    memory by VTK's XML writer of ``path``'s extension (:data:`_XML_WRITERS`). VTK's errors raise
    ``pv.VTKExecutionError``.

    Raw, not base64-encoded (what ``mesh.save(path, binary=True)`` writes): a frame of 10^4 cilia
    (650 000 points) took 0.38 s and 45.7 MB encoded, 0.11 s and 34.3 MB raw (the same data;
    Debian's ParaView reads both, tests/test_paraview.py). VTK's Python wrapping returns the
    string as ``bytes`` when it is not valid UTF-8, else as ``str``, whose UTF-8 encoding is the
    same bytes."""
    writer = _XML_WRITERS[path.suffix.lower()]()
    writer.SetFileName(str(path))
    writer.SetInputData(mesh)
    writer.SetCompressorType(COMPRESSION)
    writer.SetDataModeToAppended()  # one raw block after the XML (inline binary data is base64)
    writer.EncodeAppendedDataOff()
    writer.WriteToOutputStringOn()
    with pv.VtkErrorCatcher(raise_errors=True, send_to_logging=False):
        writer.Write()
    out = writer.GetOutputString()
    return out if isinstance(out, bytes) else out.encode("utf-8", "surrogateescape")


def _save_mesh(mesh: pv.DataObject, path: Path) -> Path:
    """Write ``mesh`` (binary, :data:`COMPRESSION`) atomically; the writer is picked from ``path``'s extension."""
    return _atomic_write(path, lambda: _mesh_bytes(mesh, path))


# --------------------------------------------------------------------------------------------
# writers


def grid_points(origin, spacing, shape) -> np.ndarray:
    """The points of a regular grid in VTK order, for evaluating fields to pass to :func:`write_field`.

    Parameters
    ----------
    origin : (3,) array_like
        Coordinates of the point ``(0, 0, 0)``.
    spacing : (3,) array_like
        Distance between neighbouring points along x, y, z (> 0).
    shape : (nx, ny, nz) ints
        Number of points along x, y, z (>= 1 each; use ``nz = 1`` for a plane z = const).

    Returns
    -------
    (nx * ny * nz, 3) ndarray of float64
        Row ``i + nx * (j + ny * k)`` is ``origin + (i, j, k) * spacing``: x fastest, then y,
        then z. A field held as an array indexed ``[i, j, k]`` (shape ``(nx, ny, nz)``, or
        ``(nx, ny, nz, 3)`` for vectors) is brought to this order by
        ``a.reshape(n, order="F")`` (``a.reshape(n, 3, order="F")``), ``n = nx * ny * nz``.

    Raises
    ------
    ValueError
        Naming the argument, if it has the wrong shape, is not finite, or spacing <= 0.
    """
    o, h, (nx, ny, nz) = _grid(origin, spacing, shape)
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(np.float64)
    return o + ijk * h


def write_pathlines(path, points: Sequence[np.ndarray], times: Sequence[np.ndarray],
                    velocities: Sequence[np.ndarray], seed_ids, reasons,
                    reason_names: Sequence[str]) -> Path:
    """Write tracer path lines as a ``.vtp``: one polyline cell per tracer.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.vtp``.
    points : sequence of K arrays (n_k, 3)
        Positions along each tracer's path, in time order; n_k >= 1 (a tracer that never
        moved is a polyline of one point). K >= 1.
    times : sequence of K arrays (n_k,)
        Time at each point (finite).
    velocities : sequence of K arrays (n_k, 3)
        Fluid velocity at each point.
    seed_ids : (K,) array_like of int
        Index of each tracer's seed (32-bit).
    reasons : (K,) array_like of int
        Why each tracer stopped: a code ``0 <= c < len(reason_names)``.
    reason_names : sequence of str
        ``reason_names[c]`` names code ``c`` (ASCII, non-empty), e.g.
        ``ciliary_carpet.transport.pathlines.REASONS``.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Arrays in the file, with ParaView's names where it has one: point data ``"time"``
    (float64), ``"IntegrationTime"`` (time since the tracer's first point, as vtkStreamTracer and
    ParticlePath name it), ``"velocity"`` (3 components, float64; the active vectors, so that
    Glyph orients by it) and ``"speed"`` (``|velocity|``); cell data ``"SeedIds"`` (int32) and
    ``"TerminationReason"`` (int32 codes of our own, deliberately not VTK's
    ``ReasonForTermination``, whose codes mean other things), decoded by the field data string
    array ``"TerminationReasonNames"`` (entry c names code c). Points of tracer k are stored
    consecutively, after those of tracers 0 .. k-1, and polyline k lists them in order.

    Raises
    ------
    ValueError
        Naming the argument, on a wrong shape or length, a non-finite point or time, a code
        outside ``reason_names``, or a bad extension.
    OutputError
        If the file cannot be written.
    """
    path = _check_suffix(path, ".vtp")
    pts, ts, vs = list(points), list(times), list(velocities)
    K = len(pts)
    if K < 1:
        raise ValueError("points must hold at least one tracer")
    if len(ts) != K:
        raise ValueError(f"times must hold one array per tracer ({K}), got {len(ts)}")
    if len(vs) != K:
        raise ValueError(f"velocities must hold one array per tracer ({K}), got {len(vs)}")
    pts = [_float_array(f"points[{k}]", p, (None, 3), finite=True) for k, p in enumerate(pts)]
    n = np.array([len(p) for p in pts], dtype=np.int64)
    ts = [_float_array(f"times[{k}]", t, (n[k],), finite=True) for k, t in enumerate(ts)]
    vs = [_float_array(f"velocities[{k}]", v, (n[k], 3), finite=False) for k, v in enumerate(vs)]
    seeds = _int32_array("seed_ids", seed_ids, K)
    codes = _int32_array("reasons", reasons, K)
    if isinstance(reason_names, (str, bytes, Mapping)) or not isinstance(reason_names, Iterable):
        raise ValueError("reason_names must be a sequence of strings (code -> name)")
    names = list(reason_names)
    for c, name in enumerate(names):
        if not isinstance(name, str) or not name or not name.isascii():
            raise ValueError(f"reason_names[{c}] must be a non-empty ASCII string, got {name!r}")
    bad = (codes < 0) | (codes >= len(names))
    if np.any(bad):
        raise ValueError(f"reasons must be codes in [0, {len(names)}) (len(reason_names)); "
                         f"tracer {int(np.argmax(bad))} has {int(codes[bad][0])}")

    offsets = np.concatenate([[0], np.cumsum(n)])
    # lines= in the constructor: PolyData(points) alone would add one vertex cell per point
    mesh = pv.PolyData(np.concatenate(pts),
                       lines=pv.CellArray.from_arrays(offsets, np.arange(offsets[-1]), deep=True))
    velocity = np.concatenate(vs)
    mesh.point_data["time"] = np.concatenate(ts)
    mesh.point_data["IntegrationTime"] = np.concatenate([t - t[0] for t in ts])
    mesh.point_data["velocity"] = velocity
    mesh.point_data.active_vectors_name = "velocity"
    mesh.point_data["speed"] = np.linalg.norm(velocity, axis=1)
    mesh.cell_data["SeedIds"] = seeds
    mesh.cell_data["TerminationReason"] = codes
    mesh.field_data["TerminationReasonNames"] = names
    logger.debug("writing %d path lines (%d points) to %s", K, int(offsets[-1]), path)
    return _save_mesh(mesh, path)


def write_field(path, origin, spacing, shape, arrays: dict[str, np.ndarray], *,
                time: float | None = None) -> Path:
    """Write fields sampled on a regular grid as a ``.vti`` (ImageData).

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.vti``.
    origin : (3,) array_like
        Coordinates of the grid point ``(0, 0, 0)``.
    spacing : (3,) array_like
        Grid spacing along x, y, z (> 0).
    shape : (nx, ny, nz) ints
        Number of points along x, y, z (>= 1 each).
    arrays : dict str -> array
        Point data, each ``(n,)`` or ``(n, k)`` with ``n = nx * ny * nz`` in VTK point order
        (x fastest: point ``(i, j, k)`` is row ``i + nx * (j + ny * k)``; evaluate on
        :func:`grid_points` to get it). Typically ``"velocity"`` (n, 3; made the active
        vectors), ``"speed"`` (n,) and ``"vorticity"``.
        Integer and float dtypes are kept; bool is stored as uint8. ``NaN`` is allowed.
    time : float, optional
        Stored as field data ``"TimeValue"``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        Naming the argument or array, on a wrong shape, non-finite origin/spacing/time,
        spacing <= 0, a non-numeric array, or a bad extension.
    OutputError
        If the file cannot be written.
    """
    path = _check_suffix(path, ".vti")
    o, h, dims = _grid(origin, spacing, shape)
    n = dims[0] * dims[1] * dims[2]
    data = _data_arrays(arrays, n)
    t = _time_value(time)

    grid = pv.ImageData(dimensions=dims, spacing=tuple(h), origin=tuple(o))
    for name, a in data.items():
        grid.point_data[name] = a
    if "velocity" in data and data["velocity"].ndim == 2 and data["velocity"].shape[1] == 3:
        grid.point_data.active_vectors_name = "velocity"
    if t is not None:
        grid.field_data["TimeValue"] = np.array([t])
    logger.debug("writing a %d x %d x %d grid (%s) to %s", *dims, ", ".join(data) or "no arrays", path)
    return _save_mesh(grid, path)


def write_cilia(path, shapes, s, cilium_ids, chi_N, phase, *, drag=None,
                time: float | None = None) -> Path:
    """Write cilium centre lines as a ``.vtp``: one polyline cell per cilium.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.vtp``.
    shapes : (C, n_s, 3) array_like
        Centre line of cilium c at the arc lengths ``s``, base first (finite). C >= 1, n_s >= 1.
    s : (n_s,) array_like
        Arc length of the samples (finite).
    cilium_ids : (C,) array_like of int
        Each cilium's index in the carpet (32-bit).
    chi_N : (C,) array_like
        Natural curvature ``L kappa_N`` of each cilium (finite).
    phase : (C,) array_like
        Phase of each cilium's beat, a fraction of a cycle in [0, 1). Exactly 1 (which
        ``np.mod(x, 1.0)`` returns for tiny negative ``x``) is stored as 0.
    drag : (C, n_s, 3) array_like, optional
        Force density the cilia exert on the fluid, at each sample.
    time : float, optional
        Stored as field data ``"TimeValue"``.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Arrays in the file: cell data ``"cilium_id"`` (int32), ``"chi_N"`` and ``"phase"``
    (float64); point data ``"arc_length"`` (float64) and, when ``drag`` is given,
    ``"drag_density"`` (3 components). Point ``c * n_s + i`` is ``shapes[c, i]``.

    Raises
    ------
    ValueError
        Naming the argument, on a wrong shape, non-finite geometry, parameters or time, a
        phase outside [0, 1], or a bad extension.
    OutputError
        If the file cannot be written.
    """
    path = _check_suffix(path, ".vtp")
    X = _float_array("shapes", shapes, (None, None, 3), finite=True)
    C, n_s, _ = X.shape
    arc = _float_array("s", s, (n_s,), finite=True)
    ids = _int32_array("cilium_ids", cilium_ids, C)
    chi = _float_array("chi_N", chi_N, (C,), finite=True)
    ph = _float_array("phase", phase, (C,), finite=True)
    if np.any((ph < 0) | (ph > 1)):
        raise ValueError(f"phase must be in [0, 1), got values in [{ph.min()}, {ph.max()}]")
    ph = np.where(ph == 1.0, 0.0, ph)
    f = None if drag is None else _float_array("drag", drag, (C, n_s, 3), finite=False)
    t = _time_value(time)

    mesh = pv.PolyData(X.reshape(C * n_s, 3),
                       lines=pv.CellArray.from_arrays(np.arange(C + 1) * n_s, np.arange(C * n_s), deep=True))
    mesh.cell_data["cilium_id"] = ids
    mesh.cell_data["chi_N"] = chi
    mesh.cell_data["phase"] = ph
    mesh.point_data["arc_length"] = np.tile(arc, C)
    if f is not None:
        mesh.point_data["drag_density"] = f.reshape(C * n_s, 3)
    if t is not None:
        mesh.field_data["TimeValue"] = np.array([t])
    logger.debug("writing %d cilia (%d samples each) to %s", C, n_s, path)
    return _save_mesh(mesh, path)


def write_points(path, points, arrays: dict[str, np.ndarray]) -> Path:
    """Write a point cloud as a ``.vtp`` of vertices (one vertex cell per point).

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.vtp``.
    points : (n, 3) array_like
        Coordinates (finite), n >= 1; e.g. the carpet's bases ``(x, y, 0)``.
    arrays : dict str -> array
        Point data, each ``(n,)`` or ``(n, k)``, e.g. ``{"chi_N": ..., "cilium_id": ...}``.
        Integer and float dtypes are kept; bool is stored as uint8.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        Naming the argument or array, on a wrong shape, non-finite points, a non-numeric array,
        or a bad extension.
    OutputError
        If the file cannot be written.
    """
    path = _check_suffix(path, ".vtp")
    X = _float_array("points", points, (None, 3), finite=True)
    data = _data_arrays(arrays, len(X))
    mesh = pv.PolyData(X)  # one vertex cell per point
    for name, a in data.items():
        mesh.point_data[name] = a
    logger.debug("writing %d points (%s) to %s", len(X), ", ".join(data) or "no arrays", path)
    return _save_mesh(mesh, path)


def write_pvd(path, entries: Iterable[PvdEntry | tuple]) -> Path:
    """Write a ParaView collection (``.pvd``) that puts data files on a time axis.

    Parameters
    ----------
    path : str or Path
        Output file; must end in ``.pvd``.
    entries : iterable of PvdEntry or tuples ``(time, file)`` / ``(time, file, part)``
        The data sets. Each ``file`` must exist inside the ``.pvd``'s folder (or a subfolder);
        relative paths are relative to the current directory, like any other path (pass what
        the writers return). The file stores it relative to the ``.pvd``'s folder, so the
        folder can be moved as a whole. ``(time, part)`` pairs must be unique.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    The format is ParaView's::

        <VTKFile type="Collection" version="0.1" byte_order="LittleEndian">
          <Collection>
            <DataSet timestep="0.5" group="" part="0" file="frames/cilia_0001.vtp"/>
            ...

    Data sets are listed by increasing time (stable: the given order within a time step).
    Times are written with ``repr`` (shortest round-trip form).

    Raises
    ------
    ValueError
        If an entry is malformed, a time is not finite, a file is missing or outside the
        ``.pvd``'s folder, a ``(time, part)`` pair repeats, or the extension is wrong.
    OutputError
        If the file cannot be written.
    """
    path = _check_suffix(path, ".pvd")
    items: list[PvdEntry] = []
    for e in entries:
        if not isinstance(e, PvdEntry):
            try:
                e = PvdEntry(*e)
            except TypeError:
                raise ValueError(f"entries must be (time, file[, part]), got {e!r}") from None
        items.append(e)
    folder = path.parent.resolve()
    rel: list[str] = []
    seen: set[tuple[float, int]] = set()
    for e in items:
        f = Path(e.file)
        if not f.is_file():
            raise ValueError(f"entries: file '{f}' does not exist")
        try:
            r = f.resolve().relative_to(folder)
        except ValueError:
            raise ValueError(f"entries: file '{f}' is not inside the .pvd's folder '{folder}'") from None
        if (e.time, e.part) in seen:
            raise ValueError(f"entries: time {e.time} part {e.part} appears twice")
        seen.add((e.time, e.part))
        rel.append(r.as_posix())

    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for i in sorted(range(len(items)), key=lambda i: items[i].time):
        ET.SubElement(coll, "DataSet", timestep=repr(items[i].time), group="",
                      part=str(items[i].part), file=rel[i])
    ET.indent(root)
    tree = ET.ElementTree(root)

    def make() -> bytes:
        buf = io.BytesIO()
        tree.write(buf, encoding="utf-8", xml_declaration=True)
        return buf.getvalue()

    logger.debug("writing a collection of %d data sets to %s", len(items), path)
    return _atomic_write(path, make)
