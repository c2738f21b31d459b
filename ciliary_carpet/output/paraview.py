"""The ParaView script a render writes beside its outputs (``open_in_paraview.py``).

The script opens the whole render folder in ParaView, from any working folder, however it is
run: ``paraview --script=DIR/open_in_paraview.py`` (the GUI runs the script's text with no
``__file__`` and an empty ``sys.argv``), ``pvpython DIR/open_in_paraview.py`` or ``pvbatch``.

What opens, readable at a glance (a 2D top view on the carpet, one legend per colour):

- the mean speed as the background (``mean_field.vti``, white for slow to mid-grey for fast),
- a sparse lattice of black mean-flow arrows (at most about 400, resampled from the mean field
  and scaled by speed so that the fastest is 0.9 lattice spacings long),
- the path lines coloured by time ("Viridis"),
- the cilia (``cilia.pvd``, moving) and their bases (``layout.vtp``) coloured by chi_N
  ("Cool to Warm"; symmetric about 0 when the layout has both signs),
- the design's target directions at its control points as orange arrows (a render with a target),
- labelled axes in the files' length unit (L, or m with ``[units]``),
- the time, and a line saying what is shown.

ParaView's clock plays through every data time step ("Snap To TimeSteps"): the cilia's frames
(one beat, repeated over the path lines' time range by ``cilia.pvd``) and the moving tracers
(``particles.pvd``) move together. The script does not move the animation itself: under
``--script`` ParaView 5.11's GUI hangs on ``UpdateAnimationUsingDataTimeSteps`` or on setting
``AnimationTime``.

Loaded but hidden, ready to switch on with their eye icon: the instantaneous fields
(``snapshots.pvd``), the FTLE field (``ftle.vti``), the design's control points
(``design.vtp``, coloured by residual) and the tracers as moving points (``particles.pvd``).
Each of them lies in the plane z = 0 like the mean field, so only one field is shown at a time.

A standing carpet's script (``geometry="standing"``) shows the same in 3D, from the front and
above: the target plane z = h (``mean_field.vti``, translucent blue by mean speed, with the
mean-flow arrows), the path lines in space, and the cilia standing on the substrate (tubes,
moving) with their bases; the vertical section (``mean_field_section.vti``, down to the wall),
the snapshots of the plane and of the section, the FTLE and the particles are loaded but hidden.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["SCRIPT", "write_script"]

SCRIPT = "open_in_paraview.py"
"""The script's name in a render folder."""

_HEADER = '''# Open this render in ParaView:
#     paraview --script=open_in_paraview.py      (the GUI; from any working folder, with the path)
#     pvpython open_in_paraview.py               (or pvbatch: loads the scene without a window)
# Written by ciliary-carpet render. The files are found beside this script (its path, or the
# --script= argument on the command line); failing that, in the folder the render was written to:
RENDER_FOLDER = {folder!r}
LENGTH, TIME, SPEED = {length!r}, {time!r}, {speed!r}  # units of the files
SCENE = {scene!r}
'''

