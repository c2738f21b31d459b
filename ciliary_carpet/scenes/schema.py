"""The scene-file schema: one home for each key's default, accepted values and meaning.

A section of a scene file (``[carpet]``, ``[target]``, ...) is a frozen dataclass whose fields
are made by :func:`key`: the field's default is the key's default, and its metadata (a
:class:`Key`) holds the accepted values (type, range, choices), the meaning and, for
``[target]``, the kinds the key applies to. From that one declaration

* :func:`read` checks a TOML table (unknown keys with a close match, types, NaN/inf, ranges)
  and returns the values of the plain keys; the section's parser adds the rules that tie keys
  together (:mod:`ciliary_carpet.scenes.scene`);
* :func:`section` writes the key list into the class docstring;
* :func:`markdown_table` writes the key reference of ``designs/README.md`` (a test checks the
  README against it: ``python -m ciliary_carpet.scenes.scene --reference`` prints the tables).

Every error is a :class:`SceneError` whose message names the file and the dotted key.
"""
from __future__ import annotations

import dataclasses
import difflib
import textwrap
from dataclasses import MISSING, dataclass, fields

import numpy as np

from single_cilium.checks import finite

__all__ = ["SceneError", "Key", "key", "keys_of", "reader", "values", "read", "validate", "section", "section_dict",
           "plain", "python_value", "markdown_table", "Section"]

TYPES = ("float", "int", "bool", "str", "pair", "pairs", "table", "custom")


class SceneError(ValueError):
    """A scene file that cannot be used; the message names the file and the dotted key."""


@dataclass(frozen=True)
class Key:
    """What one TOML key accepts, and what it means (the metadata of a section field).

    Attributes
    ----------
    type : str
        One of :data:`TYPES`: "float" (range ``lo``/``hi``, open ends ``lo_open``/``hi_open``),
        "int" (>= ``lo``), "bool", "str" (one of ``choices`` if given), "pair" ([x, y]), "pairs"
        ([[x, y], ...], or one of ``choices`` if given), "table" (a nested section, documented by
        its own class) or "custom" (read by the section's parser; the rest is documentation).
    doc : str
        The meaning (README table and docstring).
    what : str
        The accepted values as error messages say them (default: from type and range).
    shown : str
        The type column of the README (default: from type and range).
    default_shown : str
        The default column of the README (default: the field's default as TOML; needed where the
        default is None, i.e. decided later).
    kinds : tuple of str or None
        ``[target]`` keys: the target kinds the key applies to (None: every kind).
    """

    type: str
    doc: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple | None = None
    what: str | None = None
    shown: str | None = None
    default_shown: str | None = None
    kinds: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        if self.type not in TYPES:
            raise ValueError(f"Key.type must be one of {', '.join(TYPES)}, got {self.type!r}")

    def accepted(self) -> str:
        """The accepted values, as error messages say them."""
        if self.what is not None:
            return self.what
        if self.type == "float":
            return _describe_range(self.lo, self.hi, self.lo_open, self.hi_open)
        if self.type == "int":
            return "an integer" + _int_range(self.lo, self.hi)
        if self.type == "bool":
            return "true or false"
        if self.type == "str":
            return "one of " + ", ".join(repr(c) for c in self.choices) if self.choices else "a string"
        if self.type == "pair":
            return "two numbers [x, y]"
        if self.type == "pairs" and self.choices:
            return ", ".join(f'"{c}"' for c in self.choices) + " or a list of points [[x, y], ...]"
        return "a non-empty list of points [[x, y], ...]"

    def type_column(self) -> str:
        """The type column of the README table."""
        if self.shown is not None:
            return self.shown
        if self.type == "float":
            if self.lo is None and self.hi is None:
                return "float"
            if self.hi is None:
                return f"float {'>' if self.lo_open else '>='} {self.lo:g}"
            if self.lo is None:
                return f"float {'<' if self.hi_open else '<='} {self.hi:g}"
            return (f"float in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}"
                    f"{')' if self.hi_open else ']'}")
        if self.type == "int":
            return "int" + _int_range(self.lo, self.hi)
        if self.type == "str":
            return ", ".join(f'`"{c}"`' for c in self.choices) if self.choices else "string"
        if self.type == "pair":
            return "`[x, y]`"
        if self.type == "pairs":
            head = "".join(f'`"{c}"`, ' for c in self.choices or ())
            return head + "`[[x, y], ...]`"
        return self.type


def key(default=MISSING, doc: str = "", type: str = "float", **kw):
    """A section field: ``default`` (MISSING: required) and its :class:`Key` (``doc``, ``type``
    and the other :class:`Key` fields as keywords) as the field's metadata."""
    return dataclasses.field(default=default, metadata={"key": Key(type, doc, **kw)})


def keys_of(cls) -> dict:
    """``{name: (Key, default)}`` of the key fields of section class ``cls``, in order (the
    default is MISSING for a required key)."""
    return {f.name: (f.metadata["key"], f.default) for f in fields(cls) if "key" in f.metadata}


