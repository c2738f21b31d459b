"""How accurate a render's path lines are: the tolerances they run at (:data:`PATHLINE_TOL`,
:data:`PATHLINE_RTOL`, :data:`PATHLINE_ATOL`, :data:`PATHLINE_PRECISION`) and the estimate of their
end-point error (:func:`pathline_error`): some of the tracers (:data:`ERROR_SAMPLE`) integrated again
in a more accurate run (:func:`error_reference`, one task a pool can run beside the path lines),
their end points compared (:func:`end_point_error`).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from cilia_runtime.pool import InProcess

from ciliary_carpet.transport.flow import ResolvedFlow
from ciliary_carpet.transport.pathlines import pathline_tasks

if TYPE_CHECKING:
    from ciliary_carpet.carpet.carpet import Carpet

__all__ = ["pathline_error", "error_tracers", "error_reference", "end_point_error", "ERROR_SAMPLE", "PATHLINE_TOL",
           "PATHLINE_RTOL", "PATHLINE_ATOL", "PATHLINE_PRECISION", "REFERENCE_TIGHTER"]

ERROR_SAMPLE = 8
"""Tracers of a render re-integrated to estimate its path lines' end-point error (:func:`pathline_error`)."""
PATHLINE_TOL = 1e-4
"""Largest flow tolerance (levels of detail) of a render's time-resolved path lines: the scene's
tolerance when tighter. The tracers' end points are far more sensitive to the flow's error than
the fields are: measured on the designed uniform_deflection carpet at 30 x 30 (8 tracers over 142
beats, against flow tol 1e-5, rtol 1e-9, atol 2e-7 L with the step cap halved;
``benchmarks/bench_large.py --decompose``, benchmarks/results/bench_large.md), with the integration tight (rtol 1e-9, atol 2e-7 L) the end
points are off by up to 2.1e-3 L at flow tol 1e-3, 9.5e-4 L at 3e-4 and 5e-5 L at 1e-4. On 100 x 100
the render's 100 tracers end up to 1.4e-3 L from the check run (the estimate said 6.4e-4 L: the fine
runs themselves differ by that much there)."""
PATHLINE_RTOL = 1e-9
PATHLINE_ATOL = 1e-7
"""Local error test of a render's time-resolved path lines: rtol :data:`PATHLINE_RTOL`, atol this
times the carpet's spacing [L]. The test is per step, the end-point error accumulates over the
thousands of steps of a render (about 16 per beat): measured as above at flow tol 1e-4, atol
2e-4 L (the settings before, rtol 1e-6) ends up to 4e-3 L off, 2e-6 L 1.1e-3 L, 2e-7 L 5e-5 L,
for 22 % more steps than the first."""
PATHLINE_PRECISION = "fp32"
"""The precision of the far cilia's carriers in a render's time-resolved path lines
(:class:`~ciliary_carpet.transport.flow.ResolvedFlow`; the near field and everything else in fp64).
Their rounding (:func:`~ciliary_carpet.stokes.precision.fp32_error_bound`) is some 1e-7 of the
velocity, far inside the levels of detail's tolerance; the end-point error estimate's reference
run (:func:`pathline_error`) sums in fp64, so the estimate covers it. Measured with
``benchmarks/bench_evaluation.py --pathlines 0.1`` (the render's 100 tracers over a tenth of the
duration, one thread, benchmarks/results/bench_evaluation.md): 30 x 30 1.82 s in fp64, 1.37 s in
fp32, end points 4.4e-6 L apart, 3.5e-6 and 2.9e-6 L from the reference run; 100 x 100 13.1 s and
11.1 s, 6.9e-5 L apart (the two runs take different steps), 5.1e-5 and 4.5e-5 L from the
reference."""
REFERENCE_TIGHTER = (3.0, 10.0)
"""The reference of a render's end-point error estimate (:func:`pathline_error`): the flow
tolerance divided by the first, rtol and atol by the second (the step cap unchanged: at these
tolerances the local error test, not the cap, sets the steps; measured as above, halving the
cap too moves the reference's end points by at most 4e-5 L)."""


