"""The output folder of a render: what the toolkit owns in it, and how a new render is placed.

See :mod:`ciliary_carpet.render` ("Output-folder safety") for the guarantees.
"""
from __future__ import annotations

import json
import logging
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

logger = logging.getLogger(__name__)

__all__ = ["RenderError", "SUMMARY", "MANIFEST", "owned_files", "is_complete", "usual_mode"]

SUMMARY = "summary.json"
MANIFEST = "ciliary-carpet.manifest"
# the names a render writes (used to recognise renders made before the manifest existed)
_OUTPUT_NAME = re.compile(r"(layout\.(nc|vtp)|design\.(png|vtp)|mean_field\.vti|snapshot_\d+\.vti|snapshots\.pvd|"
                          r"cilia_\d+\.vtp|cilia\.pvd|pathlines\.vtp|particles_\d+\.vtp|particles\.pvd|ftle\.vti|"
                          r"open_in_paraview\.py|preview\.png|summary\.(json|md))\Z")


class RenderError(RuntimeError):
    """The output folder cannot be (re)written as asked, or the result is not finite."""


def usual_mode(executable: bool = False) -> int:
    umask = os.umask(0)
    os.umask(umask)
    return (0o777 if executable else 0o666) & ~umask


def owned_files(out_dir) -> set[str] | None:
    """The names in ``out_dir`` that a render wrote (its manifest), or None when ``out_dir`` is
    not a render's folder. A folder from before the manifest (a ``summary.json`` with the
    resolved scene) owns the entries with the names a render writes."""
    out_dir = Path(out_dir)
    m = out_dir / MANIFEST
    if m.is_file():
        try:
            names = json.loads(m.read_text())["files"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RenderError(f"{m}: unreadable manifest ({exc}); the folder is kept: remove it yourself") from None
        return {n for n in names if isinstance(n, str) and n and "/" not in n and n not in (".", "..")} | {MANIFEST}
    summ = out_dir / SUMMARY
    try:
        legacy = summ.is_file() and "scene_resolved" in json.loads(summ.read_text())
    except (OSError, ValueError, TypeError):
        legacy = False
    if not legacy:
        return None
    return {p.name for p in out_dir.iterdir() if p.is_file() and _OUTPUT_NAME.match(p.name)}


def is_complete(out_dir, sources=()) -> bool:
    """Whether ``out_dir`` holds a complete render newer than every file in ``sources``."""
    s = Path(out_dir) / SUMMARY
    if not s.is_file() or owned_files(out_dir) is None:
        return False
    t = s.stat().st_mtime
    return all(Path(p).stat().st_mtime < t for p in sources if p is not None and Path(p).exists())


# ------------------------------------------------------------------------------ output folder
_STAGE_TAIL = re.compile(r"(\d+)\.[A-Za-z0-9_]+\.partial\Z")


def _stage_prefix(out_dir: Path) -> str:
    return f".{out_dir.name}.{socket.gethostname()}-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _clean_stale_stages(out_dir: Path) -> None:
    """Remove the staging folders of ``out_dir`` left by killed renders on this host."""
    prefix = _stage_prefix(out_dir)
    try:
        entries = list(out_dir.parent.iterdir()) if out_dir.parent.is_dir() else []
    except OSError:
        return
    for e in entries:
        m = _STAGE_TAIL.match(e.name[len(prefix):]) if e.name.startswith(prefix) else None
        if m is None or int(m.group(1)) == os.getpid() or _alive(int(m.group(1))):
            continue
        if e.is_dir() and not e.is_symlink():
            shutil.rmtree(e, ignore_errors=True)
            logger.info("removed %s, the staging folder of a killed render", e)


def _check_out_dir(out_dir: Path, overwrite: bool) -> set:
    """The names in ``out_dir`` a render may replace (empty for a new or empty folder); raises
    RenderError when ``out_dir`` must be kept as it is."""
    if out_dir.is_symlink() and not out_dir.exists():
        raise RenderError(f"{out_dir} is a broken symbolic link")
    if not out_dir.exists():
        return set()
    if not out_dir.is_dir():
        raise RenderError(f"{out_dir} exists and is not a folder")
    try:
        names = {e.name for e in out_dir.iterdir()}
    except OSError as exc:
        raise RenderError(f"{out_dir}: cannot read the output folder ({exc.strerror or exc})") from None
    if not names:
        return set()
    owned = owned_files(out_dir)
    if not overwrite:
        if owned is not None:
            what = "results (" + ("complete" if (out_dir / SUMMARY).is_file() else "partial") + ")"
            raise RenderError(f"{out_dir} already holds {what}; they are kept: pass overwrite=True (--overwrite) to "
                              f"replace them (only the files ciliary-carpet wrote)")
        raise RenderError(f"{out_dir} holds files ciliary-carpet did not write ({', '.join(sorted(names)[:3])}"
                          f"{', ...' if len(names) > 3 else ''}); they are kept: choose a new or empty folder, or pass "
                          f"--overwrite to write the render beside them")
    owned = owned or set()
    clash = sorted(nm for nm in names - owned if _OUTPUT_NAME.match(nm) or nm == MANIFEST)
    if clash:
        raise RenderError(f"{out_dir / clash[0]} was not written by ciliary-carpet (it is not in the folder's "
                          f"manifest) and the render would replace it; it is kept: move it away or choose another "
                          f"folder")
    return owned


def _write_manifest(folder: Path, names) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{MANIFEST}.", suffix=".part", dir=folder)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(json.dumps({"written_by": "ciliary-carpet", "files": sorted(set(names) | {MANIFEST})}, indent=1))
        os.chmod(tmp, usual_mode())
        os.replace(tmp, folder / MANIFEST)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _place(stage: Path, out_dir: Path, owned: set) -> None:
    """Move the complete ``stage`` onto ``out_dir``: one rename for a new or empty folder;
    otherwise file by file, replacing only ``owned`` names, ``summary.json`` last."""
    if not out_dir.is_symlink():
        try:
            os.replace(stage, out_dir)
            return
        except OSError as exc:
            if not out_dir.is_dir():
                raise RenderError(f"cannot write '{out_dir}': {exc.strerror or exc}") from None
    new = {e.name for e in stage.iterdir()}
    existing = {e.name for e in out_dir.iterdir()}
    clash = sorted((new & existing) - owned)
    if clash:
        raise RenderError(f"{out_dir / clash[0]} appeared during the render and was not written by ciliary-carpet; "
                          f"it is kept, and the render was not placed")
    try:
        _write_manifest(out_dir, owned | new)  # first: a folder being replaced is marked as the toolkit's
        if SUMMARY in owned:
            (out_dir / SUMMARY).unlink(missing_ok=True)  # incomplete from here on
        for nm in sorted(owned - new - {MANIFEST}):
            q = out_dir / nm
            if q.is_symlink() or q.is_file():
                q.unlink(missing_ok=True)
        for nm in sorted(new - {SUMMARY, MANIFEST}) + [SUMMARY, MANIFEST]:
            os.replace(stage / nm, out_dir / nm)
        stage.rmdir()
    except OSError as exc:
        raise RenderError(f"cannot write '{exc.filename or out_dir}': {exc.strerror or exc}") from None
