"""The output folder of a render: what the toolkit owns in it, and how a new render replaces it.

A render writes into a folder that may hold someone else's files, may be a mount point or a
symbolic link to another filesystem, may be read while it is replaced, and may be written by a
second render at the same time. :class:`OutputFolder` gives these guarantees (tested in
``tests/test_outdir.py`` and ``tests/test_faults.py``):

Ownership (the manifest decides nothing alone). ``ciliary-carpet.manifest`` records, for every
file a render wrote, its size and SHA-256. A file may be replaced or removed only if all hold:
its name is one of the render's own output names (:data:`_OUTPUT_NAME`: the ``files`` of the
outputs in :data:`~ciliary_carpet.output.outputs.OUTPUTS`), it is a regular file
(not a symbolic link, not a folder), and its size and hash match the manifest. A manifest that
someone edited to list ``thesis.tex`` therefore deletes nothing: ``thesis.tex`` is not an output
name. A listed output whose content changed since the render (an edited ``summary.md``) is the
user's now: a render that would replace it is refused before any work. Manifests written before
hashes were recorded (a plain list of names) are read safely: their entries count as the
toolkit's only when the name is an output name and the entry is a regular file; anything else
they list is foreign and kept. A folder from before the manifest existed (a ``summary.json``
with the resolved scene) owns its regular files with output names, as before.

Staging on the output's own filesystem. A new folder is staged in a hidden folder beside it
(``.NAME.HOST-PID.*.partial``) and renamed into place in one step; a folder that exists (a
mount point, a symbolic link to a scratch disk, a folder with the user's files) is staged in a
hidden folder *inside* it (``.ciliary-carpet.stage-*``), so every rename stays on one filesystem
and "Invalid cross-device link" cannot happen. Staging folders are created with
:func:`tempfile.mkdtemp` (never through a symbolic link), and their names are bounded (a long
folder name is shortened with a hash), so no derived path leaves the output folder or its parent.

One render per folder. A render holds an exclusive :func:`fcntl.flock` on a lock file the toolkit
owns -- ``OUT/.ciliary-carpet.lock`` for an existing folder, ``.NAME.ciliary-carpet.lock`` beside
a new one (both are removed when the render ends) -- from its start to its end. A second render
of the same folder is refused at once with a :class:`RenderError` naming the folder and the
process holding it. The lock also makes clean-up exact: staging folders inside a locked folder
that are not the holder's are leftovers of a killed render and are removed.

Replacing a render (the swap). With the new render complete in its staging folder, the render
writes a journal (``OUT/.ciliary-carpet.journal``: the staging folder, an aside folder, the old
names, the new names; written atomically and fsynced), then moves the old render's files into
the aside folder (``summary.json`` and the manifest first, so the folder reads as incomplete),
moves the new files in (``summary.json`` and the manifest last), removes the journal, and
deletes the aside folder. SIGINT, SIGTERM and SIGHUP are held back from the journal's writing to
the aside folder's removal (:func:`~cilia_runtime.signals.signals_held`: in the main thread, handlers that note them
and raise them again afterwards -- blocking them with :func:`signal.pthread_sigmask` in one
thread is not enough, since numba's and BLAS's threads receive them too; in other threads the
mask), so that Ctrl-C, ``kill`` or a closed terminal take effect only once the swap is whole. A
render killed with SIGKILL (or power loss) inside the swap leaves the journal, and the next
render of that folder completes the swap from it (the staging folder is complete before the
journal is written) before it does anything else; the lock file a killed render leaves is
harmless (the kernel releases the lock) and the next render removes it. A
reader that checks completeness (:func:`is_complete`: ``summary.json`` and the manifest present,
no journal) therefore never takes a mix for a render: before the swap the folder holds the old
render whole, after it the new one, and while it runs (the time of a few renames) it reads as
incomplete; a new folder appears whole in one rename. A failure before the swap changes nothing in the folder: the previous render's
files are untouched, and the staging folder is removed.

Up to date (:func:`is_complete` with ``scene``). A complete folder counts as the result of a
scene only when the settings it was made with match -- the resolved scene (``scene_resolved`` in
``summary.json``: reduced or not, backend, tolerance, every key) and the package version -- and
every file the render read has the same contents now: the manifest's ``inputs`` record the size
and SHA-256 of each (:func:`scene_inputs`: the scene file, the table -- the shipped one for
``file = "default"`` -- and ``target.file``), hashed when the render starts (a table a
``[table.build]`` makes, when it is placed); one whose contents changed during the render is
recorded without a hash, so that the folder is never up to date for it
(:func:`inputs_differ`). Modification times decide nothing: an edited file with an old time, or
a file replaced by an older one, is noticed. A folder whose manifest records no inputs is not up
to date for any scene.

One concept over 500 lines: ownership, staging, the lock, the journal and the swap are one
mechanism, relying on each other and tested together.
"""
from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import logging
import os
import re
import shutil
import socket
import stat
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cilia_runtime.files import strict_json, usual_mode
from cilia_runtime.signals import signals_held

