"""Arrays of artificial cilia under one uniform field: inverse design of curvature layouts,
Stokeslet flows at the fidelity a scene needs, path lines and VTK output.

This layer depends on :mod:`single_cilium` only through its public API and its lookup table.
This module is its front door: the names below are what a user scripts with; each lives in one
subpackage, itself a layer with one noun per module.

Scenes (:mod:`ciliary_carpet.scenes`)
    load_scene, scene_from_dict, Scene, SceneError: a scene file read and checked;
    assemble, load_table, carpet_for: the objects it describes (the one route from a scene to
    objects); design: its carpet designed for its target.
Carpets (:mod:`ciliary_carpet.carpet`)
    Carpet (``carpet.evaluate(points, when=Instant(t) | CycleMean(), tol)`` -> FlowSample),
    Instant, CycleMean, FlowSample, layout (lattices of base points and phases).
Flow sums (:mod:`ciliary_carpet.stokes`)
    stokeslet_velocity, Wall, backend_named: sums of point forces, by backend.
Design (:mod:`ciliary_carpet.design`)
    design_layout (a carpet's curvatures for control points), Design, DesignError, reachability,
    tolerance_study, Target, Frame, PATTERNS.
Transport (:mod:`ciliary_carpet.transport`)
    pathlines, ftle_field and the flows they follow (ResolvedFlow, MeanFlow; the registry FLOWS).
Output
    render (a scene to its output folder: VTK files, pictures, summary, ParaView script),
    RenderResult, RenderError.

Example::

    import ciliary_carpet as cc

    scene = cc.load_scene("designs/focusing.toml")
    d, carpet = cc.design(scene)                       # chi_N of every cilium for the target
    s = carpet.evaluate([[0.0, 0.0, 0.5]], cc.CycleMean(), tol=1e-3)
    cc.render(scene, "out/focusing")
"""
from cilia_runtime.numba_cache import ensure_writable_cache as _ensure_writable_cache

_ensure_writable_cache(__path__[0])  # before any module compiles: a read-only install, an unwritable home

from ciliary_carpet.carpet import layout  # noqa: E402
from ciliary_carpet.carpet.carpet import Carpet, CycleMean, FlowSample, Instant  # noqa: E402
from ciliary_carpet.design import (  # noqa: E402
    PATTERNS,
    Design,
    DesignError,
    Frame,
    Target,
    design_layout,
    reachability,
    tolerance_study,
)
from ciliary_carpet.render import RenderError, RenderResult, render  # noqa: E402
from ciliary_carpet.scenes.assembly import assemble, carpet_for, design, load_table  # noqa: E402
from ciliary_carpet.scenes.scene import Scene, SceneError, load_scene, scene_from_dict  # noqa: E402
from ciliary_carpet.stokes import Wall, backend_named, stokeslet_velocity  # noqa: E402
from ciliary_carpet.transport.flow import FLOWS, MeanFlow, ResolvedFlow  # noqa: E402
from ciliary_carpet.transport.ftle import ftle_field  # noqa: E402
from ciliary_carpet.transport.pathlines import pathlines  # noqa: E402

__all__ = [
    "load_scene", "scene_from_dict", "Scene", "SceneError", "assemble", "load_table", "carpet_for", "design",
    "Carpet", "Instant", "CycleMean", "FlowSample", "layout",
    "stokeslet_velocity", "Wall", "backend_named",
    "design_layout", "Design", "DesignError", "reachability", "tolerance_study", "Target", "Frame",
    "PATTERNS",
    "pathlines", "ftle_field", "ResolvedFlow", "MeanFlow", "FLOWS",
    "render", "RenderResult", "RenderError",
]
