"""The layout's outputs: where the cilia stand and their curvatures (``layout``), and the design
that set them or the layout a standing carpet is given (``design``).
"""
from __future__ import annotations

import numpy as np

from cilia_runtime.files import write_netcdf

from ciliary_carpet.carpet.carpet import Carpet
from ciliary_carpet.output.contract import Output
from ciliary_carpet.output.figures import design_picture
from ciliary_carpet.output.plan import RenderPlan
from ciliary_carpet.output.vtkfiles import write_points

__all__ = ["LayoutOutput", "DesignOutput", "standing_layout_dataset", "design_summary"]


class LayoutOutput(Output):
    """``layout.vtp``: the cilia's base points with chi_N, thrust angle (in the flow each beats in),
    flutter and near_cutoff; for a coupled carpet also ``background_flow``, the others' mean flow
    at each cilium. A standing carpet's also has ``azimuth`` [deg] and ``mean_thrust`` (the
    cycle-mean force on the fluid in space, force per length units x L) with its force centres'
    height ``centre_z`` (its ``layout.nc`` is the ``design`` output's file)."""

    name = "layout"
    files = (r"layout\.vtp",)

    def wanted(self, plan):
        return True

    def write(self, ctx):
        if ctx.carpet.geometry == "standing":
            self._standing(ctx)
            return
        c, d = ctx.carpet, ctx.design
        L, _, V = ctx.plan.units
        near = np.zeros(c.n, np.uint8)
        if d is not None:
            near[list(d.near_cutoff)] = 1
        flow = {}
        if c.background is not None:  # each cilium's thrust in the flow it beats in (field frame)
            u = c.background @ c.rotation
            flow = {"U_perp": u[:, 0], "U_par": u[:, 1]}
        data = {"chi_N": c.chi_N, "thrust_angle": c.table.scalar("thrust_angle", c.chi_N, **flow),
                "cilium_id": np.arange(c.n), "flutter": c.flutter.astype(np.uint8), "near_cutoff": near}
        if c.background is not None:  # a coupled carpet: the others' mean flow at each cilium
            data["background_flow"] = np.column_stack([c.background * V, np.zeros(c.n)])
        write_points(ctx.stage / "layout.vtp", np.column_stack([c.bases * L, np.zeros(c.n)]), data)
        ctx.summary["layout"] = {"chi_N_min": float(c.chi_N.min()), "chi_N_max": float(c.chi_N.max())}

    @staticmethod
    def _standing(ctx):
        c = ctx.carpet
        L = ctx.plan.units[0]
        f_scale = _force_scale(ctx.plan, c)
        psi = np.round(np.degrees(c.azimuth), 9)
        data = {"chi_N": c.chi_N, "azimuth": psi, "thrust_angle": c.table.scalar("thrust_angle", c.chi_N),
                "cilium_id": np.arange(c.n), "flutter": c.flutter.astype(np.uint8), "near_cutoff": np.zeros(c.n, np.uint8),
                "mean_thrust": c.in_space("mean_thrust") * f_scale * L, "centre_z": c.in_space("centres")[:, 2] * L}
        write_points(ctx.stage / "layout.vtp", np.column_stack([c.bases * L, np.zeros(c.n)]), data)
        ctx.summary["layout"] = {"chi_N_min": float(c.chi_N.min()), "chi_N_max": float(c.chi_N.max()),
                                 "azimuth_min_deg": float(psi.min()), "azimuth_max_deg": float(psi.max())}


def _force_scale(plan: RenderPlan, c: Carpet) -> float:
    """The factor from the model's force per length to the files' (1 without SI units)."""
    sc = plan.scales
    return sc.viscosity_Pa_s * plan.units[2] / c.mu if sc is not None else 1.0


