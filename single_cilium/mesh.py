"""Spectral-element mesh of the arc length s in [0, 1], graded geometrically towards the clamp.

The clamp boundary layer of the equilibrium has width ``delta ~ 1 / (|chi_E| cos theta_lim)``
(MODEL.md section 3; about 0.005 at chi_E = 200). A geometric mesh (element sizes growing by a
fixed ratio away from the clamp) with high-degree polynomials on each element resolves such a
layer with exponential convergence in the degree (hp finite elements), which a uniform mesh or a
single Chebyshev domain cannot do at comparable size.

On each element the unknowns are nodal values at the Gauss-Lobatto-Legendre (GLL) points; nodes
on element interfaces are shared (continuous, C0 functions). All integrals use the composite GLL
rule, whose weights are the :attr:`Mesh.weights`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numpy.polynomial import legendre as npleg

from .params import CiliumParams

__all__ = ["Mesh", "gll"]


def gll(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Lobatto-Legendre nodes and weights on [-1, 1] for polynomials of the given degree.

    Returns ``degree + 1`` nodes (the end points and the roots of ``P_degree'``) in increasing
    order and the weights ``2 / (p (p + 1) P_p(x)^2)``; the rule is exact to degree ``2p - 1``.
    """
    p = int(degree)
    if p < 1:
        raise ValueError(f"degree must be >= 1, got {degree}")
    cp = np.zeros(p + 1)
    cp[-1] = 1.0
    interior = npleg.legroots(npleg.legder(cp)) if p > 1 else np.empty(0)
    x = np.concatenate(([-1.0], np.sort(interior.real), [1.0]))
    # one Newton polish of the interior roots of P_p' (legroots is accurate to ~1e-15 already)
    d1, d2 = npleg.legder(cp), npleg.legder(cp, 2)
    if p > 1:
        xi = x[1:-1]
        x[1:-1] = xi - npleg.legval(xi, d1) / npleg.legval(xi, d2)
    w = 2.0 / (p * (p + 1) * npleg.legval(x, cp) ** 2)
    return x, w


