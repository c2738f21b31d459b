"""The wall's effect on each cilium's own drag, and the viscosity's consistency with that drag
(section (a) of :mod:`ciliary_carpet.carpet.omissions`): slender-body theory's resistive
coefficients near a no-slip plane against the free-space ones the limit cycles use.

The limit cycles use free-space resistive coefficients, in slender-body form (Gray & Hancock
1955, with the filament's length as the cut-off; MODEL.md section 2
takes the slender limit c_perp = 2 c_par)

    c_par = 2 pi mu / (ln(2 L / a) - 1/2),   c_perp = 2 c_par,

for a filament of length L and radius a. A slender filament parallel to a no-slip plane at
height h, a << h << L, has instead (Katz, Blake & Paveri-Fontana 1975, J. Fluid Mech. 72, 529;
reviewed by Brennen & Winet 1977, Annu. Rev. Fluid Mech. 9, 339)

    c_par = 2 pi mu / ln(2 h / a),   c_perp = 4 pi mu / ln(2 h / a)   (normal, parallel to the wall),
    c_z = 4 pi mu / (ln(2 h / a) - 1)                                  (normal to the wall):

the wall's image system cuts the Stokeslet's logarithm off at 2 h instead of the filament's
length. These constants are checked against this package's Blake kernel (the velocity averaged
round the surface of a long singular Stokeslet line, tests/test_neglected.py: to 0.2 % at
h = 20 a, L = 1000 a). A planar carpet beats parallel to the wall, and its anisotropy stays 2,
so the wall scales the model's eta by one factor, the **closed form**

    ratio = (ln(2 L / a) - 1/2) / ln(2 h / a)     (:func:`wall_drag_formula`),

taken as 1 where it falls below 1 (h >= L e^{-1/2} = 0.61 L). Its O(1) constants matter at
the modest logarithms of a real cilium (L / a = 50), so the reported ratios are the same theory
evaluated for the finite filament (:func:`wall_drag_ratios`): a straight filament of length L
at height h, uniform force density along it or across it (parallel to the wall), its velocity
averaged round its surface (radius a) and along its length, with the singular Blake kernel, over
the same in free space. They tend to the closed form for a << h << L and to 1 smoothly as
h -> infinity (for a = 0.02 L and h = 0.05, 0.1, 0.2, 0.5, 1 L: along 2.12, 1.55, 1.28, 1.12,
1.06, across 2.59, 1.85, 1.46, 1.19, 1.10; the closed form 2.55, 1.78, 1.37, 1.05, 1); the
uniform force density (not a rigid rod's) makes them an O(1 / ln^2) estimate. NaN where
ln(2 h / a) <= 1 (h < 1.36 a: the filament touches the wall, lubrication, outside the theory);
the regime (:func:`wall_effect`) says whether h lies in a << h << L (taken as 5 a <= h <= L / 2).

For a planar carpet every filament point lies at the wall depth h = ``carpet.wall`` above the
wall, so that is the cilia's mean height; with no wall the ratios are 1. A standing carpet's
filaments rise from the wall (clamped on it, or ``carpet.wall`` above it): the same formulas are
evaluated at each cilium's mean height, its force centre's height above the wall
(``centre_z + wall``), as the estimate of the wall's effect on the filament as a whole; the
ratios are reported at the median of those heights and, the largest, at the lowest. The theory
is for a filament parallel to the wall, so for a standing one it is an order-of-magnitude
estimate (its base, at the wall, is slowed more; its tip less). A ratio of 1.5 means
the filament near the wall is 1.5 times as hard to move as its cycle assumes: it beats more
slowly than modelled, by what the single-cilium model with eta scaled by that factor gives
(MODEL.md section 4: the frequency falls as eta grows).

The viscosity. The Stokeslets use the carpet's viscosity ``mu`` (in B tau / L^4, the model's
unit: MODEL.md section 2 writes eta = mu_par L^4 / (tau B), so eta and mu are in the same units).
The filaments' tangential coefficient eta already implies, through the free-space c_par above,

    mu_sbt = eta (ln(2 L / a) - 1/2) / (2 pi)

(0.653 eta for a = 0.02 L; :func:`~ciliary_carpet.carpet.carpet.sbt_viscosity`), which is the
carpet's default (``mu_source = "filaments"``). A carpet given another viscosity
(``mu_source = "given"``, scene key ``[carpet] viscosity``) has flows mu_sbt / mu - 1 too fast
(negative: too slow) against the filaments' own drag (``flow_speed_error``; -35 % for mu = 1 = eta).

The filament radius a is the carpet's blob (its filament radius, :data:`~ciliary_carpet.carpet.carpet.BLOB`
when the carpet uses singular Stokeslets).
"""
from __future__ import annotations

