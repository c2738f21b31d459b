"""The outputs of a render: their contract, what each writes, and their registry :data:`OUTPUTS`.

The contract
------------
An output is a subclass of :class:`~ciliary_carpet.output.contract.Output`, registered in
:data:`OUTPUTS` under its ``name``. The registry's order is the order a render writes them in (an
output may use what an earlier one left on the context; the summary is last). An output provides

``name`` : str
    Its key in :data:`OUTPUTS`.
``files`` : tuple of str
    Regular expressions (matched in full) of the names of the files it may write into the render
    folder. Their union over the registry is what the output folder counts as the toolkit's
    (:mod:`ciliary_carpet.output.folder`): only files with such names are ever replaced or
    removed by a later render, and a render that writes any other name fails before placing it.
``wanted(plan) -> bool``
    Whether a render with this :class:`~ciliary_carpet.output.plan.RenderPlan` writes it
    (usually a key of the scene's ``[output]``).
``write(ctx) -> None``
    Write its files into ``ctx.stage`` (the staging folder, in the units ``ctx.plan.units``) and
    its section of ``ctx.summary``; time its stages with ``ctx.timed(key)``. ``ctx`` is the
    render's :class:`~ciliary_carpet.output.contract.RenderContext`: it may use ``ctx.mean_field``
    (left by :class:`~ciliary_carpet.output.fields.MeanFieldOutput`), ``ctx.pathlines`` (left by
    :class:`~ciliary_carpet.output.tracers.PathLinesOutput`) and the long-time flow model
    ``ctx.mean_flow()``.

:func:`~ciliary_carpet.render.render` does everything else once: the resource check, the design,
the plan, the progress bar, the output folder and its manifest.

The outputs live by kind: the layout's (``layout``, ``design``) in
:mod:`~ciliary_carpet.output.layout`, the flow and the cilia over time (``mean_field``,
``snapshots``, ``frames``) in :mod:`~ciliary_carpet.output.fields`, the tracers' (``pathlines``, ``ftle``) in
:mod:`~ciliary_carpet.output.tracers`, the views (``preview``, ``paraview``) in
:mod:`~ciliary_carpet.output.views` and the ``summary`` in :mod:`~ciliary_carpet.output.summary`.

Outputs
-------
===========================  ==================================================================
``layout``                   ``layout.vtp``: base points coloured by chi_N (and thrust angle,
                             near_cutoff); a standing carpet's also azimuth and the mean thrust
                             in space
``design``                   with a target: ``layout.nc`` (the designed layout: chi_N per cilium,
                             control points, residuals), ``design.vtp`` (control points: target and
                             achieved flow, residual), ``design.png`` (target vs achieved arrows,
                             residual per control point, the layout coloured by chi_N); a standing
                             carpet: ``layout.nc`` (its given layout: chi_N and azimuth per cilium)
``mean_field``               ``mean_field.vti``: the time-averaged velocity (active vectors),
                             speed, vorticity and the error bound on the field grid (a standing
                             carpet: the target plane z = h, and ``mean_field_section.vti`` on
                             the vertical x-z section through its centre, down to the wall)
``snapshots``                ``snapshot_NNN.vti``: instantaneous fields over one beat of the cilia,
                             tied by ``snapshots.pvd`` (a standing carpet: also on the section,
                             ``snapshot_section_NNN.vti``, ``snapshots_section.pvd``)
``frames``                   ``cilia_NNN.vtp``: filament shapes over one beat (arc length, drag
                             density), ``cilia.pvd``; both .pvd repeat that beat over the path
                             lines' time range (one clock)
``pathlines``                ``pathlines.vtp``: tracer path lines (time, IntegrationTime, velocity,
                             speed; SeedIds, TerminationReason with TerminationReasonNames), >= 16
                             points per beat; ``particles.pvd``: the tracers as moving points
                             (``particles_NNNNN.vtp``), as ParticlePath gives
``ftle``                     ``ftle.vti``: finite-time Lyapunov exponent over the carpet (mean
                             flow, a quarter of the path-line duration); the mixing number is in
                             the summary
``preview``                  ``preview.png``: the mean flow (streamlines) with the layout and path
                             lines, a colour bar for each colour
``paraview``                 ``open_in_paraview.py`` (:mod:`ciliary_carpet.output.paraview`)
``summary``                  ``summary.json``, ``summary.md``: residuals, timings, fidelity used,
                             error bounds, path-line outcome, what the model leaves out (``.md``:
                             the same in words, :mod:`ciliary_carpet.output.report`)
===========================  ==================================================================

Standing carpets (``[carpet] geometry = "standing"``, :mod:`ciliary_carpet.carpet.geometry`) write
the same files in space: the cilia's frames and the path lines are 3D polylines; the fields lie
on the target plane z = h above the cilia (``[output] height``) plus the vertical section; the
path lines follow the 3D flow (the time-resolved flow, or the cycle-mean flow evaluated directly,
:class:`~ciliary_carpet.transport.flow.SteadyMeanFlow`) from the substrate up, and a tracer that
reaches the wall ends there ("left the domain"). The FTLE and the mixing number are those of the
target plane's in-plane mean flow (2D tracers that stay in the plane z = h: the stretching along
the surface flow, not the fluid's 3D stretching). The preview looks down on the target plane.
The summary gives the geometry and the azimuths; the coupling estimate (a planar carpet's) is
left out.
"""
from __future__ import annotations

from ciliary_carpet.output.contract import Output
from ciliary_carpet.output.fields import FramesOutput, MeanFieldOutput, SnapshotsOutput
from ciliary_carpet.output.layout import DesignOutput, LayoutOutput
from ciliary_carpet.output.summary import SummaryOutput
from ciliary_carpet.output.tracers import FtleOutput, PathLinesOutput
from ciliary_carpet.output.views import ParaViewOutput, PreviewOutput

__all__ = ["OUTPUTS"]

OUTPUTS: dict[str, type[Output]] = {o.name: o for o in (
    LayoutOutput, DesignOutput, MeanFieldOutput, SnapshotsOutput, FramesOutput, PathLinesOutput, FtleOutput,
    PreviewOutput, ParaViewOutput, SummaryOutput)}
"""The outputs by name, in the order a render writes them."""