_PRELUDE = '''
import os
import sys

from paraview.simple import *  # noqa: F401,F403


def _has_render(folder):
    return bool(folder) and os.path.isfile(os.path.join(folder, "layout.vtp"))


def _render_folder():
    """The folder of this script: __file__ (pvpython, pvbatch), else the --script= argument
    (paraview --script= runs the script's text: no __file__, sys.argv == ['']), else the
    folder the render was written to."""
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        if _has_render(here):
            return here
    except NameError:
        pass
    args = list(sys.argv)
    try:
        with open("/proc/self/cmdline", "rb") as fh:
            args += [a.decode("utf-8", "replace") for a in fh.read().split(b"\\0") if a]
    except OSError:
        pass
    for a in args:
        if a.startswith("--script="):
            here = os.path.dirname(os.path.abspath(os.path.expanduser(a[len("--script="):])))
            if _has_render(here):
                return here
    if _has_render(RENDER_FOLDER):
        return RENDER_FOLDER
    if _has_render(os.getcwd()):
        return os.getcwd()
    raise RuntimeError("open_in_paraview.py: cannot find the render's files (layout.vtp ...): run it with "
                       "its path, e.g. paraview --script=out/NAME/open_in_paraview.py; the render was written "
                       "to " + RENDER_FOLDER)


here = _render_folder()
view = GetActiveViewOrCreate("RenderView")


def load(name):
    path = os.path.join(here, name)
    if not os.path.exists(path):
        return None
    if name.endswith(".pvd"):
        return PVDReader(registrationName=name, FileName=path)
    reader = XMLImageDataReader if name.endswith(".vti") else XMLPolyDataReader
    return reader(registrationName=name, FileName=[path])


def colour(source, display, association, array, preset, title, slot=None, symmetric=False, separate=False):
    """Colour ``display`` by ``array`` with its own colour map (``separate``: one of its own even
    where another dataset has an array of the same name); a legend at ``slot`` (0, 1, 2 from
    the bottom of the right edge) when given."""
    ColorBy(display, (association, array), separate=separate)
    lut = GetColorTransferFunction(array, display, separate=separate) if separate else GetColorTransferFunction(array)
    if preset != "light greys":
        lut.ApplyPreset(preset, True)
    data = source.PointData if association == "POINTS" else source.CellData
    lo, hi = data[array].GetRange()
    if symmetric and lo < 0 < hi:
        lo, hi = -max(-lo, hi), max(-lo, hi)
    hi = hi if hi > lo else lo + 1.0
    if preset == "light greys":  # a backdrop: white (slow) to mid-grey (fast), under coloured lines
        lut.ColorSpace = "RGB"
        lut.RGBPoints = [lo, 1.0, 1.0, 1.0, hi, 0.55, 0.55, 0.55]
    lut.RescaleTransferFunction(lo, hi)
    lut.AutomaticRescaleRangeMode = "Never"
    if not separate:
        GetOpacityTransferFunction(array).RescaleTransferFunction(lut.RGBPoints[0], lut.RGBPoints[-4])
    if slot is not None:
        bar = GetScalarBar(lut, view)
        bar.Title = title
        bar.ComponentTitle = ""
        bar.WindowLocation = "Any Location"
        bar.Orientation = "Vertical"
        bar.Position = [0.85, 0.05 + 0.31 * slot]  # room on the right for the labels, the title above
        bar.ScalarBarLength = 0.2
        bar.HorizontalTitle = 1  # above the bar, read across: a vertical title runs into the labels
        bar.TitleFontSize = 8
        bar.LabelFontSize = 7
        bar.RangeLabelFormat = "%-.3g"  # 142, 0.0762, 1.5e-05: no trailing point
        display.SetScalarBarVisibility(view, True)
    return lut


def target_arrows(design, h):
    """The design's target directions at its control points (``design.vtp``'s "target"), as
    orange arrows of one length (``0.8 h``, the lattice spacing): what the flow was asked to do,
    over the black arrows of what it does."""
    if design is None or "target" not in design.PointData.keys():
        return None
    glyph = Glyph(registrationName="target directions", Input=design, GlyphType="Arrow")
    glyph.OrientationArray = ["POINTS", "target"]
    glyph.ScaleArray = ["POINTS", "No scale array"]
    glyph.ScaleFactor = 0.8 * h
    glyph.GlyphMode = "All Points"
    g = Show(glyph, view)
    ColorBy(g, None)
    g.AmbientColor = g.DiffuseColor = [0.95, 0.45, 0.0]
    return glyph


def axes(view, length, planar):
    """Labelled axes with ticks in the files' length unit around the data (ParaView's axes grid):
    a planar view labels its lower x and left y edges only (the legend sits above)."""
    grid = view.AxesGrid
    grid.Visibility = 1
    grid.XTitle, grid.YTitle, grid.ZTitle = "x [%s]" % length, "y [%s]" % length, "z [%s]" % length
    grid.XTitleFontSize = grid.YTitleFontSize = grid.ZTitleFontSize = 16
    grid.XLabelFontSize = grid.YLabelFontSize = grid.ZLabelFontSize = 14
    if planar:
        grid.AxesToLabel = 1 + 2  # min x, min y
        grid.FacesToRender = 4  # the x-y face the carpet lies in
    for k in ("XTitleColor", "YTitleColor", "ZTitleColor", "XLabelColor", "YLabelColor", "ZLabelColor",
              "GridColor"):
        setattr(grid, k, [0.9, 0.9, 0.9])


def hidden(source):
    if source is not None:
        Hide(source, view)

'''