from ciliary_carpet.output import RenderError
from ciliary_carpet.output.contract import SUMMARY
from ciliary_carpet.output.outputs import OUTPUTS

logger = logging.getLogger(__name__)

__all__ = ["MANIFEST", "OutputFolder", "FileRecord", "owned_files", "is_complete", "only_toolkit_files",
           "check_parents", "settings_differ", "inputs_differ", "scene_inputs", "input_records", "is_toolkit_name",
           "PACKAGE_VERSION"]

MANIFEST = "ciliary-carpet.manifest"
MANIFEST_FORMAT = 2
LOCK = ".ciliary-carpet.lock"
JOURNAL = ".ciliary-carpet.journal"
_STAGE_IN = ".ciliary-carpet.stage-"
_ASIDE_IN = ".ciliary-carpet.aside-"
# the names a render writes (its outputs' files): only files with these names are ever replaced or removed
_OUTPUT_NAME = re.compile("(" + "|".join(f for o in OUTPUTS.values() for f in o.files) + r")\Z")
# the toolkit's own hidden entries inside an output folder (lock, journal, staging, aside, temporary files)
_HIDDEN = re.compile(r"\.ciliary-carpet\.(lock|journal|(stage|aside)-[A-Za-z0-9_]+|(journal|manifest)\.[A-Za-z0-9_]+"
                     r"\.part)\Z|\.ciliary-carpet\.manifest\.[A-Za-z0-9_]+\.part\Z")
_STAGE_TAIL = re.compile(r"(\d+)\.[A-Za-z0-9_]+\.partial\Z")


def _package_version() -> str:
    from single_cilium import __version__

    return __version__


PACKAGE_VERSION = _package_version()


@dataclass(frozen=True)
class FileRecord:
    """What the manifest records of one file a render wrote: its ``size`` in bytes and the
    hex ``sha256`` of its content."""

    size: int
    sha256: str

    @classmethod
    def of(cls, path: Path) -> "FileRecord":
        """The record of the regular file ``path`` (read in 1 MiB blocks)."""
        h = hashlib.sha256()
        size = 0
        with open(path, "rb") as fh:
            while block := fh.read(1 << 20):
                h.update(block)
                size += len(block)
        return cls(size, h.hexdigest())


def is_toolkit_name(name: str) -> bool:
    """Whether ``name`` is one of the toolkit's hidden bookkeeping entries in an output folder
    (lock, journal, staging and aside folders, temporary files)."""
    return bool(_HIDDEN.match(name))


def _is_regular(path: Path) -> bool:
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False


def _short(name: str) -> str:
    """``name``, shortened with a hash when it is long (so that derived names stay < 255 bytes)."""
    if len(name.encode("utf-8", "surrogateescape")) <= 120:
        return name
    digest = hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:16]
    cut = name
    while len(cut.encode("utf-8", "surrogateescape")) > 80:
        cut = cut[:-1]
    return f"{cut}~{digest}"


def _read_manifest(out_dir: Path) -> dict | list | None:
    """The parsed manifest's ``files`` (dict in the current format, list in the old one), or None
    without a manifest. RenderError for one that cannot be read."""
    m = out_dir / MANIFEST
    if not os.path.lexists(m):
        return None
    if not _is_regular(m):
        raise RenderError(f"{m} is not a regular file (a symbolic link or a folder); the folder is kept: remove it "
                          f"yourself")
    try:
        files = json.loads(m.read_text())["files"]
        if not isinstance(files, (dict, list)):
            raise TypeError(f"'files' is a {type(files).__name__}")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise RenderError(f"{m}: unreadable manifest ({exc}); the folder is kept: remove it yourself") from None
    return files


