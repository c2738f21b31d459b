"""Single-precision sums: what the CPU's and the GPU's fp32 backends share.

:class:`~ciliary_carpet.stokes.direct.Direct` (``"fp32"``) and
:class:`~ciliary_carpet.stokes.cuda.Cuda` (``"fp32"``, ``"fp32-acc64"``) round their inputs to
fp32 in the same way and are bounded by the same formula:

* the shift (:func:`origin`): coordinates are moved to the centre of the bounding box of
  targets and sources (x, y and, where the kernel allows any origin, z; heights stay above the
  wall), in fp64, before they are rounded, so that the rounding of ``x - xi`` is ``u L`` with
  ``L`` the largest *shifted* coordinate, not the distance from the world's origin;
* the pair formulas (:func:`retyped`): the Python source of each of
  :data:`~ciliary_carpet.stokes.kernel.PAIRS` compiled again with its constants
  (:data:`~ciliary_carpet.stokes.kernel.PAIR_CONSTANTS`) as float32, so that no literal
  promotes the arithmetic to fp64;
* the bound (:func:`fp32_error_bound`). With ``u = 2^-24``, ``rho_ij = sqrt(|x_i - xi_j|^2 +
  eps^2)`` (coincident singular pairs left out) and ``n_i`` the number of terms summed in fp32
  one after another for target ``i``, each velocity component errs by at most

  .. math::

      |u_i^{32} - u_i| \\le (C + a\\, n_i)\\, u\\, B_i, \\qquad
      B_i = \\frac{1}{8 \\pi \\mu} \\sum_j \\frac{|f_j|}{\\rho_{ij}}
            \\left(1 + \\frac{L}{\\rho_{ij}}\\right),

  ``C`` = :data:`FP32_PAIR_CONSTANT` (the rounding of the shifted inputs, whose relative
  perturbation of ``x - xi`` is ``u L / rho``, and of the pair's arithmetic) and ``a = 2`` (the
  summation bound ``n u sum_j |t_j|``, with ``|t_j| = |G f_j| <= 2 |f_j| / rho_ij`` for all four
  kernels: exact for the free ones, sampled maximum 1.99998 over heights and directions for the
  wall ones). A sum in fp32 blocks of ``b`` terms whose block sums are added in fp64 (the CPU's
  ``"fp32"``: :data:`FP32_BLOCK`) has ``n_i <= b``; fp32 pairs summed in fp64 (the GPU's
  ``"fp32-acc64"``) ``a = 2^-28``.
"""
from __future__ import annotations

import types

import numpy as np

from ciliary_carpet.stokes.kernel import INV_8PI, PAIR_CONSTANTS, Kernel

__all__ = ["FP32_BLOCK", "FP32_PAIR_CONSTANT", "U32", "fp32_error_bound", "fp32_sources", "origin", "retyped", "soa"]

U32 = 2.0 ** -24
"""The unit roundoff of fp32."""

FP32_PAIR_CONSTANT = 32.0
"""``C`` of the fp32 error bound (module docstring): the rounding of the shifted inputs and of the
pair's arithmetic, in units of ``u B_i``. The pair formulas have at most ~20 roundings and the
Blake image terms at most ~10 times the free-space magnitude ``|f| / rho``; measured maxima of
``|error| / (u B_i)`` on the tests' random cases: below 1 for every kernel (tests/test_cuda.py,
tests/test_stokeslet.py)."""

FP32_BLOCK = 128
"""Sources summed in fp32 one after another by the CPU's fp32 sums before their block sum is added
in fp64 (:class:`~ciliary_carpet.stokes.direct.Direct` ``"fp32"``): the ``n_i`` of the bound is at
most this. The cost per pair for each block size: benchmarks/results/bench_evaluation.md."""