import math

import numpy as np

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.stokes import Wall, make_kernel, stokeslet_velocity

__all__ = ["wall_drag_formula", "wall_drag_ratios", "wall_effect"]


def wall_drag_formula(h: float | None, a: float, length: float = 1.0) -> float:
    """The closed-form ratio of a slender filament's resistive coefficients at height ``h``
    above a no-slip plane (parallel to it, a << h << L) to the free-space ones the model uses,
    (ln(2L/a) - 1/2) / ln(2h/a), at least 1 (module docstring; Katz, Blake & Paveri-Fontana
    1975); 1 for ``h`` None (no wall); NaN where ln(2h/a) <= 1 (touching the wall)."""
    if h is None:
        return 1.0
    h, a = float(h), float(a)
    if not (h > 0 and a > 0):
        raise ValueError(f"need h > 0 and a > 0, got h = {h!r}, a = {a!r}")
    lg = math.log(2.0 * h / a)
    if lg <= 1.0:
        return math.nan
    return max(1.0, (math.log(2.0 * length / a) - 0.5) / lg)


def wall_drag_ratios(h: float | None, a: float, length: float = 1.0) -> tuple[float, float]:
    """(along, across) ratios of the resistance of a straight filament of length ``length`` and
    radius ``a`` parallel to a no-slip plane at height ``h`` to its resistance in free space, for
    motion along itself and across itself parallel to the wall (module docstring): a uniform
    force density on a line of singular Stokeslets, the velocity averaged round the surface and
    along the length, with and without Blake's image system. (1, 1) for ``h`` None; NaN where
    ln(2h/a) <= 1 (touching the wall)."""
    if h is None:
        return 1.0, 1.0
    if math.isnan(wall_drag_formula(h, a, length)):
        return math.nan, math.nan
    h, a, L = float(h), float(a), float(length)
    n = int(min(max(2001, 40 * L / a), 400_001)) | 1  # 40 sources per radius: the surface is resolved
    x = np.linspace(0.0, L, n)
    w = np.full(n, L / (n - 1))
    w[[0, -1]] *= 0.5
    src = np.stack([x, np.zeros(n), np.zeros(n)], axis=1)
    phi = 2.0 * np.pi * np.arange(8) / 8
    xs = L * (0.05 + 0.9 * np.arange(19) / 18)  # along the length, clear of the ends' 5 %
    tg = np.stack([np.repeat(xs, phi.size), np.tile(a * np.cos(phi), xs.size), np.tile(a * np.sin(phi), xs.size)],
                  axis=1)
    free, wall = make_kernel(None, 0.0), make_kernel(Wall(z=-h), 0.0)
    out = []
    for e in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        f = w[:, None] * e[None]
        uf = float((stokeslet_velocity(tg, src, f, kernel=free) @ e).mean())
        uw = float((stokeslet_velocity(tg, src, f, kernel=wall) @ e).mean())
        out.append(uf / uw)
    return out[0], out[1]


def wall_effect(carpet: Carpet, a: float) -> tuple[float | None, np.ndarray | None, float, float, tuple[float, float],
                                                   str]:
    """The wall's effect on the filaments of ``carpet`` of radius ``a`` (module docstring):
    (h, heights, along, across, lowest, regime). ``h`` the cilia's height above the wall (None
    without one; for a standing carpet the median of the cilia's mean heights, ``heights`` (N,),
    None otherwise), ``along``, ``across`` the ratios of :func:`wall_drag_ratios` at ``h``,
    ``lowest`` the same at the lowest mean height of a standing carpet (NaN otherwise) and
    ``regime`` in words."""
    h = None if carpet.wall is None else float(carpet.wall)
    heights = carpet.placement.mean_heights(carpet)  # each cilium's (its force centre's), None: all at h
    if heights is not None:
        h = float(np.median(heights))
    along, across = wall_drag_ratios(h, a)
    low = wall_drag_ratios(float(heights.min()), a) if heights is not None else (math.nan, math.nan)
    if h is None:
        regime = "no wall"
    elif not math.isfinite(across):
        regime = "h within a few filament radii: lubrication, outside slender-body theory"
    elif 5 * a <= h <= 0.5:
        regime = "a << h << L"
    elif h < 5 * a:
        regime = "h only a few radii: slender-body theory at its edge, the drag likely higher still"
    else:
        regime = "h comparable to L: the wall's effect is weak and only estimated"
    return h, heights, along, across, low, regime