def owned_files(out_dir) -> set[str] | None:
    """The names in ``out_dir`` that a render wrote and that are unchanged since (the names a
    render may replace or remove), or None when ``out_dir`` is not a render's folder.

    A name counts only if it is a render's output name (or the manifest itself), a regular file,
    and -- in a manifest with records -- of the recorded size and SHA-256. In an old manifest (a
    list of names, no records) the name and the file type decide. A folder from before the
    manifest (a ``summary.json`` with the resolved scene) owns its regular files with output
    names. Raises RenderError for a manifest that cannot be read."""
    out_dir = Path(out_dir)
    files = _read_manifest(out_dir)
    if files is None:
        summ = out_dir / SUMMARY
        try:
            legacy = _is_regular(summ) and "scene_resolved" in json.loads(summ.read_text())
        except (OSError, ValueError, TypeError):
            legacy = False
        if not legacy:
            return None
        return {p.name for p in out_dir.iterdir() if _OUTPUT_NAME.match(p.name) and _is_regular(p)}
    owned = {MANIFEST}
    for name in files:
        if not (isinstance(name, str) and _OUTPUT_NAME.match(name) and _is_regular(out_dir / name)):
            continue
        if isinstance(files, dict):
            rec = files[name]
            try:
                want = FileRecord(int(rec["size"]), str(rec["sha256"]))
                if os.lstat(out_dir / name).st_size != want.size or FileRecord.of(out_dir / name) != want:
                    continue
            except (OSError, KeyError, TypeError, ValueError):
                continue
        owned.add(name)
    return owned


def _normal(obj):
    """``obj`` as it reads back from summary.json (plain JSON types)."""
    return json.loads(strict_json(obj))


def settings_differ(out_dir, scene) -> list[str]:
    """The settings that differ between the render in ``out_dir`` (its ``summary.json``) and a
    render of ``scene`` now: dotted keys of the resolved scene, and ``package_version``. Empty
    when they match; ``["summary.json"]`` when it cannot be read."""
    try:
        summ = json.loads((Path(out_dir) / SUMMARY).read_text())
        old = summ["scene_resolved"]
    except (OSError, ValueError, KeyError, TypeError):
        return [SUMMARY]
    new = _normal(scene.to_dict())
    diff = []
    for k in sorted(set(old) | set(new)) if isinstance(old, dict) else ["scene"]:
        a, b = (old.get(k), new.get(k)) if isinstance(old, dict) else (old, new)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            diff += [f"{k}.{kk}" for kk in sorted(set(a) | set(b)) if a.get(kk) != b.get(kk)]
        else:
            diff.append(k)
    if summ.get("package_version") != PACKAGE_VERSION:
        diff.append("package_version")
    return diff


def check_parents(path) -> None:
    """RenderError when ``path`` has a ``..`` after a folder that does not exist
    (``dd/sub/../../o`` with no ``dd/sub``): making its parents as ``mkdir -p`` does would create
    folders the path does not name as its own. Nothing is made or changed."""
    parts = Path(path).parts
    for k, part in enumerate(parts):
        if part == ".." and k > 0 and not os.path.isdir(os.path.join(*parts[:k])):
            missing = os.path.join(*parts[:k])
            raise RenderError(f"cannot write '{path}': '..' follows {missing}, which does not exist (making it "
                              f"would create folders the path only passes through); nothing was written: name the "
                              f"output without '..', e.g. {os.path.normpath(path)}")