def origin(kernel: Kernel, targets: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """(3,) the shift applied before rounding: the centre of the bounding box of ``targets`` (M, 3)
    and ``sources`` (N, 3) (x, y; z too where the kernel allows any origin), else the kernel's
    :attr:`~ciliary_carpet.stokes.kernel.Kernel.z_origin` (the wall height: the kernels take
    heights above the wall)."""
    lo = np.minimum(targets.min(axis=0), sources.min(axis=0))
    hi = np.maximum(targets.max(axis=0), sources.max(axis=0))
    o = 0.5 * (lo + hi)
    if kernel.z_origin is not None:
        o[2] = kernel.z_origin
    return o


def soa(a: np.ndarray, dtype, shift=None) -> np.ndarray:
    """(K, 3) -> C-contiguous (3, K) of ``dtype``, shifted by ``-shift`` (3,) in fp64 first."""
    if shift is None:
        return np.ascontiguousarray(a.T, dtype=dtype)
    out = np.array(a.T, dtype=np.float64, order="C", copy=True)
    out -= shift[:, None]
    return np.ascontiguousarray(out, dtype=dtype)


def fp32_sources(kernel: Kernel, sources: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(shift, rounded)``: fixed ``sources`` (N, 3) rounded once for many fp32 sums
    (:func:`~ciliary_carpet.stokes.direct.ranged_fp32`): shifted by ``-shift`` (3,), the centre of
    their bounding box (:func:`origin`), and rounded to fp32 as coordinate rows (3, N)."""
    shift = origin(kernel, sources, sources)
    return shift, soa(sources, np.float32, shift)


def retyped(fn, fp32: bool, **extra):
    """A copy of the Python function ``fn`` (a pair formula's ``py_func``) whose pair constants are
    float32 (for ``fp32``) and whose globals ``extra`` are replaced (e.g. ``rsqrt``)."""
    g = dict(fn.__globals__)
    if fp32:
        g.update({k: np.float32(g[k]) for k in PAIR_CONSTANTS})
    g.update(extra)
    return types.FunctionType(fn.__code__, g, fn.__name__ + ("_fp32" if fp32 else "_fp64"), fn.__defaults__,
                              fn.__closure__)


def fp32_error_bound(kernel: Kernel, targets, sources, forces, mu: float = 1.0, *, precision: str = "fp32",
                     terms=None, block: int | None = None) -> np.ndarray:
    """The bound (M,) of the error of each velocity component of an fp32 sum (module docstring):
    ``(C + a n_i) u B_i``, ``a = 2`` (``"fp32"``) or ``2^-28`` (``"fp32-acc64"``).

    Parameters
    ----------
    kernel : Kernel
    targets, sources, forces : (M, 3), (N, 3), (N, 3) float arrays
    mu : float
    precision : "fp32" or "fp32-acc64"
    terms : (M,) int array, optional
        ``n_i``, the number of sources summed for each target (default N, the dense sum); ``B_i``
        is then an upper bound too (it sums over all N sources).
    block : int, optional
        Sums in fp32 blocks of at most this many terms, added in fp64 (the CPU's fp32,
        :data:`FP32_BLOCK`): ``n_i`` is at most ``block``.
    """
    if precision not in ("fp32", "fp32-acc64"):
        raise ValueError(f"precision must be 'fp32' or 'fp32-acc64', got {precision!r}")
    t = np.asarray(targets, float)
    s = np.asarray(sources, float)
    f = np.asarray(forces, float)
    o = origin(kernel, t, s)
    L = float(max(np.abs(t - o).max(), np.abs(s - o).max()))
    rho = np.sqrt(np.sum((t[:, None, :] - s[None, :, :]) ** 2, axis=-1) + kernel.eps ** 2)
    fn = np.linalg.norm(f, axis=1)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.where(rho > 0, fn / rho * (1.0 + L / rho), 0.0)
    B = b.sum(axis=1) * INV_8PI / mu
    n = np.full(t.shape[0], s.shape[0]) if terms is None else np.asarray(terms)
    if block is not None:
        n = np.minimum(n, int(block))
    a = 2.0 if precision == "fp32" else 2.0 ** -28
    return (FP32_PAIR_CONSTANT + a * n) * U32 * B
