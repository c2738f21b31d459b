"""Equilibrium shapes of the clamped filament (MODEL.md section 3), in closed form.

At rest the drag vanishes and the angle ``theta(s)`` of the tangent solves the scalar problem

.. math::

    \\theta'(s) + \\chi_E \\sin\\theta(s) = \\chi_N, \\qquad \\theta(0) = \\varphi,

with ``theta`` the anticlockwise angle of the tangent from ``e2`` (the field direction), so the unit
tangent is ``t = (-sin theta, cos theta)`` and the position ``r(s) = int_0^s t`` with the clamp at
the origin.

Method
------
With ``u = tan(theta/2) = p/q`` the equation is the Riccati equation
``u' = (chi_N/2) u^2 - chi_E u + chi_N/2``, whose flow is linear in ``v = (p, q)``:
``v' = H v`` with the traceless ``H = [[-chi_E/2, chi_N/2], [-chi_N/2, chi_E/2]]``,
``H^2 = lambda^2 I``, ``lambda^2 = (chi_E - chi_N)(chi_E + chi_N)/4``. Hence
``v(s) = exp(sH) v0`` with ``v0 = (sin(phi/2), cos(phi/2))`` and
``exp(sH) = C(s) I + S(s) H`` where ``C = cosh(lambda s)``, ``S = sinh(lambda s)/lambda``
(``cos``/``sin`` when ``lambda^2 < 0``). In the orthonormal frame ``(v0, v0_perp)``,

* ``v = (C + S a/2, S f/2)`` with ``a = chi_E cos(phi)``,
  ``f = chi_N - chi_E sin(phi) = theta'(0)``;
  ``theta = phi + 2 * (angle of v)``: the half-angle increment is an ``atan2``;
* ``(|v|^2)' = chi_E cos(theta) |v|^2``, hence ``y(s) = ln|v(s)|^2 / chi_E``, and
  ``|v|^2 - 1 = chi_E G`` with ``G = S^2 (chi_E - chi_N sin(phi))/2 + C S cos(phi)``, hence
  ``y = log1p(chi_E G)/chi_E`` (``= G`` at ``chi_E = 0``);
* ``x = (theta - phi - chi_N s)/chi_E`` (from ``-sin(theta) = (theta' - chi_N)/chi_E``).

Every formula is arranged so that no term overflows and no cancellation occurs that the problem
itself does not have: the hyperbolic case is scaled by ``exp(-lambda s)`` (``E = exp(-2 lambda s)``,
``T = (1 - E)/(2 lambda)``), ``b + a`` is computed as ``-f g/(b - a)`` (``b = 2 lambda``,
``g = chi_N + chi_E sin(phi)``) when ``a < 0``, and in the coiled case (``|chi_E| < |chi_N|``)
the phase is reduced modulo the period and ``x`` is computed from the angle of ``v`` relative to
the ``chi_E = 0`` rotation, with ``chi_E`` factored out analytically. Negative ``chi_N`` is mapped
to positive ``chi_N`` by the mirror symmetry ``theta -> -theta``, which therefore holds exactly.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from single_cilium.checks import finite
from single_cilium.params import CiliumParams

__all__ = ["NoLimitAngleError", "equilibrium", "equilibrium_shape", "limit_angle"]

_SMALL_Z = 1e-8  # below this |z|, log1p(z)/z and atan(z)/z use two-term series
_TINY = 1e-280  # |v| components below this are rescaled before atan2 / log (underflow)
CHI_MAX = 1e300  # |chi_E|, |chi_N| and s max(|chi_E|, |chi_N|) above this are refused (overflow)


class NoLimitAngleError(ValueError):
    """Raised by :func:`limit_angle` when ``theta(s)`` has no limit as ``s -> inf`` (coiling)."""


# ----------------------------------------------------------------------------------------------
# validation
# ----------------------------------------------------------------------------------------------
def _check_s(s: ArrayLike) -> NDArray[np.float64]:
    try:
        arr = np.asarray(s)
        if np.iscomplexobj(arr):
            raise TypeError
        arr = arr.astype(np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"s must be an array of real numbers, got {s!r}") from None
    if not np.all(np.isfinite(arr)):
        raise ValueError("s must be finite (got NaN or inf)")
    if np.any(arr < 0.0):
        raise ValueError(f"s must be >= 0 (arc length from the clamp), got min(s) = {arr.min()}")
    return arr


def _check_phi(phi: float) -> float:
    return finite("phi", phi)


def _groups(params: CiliumParams) -> tuple[float, float]:
    if getattr(params, "has_background", False):
        raise ValueError(
            f"the closed-form equilibrium holds in fluid at rest, but {params} is in a background flow: "
            "there the equilibrium is the steady state of the discrete system, "
            "single_cilium.steady_state(params) (or Filament(params, mesh).equilibrium_state()); "
            "params.with_background((0, 0)) gives the still-fluid closed form")
    chi_E, chi_N = float(params.chi_E), float(params.chi_N)
    if not (math.isfinite(chi_E) and math.isfinite(chi_N)):
        raise ValueError(f"params.chi_E and params.chi_N must be finite, got {chi_E}, {chi_N}")
    for k, v in (("chi_E", chi_E), ("chi_N", chi_N)):
        if abs(v) > CHI_MAX:
            raise ValueError(f"params.{k} = {v:g} is beyond the range of the closed form (|{k}| <= {CHI_MAX:g})")
    return chi_E, chi_N


# ----------------------------------------------------------------------------------------------
# small helpers without cancellation
# ----------------------------------------------------------------------------------------------
def _log1p_over(c: float, G: NDArray[np.float64]) -> NDArray[np.float64]:
    """``log1p(c G)/c`` (``= G`` at ``c = 0``), accurate relative to ``G`` for any ``c``."""
    z = c * G
    out = np.empty_like(G)
    small = np.abs(z) < _SMALL_Z
    out[small] = G[small] * (1.0 - z[small] / 2.0)
    big = ~small
    out[big] = np.log1p(z[big]) / c
    return out


def _atan2_over(c: float, N: NDArray[np.float64], D: NDArray[np.float64]) -> NDArray[np.float64]:
    """``atan2(c N, D)/c`` (``= N/D`` at ``c = 0``), accurate relative to the result."""
    out = np.empty_like(N)
    small = (D > 0.0) & (np.abs(c * N) < _SMALL_Z * D)
    ratio = N[small] / D[small]
    z = c * ratio
    out[small] = ratio * (1.0 - z * z / 3.0)
    big = ~small
    out[big] = np.arctan2(c * N[big], D[big]) / c
    return out


def _sinhc(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """``sinh(z)/z`` with the value 1 at 0."""
    out = np.ones_like(z)
    nz = z != 0.0
    out[nz] = np.sinh(z[nz]) / z[nz]
    return out


# ----------------------------------------------------------------------------------------------
# the closed form, for chi_N >= 0 (the mirror image is handled by the caller)
# ----------------------------------------------------------------------------------------------
def _canonical(
    chi_E: float, chi_N: float, phi: float, s: NDArray[np.float64], shape: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64] | None]:
    sp, cp = math.sin(phi), math.cos(phi)
    f = chi_N - chi_E * sp  # theta'(0)
    if f == 0.0:  # phi is a fixed point (includes chi_E = chi_N = 0): the constant solution
        theta = np.full_like(s, phi)
        return theta, (-sp * s if shape else None), (cp * s if shape else None)

    a = chi_E * cp
    # 4 lambda^2 = (chi_E - chi_N)(chi_E + chi_N), factored (no cancellation); its sign is that of
    # |chi_E| - |chi_N| exactly, and its square root is taken factor by factor (halved), so that
    # nothing overflows for |chi| up to the largest double; below 2^-1000 halving would round
    # subnormals to 0 (w = 0 for chi_E = 0, chi_N = 5e-324), and there nothing can overflow
    if max(abs(chi_E), chi_N) >= 2.0 ** -1000:
        dm, dp = 0.5 * chi_E - 0.5 * chi_N, 0.5 * chi_E + 0.5 * chi_N
        root = 2.0 * math.sqrt(abs(dm)) * math.sqrt(abs(dp))  # sqrt(|4 lambda^2|)
    else:
        root = math.sqrt(abs(chi_E - chi_N)) * math.sqrt(abs(chi_E + chi_N))
    x = y = None
    if abs(chi_E) >= chi_N:
        # a fixed point exists: |theta - phi| < 2 pi, one atan2 suffices. (chi_E != 0 here:
        # chi_E = 0 would force chi_N = 0 and f = 0.)
        b = root  # 2 lambda >= 0
        g = chi_N + chi_E * sp
        # b + a without cancellation (b^2 - a^2 = -f g); f g may overflow for |chi| > 1e154
        fg = f * g
        bpa = b + a if a >= 0.0 else (-fg / (b - a) if math.isfinite(fg) else -(f / (b - a)) * g)
        bs = b * s
        with np.errstate(under="ignore"):
            E = np.exp(-bs)
        T = -np.expm1(-bs) / b if b > 0.0 else s.copy()  # (1 - E)/b, -> s as b -> 0
        cross = T * f
        dot = 2.0 * E + T * bpa  # = 1 + E + T a; < 0 only once |theta - phi| has passed pi
        h = np.arctan2(cross, dot)  # half of theta - phi, in (-pi, pi)
        # both underflow (|f| and b + a near the smallest doubles): the same in units of T > 0
        lo = (np.abs(cross) < _TINY) & (np.abs(dot) < _TINY) & (T > 0.0)
        with np.errstate(under="ignore"):  # 2 E / T in logs: E itself may have underflowed where 2 E / T has not
            q = (np.exp(math.log(2.0 * b) - bs[lo]) / -np.expm1(-bs[lo]) if b > 0.0 else 2.0 * E[lo] / T[lo]) + bpa
        h[lo] = np.arctan2(f, q)
        theta = phi + 2.0 * h
        if shape:
            x = (2.0 * h - chi_N * s) / chi_E
            y = np.empty_like(s)
            near = np.abs(chi_E) * s <= 1.0  # |v|^2 = O(1): log1p form
            sn = s[near]
            lam_s = 0.5 * b * sn
            S = sn * _sinhc(lam_s)
            G = S * (S * (chi_E - chi_N * sp) / 2.0 + np.cosh(lam_s) * cp)  # S^2 alone may underflow
            y[near] = _log1p_over(chi_E, G)
            far = ~near  # |chi_E| s > 1: ln|v|^2 = b s + 2 ln(|scaled v|), error ~ eps s
            with np.errstate(divide="ignore"):  # log(0) where lo: replaced on the next line
                lv = np.log(0.5 * np.hypot(cross, dot), where=far, out=np.zeros_like(s))
            lv[lo] = np.log(T[lo]) + (np.log(np.hypot(f, q)) - math.log(2.0))  # (halving 5e-324 gives 0)
            y[far] = (bs[far] + 2.0 * lv[far]) / chi_E
    else:
        # coiled: |chi_E| < chi_N, f > 0, theta increases by 2 pi per period 2 pi / w
        w = root
        psi = 0.5 * w * s  # rotation phase of v; theta - phi advances by 2 pi per pi of psi
        k, r = np.divmod(psi, math.pi)
        sr, cr = np.sin(r), np.cos(r)  # sr >= 0 on [0, pi]
        cross = sr * (f / w)
        dot = cr + sr * (a / w)
        h = np.arctan2(cross, dot)  # in [0, pi]
        theta = phi + 2.0 * (h + k * math.pi)
        if shape:
            # theta - phi - chi_N s = 2 (h - r) - chi_E^2 s/(chi_N + w); the angle h - r of v
            # relative to the chi_E = 0 rotation is atan2(chi_E N, 1 + chi_E M).
            c = chi_E / (chi_N + w)
            q = sr / w
            N = q * (cr * (c - sp) - sr * cp)
            M = q * (sr * (c - sp) + cr * cp)
            x = 2.0 * _atan2_over(chi_E, N, 1.0 + chi_E * M) - c * s
            S = 2.0 * q
            G = S * (S * (chi_E - chi_N * sp) / 2.0 + cr * cp)  # S^2 alone may underflow
            y = _log1p_over(chi_E, G)
    return theta, x, y


def _solve(
    params: CiliumParams, s: ArrayLike, phi: float, shape: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None, NDArray[np.float64] | None]:
    chi_E, chi_N = _groups(params)
    s_arr = _check_s(s)
    phi = _check_phi(phi)
    flat = s_arr.reshape(-1)
    top = float(flat.max()) * max(abs(chi_E), abs(chi_N)) if flat.size else 0.0
    if top > CHI_MAX:
        raise ValueError(f"s up to {float(flat.max()):g} with max(|chi_E|, |chi_N|) = {max(abs(chi_E), abs(chi_N)):g}: "
                         f"s |chi| = {top:g} is beyond the range of the closed form (<= {CHI_MAX:g})")
    # mirror to chi_N >= 0 (and phi >= 0 when chi_N = 0): theta -> -theta, x -> -x, y -> y
    sign = -1.0 if (chi_N < 0.0 or (chi_N == 0.0 and phi < 0.0)) else 1.0
    theta, x, y = _canonical(chi_E, abs(chi_N), sign * phi, flat, shape)
    theta = (sign * theta).reshape(s_arr.shape)
    if shape:
        assert x is not None and y is not None
        x = (sign * x).reshape(s_arr.shape)
        y = y.reshape(s_arr.shape)
    return theta, x, y


# ----------------------------------------------------------------------------------------------
# public API
# ----------------------------------------------------------------------------------------------
def equilibrium(params: CiliumParams, s: ArrayLike, phi: float = 0.0) -> np.ndarray:
    """Equilibrium angle ``theta_eq(s)``: the solution of ``theta' + chi_E sin(theta) = chi_N``.

    Solves ``theta'(s) + chi_E sin(theta(s)) = chi_N`` for ``s >= 0`` with ``theta(0) = phi``
    exactly (closed form, see the module docstring), in every regime: large ``|chi_E|`` (the
    boundary layer of width ``1/(chi_E cos(theta_lim))`` at the clamp), ``chi_E = +-chi_N`` and its
    neighbourhood, ``chi_E = 0`` (an arc), ``chi_N = 0``, ``phi`` at a fixed point (constant
    solution), and the coiled regime ``|chi_E| < |chi_N|`` in which ``theta`` winds by
    ``2 pi sign(chi_N)`` per period ``2 pi / sqrt(chi_N^2 - chi_E^2)``.

    Parameters
    ----------
    params : CiliumParams
        Only ``chi_E`` (stimulus, sign of the field along ``e2``) and ``chi_N`` (natural curvature)
        are used.
    s : array_like of float, any shape
        Arc lengths, finite and ``>= 0``; ``s > 1`` is allowed (the equation is continued).
    phi : float, default 0
        Clamp angle ``theta(0)`` (radians, anticlockwise from ``e2``).

    Returns
    -------
    numpy.ndarray of float, shape ``np.shape(s)``
        ``theta_eq(s)``, the angle of the tangent ``t = (-sin theta, cos theta)`` from ``e2``,
        anticlockwise positive. It is the continuous solution: no ``2 pi`` jumps, windings are
        counted (e.g. ``chi_E = 0``: ``theta = phi + chi_N s``).

    Raises
    ------
    ValueError
        If ``s`` is not real, not finite or negative (message names ``s``), or ``phi`` is not a
        finite real number (message names ``phi``); or ``params`` has a background flow (the
        closed form holds in fluid at rest: use :func:`single_cilium.steady.steady_state` there).

    Notes
    -----
    The mirror symmetry ``theta(s; chi_E, -chi_N, -phi) = -theta(s; chi_E, chi_N, phi)`` holds
    exactly (it is used to reduce to ``chi_N >= 0``). At an unstable fixed point ``phi`` (e.g.
    ``phi = 0``, ``chi_N = 0``, ``chi_E < 0``) the solution is constant when
    ``chi_N - chi_E sin(phi)`` evaluates to exactly 0; otherwise the rounded ``phi`` departs from it
    as the true solution for that ``phi`` does (exponentially, at rate ``|chi_E cos(phi)|``).
    """
    theta, _, _ = _solve(params, s, phi, shape=False)
    return theta


def equilibrium_shape(
    params: CiliumParams, s: ArrayLike, phi: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Position ``r(s) = (x, y) = int_0^s t`` of the equilibrium filament, clamp at the origin.

    ``t = (-sin theta, cos theta)`` with ``theta = equilibrium(params, s, phi)``; ``e2`` (the
    ``y`` axis) is the field direction, ``x`` is along ``e1``. Closed forms (see the module
    docstring): ``x = (theta - phi - chi_N s)/chi_E`` and ``y = ln|v(s)|^2/chi_E``, each evaluated
    in a form without cancellation, so that no quadrature is needed. Measured absolute error:
    <= 1e-14 against subdivided adaptive quadrature of the tangent for 532 parameter sets
    (``|chi_E|`` from 0 to 1e4, ``chi_E = +-chi_N (1 +- 1e-12)``, coiled and folded, ``s <= 2.5``),
    <= 4e-16 against 40-digit arithmetic on the hardest of them.

    Parameters
    ----------
    params : CiliumParams
        Only ``chi_E`` and ``chi_N`` are used.
    s : array_like of float, any shape
        Arc lengths, finite and ``>= 0``.
    phi : float, default 0
        Clamp angle ``theta(0)``.

    Returns
    -------
    x, y : numpy.ndarray of float, each of shape ``np.shape(s)``
        Coordinates along ``e1`` and ``e2``. Mirror image: ``chi_N -> -chi_N``, ``phi -> -phi``
        maps ``(x, y) -> (-x, y)``.

    Raises
    ------
    ValueError
        As :func:`equilibrium`.
    """
    _, x, y = _solve(params, s, phi, shape=True)
    assert x is not None and y is not None
    return x, y