def _describe_range(lo, hi, lo_open, hi_open) -> str:
    if lo == 0 and lo_open and hi is None:
        return "a positive number"
    if lo == 0 and not lo_open and hi is None:
        return "a number >= 0"
    if lo is not None and hi is not None:
        return f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if lo is not None:
        return f"a number {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"a number {'<' if hi_open else '<='} {hi:g}"
    return "a number"


def _int_range(lo, hi) -> str:
    if lo is not None and hi is not None:
        return f" in [{lo:g}, {hi:g}]"
    if lo is not None:
        return f" >= {lo:g}"
    return f" <= {hi:g}" if hi is not None else ""


def python_value(v):
    """``v`` with numpy scalars as the Python numbers (and bools) they hold and numpy arrays as
    lists, recursively through lists, tuples and dicts: what a scene made in code may hold
    where a TOML file holds plain values."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return python_value(v.tolist())
    if isinstance(v, (list, tuple)):
        return [python_value(x) for x in v]
    if isinstance(v, dict):
        return {k: python_value(x) for k, x in v.items()}
    return v


# ------------------------------------------------------------------------------ reading
class Reader:
    """Validates one TOML table: the typed getters return checked values (the default when the
    key is absent), :meth:`fail` makes the error of a key."""

    def __init__(self, src: str, data, section: str, known: tuple[str, ...]):
        self.src, self.section, self.known = src, section, known
        if not isinstance(data, dict):
            raise SceneError(f"{src}: {self._where()} must be a table ({self._header()}), got {data!r}")
        unknown = [k for k in data if k not in known]
        if unknown:
            k = unknown[0]
            close = difflib.get_close_matches(k, known, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            where = f"{self._header()} unknown key" if section else "unknown top-level key"
            raise SceneError(f"{src}: {where} '{k}' (known: {', '.join(known)}){hint}")
        self.data = {k: python_value(v) for k, v in data.items()}

    def _where(self) -> str:
        return self.section or "the scene"

    def _header(self) -> str:
        return f"[{self.section}]" if self.section else "top level"

    def key(self, k: str) -> str:
        return f"{self.section}.{k}" if self.section else k

    def has(self, k: str) -> bool:
        return k in self.data

    def fail(self, k: str, what: str, value) -> SceneError:
        return SceneError(f"{self.src}: {self.key(k)} must be {what}, got {value!r}")

    def get(self, k: str, spec: Key, default):
        """The value of key ``k`` checked against ``spec`` (``default`` when absent)."""
        if k not in self.data:
            return default
        v, what = self.data[k], spec.accepted()
        if spec.type == "float":
            return self.number(k, v, spec, what)
        if spec.type == "int":
            if (isinstance(v, bool) or not isinstance(v, int) or (spec.lo is not None and v < spec.lo)
                    or (spec.hi is not None and v > spec.hi)):
                raise self.fail(k, what, v)
            return int(v)
        if spec.type == "bool":
            if not isinstance(v, bool):
                raise self.fail(k, what, v)
            return v
        if spec.type == "str":
            if not isinstance(v, str) or (spec.choices is not None and v not in spec.choices):
                raise self.fail(k, what, v)
            return v
        if spec.type == "pair":
            return _pair(self.src, self.key(k), v, what)
        if spec.type == "pairs":
            if isinstance(v, str) and spec.choices:
                if v not in spec.choices:
                    raise self.fail(k, what, v)
                return v
            return _pairs(self.src, self.key(k), v, what)
        raise TypeError(f"key {self.key(k)} of type {spec.type!r} is read by its section's parser")

    def number(self, k: str, v, spec: Key, what: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(k, what, v)
        try:
            x = finite(self.key(k), v)
        except ValueError:
            raise SceneError(f"{self.src}: {self.key(k)} must be a finite number, got {float(v)}") from None
        if spec.lo is not None and (x < spec.lo or (spec.lo_open and x == spec.lo)):
            raise self.fail(k, what, v)
        if spec.hi is not None and (x > spec.hi or (spec.hi_open and x == spec.hi)):
            raise self.fail(k, what, v)
        return x


def reader(src: str, cls, data, section: str | None = None, extra: tuple[str, ...] = ()) -> Reader:
    """A :class:`Reader` of the TOML table ``data`` for section class ``cls`` (``section``: its
    dotted name, default ``cls.SECTION``; ``extra``: further known keys, e.g. nested sections):
    unknown keys are an error here."""
    return Reader(src, data, cls.SECTION if section is None else section, tuple(keys_of(cls)) + extra)


def values(r: Reader, cls) -> dict:
    """``{name: value}`` of the keys of ``cls`` with a plain type, given (checked) or default;
    "table" and "custom" keys are left to the section's parser."""
    return {name: r.get(name, k, None if default is MISSING else default)
            for name, (k, default) in keys_of(cls).items() if k.type not in ("table", "custom")}


