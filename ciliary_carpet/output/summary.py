"""The summary (``summary``: ``summary.json`` and ``summary.md``), last of a render's outputs, and
its computations that need only the carpet (what the model leaves out, the size of the coupling:
:func:`summary_tasks`), which a render's pool runs beside the path lines.
"""
from __future__ import annotations

import re
import time as _time

from cilia_runtime.files import non_finite, strict_json
from cilia_runtime.pool import Task
from cilia_runtime.threads import threads_in_use

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.carpet.coupling import coupling_estimate
from ciliary_carpet.carpet.omissions import omissions
from ciliary_carpet.output import RenderError
from ciliary_carpet.output.contract import SUMMARY, Output, RenderContext
from ciliary_carpet.output.report import markdown

__all__ = ["SummaryOutput", "summary_tasks", "OMISSIONS_UNITS"]

_COUPLING_SPEEDS = ("median_speed_coupled", "median_speed_uncoupled")
"""The speeds (L/tau in the model) of the summary's ``coupling`` section."""
OMISSIONS_UNITS = "L, tau: model units, as the key names say (viscosities in B tau / L^4)"
"""The summary's ``omissions`` section is in model units whatever ``[units]`` says (its keys
name their unit: ``spacing_L``, ``mean_flow_others_median_L_per_tau``); its ``units`` key says so."""



def _omissions_summary(carpet: Carpet, tol: float) -> dict:
    """The summary's ``omissions`` section (:func:`~ciliary_carpet.carpet.omissions.omissions`)."""
    return omissions(carpet, tol=tol).summary()


def _coupling_summary(carpet: Carpet, tol: float) -> dict:
    """The summary's ``coupling`` section of an uncoupled planar carpet (its size estimated)."""
    return {**coupling_estimate(carpet, tol=tol), "status": "not solved"}


def summary_tasks(ctx: RenderContext, pool_only: bool = True) -> list:
    """The summary's computations that need only the carpet, as ``(name, Task)``: what the model
    leaves out (``omissions``) and, for an uncoupled planar carpet, the size of the coupling
    (``coupling``). The path lines run them in their pool after their own tasks (cost 0: last),
    so that on two cores a worker takes them once the error estimate's reference is done, beside
    the path lines' main run; the numbers are the same wherever they run (one BLAS thread in a
    worker; the sums give the same numbers on any numba thread count). ``pool_only``: none unless
    the render's pool has worker processes (in this process they run where the summary is made)."""
    if pool_only and getattr(ctx.pool, "workers", 1) < 2:
        return []
    c, tol = ctx.carpet, min(ctx.plan.settings.tolerance, 1e-3)
    out = [("omissions", Task("the summary: what the model leaves out", _omissions_summary, (c, tol), cost=0.0))]
    if c.coupled is None:  # uncoupled: the linear estimate of the coupling's size (each cilium's frame)
        out.append(("coupling", Task("the summary: the size of the coupling", _coupling_summary, (c, tol), cost=0.0)))
    return out



class SummaryOutput(Output):
    """``summary.json`` (strict JSON) and ``summary.md``: the summary, with what the model leaves
    out, the seconds by stage, the resolved scene and the threads used. Last: a summary with a
    NaN or an infinity is a :class:`~ciliary_carpet.output.RenderError` (nothing is placed)."""

    name = "summary"
    files = (re.escape(SUMMARY), r"summary\.md")

    def wanted(self, plan):
        return True

    def write(self, ctx):
        summary = ctx.summary
        # what the model leaves out (interaction between cilia, the wall's drag, the viscosity), sized,
        # and the cilia's coupling through their mean flow: solved ("mean"), or its size estimated
        # ("none"); computed here, or beside the path lines (summary_tasks), then timed there
        todo = dict(summary_tasks(ctx, pool_only=False))
        for name in ("omissions", "coupling"):
            got = ctx.beside.get(name)
            if got is not None:
                summary[name] = got.value
                ctx.clock[name] = 0.0
                ctx.clock[f"{name}_beside_pathlines"] = got.seconds
            elif name in todo:
                with ctx.timed(name):
                    task = todo[name]
                    summary[name] = task.func(*task.args, **task.kwargs)
        c = ctx.carpet
        if c.coupled is not None:  # solved: the carpet says how
            summary["coupling"] = c.coupled.summary()
        if "coupling" in summary:  # its speeds in the summary's units
            V = ctx.plan.units[2]
            summary["coupling"] = {k: (v * V if k in _COUPLING_SPEEDS and v is not None else v)
                                   for k, v in summary["coupling"].items()}
        if "omissions" in summary:
            summary["omissions"]["units"] = OMISSIONS_UNITS
        ctx.clock["total"] = _time.perf_counter() - ctx.started
        summary["seconds"] = ctx.clock
        summary["scene_resolved"] = ctx.scene_resolved
        summary["threads"] = threads_in_use()  # the numba and BLAS threads (and batch workers) used
        bad = non_finite(summary)
        if bad:
            listed = "; ".join(f"{k} = {v}" for k, v in list(bad.items())[:3])
            raise RenderError(f"{ctx.plan.settings.source}: the render gave non-finite numbers ({listed}); nothing was "
                              f"written to {ctx.out_dir}")
        (ctx.stage / "summary.md").write_text(markdown(summary))
        (ctx.stage / SUMMARY).write_text(strict_json(summary, indent=2))
