"""Inverse design: target flows and the curvature layouts that make them (objects in, objects out).

The layer's front door: :func:`design_target` and :func:`design_standing_target` (a carpet designed
for a resolved :class:`Target`, with the verdict), :func:`design_layout` (a carpet and control
points), their result :class:`Design`, what a carpet can make (:func:`reachability`), the
fabrication tolerance (:func:`tolerance_study`), and the targets (:class:`Target`, :class:`Frame`,
the registry :data:`PATTERNS`). Modules: ``patterns`` (the target kinds), ``frame``, ``target``,
``control`` (control points, reachable angles), ``target_files`` (control-point files), ``model``
(the design model), ``inverse`` (the solve), ``target_design`` (the solve for a target, the
verdict), ``result``, ``reachability``, ``tolerance``, ``surface`` and ``surface_target`` (standing
carpets). A scene's carpet designed for its target: :func:`ciliary_carpet.scenes.assembly.design`.
"""
from ciliary_carpet.design.control import control_points
from ciliary_carpet.design.errors import TargetError
from ciliary_carpet.design.frame import Frame
from ciliary_carpet.design.inverse import carpet_with, design_layout
from ciliary_carpet.design.model import DesignModel, NearField
from ciliary_carpet.design.patterns import PATTERNS, Pattern
from ciliary_carpet.design.reachability import Reachability, reachability
from ciliary_carpet.design.result import Design, DesignError
from ciliary_carpet.design.target import Target
from ciliary_carpet.design.target_design import design_standing_target, design_target
from ciliary_carpet.design.tolerance import ToleranceStudy, tolerance_study

__all__ = ["design_target", "design_standing_target", "design_layout", "carpet_with", "Design", "DesignError",
           "DesignModel", "NearField", "Reachability", "reachability", "ToleranceStudy", "tolerance_study", "Target",
           "TargetError", "Frame", "Pattern", "PATTERNS", "control_points"]
