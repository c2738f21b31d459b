"""A program: one layout whose flow is switched by the field's strength
=====================================================================

The cilia's curvatures are fixed when the chip is made; the field strength chi_E can be switched.
This script takes the bundled ``program_valve`` scene (its flow turned -12 degrees at
chi_E = 150 and +12 degrees at chi_E = 200) at its reduced size, asks first what pairs of flows
its cilia can make (``program_reachability``: per field the reachable thrust angles, and the
curvatures that beat in one field and rest in the other), then designs the one layout for both
fields (``design_program_scene``) and measures each field's flow with its error bar.

Angles are in radians (anticlockwise, relative to the straight cilia's flow); chi_N, chi_E are
dimensionless (MODEL.md).

Results: ``low_rms``, ``high_rms`` (each state's rms residual, rad), ``low_error``, ``high_error``
(their error bars, rad), ``resting_low`` (cilia that rest at chi_E = 150) and ``largest_change``
(the largest change of one cilium's thrust angle between the two fields, rad).
"""
from pathlib import Path

import numpy as np

import ciliary_carpet as cc
from ciliary_carpet.design.program_reach import program_reachability
from ciliary_carpet.scenes.assembly import load_table
from ciliary_carpet.scenes.program import design_program_scene
from ciliary_carpet.scenes.states import state_scenes

HERE = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
DESIGNS = next(d / "designs" for d in (HERE, *HERE.parents) if (d / "designs").is_dir())  # the bundled scenes
scene = cc.load_scene(DESIGNS / "program_valve.toml").reduced()

# 1. before designing: what one cilium makes in each field (its tables, seconds)
pairs = state_scenes(scene)                        # (state, its one-field scene) per state
reach = program_reachability([load_table(s).in_still_fluid() for _, s in pairs], [st.name for st, _ in pairs])
largest_change = abs(float(reach.summary()["pairs"][0]["largest_angle_change"]["delta_rad"]))

# 2. one layout for both fields, each measured in its own coupled model
program, states = design_program_scene(scene)
(low, high) = program.designs
low_rms, high_rms = float(low.residual_rms), float(high.residual_rms)
low_error, high_error = float(low.residual_error), float(high.residual_error)
resting_low = len(program.resting[0])

if __name__ == "__main__":
    print(reach.describe())
    print(program.message)
    print(f"chi_N from {program.chi_N.min():.1f} to {program.chi_N.max():.1f}; {resting_low} of {program.chi_N.size} "
          f"cilia rest at chi_E = 150; low {np.degrees(low_rms):.1f} deg rms, high {np.degrees(high_rms):.1f} deg rms")
