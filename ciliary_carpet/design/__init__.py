"""Inverse design: target flows and the curvature layouts that make them.

The layer's front door: :func:`design` (a scene's carpet designed for its target),
:func:`design_layout` (a carpet and control points), their result :class:`Design`, what a carpet
can make (:func:`reachability`), the fabrication tolerance (:func:`tolerance_study`), and the
targets (:class:`Target`, :class:`Frame`, the registry :data:`PATTERNS`). Modules: ``target``
(target kinds and the ``[target]`` section), ``model`` (the design model), ``inverse`` (the
solve), ``result``, ``reachability``, ``tolerance``.
"""
from ciliary_carpet.design.inverse import carpet_with, design, design_layout
from ciliary_carpet.design.model import DesignModel, NearField
from ciliary_carpet.design.reachability import Reachability, reachability
from ciliary_carpet.design.result import Design, DesignError
from ciliary_carpet.design.target import PATTERNS, Frame, Pattern, Target, TargetError, control_points
from ciliary_carpet.design.tolerance import ToleranceStudy, tolerance_study

__all__ = ["design", "design_layout", "carpet_with", "Design", "DesignError", "DesignModel", "NearField",
           "Reachability", "reachability", "ToleranceStudy", "tolerance_study", "Target", "TargetError", "Frame",
           "Pattern", "PATTERNS", "control_points"]
