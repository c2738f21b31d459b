"""What a render is looked at with: the preview picture (``preview``) and the script that opens the
folder in ParaView (``paraview``).
"""
from __future__ import annotations

import re

from ciliary_carpet.output.contract import Output
from ciliary_carpet.output.figures import preview, standing_preview
from ciliary_carpet.output.paraview import SCRIPT, write_script

__all__ = ["PreviewOutput", "ParaViewOutput"]


class PreviewOutput(Output):
    """``preview.png``: the mean flow's streamlines, the path lines and the layout."""

    name = "preview"
    files = (r"preview\.png",)

    def wanted(self, plan):
        return bool(plan.settings.output.preview)

    def write(self, ctx):
        with ctx.timed("preview"):
            if ctx.carpet.geometry == "standing":
                s = ctx.plan.settings
                standing_preview(ctx.stage / "preview.png", s.name, s.output.height, ctx.carpet, ctx.mean_field,
                                 ctx.pathlines)
            else:
                preview(ctx.stage / "preview.png", ctx.plan.settings.name, ctx.carpet, ctx.mean_field, ctx.pathlines,
                        ctx.design)


class ParaViewOutput(Output):
    """``open_in_paraview.py``: the script that opens the render folder in ParaView."""

    name = "paraview"
    files = (re.escape(SCRIPT),)

    def wanted(self, plan):
        return True

    def write(self, ctx):
        write_script(ctx.stage / SCRIPT, ctx.out_dir, si=ctx.plan.scales is not None, scene=ctx.plan.settings.name,
                     geometry=ctx.carpet.geometry)
