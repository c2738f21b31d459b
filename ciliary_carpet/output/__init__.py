"""What a render writes: VTK files, pictures, the summary in words, the ParaView script, and the
output folder that holds them.

:func:`ciliary_carpet.render.render` is the front door. Below it: :mod:`~ciliary_carpet.output.resources`
(what a render needs in memory and time, from numbers), :mod:`~ciliary_carpet.output.plan` (what
a render will do, decided once from the scene's render settings), :mod:`~ciliary_carpet.output.outputs` (the outputs' registry, which also
names the files a render owns) over their contract (:mod:`~ciliary_carpet.output.contract`) and
the outputs, one class each, by kind (:mod:`~ciliary_carpet.output.layout`,
:mod:`~ciliary_carpet.output.fields`, :mod:`~ciliary_carpet.output.tracers`,
:mod:`~ciliary_carpet.output.views`, :mod:`~ciliary_carpet.output.summary`),
:mod:`~ciliary_carpet.output.folder` (the output folder's safety), and the writers they use
(:mod:`~ciliary_carpet.output.vtkfiles`, :mod:`~ciliary_carpet.output.figures`,
:mod:`~ciliary_carpet.output.report`, :mod:`~ciliary_carpet.output.paraview`).
"""

__all__ = ["RenderError"]


class RenderError(RuntimeError):
    """The output folder cannot be (re)written as asked, or the result is not finite."""
