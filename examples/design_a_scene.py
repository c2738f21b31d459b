"""Design a layout: from a scene file, and from Python objects
============================================================

The front door is ``ciliary_carpet.design(scene)``: a scene file (or a :class:`Scene`) in, the
designed curvature of every cilium and the carpet that has it out. This script designs the
bundled ``uniform_deflection`` scene (a carpet whose mean flow is turned by 30 degrees) at its
reduced size, then the same kind of design from objects: a focusing pattern on a 6 x 6 carpet with
``design_layout``, and what a two-sided pattern can reach on it (``reachability``).

Angles are in radians (anticlockwise, relative to the straight cilia's flow); lengths in L.

Results: ``scene_rms`` and ``scene_error`` (the scene design's rms residual and its error bar,
rad), ``focus_rms`` (the focusing design's rms residual, rad) and ``pattern_max_deg`` (the
largest amplitude of a two-sided pattern on that carpet, degrees).
"""
import math
from pathlib import Path

import numpy as np

import ciliary_carpet as cc
from ciliary_carpet.design import control_points

HERE = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
DESIGNS = next(d / "designs" for d in (HERE, *HERE.parents) if (d / "designs").is_dir())  # the bundled scenes
SCENE = DESIGNS / "uniform_deflection.toml"

# 1. from a scene file: the front door (the scene at its reduced size, seconds)
scene = cc.load_scene(SCENE).reduced()
d, carpet = cc.design(scene)                       # Design, and the Carpet with the designed chi_N
scene_rms, scene_error = float(d.residual_rms), float(d.residual_error)

# 2. from objects: the scene's builder gives the table, target and frame of any scene file
built = cc.assemble(cc.load_scene(DESIGNS / "focusing.toml").reduced())
frame, target = built.frame, built.target
plain = built.carpet()                             # the scene's carpet, straight cilia
X = control_points(plain.bases, frame, "cells")    # (P, 2) where the flow is compared with the target
angles = target.deflection(X, frame)               # (P,) the pattern's deflection there, rad
focus = cc.design_layout(plain, X, angles=angles, spacing=built.scene.carpet.spacing)
focus_rms = float(focus.residual_rms)
pattern_max_deg = math.degrees(cc.reachability(plain, X, frame).pattern_max)

if __name__ == "__main__":
    print(d.message)                               # the verdict, with its residual and error bar
    print(f"uniform_deflection: rms {scene_rms:.3g} rad +- {scene_error:.2g}; chi_N {np.ptp(carpet.chi_N):.3g} "
          f"apart; focusing: rms {focus_rms:.3g} rad; a two-sided pattern reaches about {pattern_max_deg:.1f} deg")
