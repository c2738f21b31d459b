"""A program scene (``[[state]]``) to objects: each state's carpet and target, the joint design.

:func:`design_program_scene` builds every state as the single-state scene it is
(:func:`~ciliary_carpet.scenes.states.state_scenes`: the program's carpet in the state's field,
with the state's target and table), assembles it as any scene (:func:`~ciliary_carpet.scenes.assembly.assemble`),
and designs one layout for all of them (:func:`~ciliary_carpet.design.program.design_program`).
Its verdict: a state whose rms residual exceeds its threshold is a warning naming the limiting
state, or with ``strict = true`` in any state's target a
:class:`~ciliary_carpet.design.result.DesignError` (exit status 3 of the command line); a state's
fabrication tolerance (``sigma`` of its target) is studied on the program's layout in that field.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.design.program import Program, design_program, state_problem
from ciliary_carpet.design.result import Design, DesignError
from ciliary_carpet.design.tolerance import tolerance_study
from ciliary_carpet.scenes.assembly import Assembly, assemble
from ciliary_carpet.scenes.schema import SceneError
from ciliary_carpet.scenes.states import state_scenes

if TYPE_CHECKING:
    from ciliary_carpet.scenes.scene import Scene

logger = logging.getLogger(__name__)

__all__ = ["DesignedState", "design_program_scene"]


@dataclass(frozen=True, eq=False)
class DesignedState:
    """One state of a designed program: its name, its single-state ``scene`` (the program's
    carpet in the state's field, :func:`~ciliary_carpet.scenes.states.state_scenes`), the
    program's layout measured in that field (``design``: residual, error bar, verdict) and the
    carpet with that layout (``carpet``)."""

    name: str
    scene: "Scene"
    design: Design
    carpet: Carpet


def design_program_scene(scene: "Scene") -> tuple[Program, tuple[DesignedState, ...]]:
    """Design the program ``scene`` (a scene with ``[[state]]``): returns the
    :class:`~ciliary_carpet.design.program.Program` and its states (module docstring).

    Raises SceneError for a scene without states or a standing carpet (a program designs
    planar carpets), the errors of assembling each state's scene (its table, its target), and
    DesignError when a state with ``strict = true`` is not met."""
    if not scene.states:
        raise SceneError(f"{scene.source_name}: the scene has no [[state]]: it is not a program")
    if scene.carpet.geometry != "planar":
        raise SceneError(f"{scene.source_name}: carpet.geometry = {scene.carpet.geometry!r}: a program ([[state]]) "
                         "designs planar carpets; a standing carpet's program is not available")
    pairs = state_scenes(scene)
    problems, targets = [], []
    for spec, sc in pairs:
        built = assemble(sc)
        carpet, carpet_of = built.carpet, built.carpet
        if sc.carpet.coupling == "mean":  # the design model's stand-in: the same table in still fluid, uncoupled
            still = Assembly(replace(sc, carpet=replace(sc.carpet, coupling="none")), built.table.in_still_fluid(),
                             built.bases, built.frame, built.target)
            carpet = still.carpet
        problems.append(state_problem(spec.name, built.target, carpet(), built.bases, built.frame,
                                      spacing=sc.carpet.spacing, weight=spec.weight, carpet_of=carpet_of))
        targets.append(built.target)
    smoothness = max(t.smoothness for t in targets)
    prog = design_program(problems, tol=scene.tolerance, smoothness=smoothness)
    states = []
    for (spec, sc), t, d in zip(pairs, targets, prog.designs):
        if t.sigma > 0:
            d = replace(d, tolerance=tolerance_study(d.carpet, d, t.sigma, t.samples).summary())
        states.append(DesignedState(spec.name, sc, d, d.carpet))
    prog = replace(prog, designs=tuple(s.design for s in states))
    if not all(prog.met):
        bad = [n for n, m in zip(prog.states, prog.met) if not m]
        lim = prog.limiting
        msg = (f"{scene.source_name}: the cilia cannot make every state of this program with one layout: "
               f"{', '.join(bad)} not met (limiting: state {lim[0]}, rms residual {lim[1]:.2f}x its threshold); "
               f"{prog.message}. Lower the states' angles, lower a state's weight to favour the others, or raise "
               "its residual; `ciliary-carpet reach` shows which pairs of flows the cilia can make")
        if any(t.strict for t in targets):
            raise DesignError(msg)
        warnings.warn(msg + " (strict = false: returning the closest layout)", UserWarning, stacklevel=2)
    return prog, tuple(states)
