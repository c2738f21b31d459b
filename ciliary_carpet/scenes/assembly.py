"""The objects a scene describes: its thrust table, base points, target frame, target and carpet.

:func:`assemble` is the one path from a :class:`~ciliary_carpet.scenes.scene.Scene` to them: the design
(:func:`ciliary_carpet.design.inverse.design`), and through it the render and the command line, build
what they need here. The table is the scene's (``scene.load_table()``, cached) and is checked
against ``carpet.chi_N``; the target is resolved against the table (its default angle) and the
carpet's frame; the carpet is built on demand with the curvatures asked for (the design's
starting layout, or the scene's own ``carpet.chi_N``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from single_cilium.table import ThrustTable

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.scenes.schema import SceneError
from ciliary_carpet.stokes import backend_named
from ciliary_carpet.design.target import Frame, Target

if TYPE_CHECKING:
    from ciliary_carpet.scenes.scene import Scene

__all__ = ["Assembly", "assemble", "check_table_range"]


def check_table_range(scene: "Scene", table: ThrustTable) -> None:
    """SceneError naming ``carpet.chi_N`` when it lies outside ``table``'s range."""
    lo, hi = table.chi_N_range
    c = scene.carpet.chi_N
    if not lo <= abs(c) <= hi:
        raise SceneError(f"{scene.source_name}: carpet.chi_N = {c:g} is outside the thrust table's range "
                         f"[{lo:g}, {hi:g}] (by mirror symmetry also negative; the top is the flutter cutoff)")


@dataclass(frozen=True, eq=False)
class Assembly:
    """What :func:`assemble` builds from ``scene``.

    table : the scene's thrust table; bases : (N, 2) base points; frame : the
    target's :class:`~ciliary_carpet.design.target.Frame` of those bases; target : the resolved
    :class:`~ciliary_carpet.design.target.Target` (kind "none" without a target).
    """

    scene: "Scene"
    table: ThrustTable
    bases: np.ndarray
    frame: Frame
    target: Target

    def carpet(self, chi_N=None) -> Carpet:
        """The scene's carpet with curvatures ``chi_N`` (scalar or (N,); default the scene's
        ``carpet.chi_N``): its base points, initial phases, field direction, wall, units, blob
        size and the evaluator of its sums (the scene's ``backend``)."""
        s = self.scene
        return Carpet(self.bases, s.carpet.chi_N if chi_N is None else chi_N, self.table,
                      s.carpet.initial_phases(self.bases), direction=s.field.direction_rad, wall=s.carpet.wall,
                      scales=None if s.units is None else s.units.scales(), blob=s.carpet.blob,
                      backend=backend_named(s.backend))


def assemble(scene: "Scene", table: ThrustTable | None = None) -> Assembly:
    """Build the objects ``scene`` describes (``table`` default: ``scene.load_table()``).

    Raises SceneError for an unreadable table or one for another field, or ``carpet.chi_N``
    outside the table's range; TargetError for a target that cannot be resolved (an unreadable
    control-point file)."""
    table = table if table is not None else scene.load_table()
    check_table_range(scene, table)
    bases = scene.carpet.bases()
    return Assembly(scene, table, bases, Frame.from_scene(scene, bases), Target.from_scene(scene, table))