def read(src: str, cls, data, section: str | None = None, extra: tuple[str, ...] = ()) -> tuple[Reader, dict]:
    """:func:`reader` and :func:`values`: the Reader (for the section's own rules) and the values
    of the plain keys."""
    r = reader(src, cls, data, section, extra)
    return r, values(r, cls)


def validate(obj, parse, *args) -> None:
    """``__post_init__`` of a section: read its TOML form with the same checks as a file (so a
    section made in code or by ``dataclasses.replace`` is validated too) and store the
    normalised values (floats, tuples)."""
    for k, v in parse(f"<{type(obj).__name__}>", obj.to_dict(), *args).items():
        object.__setattr__(obj, k, v)


class Section:
    """Base of the section dataclasses: validated on construction (:func:`validate`), read from
    TOML by :meth:`parse` (the plain keys; sections with rules between keys extend it), written
    back by :meth:`to_dict`. ``SECTION`` is the section's dotted name ("" = top level)."""

    SECTION = ""

    def __post_init__(self) -> None:
        validate(self, self.parse)

    @classmethod
    def parse(cls, src: str, data) -> dict:
        """The keyword arguments of the section from its TOML table ``data`` (file ``src``)."""
        return read(src, cls, data)[1]

    def to_dict(self) -> dict:
        """The section as TOML types (None values left out)."""
        return section_dict(self)


def _finite_number(src: str, key: str, v, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SceneError(f"{src}: {key} must be {what}, got {v!r}")
    try:
        return finite(key, v)
    except ValueError:
        raise SceneError(f"{src}: {key} must be {what} (finite), got {float(v)}") from None


def _pair(src: str, key: str, v, what: str) -> tuple[float, float]:
    if not isinstance(v, (list, tuple)) or len(v) != 2:
        raise SceneError(f"{src}: {key} must be {what}, got {v!r}")
    return (_finite_number(src, key, v[0], what), _finite_number(src, key, v[1], what))


def _pairs(src: str, key: str, v, what: str) -> tuple[tuple[float, float], ...]:
    if not isinstance(v, (list, tuple)) or len(v) == 0:
        raise SceneError(f"{src}: {key} must be {what}, got {v!r}")
    return tuple(_pair(src, f"{key}[{i}]", p, "two numbers [x, y]") for i, p in enumerate(v))


# ------------------------------------------------------------------------------ sections
def plain(v):
    """Tuples to lists and numpy scalars to Python numbers, recursively (TOML/JSON-ready)."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (tuple, list)):
        return [plain(x) for x in v]
    return v


def section_dict(obj) -> dict:
    """The section ``obj`` as a dict of its TOML keys, None values left out."""
    out = {}
    for name in keys_of(type(obj)):
        v = getattr(obj, name)
        if v is not None:
            out[name] = plain(v)
    return out


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:g}" if v != 0 and (abs(v) < 1e-2 or abs(v) >= 1e6) else repr(v)
    return repr(v)


def default_column(k: Key, default) -> str:
    """The default column of the README table."""
    if k.default_shown is not None:
        return k.default_shown
    if default is MISSING:
        return "required"
    if default is None:
        return "absent"
    return f"`{_toml(default)}`"


def section(cls):
    """Class decorator of a section: appends the key list, made from the fields' metadata, to the
    docstring as its numpydoc ``Attributes`` (one per TOML key; the same text as the README table)."""
    lines = ["", "    Attributes", "    ----------"]
    for name, (k, default) in keys_of(cls).items():
        if k.type == "table":
            continue
        d = default_column(k, default).replace("`", "")
        kinds = f" (kind = {', '.join(k.kinds)})" if k.kinds is not None else ""
        lines.append(f"    {name} : {k.type_column().replace('`', '')}, default {d}{kinds}")
        lines += textwrap.wrap(k.doc.replace("`", "") + ".", 96, initial_indent=" " * 8, subsequent_indent=" " * 8)
    cls.__doc__ = (cls.__doc__ or "").rstrip() + "\n" + "\n".join(lines) + "\n"
    return cls


def markdown_table(*parts, kinds: bool = False) -> str:
    """The README key table of section classes: ``parts`` are classes or (prefix, class) pairs
    (a nested section's keys shown as ``prefix.key``); ``kinds`` adds the column of the target
    kinds a key applies to."""
    head = "| key | type | default |" + (" kinds |" if kinds else "") + " meaning |"
    rows = [head, "|---|---|---|" + ("---|" if kinds else "") + "---|"]
    for part in parts:
        prefix, cls = part if isinstance(part, tuple) else ("", part)
        for name, (k, default) in keys_of(cls).items():
            if k.type == "table":
                continue
            cells = [f"`{prefix}{name}`", k.type_column(), default_column(k, default)]
            if kinds:
                cells.append("all" if k.kinds is None else ", ".join(k.kinds))
            cells.append(k.doc)
            rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)
