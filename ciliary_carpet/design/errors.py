"""The errors of a target (:mod:`ciliary_carpet.design.target`, :mod:`ciliary_carpet.design.surface_target`),
in a module of their own so that both raise the same classes."""
from __future__ import annotations

__all__ = ["TargetError", "UnreachableTargetError"]


class TargetError(ValueError):
    """A target that cannot be used: unreadable control file, unreachable angles, bad input."""


class UnreachableTargetError(TargetError):
    """Deflections outside the table's reachable range: a target the cilia cannot make."""
