"""The registry of target kinds: :data:`PATTERNS`, one :class:`Pattern` per value of ``[target] kind``.

Each pattern holds its formula (``A`` the amplitude in rad, ``w`` the width, ``xi = (x - centre) .
cross - line`` the cross-stream coordinate measured from the line, in the
:class:`~ciliary_carpet.design.frame.Frame` of the carpet), its deflection function and the
geometry keys it reads. The shear pattern is not antisymmetric about its line (unlike focus and
spread), so the three are distinct; the turn cannot push upstream, so it turns the flow fully
(+-A) where the tangent is across the stream and not at all where it runs with or against it (a
clipped tangent would jump from +A to -A behind the centre, which no superposition of Stokeslets
can follow).

Adding a target kind means adding a :class:`Pattern` here (and a key to the ``[target]`` section,
:class:`~ciliary_carpet.scenes.target_spec.TargetSpec`, if it needs one). The scene parser, the key
reference of ``designs/README.md`` and its kinds table (:func:`kinds_table`) are made from the
registry. The groups of kinds below (:data:`KINDS`, :data:`ANGLE_KINDS`, ...) are derived from it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Pattern", "PATTERNS", "PATTERN_OF", "KINDS", "ANGLE_KINDS", "SURFACE_KINDS", "DESIGNED_KINDS",
           "DIRECTION_KINDS", "STANDING_KINDS", "kinds_using", "kinds_table"]


@dataclass(frozen=True)
class Pattern:
    """One target kind of the registry :data:`PATTERNS`.

    Attributes
    ----------
    name : str
        The value of ``target.kind``.
    doc : str
        What it asks, with its formula (README kinds table).
    keys : tuple of str
        The ``[target]`` keys of its own geometry (line, width, centre, file); the keys every
        angle kind or every designed kind takes say so themselves (:class:`~ciliary_carpet.scenes.target_spec.TargetSpec`).
    deflection : callable or None
        ``f(target, points (P, 2), frame) -> delta (P,)`` [rad] for the angle kinds; None for
        "none" and "points".
    signed : bool
        ``target.angle`` is a signed deflection in [-180, 180] (else an amplitude in (0, 180]);
        for a surface kind a direction in [-180, 180].
    surface : bool
        A surface-flow kind of standing carpets: the direction of the mean flow on the plane
        z = ``height`` (:mod:`~ciliary_carpet.design.surface_target`), any direction.
    two_sided : bool
        The flow turns toward (or away from) a line from both sides: the design's estimate of
        the reachable amplitude of such a pattern applies
        (:func:`~ciliary_carpet.design.reachability.reachability`).

    A pattern whose ``keys`` hold ``"width"`` has a transition width (:attr:`has_width`): the
    reachability estimates the narrowest width it meets its threshold at.
    """

    name: str
    doc: str
    keys: tuple[str, ...] = ()
    deflection: Callable | None = None
    signed: bool = False
    two_sided: bool = False
    surface: bool = False

    @property
    def has_width(self) -> bool:
        """The pattern has a transition width (the ``[target]`` key ``width`` is one of its keys)."""
        return "width" in self.keys


def _across_line(t, x: np.ndarray, frame) -> np.ndarray:
    """tanh(xi / w), xi the cross-stream coordinate from the line, w the width (one spacing)."""
    w = t.width if t.width is not None else frame.spacing
    xi = frame.cross_coordinate(x) - t.line
    return np.tanh(xi / w)


def _turn(t, x: np.ndarray, frame) -> np.ndarray:
    """A times the sine of the angle from d0 to the anticlockwise tangent around the centre."""
    c = frame.centre if t.centre is None else np.asarray(t.centre)
    r = x - c
    tg = np.column_stack([-r[:, 1], r[:, 0]])  # anticlockwise tangent (unnormalised)
    n = np.hypot(tg[:, 0], tg[:, 1])
    return t.amplitude * np.where(n > 0, (tg @ frame.cross) / np.where(n > 0, n, 1.0), 0.0)


PATTERNS: tuple[Pattern, ...] = (
    Pattern("none", "no target: every cilium gets `carpet.chi_N`"),
    Pattern("uniform", "delta = A everywhere (A signed)",
            deflection=lambda t, x, fr: np.full(x.shape[0], t.amplitude), signed=True),
    Pattern("focus", "delta = -A tanh(xi / w): the flow turns toward the line from both sides", ("line", "width"),
            deflection=lambda t, x, fr: -t.amplitude * _across_line(t, x, fr), two_sided=True),
    Pattern("spread", "delta = +A tanh(xi / w): away from the line on both sides", ("line", "width"),
            deflection=lambda t, x, fr: t.amplitude * _across_line(t, x, fr), two_sided=True),
    Pattern("shear", "delta = (A / 2) (1 - tanh(xi / w)): the -cross side (direction 0: the left, x below the "
            "line) turned by A, the other side straight: two streams side by side, a layer of shear",
            ("line", "width"), deflection=lambda t, x, fr: 0.5 * t.amplitude * (1.0 - _across_line(t, x, fr))),
    Pattern("turn", "delta = A times the sine of the angle from d0 to the anticlockwise tangent around `centre`: "
            "full (+-A) upstream and downstream of the centre, zero beside it (the cilia cannot push upstream), "
            "smooth in between; 0 at the centre", ("centre",), deflection=_turn),
    Pattern("points", "target velocities (lab frame, model units L / tau) at control points read from `file` "
            "(a standing carpet: the mean flow on the plane z = `height`)", ("file",)),
    Pattern("pump", "standing carpets: the surface flow along `angle` (degrees anticlockwise from +x) everywhere",
            signed=True, surface=True),
    Pattern("vortex", "standing carpets: the surface flow circling `centre` (`sense`); points within half a "
            "spacing of the centre are left out", ("centre", "sense"), surface=True),
    Pattern("mixer", "standing carpets: two counter-rotating vortices at `centre` -+ (`separation` / 2) along "
            "`angle`, a jet between them; points within half a spacing of either centre are left out",
            ("centre", "separation", "sense"), signed=True, surface=True),
    Pattern("u_turn", "standing carpets: the surface flow comes in along `angle` on one side of the axis through "
            "`centre`, turns about `centre` and goes back on the other side (`sense`)", ("centre", "sense"),
            signed=True, surface=True),
    Pattern("source_sink", "standing carpets: out of a source at `centre` - (`separation` / 2) e and into a sink "
            "at `centre` + (`separation` / 2) e, e along `angle`", ("centre", "separation"), signed=True,
            surface=True),
)
"""The registry of target kinds."""
PATTERN_OF: dict[str, Pattern] = {p.name: p for p in PATTERNS}
"""Each kind's :class:`Pattern` by name."""
KINDS = tuple(PATTERN_OF)
"""Every value of ``[target] kind``."""
ANGLE_KINDS = tuple(p.name for p in PATTERNS if p.deflection is not None)
"""The deflection kinds of planar carpets (uniform and the patterns)."""
SURFACE_KINDS = tuple(p.name for p in PATTERNS if p.surface)
"""The surface-flow kinds of standing carpets (:mod:`~ciliary_carpet.design.surface_target`)."""
DESIGNED_KINDS = tuple(k for k in KINDS if k != "none")
"""The kinds a carpet is designed for (all but "none")."""
DIRECTION_KINDS = ANGLE_KINDS + SURFACE_KINDS
"""The kinds that ask for directions at control points (not velocities from a file)."""
STANDING_KINDS = SURFACE_KINDS + ("points",)
"""The target kinds of a standing carpet: the surface flows and velocities from a file."""


def kinds_using(key: str) -> tuple[str, ...]:
    """The kinds whose own geometry keys (:attr:`Pattern.keys`) hold the ``[target]`` key ``key``."""
    return tuple(p.name for p in PATTERNS if key in p.keys)


def kinds_table() -> str:
    """The "Target kinds" table of ``designs/README.md``: each kind, the keys of its own geometry
    (the others: the kinds column of the key table) and its pattern."""
    rows = ["| kind | its own keys | pattern |", "|---|---|---|"]
    for p in PATTERNS:
        ks = ", ".join(f"`{k}`" for k in p.keys) or "-"
        rows.append(f'| `"{p.name}"` | {ks} | {p.doc} |')
    return "\n".join(rows)
