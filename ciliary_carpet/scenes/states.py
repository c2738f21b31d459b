"""A program's states as scenes of one field each.

A program is a scene with ``[[state]]`` tables (:class:`~ciliary_carpet.scenes.scene.StateSpec`):
one layout of cilia designed for several field strengths at once. :func:`state_scenes` gives,
for each state, the ordinary scene of that one field: the program's carpet, output and units with
the state's field strength, target and table. Everything that takes a scene of one field (its
table, :func:`~ciliary_carpet.scenes.assembly.load_table`; its target and frame; a render) takes
these.
"""
from __future__ import annotations

import logging
from dataclasses import replace

from ciliary_carpet.scenes.scene import Scene, StateSpec
from ciliary_carpet.scenes.schema import SceneError

logger = logging.getLogger(__name__)

__all__ = ["state_scenes"]


def state_scenes(scene: Scene) -> tuple[tuple[StateSpec, Scene], ...]:
    """Each state of the program ``scene`` with its own scene of one field.

    Parameters
    ----------
    scene : Scene
        A program: a scene with states (``scene.states``, at least two).

    Returns
    -------
    tuple of (StateSpec, Scene)
        In the order of ``scene.states``: the state, and the scene that is ``scene`` with
        ``field.chi_E`` the state's ``chi_E``, ``target`` the state's target, ``table`` the
        state's table, no states, and the name ``<scene name>_<state name>``; the same carpet,
        output, units, tolerance, backend and ``source`` (relative paths resolve as in the
        program). Each is made through :class:`~ciliary_carpet.scenes.scene.Scene`'s validation,
        so it passes every check of a scene of one field (a standing program's ``output.height``,
        when not given, is the state's target height).

    Raises
    ------
    SceneError
        If ``scene`` has no states (it is a scene of one field already), or if a state's scene
        breaks a rule of a scene of one field.
    """
    if not scene.states:
        raise SceneError(f"{scene.source_name}: state_scenes takes a program (a scene with [[state]] tables); this "
                         f"scene has one field: it is its own scene")
    out = []
    for st in scene.states:
        one = replace(scene, name=f"{scene.name}_{st.name}", field=replace(scene.field, chi_E=st.chi_E),
                      target=st.target, table=st.table, states=())
        logger.debug("state %s of %s: chi_E = %g, target %s", st.name, scene.name, st.chi_E, st.target.kind)
        out.append((st, one))
    return tuple(out)
