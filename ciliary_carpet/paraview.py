"""The ParaView script a render writes beside its outputs (``open_in_paraview.py``)."""
from __future__ import annotations

from pathlib import Path

_PARAVIEW = """# Open this render in ParaView, in one command:  paraview --script=open_in_paraview.py
# (or pvpython open_in_paraview.py to check it loads). Written by ciliary-carpet render; the
# files are found next to this script, so the folder can be moved as a whole.
import os

from paraview.simple import *  # noqa: F401,F403

here = os.path.dirname(os.path.abspath(__file__))
view = GetActiveViewOrCreate("RenderView")


def show(name, reader, color=None, **kw):
    path = os.path.join(here, name)
    if not os.path.exists(path):
        return None
    src = reader(registrationName=name, FileName=path if reader is PVDReader else [path], **kw)
    d = Show(src, view)
    if color:
        ColorBy(d, color)
        d.RescaleTransferFunctionToDataRange(True, False)
    return src


field = show("mean_field.vti", XMLImageDataReader, ("POINTS", "speed"))
if field is not None:
    glyph = Glyph(registrationName="velocity arrows", Input=field, GlyphType="Arrow")
    glyph.OrientationArray = ["POINTS", "velocity"]
    glyph.ScaleArray = ["POINTS", "No scale array"]
    glyph.MaximumNumberOfSamplePoints = 1500
    Show(glyph, view)
show("layout.vtp", XMLPolyDataReader, ("POINTS", "chi_N"))
show("cilia.pvd", PVDReader, ("POINTS", "chi_N"))
show("pathlines.vtp", XMLPolyDataReader, ("POINTS", "IntegrationTime"))
show("particles.pvd", PVDReader, ("POINTS", "speed"))
show("snapshots.pvd", PVDReader)
view.InteractionMode = "2D"
ResetCamera(view)
GetAnimationScene().UpdateAnimationUsingDataTimeSteps()
Render(view)
"""


def _paraview_script(path: Path) -> None:
    """Write the pvpython script that opens every output of the render in ParaView."""
    path.write_text(_PARAVIEW)