@lru_cache(maxsize=64)
def _reference_element(degree: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """GLL nodes, weights, differentiation and cumulative integration matrices (read-only)."""
    x, w = gll(degree)
    Dx, Ix = _lagrange_tools(x)
    for a in (x, w, Dx, Ix):
        a.setflags(write=False)
    return x, w, Dx, Ix


def _lagrange_tools(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Differentiation matrix ``Dx[a, b] = l_b'(x_a)`` and cumulative integration matrix
    ``Ix[a, b] = int_{-1}^{x_a} l_b`` of the Lagrange basis on the nodes ``x`` (exact, via the
    Legendre expansion of each basis polynomial)."""
    n = x.size
    V = npleg.legvander(x, n - 1)  # V[a, k] = P_k(x_a)
    C = np.linalg.solve(V, np.eye(n))  # columns: Legendre coefficients of l_b
    Dx = np.empty((n, n))
    Ix = np.empty((n, n))
    for b in range(n):
        Dx[:, b] = npleg.legval(x, npleg.legder(C[:, b]))
        Ix[:, b] = npleg.legval(x, npleg.legint(C[:, b], lbnd=-1.0))
    return Dx, Ix


def _barycentric_weights(x: np.ndarray) -> np.ndarray:
    diff = x[:, None] - x[None, :]
    np.fill_diagonal(diff, 1.0)
    return 1.0 / np.prod(diff, axis=1)


@dataclass(frozen=True)
class Mesh:
    """Continuous piecewise-polynomial (spectral-element) mesh of [0, 1].

    Parameters
    ----------
    breaks : tuple of float
        Element boundaries ``0 = b_0 < b_1 < ... < b_E = 1``.
    degree : int
        Polynomial degree on every element (>= 2).

    Notes
    -----
    Global nodes ``s`` (shape ``(n,)``, ``n = E * degree + 1``) are the GLL points of each element,
    shared at interfaces; node 0 is the clamp, node ``n - 1`` the tip.
    """

    breaks: tuple[float, ...]
    degree: int

    def __post_init__(self) -> None:
        b = np.asarray(self.breaks, dtype=float)
        if b.ndim != 1 or b.size < 2 or not np.all(np.isfinite(b)):
            raise ValueError(f"breaks must be a finite 1-d sequence of >= 2 values, got {self.breaks!r}")
        if b[0] != 0.0 or b[-1] != 1.0 or np.any(np.diff(b) <= 0):
            raise ValueError("breaks must increase strictly from 0 to 1")
        if int(self.degree) != self.degree or self.degree < 2:
            raise ValueError(f"degree must be an integer >= 2, got {self.degree!r}")
        object.__setattr__(self, "breaks", tuple(float(v) for v in b))
        object.__setattr__(self, "degree", int(self.degree))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def uniform(cls, n_elements: int, degree: int) -> "Mesh":
        """``n_elements`` equal elements of the given degree."""
        if n_elements < 1:
            raise ValueError(f"n_elements must be >= 1, got {n_elements}")
        return cls(tuple(np.linspace(0.0, 1.0, n_elements + 1)), degree)

    @classmethod
    def graded(
        cls, layer_width: float, degree: int = 12, ratio: float = 3.0, n_outer: int = 2,
        first: float = 3.0,
    ) -> "Mesh":
        """Geometric mesh for a clamp boundary layer of the given width.

        The first element has size ``first * layer_width``; each next one is ``ratio`` times
        larger as long as it stays smaller than the ``n_outer`` equal elements that split the
        rest of [0, 1]. A wide layer gets no grading.
        """
        if not (layer_width > 0 and math.isfinite(layer_width)):
            raise ValueError(f"layer_width must be finite and > 0, got {layer_width}")
        if ratio <= 1:
            raise ValueError(f"ratio must be > 1, got {ratio}")
        b = [0.0]
        h = first * layer_width
        while h < (1.0 - b[-1] - h) / n_outer:
            b.append(b[-1] + h)
            h *= ratio
        b.extend(np.linspace(b[-1], 1.0, n_outer + 1)[1:])
        return cls(tuple(b), degree)

    @classmethod
    def for_params(cls, params: CiliumParams, degree: int = 12, turns: float | None = None) -> "Mesh":
        """A graded mesh suited to ``params``.

        The clamp layer width is ``1 / (|chi_E| cos theta_lim)`` when ``|chi_E| > |chi_N|``
        (no layer otherwise); ``theta`` may wind ``turns`` times along the filament (default:
        ``|chi_N| / (2 pi)`` in the coiled regime ``|chi_E| <= |chi_N|``, 0 otherwise; pass
        ``turns = |chi_N| / (2 pi)`` to start an unrolling filament from its stress-free arc),
        and each half turn gets an element. Elements where the closed-form equilibrium is
        not resolved to about ``10^-(degree/2 - 1)`` are then bisected (e.g. the interior fold
        of a filament with ``chi_E < 0`` and a small ``chi_N``).
        """
        cE, cN = abs(params.chi_E), abs(params.chi_N)
        if cE >= cN:
            # exponential approach at rate sqrt(chi_E^2 - chi_N^2) = |chi_E| cos theta_lim, or, at
            # chi_E = chi_N, algebraic on the scale 1/chi_N
            width = 1.0 / max(math.sqrt((cE - cN) * (cE + cN)), 0.5 * cN, 1.0)
        else:
            width = 1.0
        if turns is None:
            turns = 0.0 if cE >= cN else cN / (2 * math.pi)
        n_outer = max(2, int(math.ceil(2 * turns)))
        mesh = cls.graded(width, degree=degree, n_outer=n_outer)
        from .equilibrium import equilibrium

        still = params.with_background((0.0, 0.0))  # the clamp layer is the still fluid's (a stream leaves it)
        return mesh.refined(lambda s: equilibrium(still, s), 10.0 ** (1.0 - degree / 2.0))

    # ------------------------------------------------------------------ reference element
    @property
    def _reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return _reference_element(self.degree)

    @property
    def n_elements(self) -> int:
        return len(self.breaks) - 1

    @property
    def n_nodes(self) -> int:
        return self.n_elements * self.degree + 1

    @cached_property
    def element_nodes(self) -> np.ndarray:
        """Global node index of each local node, shape ``(E, degree + 1)``."""
        p = self.degree
        return np.arange(self.n_elements)[:, None] * p + np.arange(p + 1)[None, :]

    @cached_property
    def sizes(self) -> np.ndarray:
        """Element sizes, shape ``(E,)``."""
        return np.diff(np.asarray(self.breaks))

    @cached_property
    def nodes(self) -> np.ndarray:
        """Global nodes s, shape ``(n,)``."""
        x = self._reference[0]
        b = np.asarray(self.breaks)
        s = np.empty(self.n_nodes)
        for e in range(self.n_elements):
            s[self.element_nodes[e]] = b[e] + (x + 1.0) * 0.5 * self.sizes[e]
        s[0], s[-1] = 0.0, 1.0
        return s

    @cached_property
    def weights(self) -> np.ndarray:
        """Composite GLL weights, shape ``(n,)``: ``int_0^1 f ds ~ weights @ f(nodes)``."""
        w = np.zeros(self.n_nodes)
        wr = self._reference[1]
        for e in range(self.n_elements):
            w[self.element_nodes[e]] += 0.5 * self.sizes[e] * wr
        return w

    @cached_property
    def element_derivative(self) -> np.ndarray:
        """Per-element derivative matrices in s, shape ``(E, p+1, p+1)``: ``f'`` at the element's
        nodes from its nodal values (the derivative is discontinuous across interfaces)."""
        Dx = self._reference[2]
        return (2.0 / self.sizes)[:, None, None] * Dx[None, :, :]

    @cached_property
    def cumulative(self) -> np.ndarray:
        """Cumulative integration matrix, shape ``(n, n)``: ``(I @ f)[q] = int_0^{s_q} f_h ds`` for
        the piecewise polynomial ``f_h`` interpolating nodal values ``f``."""
        n = self.n_nodes
        Ix = self._reference[3]
        wr = self._reference[1]
        I = np.zeros((n, n))
        total = np.zeros(n)  # int over all previous elements of each basis function
        for e in range(self.n_elements):
            idx = self.element_nodes[e]
            half = 0.5 * self.sizes[e]
            I[idx, :] = total[None, :]
            I[np.ix_(idx, idx)] += half * Ix
            total[idx] += half * wr
        return I

    # ------------------------------------------------------------------ functions on the mesh
    def interpolate(self, values: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Evaluate the piecewise polynomial with nodal ``values`` (shape ``(n, ...)``) at the
        points ``s`` in [0, 1] (barycentric formula per element); returns shape ``s.shape + values.shape[1:]``."""
        values = np.asarray(values)
        s = np.asarray(s, dtype=float)
        if values.shape[0] != self.n_nodes:
            raise ValueError(f"values must have {self.n_nodes} rows (the nodes), got {values.shape[0]}")
        if np.any(~np.isfinite(s)) or np.any(s < 0) or np.any(s > 1):
            raise ValueError("s must lie in [0, 1]")
        flat = s.ravel()
        b = np.asarray(self.breaks)
        e = np.clip(np.searchsorted(b, flat, side="right") - 1, 0, self.n_elements - 1)
        x = self._reference[0]
        bw = _barycentric_weights(x)
        xi = 2.0 * (flat - b[e]) / self.sizes[e] - 1.0
        diff = xi[:, None] - x[None, :]
        exact = diff == 0.0
        diff[exact] = 1.0
        c = bw[None, :] / diff
        local = values[self.element_nodes[e]]  # (m, p+1, ...)
        c_shape = c.shape + (1,) * (local.ndim - 2)
        num = np.sum(c.reshape(c_shape) * local, axis=1)
        den = np.sum(c, axis=1).reshape((-1,) + (1,) * (local.ndim - 2))
        out = num / den
        rows, cols = np.nonzero(exact)
        out[rows] = local[rows, cols]
        return out.reshape(s.shape + values.shape[1:])

    def element_tails(self, values: np.ndarray) -> np.ndarray:
        """Per element, the sum of the moduli of the two highest Legendre coefficients of nodal
        ``values`` (shape ``(n,)``), relative to ``max |values|``; shape ``(E,)``."""
        values = np.asarray(values, dtype=float)
        scale = np.max(np.abs(values))
        if scale == 0:
            return np.zeros(self.n_elements)
        x = self._reference[0]
        coef = np.linalg.solve(npleg.legvander(x, self.degree), values[self.element_nodes].T)
        return (np.abs(coef[-1]) + np.abs(coef[-2])) / scale

    def tail(self, values: np.ndarray) -> float:
        """Resolution indicator of nodal ``values``: the largest of :meth:`element_tails`. For a
        resolved smooth function it is about the relative interpolation error and falls
        exponentially with the degree."""
        return float(np.max(self.element_tails(values)))

    def refined(self, values_at, target: float, max_elements: int = 256) -> "Mesh":
        """Bisect the elements where the function ``values_at(s)`` (evaluated at the nodes) has
        an element tail above ``target``, until none has or ``max_elements`` is reached."""
        mesh = self
        while mesh.n_elements < max_elements:
            bad = mesh.element_tails(values_at(mesh.nodes)) > target
            if not np.any(bad):
                break
            b = np.asarray(mesh.breaks)
            mids = 0.5 * (b[:-1] + b[1:])[bad][: max_elements - mesh.n_elements]
            mesh = Mesh(tuple(np.sort(np.concatenate([b, mids]))), mesh.degree)
        return mesh

    def derivative_at_nodes(self, values: np.ndarray) -> np.ndarray:
        """Per-element derivative of nodal ``values``, shape ``(E, p+1)``."""
        return np.einsum("eab,eb->ea", self.element_derivative, values[self.element_nodes])

    def describe(self) -> str:
        return (f"{self.n_elements} elements of degree {self.degree} ({self.n_nodes} nodes), "
                f"smallest element {self.sizes.min():.3g} at the clamp")