def error_tracers(k: int) -> np.ndarray:
    """The indices of the :data:`ERROR_SAMPLE` tracers (spread evenly over ``k`` seeds) that
    :func:`pathline_error` re-integrates."""
    n = min(ERROR_SAMPLE, int(k))
    return np.unique(np.linspace(0, int(k) - 1, n).round().astype(int))


def pathline_error(carpet: "Carpet", seeds: np.ndarray, duration: float, pl, model: str, flow, tol: float,
                   spacing: float, domain=None, pool=None) -> dict:
    """End-point error estimate of rendered path lines ``pl`` in ``flow``: :data:`ERROR_SAMPLE` of
    its tracers (:func:`error_tracers`) integrated again, against a more accurate run.

    For the time-resolved flow (``flow`` a :class:`~ciliary_carpet.transport.flow.ResolvedFlow`)
    the reference is the same integration with every tolerance tightened
    (:data:`REFERENCE_TIGHTER`: the flow tolerance ``flow.tol`` / 3, ``pl.rtol`` and ``pl.atol`` /
    10): the estimate covers the integration and the levels of detail. For the long-time model
    (``model == "mean"``, ``flow`` its :class:`~ciliary_carpet.transport.flow.MeanFlow`) the
    reference is the time-resolved flow at the scene's tolerance ``tol`` in the same domain (the
    flow's box): the estimate is the model's error. Returns max and
    median of the end-point distances [L], the tracers used and the reference in words.
    ``domain`` (6,), where given (a standing carpet's, from the substrate up), bounds the time-resolved
    reference too. The reference run is one task (:func:`error_reference`), in this process
    unless ``pool`` says where (a render runs it beside its path lines' chunks)."""
    task, idx, what = error_reference(carpet, seeds, duration, pl.rtol, pl.atol, model, flow, tol, spacing,
                                      domain=domain)
    if pool is None:
        pool = InProcess()
    ref = pool.run([task], shared=[carpet])[0].value
    return end_point_error(pl, ref, idx, what)


def error_reference(carpet: "Carpet", seeds: np.ndarray, duration: float, rtol: float, atol: float, model: str, flow,
                    tol: float, spacing: float, domain=None):
    """The reference run of :func:`pathline_error` for path lines integrated with ``rtol`` and
    ``atol`` in ``flow``, as one :class:`~cilia_runtime.pool.Task` (its
    :data:`ERROR_SAMPLE` tracers integrated together): ``(task, tracer indices, the reference in
    words)``; :func:`end_point_error` compares its result with the path lines."""
    idx = error_tracers(seeds.shape[0])
    label = "path lines' error estimate: the reference run"
    if model == "mean":
        (task,) = pathline_tasks(ResolvedFlow(carpet, tol), seeds[idx], (0.0, duration), chunk_size=None, label=label,
                                 rtol=1e-6, atol=1e-4 * spacing, samples_per_period=1,
                                 domain=tuple(float(v) for v in flow.box))
        what = f"the time-resolved flow (rtol 1e-6, flow tol {tol:g}): the long-time model's error"
    else:
        ft, ti = REFERENCE_TIGHTER
        t_ref, r_rtol, r_atol = flow.tol / ft, rtol / ti, atol / ti
        (task,) = pathline_tasks(ResolvedFlow(carpet, t_ref), seeds[idx], (0.0, duration), chunk_size=None,
                                 label=label, rtol=r_rtol, atol=r_atol, samples_per_period=1, domain=domain)
        what = (f"flow tol {t_ref:.3g}, rtol {r_rtol:.3g}, atol {r_atol:.3g} L (the render's path lines: flow tol "
                f"{flow.tol:.3g}, rtol {rtol:.3g}, atol {atol:.3g} L): integration and levels of detail")
    return task, idx, what


def end_point_error(pl, ref, idx: np.ndarray, what: str) -> dict:
    """The estimate of :func:`pathline_error` from its reference run ``ref`` of tracers ``idx``."""
    e = np.linalg.norm(pl.end_points[idx] - ref.end_points, axis=1)
    return {"max": float(e.max()), "median": float(np.median(e)), "tracers": int(idx.size), "reference": what}