def scene_inputs(scene) -> dict[str, Path]:
    """The files a render of ``scene`` reads, by role: ``"scene"`` (its file; none for a scene
    made in memory), ``"table.file"`` (for ``file = "default"`` the shipped table the carpet's coupling reads) and
    ``"target.file"`` (when the target names one), as absolute paths."""
    from importlib import resources

    from single_cilium.lookup import DEFAULT_FILE, DEFAULT_FLOW_FILE, SHIPPED_TABLES, shipped_field

    found: dict[str, Path] = {}
    if getattr(scene, "source", None) is not None:
        found["scene"] = Path(scene.source)
    table = scene.table.path(scene)
    field = shipped_field(scene.field.chi_E)
    still, flow = SHIPPED_TABLES[field] if field is not None else (DEFAULT_FILE, DEFAULT_FLOW_FILE)
    shipped = flow if scene.carpet.coupling == "mean" else still
    found["table.file"] = table if table is not None else Path(str(resources.files("single_cilium") / "data"
                                                                   / shipped))
    target_file = getattr(scene.target, "file", None)
    if isinstance(target_file, str) and target_file.strip():
        t = Path(target_file).expanduser()
        found["target.file"] = t if t.is_absolute() else scene.base_dir / t
    return {k: Path(os.path.abspath(v)) for k, v in found.items()}


def input_records(scene) -> dict[str, dict]:
    """``{role: {"path", "size", "sha256"}}`` of :func:`scene_inputs` as they are now (``size``
    and ``sha256`` None for a file that cannot be read, e.g. a table not built yet)."""
    out: dict[str, dict] = {}
    for role, path in scene_inputs(scene).items():
        try:
            r = FileRecord.of(path)
            out[role] = {"path": str(path), "size": r.size, "sha256": r.sha256}
        except OSError:
            out[role] = {"path": str(path), "size": None, "sha256": None}
    return out


def inputs_differ(out_dir, scene) -> list[str]:
    """The roles of :func:`scene_inputs` whose contents differ between the render in ``out_dir``
    (its manifest's ``inputs``) and now, the unreadable ones included; ``["inputs"]`` when the
    manifest records none. Empty when every file the render read is as it was."""
    try:
        recorded = json.loads((Path(out_dir) / MANIFEST).read_text()).get("inputs")
    except (OSError, ValueError, AttributeError):
        recorded = None
    if not isinstance(recorded, dict):
        return ["inputs"]
    now = input_records(scene)
    diff = []
    for role in sorted(set(recorded) | set(now)):
        old, new = recorded.get(role), now.get(role)
        if not (isinstance(old, dict) and new is not None and new["sha256"] is not None
                and old.get("sha256") == new["sha256"] and old.get("size") == new["size"]):
            diff.append(role)
    return diff


def only_toolkit_files(out_dir) -> bool:
    """Whether every visible entry of ``out_dir`` is a file a render wrote, unchanged since
    (:func:`owned_files`): a folder a new render may replace whole without losing anyone's work."""
    out_dir = Path(out_dir)
    try:
        owned = owned_files(out_dir)
        names = {e.name for e in out_dir.iterdir() if not is_toolkit_name(e.name)}
    except (OSError, RenderError):
        return False
    return owned is not None and names <= owned


def is_complete(out_dir, scene=None) -> bool:
    """Whether ``out_dir`` holds a complete render and, given ``scene``, is up to date for it:
    made with its settings (:func:`settings_differ`) from inputs with the same contents as now
    (:func:`inputs_differ`).

    Complete: ``summary.json`` and the manifest are there (or, for a folder from before the
    manifest, ``summary.json`` with the resolved scene), every file the manifest lists is there
    (with its recorded size), and no replacement is under way (no journal). Without ``scene`` no
    file is read but the manifest and ``summary.json``; with it, the scene's inputs are hashed."""
    out_dir = Path(out_dir)
    s = out_dir / SUMMARY
    if not _is_regular(s) or os.path.lexists(out_dir / JOURNAL):
        return False
    try:
        files = _read_manifest(out_dir)
    except RenderError:
        return False
    if files is None and owned_files(out_dir) is None:  # no manifest: a render from before it, or not one
        return False
    for name in files or ():
        if name == MANIFEST:
            continue
        try:
            size = os.lstat(out_dir / name).st_size
            if isinstance(files, dict) and size != int(files[name]["size"]):
                return False
        except (OSError, KeyError, TypeError, ValueError):
            return False
    return scene is None or not (settings_differ(out_dir, scene) or inputs_differ(out_dir, scene))