def limit_angle(params: CiliumParams) -> float:
    """``lim_{s -> inf} theta_eq(s)`` for the clamp ``phi = 0``.

    * ``chi_E > 0``, ``|chi_N| <= chi_E``: ``arcsin(chi_N/chi_E)`` (the stable fixed point;
      ``+-pi/2`` at ``chi_N = +-chi_E``, approached algebraically).
    * ``chi_E < 0``, ``chi_N != 0``, ``|chi_N| <= |chi_E|``: the filament folds over; ``theta``
      runs from 0 in the direction of ``sign(chi_N)`` to the stable fixed point
      ``sign(chi_N) pi - arcsin(chi_N/chi_E)``, whose modulus lies in ``(pi, 3 pi/2]``
      (``3 pi/2 sign(chi_N)`` at ``chi_E = -|chi_N|``: the limit of the continuous ``theta``,
      equal to ``-+pi/2`` modulo ``2 pi``). So an arbitrarily small ``chi_N`` flips the filament.
    * ``chi_E < 0``, ``chi_N = 0``: ``theta`` stays at the unstable fixed point 0; returns 0.
    * ``chi_E = chi_N = 0``: ``theta = 0`` for all ``s``; returns 0.

    Parameters
    ----------
    params : CiliumParams
        Only ``chi_E`` and ``chi_N`` are used.

    Returns
    -------
    float
        The limit angle (radians, anticlockwise from ``e2``).

    Raises
    ------
    NoLimitAngleError
        (a ``ValueError``) If ``|chi_E| < |chi_N|`` (including ``chi_E = 0 != chi_N``): there is
        no fixed point, the filament coils and ``theta`` winds without limit.
    ValueError
        If ``params`` has a background flow (a property of the still-fluid closed form).
    """
    chi_E, chi_N = _groups(params)
    if chi_E == 0.0 and chi_N == 0.0:
        return 0.0
    if abs(chi_E) < abs(chi_N):
        raise NoLimitAngleError(
            f"no limit angle for chi_E = {chi_E!r}, chi_N = {chi_N!r}: with |chi_E| < |chi_N| the "
            "equilibrium has no fixed point, the filament coils and theta winds without limit "
            "(by 2 pi every 2 pi/sqrt(chi_N^2 - chi_E^2) of arc length); a limit angle needs "
            "|chi_E| >= |chi_N|"
        )
    r = chi_N / chi_E  # |r| <= 1 exactly (division is monotone)
    if chi_E > 0.0:
        return math.asin(r)
    if chi_N == 0.0:
        return 0.0
    return math.copysign(math.pi, chi_N) - math.asin(r)