_TRACERS = '''ftle = load("ftle.vti")
if ftle is not None:
    d = Show(ftle, view)
    d.SetRepresentationType("Slice")
    colour(ftle, d, "POINTS", "FTLE", "Inferno (matplotlib)", "FTLE [1/%s]" % TIME)
    hidden(ftle)
path = load("pathlines.vtp")
if path is not None:
    d = Show(path, view)
    colour(path, d, "POINTS", "time", "Viridis (matplotlib)", "path lines:\\ntime [%s]" % TIME, slot=1)
    d.LineWidth = 2.0
    shown.append("lines: path lines (time)")
particles = load("particles.pvd")
if particles is not None:
    d = Show(particles, view)
    ColorBy(d, None)
    d.SetRepresentationType("Points")
    d.PointSize = 5.0
    d.RenderPointsAsSpheres = 1
    d.AmbientColor = d.DiffuseColor = [1.0, 1.0, 1.0]
    hidden(particles)
'''
"""The FTLE, the path lines and the particles, in both views (the FTLE and the particles hidden)."""

_CLOCK = '''clock = AnnotateTime(registrationName="time")
clock.Format = "t = {time:.3f} " + TIME
c = Show(clock, view)
c.WindowLocation = "Lower Left Corner"
c.FontSize = 8
'''
"""The time in the lower left corner, in both views."""

_PLANAR = '''
shown = []
# the mean speed behind everything, with a sparse lattice of mean-flow arrows over it
field = load("mean_field.vti")
if field is not None:
    d = Show(field, view)
    d.SetRepresentationType("Slice")
    colour(field, d, "POINTS", "speed", "light greys", "mean speed\\n[%s]" % SPEED, slot=0)
    b = field.GetDataInformation().GetBounds()
    lo, hi = field.PointData["speed"].GetRange()
    n = 20  # arrows along the longer side: about 400 in all
    h = max(b[1] - b[0], b[3] - b[2]) / (n - 1)
    lattice = ResampleToImage(registrationName="arrow lattice", Input=field)
    lattice.UseInputBounds = 0
    lattice.SamplingBounds = [b[0] + h / 2, b[1] - h / 2, b[2] + h / 2, b[3] - h / 2, 0.0, 0.0]
    lattice.SamplingDimensions = [max(2, int((b[1] - b[0]) / h)), max(2, int((b[3] - b[2]) / h)), 1]
    arrows = Glyph(registrationName="mean-flow arrows", Input=lattice, GlyphType="Arrow")
    arrows.OrientationArray = ["POINTS", "velocity"]
    arrows.ScaleArray = ["POINTS", "speed"]
    arrows.ScaleFactor = 0.9 * h / hi if hi > 0 else h
    arrows.GlyphMode = "All Points"
    a = Show(arrows, view)
    ColorBy(a, None)
    a.AmbientColor = a.DiffuseColor = [0.1, 0.1, 0.1]
    shown.append("grey: mean speed; arrows: mean flow")
# the fields of single instants, the FTLE and the design's control points: hidden
snap = load("snapshots.pvd")
if snap is not None:
    d = Show(snap, view)
    d.SetRepresentationType("Slice")
    colour(snap, d, "POINTS", "speed", "light greys", "speed [%s]" % SPEED, separate=True)
    hidden(snap)
''' + _TRACERS + '''design = load("design.vtp")
if design is not None:
    d = Show(design, view)
    d.SetRepresentationType("Points")
    d.PointSize = 9.0
    d.RenderPointsAsSpheres = 1
    colour(design, d, "POINTS", "residual", "Reds", "design residual")
    hidden(design)
    if field is not None and target_arrows(design, h) is not None:
        shown.append("orange arrows: the target's directions")
# the cilia (moving) and their bases, coloured by chi_N
cilia = load("cilia.pvd")
if cilia is not None:
    d = Show(cilia, view)
    colour(cilia, d, "CELLS", "chi_N", "Cool to Warm", "chi_N", slot=2, symmetric=True)
    d.LineWidth = 2.5
layout = load("layout.vtp")
if layout is not None:
    d = Show(layout, view)
    d.SetRepresentationType("Points")
    d.PointSize = 6.0
    d.RenderPointsAsSpheres = 1
    colour(layout, d, "POINTS", "chi_N", "Cool to Warm", "chi_N", slot=2, symmetric=True)
    shown.insert(0, "cilia and bases: chi_N")

''' + _CLOCK + '''label = Text(registrationName="legend")
label.Text = SCENE + "\\n" + "\\n".join(shown) + "\\nhidden (eye icon): snapshots, FTLE, design, particles"
t = Show(label, view)
t.WindowLocation = "Upper Left Corner"
t.FontSize = 7
t.Justification = "Left"

# a 2D top view on the carpet (the mean field's box, else the layout's), with labelled axes
view.InteractionMode = "2D"
view.OrientationAxesVisibility = 0
axes(view, LENGTH, True)
box = (field or layout or path or cilia).GetDataInformation().GetBounds()
cx, cy = 0.5 * (box[0] + box[1]), 0.5 * (box[2] + box[3])
view.CameraFocalPoint = [cx, cy, 0.0]
view.CameraPosition = [cx, cy, 10.0 * max(box[1] - box[0], box[3] - box[2], 1e-300)]
view.CameraViewUp = [0.0, 1.0, 0.0]
view.ResetCamera(box[0], box[1], box[2], box[3], 0.0, 0.0)
view.CameraParallelScale = 0.62 * max(box[3] - box[2], (box[1] - box[0]) * 0.75)  # room for the axes' labels
# play through every data time step (cilia frames, particles); the time starts at 0. Nothing here
# moves the animation: in the GUI under --script that hangs ParaView 5.11 (UpdateAnimationUsingDataTimeSteps,
# AnimationTime), and the animation already spans the data's time range.
GetAnimationScene().PlayMode = "Snap To TimeSteps"
SetActiveSource(cilia or layout)
Render(view)
'''


