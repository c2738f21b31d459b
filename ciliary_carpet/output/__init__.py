"""What a render writes: VTK files, pictures, the summary in words, the ParaView script, and the
output folder that holds them.

:func:`ciliary_carpet.render.render` is the front door. Below it: :mod:`~ciliary_carpet.output.resources`
(what a scene needs, checked before any work), :mod:`~ciliary_carpet.output.plan` (what a render
will do, decided once), :mod:`~ciliary_carpet.output.outputs` (the outputs, one class each, and
their registry, which also names the files a render owns), :mod:`~ciliary_carpet.output.folder`
(the output folder's safety), and the writers they use (:mod:`~ciliary_carpet.output.vtkfiles`,
:mod:`~ciliary_carpet.output.figures`, :mod:`~ciliary_carpet.output.report`,
:mod:`~ciliary_carpet.output.paraview`).
"""

__all__ = ["RenderError"]


class RenderError(RuntimeError):
    """The output folder cannot be (re)written as asked, or the result is not finite."""
