"""One artificial cilium: a naturally curved, active (polyelectrolyte hydrogel) filament,
clamped at one end, that flutters under a steady uniform field.

The model and its conventions are in MODEL.md (shared with the project): dimensionless groups
``chi_E`` (stimulus), ``eta`` (drag vs bending), ``chi_N`` (natural curvature); the field is
along ``e2``; ``theta`` is the tangent angle from ``e2``, anticlockwise.

Front doors
-----------
CiliumParams      the three groups, an optional background flow U (and SI conversion)
equilibrium       closed-form equilibrium theta(s) in fluid at rest; limit_angle, equilibrium_shape;
                  steady_state: the discrete equilibrium in a background flow (params.background)
Mesh              graded spectral-element mesh of the arc length
simulate          nonlinear dynamics (Galerkin in space, Radau IIA(5) in time) with error estimates
stability         leading eigenvalues, modes and regime of the linearisation; flutter_cutoff,
                  flutter_boundary (continuation), stability_map
limit_cycle       periodic orbit by shooting with the exact monodromy (single_cilium.orbit): period,
                  mean thrust, Floquet multipliers, error estimates; mean_thrust: Fbar at (chi_N, U)
                  with an error estimate
"""
from .version import __version__

from cilia_runtime.numba_cache import ensure_writable_cache as _ensure_writable_cache

_ensure_writable_cache(__path__[0])  # before any module compiles: a read-only install, an unwritable home

from .params import CiliumParams, PhysicalCilium
from .equilibrium import NoLimitAngleError, equilibrium, equilibrium_shape, limit_angle
from .mesh import Mesh
from .filament import Filament
from .steady import SteadyState, steady_state
from .radau import ConvergenceError
from .dynamics import Simulation, simulate
from .cycle import CycleError, LimitCycle, MeanThrust, limit_cycle, mean_thrust
from .stability import (Cutoff, FlutterBoundary, ResolutionWarning, Stability, flutter_boundary,
                        flutter_cutoff, stability, stability_map)

__all__ = [
    "CiliumParams", "PhysicalCilium", "equilibrium", "equilibrium_shape", "limit_angle",
    "NoLimitAngleError", "steady_state", "SteadyState", "Mesh", "Filament", "simulate", "Simulation",
    "ConvergenceError",
    "stability", "Stability", "ResolutionWarning", "flutter_cutoff",
    "Cutoff", "flutter_boundary", "FlutterBoundary", "stability_map", "limit_cycle", "LimitCycle",
    "CycleError", "mean_thrust", "MeanThrust", "__version__",
]