_STANDING = '''
shown = []
# the target plane z = h above the cilia: its mean speed, with a sparse lattice of mean-flow arrows
field = load("mean_field.vti")
if field is not None:
    d = Show(field, view)
    d.SetRepresentationType("Slice")
    colour(field, d, "POINTS", "speed", "Blues", "mean speed\\n[%s]" % SPEED, slot=0)
    d.Opacity = 0.55
    b = field.GetDataInformation().GetBounds()
    lo, hi = field.PointData["speed"].GetRange()
    n = 20  # arrows along the longer side: about 400 in all
    h = max(b[1] - b[0], b[3] - b[2]) / (n - 1)
    lattice = ResampleToImage(registrationName="arrow lattice", Input=field)
    lattice.UseInputBounds = 0
    lattice.SamplingBounds = [b[0] + h / 2, b[1] - h / 2, b[2] + h / 2, b[3] - h / 2, b[4], b[5]]
    lattice.SamplingDimensions = [max(2, int((b[1] - b[0]) / h)), max(2, int((b[3] - b[2]) / h)), 1]
    arrows = Glyph(registrationName="mean-flow arrows", Input=lattice, GlyphType="Arrow")
    arrows.OrientationArray = ["POINTS", "velocity"]
    arrows.ScaleArray = ["POINTS", "speed"]
    arrows.ScaleFactor = 0.9 * h / hi if hi > 0 else h
    arrows.GlyphMode = "All Points"
    a = Show(arrows, view)
    ColorBy(a, None)
    a.AmbientColor = a.DiffuseColor = [0.1, 0.1, 0.1]
    shown.append("plane z = %.3g %s: mean speed; arrows: mean flow" % (b[4], LENGTH))
# the vertical section through the carpet's centre (down to the wall), the snapshots, the FTLE: hidden
section = load("mean_field_section.vti")
if section is not None:
    d = Show(section, view)
    d.SetRepresentationType("Slice")
    colour(section, d, "POINTS", "speed", "Blues", "speed [%s]" % SPEED, separate=True)
    hidden(section)
design = load("design.vtp")
if design is not None and field is not None and target_arrows(design, h) is not None:
    shown.append("orange arrows: the target's directions")
for name in ("snapshots.pvd", "snapshots_section.pvd"):
    snap = load(name)
    if snap is not None:
        d = Show(snap, view)
        d.SetRepresentationType("Slice")
        colour(snap, d, "POINTS", "speed", "Blues", "speed [%s]" % SPEED, separate=True)
        hidden(snap)
''' + _TRACERS + '''# the cilia standing on the substrate (moving, in 3D) and their bases, coloured by chi_N
cilia = load("cilia.pvd")
if cilia is not None:
    d = Show(cilia, view)
    colour(cilia, d, "CELLS", "chi_N", "Cool to Warm", "chi_N", slot=2, symmetric=True)
    d.LineWidth = 3.0
    d.RenderLinesAsTubes = 1
layout = load("layout.vtp")
if layout is not None:
    d = Show(layout, view)
    d.SetRepresentationType("Points")
    d.PointSize = 6.0
    d.RenderPointsAsSpheres = 1
    colour(layout, d, "POINTS", "chi_N", "Cool to Warm", "chi_N", slot=2, symmetric=True)
    shown.insert(0, "standing cilia and bases: chi_N")

''' + _CLOCK + '''label = Text(registrationName="legend")
label.Text = (SCENE + "\\n" + "\\n".join(shown)
              + "\\nhidden (eye icon): section y = const, snapshots, FTLE, particles")
t = Show(label, view)
t.WindowLocation = "Upper Left Corner"
t.FontSize = 7
t.Justification = "Left"

# a 3D view from the front and above: the cilia on the substrate under the plane of the flow (set
# after a first render: paraview.simple resets the camera on a view's first render)
Render(view)
view.OrientationAxesVisibility = 1
axes(view, LENGTH, False)
box = (field or layout or path or cilia).GetDataInformation().GetBounds()
top = max(box[5], 1.0)
cx, cy = 0.5 * (box[0] + box[1]), 0.5 * (box[2] + box[3])
span = max(box[1] - box[0], box[3] - box[2], 1e-300)
view.CameraFocalPoint = [cx, cy, 0.3 * top]
view.CameraPosition = [cx + 0.35 * span, cy - 1.1 * span, 0.3 * top + 0.75 * span]
view.CameraViewUp = [0.0, 0.0, 1.0]
view.ResetCamera(box[0], box[1], box[2], box[3], 0.0, top)
GetActiveCamera().Dolly(1.1)  # closer, with room left for the axes' labels
# play through every data time step (cilia frames, particles); nothing here moves the animation
# (see the planar script: under --script that hangs ParaView 5.11's GUI)
GetAnimationScene().PlayMode = "Snap To TimeSteps"
SetActiveSource(cilia or layout)
Render(view)
'''


def write_script(path, folder, *, si: bool = False, scene: str = "", geometry: str = "planar") -> Path:
    """Write the ParaView script that opens a render folder.

    Parameters
    ----------
    path : str or Path
        The script to write (``DIR/open_in_paraview.py``).
    folder : str or Path
        The render folder as it will be once complete (the script finds its files beside
        itself first; this absolute path is its fallback when ParaView does not tell it where
        it is).
    si : bool, optional
        Whether the files are in SI units (m, s) rather than L and tau.
    scene : str, optional
        The scene's name, shown in the view.
    geometry : str, optional
        The carpet's geometry: ``"planar"`` (a 2D top view) or ``"standing"`` (a 3D view: the
        module docstring).

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    length, time = ("m", "s") if si else ("L", "tau")
    header = _HEADER.format(folder=str(Path(folder).resolve()), length=length, time=time,
                            speed=f"{length}/{time}", scene=scene)
    body = _PRELUDE + (_STANDING if geometry == "standing" else _PLANAR)
    path.write_text(header + body)
    return path