def write_manifest(folder: Path, inputs: dict | None = None) -> None:
    """Write ``folder``'s manifest: a record (size, SHA-256) of every file in it but the
    toolkit's hidden entries, and ``inputs`` (:func:`input_records`: the files the render read)."""
    files: dict = {MANIFEST: {"self": True}}
    for e in sorted(folder.iterdir()):
        if e.name != MANIFEST and not is_toolkit_name(e.name) and _is_regular(e):
            if not _OUTPUT_NAME.match(e.name):  # a later render could never replace it: a bug, caught here
                raise RenderError(f"internal error: the render wrote {e.name}, which is not one of its output names "
                                  f"(no output in ciliary_carpet.output.outputs.OUTPUTS names it); nothing was placed")
            r = FileRecord.of(e)
            files[e.name] = {"size": r.size, "sha256": r.sha256}
    body = {"written_by": "ciliary-carpet", "format": MANIFEST_FORMAT, "package_version": PACKAGE_VERSION,
            "files": files}
    if inputs is not None:
        body["inputs"] = inputs
    _write_json(folder / MANIFEST, body, sync=False)


def _write_json(path: Path, obj, *, sync: bool) -> None:
    """Write ``obj`` to ``path`` atomically (a temporary file beside it, renamed), fsynced if ``sync``."""
    fd, tmp = tempfile.mkstemp(prefix=f"{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(json.dumps(obj, indent=1))
            if sync:
                fh.flush()
                os.fsync(fh.fileno())
        os.chmod(tmp, usual_mode())
        os.replace(tmp, path)
        if sync:
            _sync_dir(path.parent)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _sync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ------------------------------------------------------------------------------ the lock
class _Lock:
    """An exclusive flock on ``path`` (created if needed, never through a symbolic link),
    refused at once when another process holds it. Released by :meth:`release`, which also
    removes the file."""

    def __init__(self, path: Path, folder: Path) -> None:
        self.path = path
        while True:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                if exc.errno == errno.ELOOP:
                    raise RenderError(f"{path} is a symbolic link, not ciliary-carpet's lock file; {folder} is "
                                      f"kept: remove the link") from None
                raise RenderError(f"cannot write '{folder}': {exc.strerror or exc} ({path})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                try:
                    who = os.pread(fd, 200, 0).decode("utf-8", "replace").split()
                except OSError:
                    who = []
                os.close(fd)
                by = f"process {who[0]} on {who[1]}" if len(who) >= 2 else "another process"
                raise RenderError(f"{folder} is being written by another ciliary-carpet render ({by}); it is "
                                  f"kept: wait for that render to finish (or stop it), then try again") from None
            except OSError as exc:  # a filesystem without locks (some network or FUSE ones)
                logger.warning("%s: cannot lock %s (%s); two renders of this folder at once are not prevented "
                               "there", folder, path, exc.strerror or exc)
            try:
                same = os.path.samestat(os.fstat(fd), os.lstat(path))
            except FileNotFoundError:
                same = False
            if same:  # the file is still the one at the path (its last holder may have removed it)
                break
            os.close(fd)
        try:  # who holds it, for a second render's message; the lock itself does not need it
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()} {socket.gethostname()}\n".encode(), 0)
        except OSError as exc:  # a full disk: the render goes on and fails naming what it cannot write
            logger.debug("%s: cannot record the lock's holder (%s)", path, exc.strerror or exc)
        self.fd: int | None = fd

    def release(self) -> None:
        """Remove the lock file (while still holding it) and release it."""
        if self.fd is None:
            return
        try:
            if os.path.samestat(os.fstat(self.fd), os.lstat(self.path)):
                os.unlink(self.path)
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None


# ------------------------------------------------------------------------------ stale staging beside
def _stage_prefix(out_dir: Path) -> str:
    return f".{_short(out_dir.name)}.{socket.gethostname()}-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _clean_stale_stages(out_dir: Path) -> None:
    """Remove the staging folders beside ``out_dir`` left by killed renders on this host."""
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


# ------------------------------------------------------------------------------ the journal
def _order_old(names: Iterable[str]) -> list[str]:
    """Old files go aside summary.json first, then the manifest (the folder reads as incomplete)."""
    names = set(names)
    return [n for n in (SUMMARY, MANIFEST) if n in names] + sorted(names - {SUMMARY, MANIFEST})


def _order_new(names: Iterable[str]) -> list[str]:
    """New files come in summary.json and the manifest last."""
    names = set(names)
    return sorted(names - {SUMMARY, MANIFEST}) + [n for n in (SUMMARY, MANIFEST) if n in names]


def _roll_forward(out_dir: Path, j: dict) -> None:
    """Complete the swap the journal ``j`` describes (idempotent: safe to repeat after a kill
    at any point), then remove the journal."""
    stage, aside = out_dir / j["stage"], out_dir / j["aside"]
    new = set(j["new"])
    aside.mkdir(exist_ok=True)
    for nm in _order_old(j["old"]):
        if nm in new and not os.path.lexists(stage / nm):
            continue  # already replaced by the new file
        if os.path.lexists(out_dir / nm):
            os.rename(out_dir / nm, aside / nm)
    for nm in _order_new(new):
        if os.path.lexists(stage / nm):
            os.rename(stage / nm, out_dir / nm)
    os.unlink(out_dir / JOURNAL)
    _sync_dir(out_dir)


def _journal(out_dir: Path) -> dict | None:
    """The journal of an interrupted swap in ``out_dir`` (checked), or None."""
    p = out_dir / JOURNAL
    if not os.path.lexists(p):
        return None
    try:
        if not _is_regular(p):
            raise ValueError("not a regular file")
        j = json.loads(p.read_text())
        ok = (isinstance(j, dict) and isinstance(j.get("stage"), str) and j["stage"].startswith(_STAGE_IN)
              and is_toolkit_name(j["stage"]) and isinstance(j.get("aside"), str) and j["aside"].startswith(_ASIDE_IN)
              and is_toolkit_name(j["aside"])
              and all(isinstance(j.get(k), list) and all(isinstance(n, str) and (_OUTPUT_NAME.match(n) or n == MANIFEST)
                                                          for n in j[k]) for k in ("old", "new")))
        if not ok:
            raise ValueError("not a ciliary-carpet journal")
    except (OSError, ValueError) as exc:
        raise RenderError(f"{p}: unreadable journal of an interrupted render ({exc}); the folder is kept: check "
                          f"the folder and remove the journal yourself") from None
    return j


# ------------------------------------------------------------------------------ the folder
class OutputFolder:
    """The output folder of one render, held from :meth:`__enter__` to :meth:`__exit__` (see the
    module docstring for the guarantees).

    Parameters
    ----------
    path : Path
        The output folder (it may not exist yet; it may be a symbolic link to a folder).
    overwrite : bool
        Whether the toolkit's files in it may be replaced; without it a folder holding anything
        is kept and the render refused.
    scene : Scene, optional
        The scene being rendered (for the message when the folder holds a render of other
        settings).
    within : Path, optional
        A folder the output folder must resolve below (a batch's output root, for a folder
        named from the scene's ``name``); None (a caller that allows outside paths): anywhere.

    Use it as a context manager: entering checks the folder, takes its lock, completes an
    interrupted swap and removes leftovers of killed renders (RenderError when the folder must be
    kept as it is); :meth:`stage` gives the staging folder to write into; :meth:`place` swaps it
    in; leaving removes what was not placed and releases the lock.
    """

    def __init__(self, path, *, overwrite: bool = False, scene=None, within=None) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.scene = scene
        self.within = None if within is None else Path(within)
        self.fresh = False
        self.owned: set = set()
        self.placed = False
        self._locks: list[_Lock] = []
        self._stage: Path | None = None
        self._aside: Path | None = None
        self._journaled = False  # a swap began: on failure, its folders are kept for the next render
        self._inputs: dict | None = None  # the files the render reads, hashed when it starts

    # -------------------------------------------------------------- enter / exit
    def __enter__(self) -> "OutputFolder":
        try:
            self._open()
        except BaseException:
            self._close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._close()

    def _open(self) -> None:
        out = self.path
        self._check_within()
        if out.is_symlink() and not out.exists():
            raise RenderError(f"{out} is a broken symbolic link")
        if out.exists() and not out.is_dir():
            raise RenderError(f"{out} exists and is not a folder")
        _clean_stale_stages(out)
        for _ in range(100):  # the folder may appear or vanish while the lock is taken
            if out.is_dir():
                lock = _Lock(out / LOCK, out)
                if out.is_dir():
                    self._locks.append(lock)
                    self.fresh = False
                    break
                lock.release()
            else:
                self._make_parents()
                lock = _Lock(out.parent / f".{_short(out.name)}.ciliary-carpet.lock", out)
                if not os.path.lexists(out):
                    self._locks.append(lock)
                    self.fresh = True
                    break
                lock.release()
        else:
            raise RenderError(f"{out} keeps appearing and vanishing; it is kept: try again")
        if not self.fresh:
            self._recover()
            self._clean_inside()
        self.owned = self._check()
        if self.scene is not None:
            self._inputs = input_records(self.scene)  # before the render reads them

    def _close(self) -> None:
        for p in (self._stage, self._aside):
            if p is not None and p.is_dir() and not p.is_symlink() and (self.placed or not self._journaled):
                shutil.rmtree(p, ignore_errors=True)
        self._stage = self._aside = None
        while self._locks:
            self._locks.pop().release()

    def _make_parents(self) -> None:
        """The folders above a new output folder, made as ``mkdir -p`` does (kept: a batch's
        other scenes may be writing there); none when the path climbs out of one that does not
        exist (:func:`check_parents`)."""
        check_parents(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RenderError(f"cannot write '{self.path}': {exc.strerror or exc}") from None

    def _check_within(self) -> None:
        if self.within is None:
            return
        root = Path(os.path.realpath(self.within))
        real = Path(os.path.realpath(self.path))
        if real != root and root not in real.parents:
            raise RenderError(f"{self.path} resolves to {real}, outside the output folder {root} (a symbolic link "
                              f"there points elsewhere); nothing was written: remove the link, render into that "
                              f"folder with -o, or pass --allow-outside-paths if you trust it")

    def _recover(self) -> None:
        j = _journal(self.path)
        if j is None:
            return
        if (self.path / j["stage"]).is_dir():
            with signals_held():
                _roll_forward(self.path, j)
        else:
            os.unlink(self.path / JOURNAL)
        logger.warning("%s: completed the replacement that a killed render had begun (from its journal)", self.path)

    def _clean_inside(self) -> None:
        """Under the lock: every staging or aside folder and temporary file of the toolkit in the
        folder is a killed render's leftover."""
        try:
            entries = list(self.path.iterdir())
        except OSError:
            return
        for e in entries:
            if not is_toolkit_name(e.name) or e.name in (LOCK, JOURNAL):
                continue
            if e.name.startswith((_STAGE_IN, _ASIDE_IN)):
                if e.is_dir() and not e.is_symlink():
                    shutil.rmtree(e, ignore_errors=True)
                    logger.info("removed %s, left by a killed render", e)
            elif _is_regular(e):
                e.unlink(missing_ok=True)

    def _names(self) -> set[str]:
        try:
            return {e.name for e in self.path.iterdir() if not is_toolkit_name(e.name)}
        except OSError as exc:
            raise RenderError(f"{self.path}: cannot read the output folder ({exc.strerror or exc})") from None

    def _check(self) -> set:
        """The names a render may replace (empty for a new or empty folder); RenderError when the
        folder must be kept as it is."""
        out = self.path
        if self.fresh:
            return set()
        names = self._names()
        if not names:
            return set()
        owned = owned_files(out)
        if not self.overwrite:
            if owned is not None:
                if _is_regular(out / SUMMARY):
                    differ = settings_differ(out, self.scene) if self.scene is not None else []
                    what = "complete" + (f", made with other settings: {', '.join(differ[:4])}"
                                         f"{', ...' if len(differ) > 4 else ''}" if differ else "")
                else:
                    what = "partial"
                raise RenderError(f"{out} already holds results ({what}); they are kept: pass overwrite=True "
                                  f"(--overwrite) to replace them (only the files ciliary-carpet wrote)")
            raise RenderError(f"{out} holds files ciliary-carpet did not write ({', '.join(sorted(names)[:3])}"
                              f"{', ...' if len(names) > 3 else ''}); they are kept: choose a new or empty folder, or "
                              f"pass --overwrite to write the render beside them")
        owned = owned or set()
        clash = sorted(nm for nm in names - owned if _OUTPUT_NAME.match(nm) or nm == MANIFEST)
        if clash:
            raise RenderError(f"{out / clash[0]} was not written by ciliary-carpet or was changed since (it is not "
                              f"in the folder's manifest with this content, or is not a regular file) and the "
                              f"render would replace it; it is kept: move it away or choose another folder")
        return owned

    # -------------------------------------------------------------- stage / place
    def stage(self) -> Path:
        """A new, empty staging folder on the output's filesystem: beside a new folder, inside an
        existing one."""
        try:
            if self.fresh:
                self._stage = Path(tempfile.mkdtemp(prefix=f"{_stage_prefix(self.path)}{os.getpid()}.",
                                                    suffix=".partial", dir=self.path.parent))
                # held when the staging folder becomes the output folder (its path is moved then)
                self._locks.append(_Lock(self._stage / LOCK, self.path))
            else:
                self._stage = Path(tempfile.mkdtemp(prefix=_STAGE_IN, dir=self.path))
        except OSError as exc:
            raise RenderError(f"cannot write '{self.path}': {exc.strerror or exc}") from None
        return self._stage

    def place(self) -> None:
        """Swap the complete staging folder in (see the module docstring): one rename for a new
        folder, the journalled swap for an existing one. RenderError (nothing changed) when a
        file the swap would replace is no longer the toolkit's."""
        stage = self._stage
        assert stage is not None, "stage() first"
        write_manifest(stage, self._read_inputs())
        try:
            if self.fresh:
                os.chmod(stage, usual_mode(executable=True))
                with signals_held():
                    try:
                        os.rename(stage, self.path)
                    except OSError as exc:
                        if os.path.lexists(self.path):
                            raise RenderError(f"{self.path} appeared during the render (made by someone else); it "
                                              f"is kept, and the render was not placed") from None
                        raise
                    self._locks[-1].path = self.path / LOCK
                    self._stage = None
                    self.placed = True
                return
            owned = owned_files(self.path) or set()  # again, under the lock: the render may have taken hours
            new = {e.name for e in stage.iterdir() if not is_toolkit_name(e.name)}
            existing = self._names()
            clash = sorted((new & existing) - owned)
            if clash:
                raise RenderError(f"{self.path / clash[0]} appeared or was changed during the render and is not "
                                  f"ciliary-carpet's; it is kept, and the render was not placed")
            self._aside = Path(tempfile.mkdtemp(prefix=_ASIDE_IN, dir=self.path))
            j = {"stage": stage.name, "aside": self._aside.name, "old": sorted(owned & existing),
                 "new": sorted(new)}
            with signals_held():
                _write_json(self.path / JOURNAL, j, sync=True)
                self._journaled = True
                _roll_forward(self.path, j)
                self.placed = True
                # the old render removed and the empty staging folder too, before a held signal acts
                shutil.rmtree(self._aside, ignore_errors=True)
                self._aside = None
                shutil.rmtree(stage, ignore_errors=True)
                self._stage = None
        except OSError as exc:
            half = (f"; the replacement stopped half-way and the next render of {self.path} completes it from "
                    f"its journal" if self._journaled and not self.placed else "")
            raise RenderError(f"cannot write '{exc.filename or self.path}': {exc.strerror or exc}{half}") from None

    def _read_inputs(self) -> dict | None:
        """The inputs to record: as hashed at the start; one missing then (a table the render
        built) as it is now; one whose contents changed during the render without a hash (the
        render may have read either version)."""
        if self._inputs is None:
            return None
        now = input_records(self.scene)
        rec = {}
        for role, start in self._inputs.items():
            end = now.get(role, start)
            if start["sha256"] is None:
                rec[role] = end
            elif end["sha256"] != start["sha256"]:
                logger.warning("%s changed during the render; %s is not up to date for it", start["path"], self.path)
                rec[role] = {"path": start["path"], "size": None, "sha256": None}
            else:
                rec[role] = start
        return rec

    def files(self) -> tuple[str, ...]:
        """The names in the folder, the toolkit's hidden entries left out."""
        return tuple(sorted(self._names()))