def standing_layout_dataset(c: Carpet):
    """A standing carpet's layout as an xarray Dataset (dim ``cilium``, CF attributes; what
    ``layout.nc`` holds): base point x, y [L], chi_N, azimuth psi [degrees anticlockwise from +x],
    thrust angle [rad], beat phase at t = 0, the cycle-mean force on the fluid in space
    (``mean_thrust_x``, ``_y``, ``_z``; force per length x L, model units) and the force centre's
    height ``centre_z`` [L]; attributes: geometry, chi_E, eta, wall (distance below the clamps,
    -1 for none)."""
    import xarray as xr

    F = c.in_space("mean_thrust")
    return xr.Dataset(
        {"x": ("cilium", c.bases[:, 0], {"long_name": "base point x", "units": "L"}),
         "y": ("cilium", c.bases[:, 1], {"long_name": "base point y", "units": "L"}),
         "chi_N": ("cilium", c.chi_N, {"long_name": "natural curvature chi_N = L kappa_N", "units": "1"}),
         "azimuth": ("cilium", np.round(np.degrees(c.azimuth), 9),  # (to 1e-9 deg: 30, not 29.999999999999996)
                     {"long_name": "beat-plane azimuth psi, anticlockwise from +x", "units": "degree"}),
         "thrust_angle": ("cilium", c.table.scalar("thrust_angle", c.chi_N),
                          {"long_name": "lean of the mean thrust from the normal towards e_psi", "units": "rad"}),
         "phase": ("cilium", c.phases, {"long_name": "beat phase at t = 0", "units": "1"}),
         "mean_thrust_x": ("cilium", F[:, 0], {"long_name": "cycle-mean force on the fluid, x", "units": "B/L^2"}),
         "mean_thrust_y": ("cilium", F[:, 1], {"long_name": "cycle-mean force on the fluid, y", "units": "B/L^2"}),
         "mean_thrust_z": ("cilium", F[:, 2], {"long_name": "cycle-mean force on the fluid, z", "units": "B/L^2"}),
         "centre_z": ("cilium", c.in_space("centres")[:, 2], {"long_name": "height of the force centre",
                                                              "units": "L"})},
        attrs={"geometry": c.geometry, "chi_E": c.table.chi_E, "eta": c.table.eta,
               "wall": -1.0 if c.wall is None else float(c.wall)})


class DesignOutput(Output):
    """With a target: ``layout.nc``, ``design.vtp`` (control points: target, achieved flow,
    residual) and ``design.png``. A standing carpet (given its layout, no target): ``layout.nc``
    alone, chi_N and azimuth per cilium (:func:`standing_layout_dataset`)."""

    name = "design"
    files = (r"layout\.nc", r"design\.vtp", r"design\.png")

    def wanted(self, plan):
        return plan.designed or plan.settings.geometry == "standing"

    def write(self, ctx):
        if ctx.design is None:  # a standing carpet's given layout
            write_netcdf(standing_layout_dataset(ctx.carpet), ctx.stage / "layout.nc")
            return
        d, stage = ctx.design, ctx.stage
        L, _, V = ctx.plan.units
        write_netcdf(d.to_dataset(ctx.carpet), stage / "layout.nc")
        z = np.zeros((d.control.shape[0], 1))
        write_points(stage / "design.vtp", np.column_stack([d.control * L, z]),
                     {"target": np.concatenate([d.target * (V if d.kind == "velocity" else 1.0), z], axis=1),
                      "achieved": np.concatenate([d.achieved * V, z], axis=1), "residual": d.residual,
                      **({"speed_ratio": d.speed_ratio} if d.speed_ratio is not None else {})})
        design_picture(stage / "design.png", ctx.plan.settings.name, ctx.carpet, d)
        ctx.summary["design"] = design_summary(d, L)


def design_summary(d, length: float) -> dict:
    """The design's summary (:meth:`Design.summary <ciliary_carpet.design.result.Design.summary>`,
    lengths in L) with its lengths times ``length`` (the summary's unit of length: 1, or
    ``[units] length_m``): the worst control points' x, y, a standing design's surface height and
    the reachability's line, widths and width scan. Its residuals are angles or relative."""
    out = d.summary()
    out["worst"] = [dict(w, x=w["x"] * length, y=w["y"] * length) for w in out["worst"]]
    if out.get("surface_height") is not None:
        out["surface_height"] = out["surface_height"] * length
    r = out.get("reachability")
    if r is not None:
        r = dict(r)
        for k in ("line", "width", "width_min"):
            if r.get(k) is not None:
                r[k] = r[k] * length
        if "width_scan" in r:
            r["width_scan"] = [[w * length, res] for w, res in r["width_scan"]]
        out["reachability"] = r
    return out
