"""Path rules of scene files: what a scene may name, read and write.

A scene file is input that may come from someone else, so the paths in it are confined:

* ``name`` (the output folder of the scene in a batch, ``OUTPUT/NAME``) is a file name, not a
  path: no ``/`` or ``\\``, not ``.`` or ``..``, no leading ``.`` (hidden names are the toolkit's
  staging folders), no control characters, at most 255 bytes (:func:`check_name`).
* ``table.file`` and ``target.file`` resolve (symbolic links followed) to a path below the scene
  file's own folder (:func:`check_input`). ``table.file`` with ``[table.build]`` is where the
  table is *written*, so the same rule keeps that write below the scene's folder. A user who
  trusts the scene file can lift the rule: ``allow_outside=True`` in
  :func:`~ciliary_carpet.scenes.scene.load_scene`, or ``--allow-outside-paths`` on the command line, or
  the environment variable ``CILIARY_CARPET_ALLOW_OUTSIDE_PATHS=1`` (read by the command line, so
  that batch workers inherit it).
* Paths the toolkit *derives* obey the same rule, symbolic links resolved: the row folder
  ``TABLE.parts`` that a table build writes next to ``table.file`` (and removes its own row files
  from once the table is written) is checked when the scene is read and again just before the build
  (:func:`check_derived`; at build time the rule applies whenever ``table.file`` itself lies
  below the scene's folder, unless the environment variable lifts it). The output folder of a
  scene in a batch, ``OUTPUT/NAME``, must resolve below ``OUTPUT``
  (:class:`~ciliary_carpet.output.folder.OutputFolder`), and staging folders are created inside the
  output folder or next to it, never through a symbolic link.

Every violation is a :class:`~ciliary_carpet.scenes.schema.SceneError` (exit status 2) naming the scene
file, the key and the value; nothing is read or written before the check.
"""
from __future__ import annotations

import os
from pathlib import Path

from ciliary_carpet.scenes.schema import SceneError

__all__ = ["check_name", "check_input", "check_derived", "check_scene_paths", "table_parts", "inside", "ALLOW_ENV"]

ALLOW_ENV = "CILIARY_CARPET_ALLOW_OUTSIDE_PATHS"


def _error(msg: str) -> SceneError:
    return SceneError(msg)


def check_name(src: str, key: str, name: str) -> str:
    """Return ``name`` if it is a plain file name (see the module docstring), else raise
    SceneError naming ``src`` and ``key``."""
    why = None
    if "/" in name or "\\" in name:
        why = "contains a path separator"
    elif name in (".", ".."):
        why = "is a relative folder"
    elif name.startswith("."):
        why = "starts with '.' (hidden names are reserved for staging folders)"
    elif any(ord(c) < 32 or ord(c) == 127 for c in name):
        why = "contains a control character"
    elif len(name.encode("utf-8", "surrogateescape")) > 255:
        why = "is longer than 255 bytes"
    if why is not None:
        raise _error(f"{src}: {key} must be a file name (the scene's output folder), not a path: {name!r} {why}")
    return name


def _kind(path: Path) -> str:
    """What ``path`` (which exists) is, in words, for a message."""
    import stat

    mode = path.stat().st_mode
    return ("a folder" if stat.S_ISDIR(mode) else "a named pipe" if stat.S_ISFIFO(mode) else "a device"
            if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode) else "not a file")


def check_input(src: str, key: str, value: str, base_dir: Path, *, allow_outside: bool = False) -> Path:
    """The path ``value`` (relative to ``base_dir``, ``~`` expanded) as it will be opened.

    Raises SceneError naming ``src``, ``key`` and ``value`` when it resolves (symbolic links
    followed, also for a file that does not exist yet) outside ``base_dir``, unless
    ``allow_outside``; and, always, when it exists and is not a regular file (a named pipe, a
    device, a folder: reading it could hang).
    """
    p = Path(value).expanduser()
    full = p if p.is_absolute() else base_dir / p
    if full.exists() and not full.is_file():  # a named pipe would hang the reader, a device never end
        raise _error(f"{src}: {key} = {value!r} is not a regular file ({_kind(full)}); name a file")
    if allow_outside or os.environ.get(ALLOW_ENV, "") == "1":
        return full
    root = Path(os.path.realpath(base_dir))
    real = Path(os.path.realpath(full))
    if real != root and root not in real.parents:
        raise _error(f"{src}: {key} = {value!r} is outside the scene's folder {root} (it resolves to {real}); "
                     f"scene files may only name files below their own folder: move the file there, or pass "
                     f"--allow-outside-paths (load_scene(..., allow_outside=True)) if you trust this scene")
    return full


def inside(path: Path, base_dir: Path) -> tuple[bool, Path, Path]:
    """(whether ``path`` resolves, symbolic links followed, to ``base_dir`` or below it, the resolved
    base_dir, the resolved path)."""
    root = Path(os.path.realpath(base_dir))
    real = Path(os.path.realpath(path))
    return real == root or root in real.parents, root, real


def table_parts(table_file) -> Path:
    """The row folder a table build derives from ``table_file`` (``single_cilium.table.build_table``)."""
    return Path(str(table_file) + ".parts")


def check_derived(src: str, key: str, what: str, path: Path, base_dir: Path, *, allow_outside: bool = False) -> Path:
    """``path``, a path the toolkit derives from the scene's ``key`` (``what`` says which), if it
    resolves (symbolic links followed) below ``base_dir``; else SceneError naming ``src``, the key
    and where it resolves to, unless ``allow_outside``."""
    path = Path(path)
    if allow_outside or os.environ.get(ALLOW_ENV, "") == "1":
        return path
    ok, root, real = inside(path, base_dir)
    if not ok:
        raise _error(f"{src}: {what} {path.name!r}, derived from {key}, resolves to {real}, outside the scene's "
                     f"folder {root} (a symbolic link there points elsewhere); nothing was written: remove the link, "
                     f"or pass --allow-outside-paths (load_scene(..., allow_outside=True)) if you trust this scene")
    return path


def check_scene_paths(src: str, data, base_dir: Path, *, allow_outside: bool = False) -> None:
    """Apply :func:`check_input` to ``table.file`` (unless "default") and ``target.file`` of the
    parsed TOML ``data``, before anything is opened. Values of the wrong type are left to the
    scene's own checks."""
    if not isinstance(data, dict):
        return
    for section, skip in (("table", "default"), ("target", None)):
        sec = data.get(section)
        v = sec.get("file") if isinstance(sec, dict) else None
        if isinstance(v, str) and v.strip() and v != skip:
            full = check_input(src, f"{section}.file", v, base_dir, allow_outside=allow_outside)
            if section == "table" and isinstance(sec.get("build"), dict):  # the build's row folder
                check_derived(src, "table.file", "the table build's row folder", table_parts(full), base_dir,
                              allow_outside=allow_outside)
