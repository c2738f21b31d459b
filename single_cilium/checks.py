"""Checks of scalar inputs, shared by both packages: one finite-number validator.

:func:`finite` and :func:`positive` turn a value into a float or raise ValueError naming the
argument; every parameter class and front door of :mod:`single_cilium` and :mod:`ciliary_carpet`
(the parameters, the flow sums' viscosity and precision, the VTK writers' times, the scene
reader's numbers) checks its numbers here.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["finite", "positive"]


def finite(name: str, value: Any) -> float:
    """``value`` as a finite float, or ValueError naming ``name`` (not a real number, NaN, inf).
    A complex value is refused even with a zero imaginary part (``float`` of a numpy complex
    would drop the imaginary part with only a warning)."""
    if isinstance(value, (complex, np.complexfloating)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x}")
    return x


def positive(name: str, value: Any) -> float:
    """``value`` as a finite float > 0, or ValueError naming ``name``."""
    x = finite(name, value)
    if x <= 0.0:
        raise ValueError(f"{name} must be > 0, got {x}")
    return x
