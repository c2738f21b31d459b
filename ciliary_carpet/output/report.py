"""The render's summary in words (``summary.md``): what the numbers of ``summary.json`` mean for
the design, each with its unit.

Lengths are in L (the cilium's length) and times in tau (the filament's relaxation time,
MODEL.md) unless the scene has ``[units]`` (then m and s); durations are also counted in beats
of the cilia themselves (their median period, ``summary["beat"]``). Angles are given in degrees
with the radians the scene's ``[target] residual`` is written in. An error bar is stated as the
bound it is: the flow model's tolerance can move a figure by at most that much.
"""
from __future__ import annotations

import math

from ciliary_carpet.design.inverse import NEAR_CUTOFF_FRACTION
from ciliary_carpet.output.plan import ANIMATION_STEPS, DOMAIN_MARGIN
from ciliary_carpet.design.patterns import PATTERNS

__all__ = ["markdown", "program_markdown"]

_TWO_SIDED = {p.name for p in PATTERNS if p.two_sided}
_SUMMED = {"mean": "far from the cilium from its cycle-averaged forces",
           "point": "far from the cilium from point forces at its current phase",
           "resolved": "near it from the whole moving filament"}


def _g(x: float, digits: int = 3) -> str:
    return f"{x:.{digits}g}"


def _deg(rad: float) -> str:
    return f"{math.degrees(rad):.2g} deg" if abs(math.degrees(rad)) < 10 else f"{math.degrees(rad):.1f} deg"


def markdown(s: dict) -> str:
    """``summary.md`` from the render's summary dict (``summary.json``)."""
    si = s.get("units") == "SI"
    Lu, Tu = ("m", "s") if si else ("L", "tau")
    Vu = f"{Lu}/{Tu}"
    scene = s.get("scene_resolved", {})
    beat = s.get("beat")
    period = beat["period"] if beat else s.get("T0")

    def dur(t: float) -> str:
        out = f"{_g(t, 4)} {Tu}"
        if period and period > 0:
            out += f" ({_g(t / period)} beats)"
        return out

    lines = [f"# {s['scene']}", ""]
    if scene.get("description"):
        lines += [scene["description"] + ".", ""]
    if s.get("program"):
        lines += _program_state(s["program"]) + [""]
    units = ("SI: lengths in m, times in s, speeds in m/s" if si else
             "lengths in L (the cilium's length), times in tau (the filament's relaxation time), speeds in L/tau")
    lines.append(f"Scene `{s['source']}`: {s['n_cilia']} cilia; {units}.")
    if s.get("geometry") == "standing":
        st = s["standing"]
        az = st["azimuth_deg"]
        turn = (f"all turned to {az['min']:.3g} deg" if az["max"] - az["min"] < 1e-9 else
                f"turned from {az['min']:.3g} to {az['max']:.3g} deg (median {az['median']:.3g})")
        lines.append(f"Standing carpet: each cilium is {_clamped(st['wall_below_clamps'], Lu)} with the field along "
                     f"+z, its beat plane turned about the normal by its azimuth (anticlockwise from +x): {turn}. The "
                     f"flow is three-dimensional: its mean is shown on the target plane z = {_g(st['target_height'])} "
                     f"{Lu} (`mean_field.vti`) and on a vertical section through the carpet's centre down to the wall "
                     "(`mean_field_section.vti`).")
    if beat:
        if beat["beating"] == 0:
            lines.append("None of the cilia beats (every one is beyond the flutter cutoff): they stand still.")
        else:
            spread = beat["period_max"] / beat["period_min"] - 1.0 if beat["period_min"] > 0 else 0.0
            txt = f"The cilia beat once every {_g(beat['period'])} {Tu}"
            if spread > 1e-6:
                txt += (f" (the median; each cilium beats with its own period, from {_g(beat['period_min'])} to "
                        f"{_g(beat['period_max'])} {Tu})")
            still = s["n_cilia"] - beat["beating"]
            if still:
                txt += f"; {still} of them do not beat (beyond the flutter cutoff) and stand still"
            lines.append(txt + ".")
    lines += ["", *_verdict(s, Lu)]
    if "design" in s:
        lines += ["", "## The design", ""] + _design(s, scene)
    if any(k in s for k in ("mean_field", "snapshots", "pathlines", "mixing")):
        lines += ["", "## The flow", ""]
    if "mean_field" in s:
        m = s["mean_field"]
        parts = [f"{_SUMMED.get(k, k)} ({v:.1%} of the cilium-point pairs)" for k, v in m["fidelity"].items() if v > 0]
        top = m.get("max_speed")
        rel = f" ({m['max_error_bound'] / top:.2%} of the fastest flow)" if top else ""
        lines.append(f"- **Mean flow** (averaged over the beat; `mean_field.vti`, {m['points']} grid points): "
                     + (f"up to {_g(top)} {Vu}; " if top else "")
                     + f"accurate to {_g(m['max_error_bound'], 2)} {Vu} or better everywhere{rel}, a bound. To "
                     f"save time, each cilium's flow was summed {', and '.join(parts)}; the bound covers that.")
    if "snapshots" in s:
        n = s["snapshots"]["count"]
        lines.append(f"- **Instantaneous flow**: {n} snapshot{'s' if n > 1 else ''} over one beat "
                     "(`snapshots.pvd`; hidden when ParaView opens).")
    if "pathlines" in s:
        lines += _pathlines(s["pathlines"], dur, Lu, Vu, s.get("geometry") == "standing")
    if "mixing" in s:
        mx = s["mixing"]
        flow = "the mean flow" if mx["model"] == "mean" else "the time-resolved flow"
        if s.get("geometry") == "standing":
            flow += f" in the plane z = {_g(s['standing']['target_height'])} {Lu} (tracers kept in that plane)"
        txt = (f"- **Mixing**: over {dur(mx['duration'])} of {flow}, neighbouring fluid parcels over the carpet "
               f"move apart by a factor {math.exp(mx['mixing_number']):.3f} on average (mixing number "
               f"{_g(mx['mixing_number'])}: the mean log-stretching; 0 for a flow that only carries or turns "
               "the fluid)")
        if mx["ftle_max"] is not None:
            txt += f"; the fastest stretching is {_g(mx['ftle_max'])} per {Tu} (the FTLE field, `ftle.vti`)"
        if mx["defined_fraction"] < 1:
            txt += (f"; measured on {mx['defined_fraction']:.0%} of the grid (the rest starts inside a cilium "
                    "or leaves the field)")
        if "uniform_pump" in mx:
            up = mx["uniform_pump"]
            txt += (f". The same carpet pumping uniformly (every cilium at chi_N = {_g(up['chi_N'])}, every beat "
                    f"plane at {up['azimuth_deg']:.0f} deg) over the same grid and time: mixing number "
                    f"{_g(up['mixing_number'])}")
        lines.append(txt + ".")
    if beat and beat["beating"] and "loop_until" in beat and beat["loop_until"] > 1.5 * beat["period"]:
        txt = (f"- **In ParaView** the cilia and the snapshots repeat one beat ({_g(beat['period'])} {Tu}) until "
               f"{_g(beat['loop_until'], 4)} {Tu}, the path lines' end, so that everything moves on one clock")
        spread = beat["period_max"] / beat["period_min"] - 1.0 if beat["period_min"] > 0 else 0.0
        if spread > 1e-6:
            txt += (f"; the cilia's own periods differ by up to {spread:.1%}, so after the first beat the "
                    "animated cilia keep the first beat's phases, not the drifting ones of the computed flow")
        frames = scene.get("output", {}).get("frames") or 0
        if frames and beat["loop_until"] / beat["period"] * frames > ANIMATION_STEPS:
            txt += (f"; over {beat['loop_until'] / beat['period']:.0f} beats the animation has "
                    f"{ANIMATION_STEPS} steps, each showing the cilia at its own phase of the beat (a "
                    "stroboscope: the beat itself is not resolved at that speed)")
        lines.append(txt + ".")
    if s.get("omissions", {}).get("lines"):
        lines += ["", "## What the model leaves out", ""] + [f"- {t}" for t in s["omissions"]["lines"]]
    cp = s.get("coupling")
    if cp:
        lines += ["", "## Cilia that feel the flow", ""]
        if cp["model"] == "mean":
            lines.append(f"- Coupled carpet (`coupling = \"mean\"`): each cilium beats in the mean flow the others "
                         f"make at it, median {_g(cp['median_speed_coupled'])} {Vu} at the cilia; {cp['message']}. "
                         f"Uncoupled, that flow would be {_g(cp['median_speed_uncoupled'])} {Vu}: "
                         f"{cp['relative_change_median']:.0%} off the coupled one (median; largest "
                         f"{cp['relative_change_max']:.0%}).")
            nf = cp.get("normal_flow")
            if nf is not None and nf > 0.01:
                lines.append(f"- The part of the others' mean flow a cilium cannot feel, normal to its beat plane "
                             f"(its beat is planar), reaches {nf:.0%} of the largest flow it beats in (`normal_flow`); "
                             "the model leaves it out.")
        else:
            lines.append(f"- Uncoupled carpet (`coupling = \"none\"`): each cilium beats as in still fluid, although "
                         f"the others' mean flow at it is {_g(cp['median_speed_uncoupled'])} {Vu} (median). "
                         f"With the filaments' drag against that flow (a linear estimate: slender-body drag of a "
                         f"straight filament) the flow they can sustain is about {_g(cp['median_speed_coupled'])} "
                         f"{Vu}: the uncoupled flow at the cilia is about {cp['relative_change_median']:.0%} off "
                         f"(largest {cp['relative_change_max']:.0%}). `coupling = \"mean\"` solves it (needs a "
                         "table over the background flow).")
    lines += ["", "## How it was computed", ""]
    tb = s.get("table")
    if tb and tb.get("built"):
        lines.append(f"- The thrust table `{tb['file']}` was computed for this render (`[table.build]`): "
                     f"{tb['build_seconds']:.0f} s, {tb['size_bytes'] / 1e6:.1f} MB; later renders read it.")
    lines.append(f"- Flow tolerance {s['tolerance']:g} (relative to the carpet's far-field flow); flow sums: "
                 f"{s['backend']}.")
    if "design" in s:
        w = s["design"]["work"]
        lines.append(f"- Design: {w['iterations']} optimiser iterations (L-BFGS-B on the design model), "
                     f"{w['checks']} checks with the full flow model.")
    lines += ["", "| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.2f} |" for k, v in s["seconds"].items()]
    return "\n".join(lines) + "\n"


UNRELIABLE_END_POINTS = 1.0
"""End-point error estimate (in cilium lengths L) above which the path lines are flagged as
unreliable in the summary's first lines: beyond a cilium's length they no longer resolve the
carpet's structure."""

COUPLING_MATTERS = 0.1
"""Relative change of the flow at the cilia (uncoupled against the coupling's estimate) above which
the first lines say that the uncoupled model is far from the coupled one."""


def _clamped(h: float | None, Lu: str) -> str:
    """Where a standing carpet's cilia are clamped, given the wall's distance ``h`` below the
    clamps (None: no wall)."""
    if h is None:
        return "clamped at z = 0 in free space (no wall)"
    if h == 0:
        return "clamped on the substrate z = 0 (a no-slip wall)"
    return f"clamped at z = 0, {_g(h)} {Lu} above the substrate (a no-slip wall at z = -{_g(h)} {Lu})"


def _verdict(s: dict, Lu: str) -> list:
    """The summary's first lines: the verdict (or what the flow shown is), in which model, how far
    that model is from the fuller one, and any result too uncertain to use."""
    cp, dd = s.get("coupling"), s.get("design")
    coupled = cp is not None and cp.get("model") == "mean"
    name, how = (("the coupled model", "each cilium beats in the mean flow the others make at it") if coupled else
                 ("the uncoupled model", "each cilium beats as if in still fluid"))
    if dd is not None and "met" in dd:
        head = f"**Verdict: target {'met' if dd['met'] else 'NOT met'}, in {name}** ({how})"
        what = "the verdict"
    else:
        head = f"**The flow shown is {name}'s** ({how})"
        what = "the flow"
    if coupled:
        head += (f"; the coupling solved to a residual of {_g(cp['residual'], 2)} "
                 f"({cp.get('status', 'converged')}).")
    elif cp is not None and math.isfinite(cp.get("relative_change_median", math.nan)):
        rc = cp["relative_change_median"]
        if rc > COUPLING_MATTERS:
            head += (f". **The coupled model differs here**: the flow at the cilia is about {rc:.0%} off the flow "
                     f"they can sustain (a linear estimate; section \"Cilia that feel the flow\"), so the flow drawn "
                     f"is faster than a device's; `[carpet] coupling = \"mean\"` (with a table over the background "
                     f"flow) gives {what} in the coupled model.")
        else:
            head += (f"; the coupled model would change the flow at the cilia by about {rc:.0%} (a linear estimate): "
                     f"{what} stands within that.")
    elif s.get("omissions", {}).get("pushback", {}).get("median") is not None:
        pb = s["omissions"]["pushback"]
        if pb["median"] > COUPLING_MATTERS:
            head += (f". **The coupled model differs here**: the others' mean flow at a cilium is "
                     f"{pb['median']:.0%} (median) of the stream that would cancel its thrust (section \"What the "
                     f"model leaves out\"), so the flow drawn is faster than a device's.")
        else:
            head += (f"; the others' mean flow at a cilium is {pb['median']:.1%} (median) of the stream that would "
                     f"cancel its thrust, so the coupled model would change little.")
    else:
        head += "."
    out = [head]  # (each its own paragraph)
    e = s.get("pathlines", {}).get("end_point_error")
    if e and e.get("max") is not None:
        L = (s.get("scene_resolved", {}).get("units", {}).get("length_m", 1.0)  # a cilium's length, in Lu
             if s.get("units") == "SI" else 1.0)
        if e["max"] > UNRELIABLE_END_POINTS * L:
            out.append("")
            out.append(f"**Path lines unreliable**: their end points are uncertain by up to {_g(e['max'], 2)} {Lu} "
                       f"(more than a cilium's length; section \"The flow\"): read them as a sketch of the flow.")
    return out


def _design(s: dict, scene: dict) -> list:
    dd = s["design"]
    Lu = "m" if s.get("units") == "SI" else "L"
    tgt = scene.get("target", {})
    kind = tgt.get("kind", "")
    angle = dd["residual_unit"] == "rad"
    P = dd["control_points"]

    def r(x):  # a residual in words
        return f"{_deg(x)} ({_g(x, 2)} rad)" if angle else f"{x:.1%} of the target speed"

    what = "off the target direction" if angle else "off the target velocity"
    out = []
    rms, err = dd["residual_rms"], dd["residual_error"]
    if "met" in dd:
        thr = dd["residual_threshold"]
        if dd["met"]:
            head = f"- **Target met**: the designed carpet's mean flow is {r(rms)} rms {what}"
        else:
            head = f"- **Target NOT met**: the closest flow these cilia make is {r(rms)} rms {what}"
        given = tgt.get("residual", thr)
        if abs(given - thr) > 1e-12 * thr:  # sampled velocities with uncertainties: their noise counts
            allows = (f"the scene allows {r(thr)}: `[target] residual = {given:g}` combined with the samples' own "
                      f"noise, {r(math.sqrt(max(thr * thr - given * given, 0.0)))} rms (no flow comes closer to noisy "
                      f"samples than their noise)")
        else:
            allows = f"the scene allows {r(thr)} (`[target] residual = {thr:g}`)"
        out.append(f"{head} at the {P} control points; {allows}.")
    else:
        out.append(f"- The designed carpet's mean flow is {r(rms)} rms {what} at the {P} control points.")
    hi = rms + err
    if err == 0.0:
        txt = "- The flow at the control points was summed exactly (every cilium resolved): no level-of-detail error"
    else:
        txt = f"- The flow model's tolerance can move that figure by at most {r(err)} (a bound): the true rms is "
        txt += f"between {r(rms - err)} and {r(hi)}" if err < rms else f"at most {r(hi)}"
    if "met" in dd:
        thr = dd["residual_threshold"]
        if dd["met"] and hi <= thr:
            txt += ", below the allowed, so the target is met whatever that error"
        elif dd["met"]:
            txt += ", past the allowed: met by the computed flow, but not beyond the model's error"
    out.append(txt + ".")
    worst = ", ".join(f"({w['x']:.3g}, {w['y']:.3g}) {r(w['residual'])}" for w in dd["worst"][:3])
    out.append(f"- Largest misses, at the control points (x, y in {Lu}): {worst}.")
    lay = s.get("layout")
    txt = "- The layout: "
    if lay:
        txt += f"chi_N (natural curvature) from {lay['chi_N_min']:.3g} to {lay['chi_N_max']:.3g}; "
    nc = dd["cilia_near_cutoff"]
    if s.get("geometry") == "standing":  # weak along the surface: chi_N near 0 (a straight beat) or the cutoff
        txt += (f"{nc} of {s['n_cilia']} cilia pump weakly along the surface (below a quarter of the strongest: "
                f"chi_N near 0, where the beat is symmetric, or near the flutter cutoff, where it stops)"
                if nc else "no cilium pumps weakly along the surface")
    else:
        txt += (f"{nc} of {s['n_cilia']} cilia close to the flutter cutoff (their thrust below "
                f"{NEAR_CUTOFF_FRACTION:.0%} of a straight cilium's: the beat stops there and the push fades)"
                if nc else "no cilium close to the flutter cutoff (where the beat stops and the push fades)")
    out.append(txt + " (`layout.vtp`, `layout.nc`, `design.png`).")
    if dd.get("returned") == "local":
        out.append(f"- The starting layout (each cilium curved for the target on its own) was already the best: "
                   f"{r(dd['local_rms'])} rms; the design kept it.")
    elif dd.get("local_rms") is not None and math.isfinite(dd["local_rms"]):
        out.append(f"- Without the design (each cilium curved for the target on its own) the flow would be "
                   f"{r(dd['local_rms'])} rms off: the cilia's flows interfere, and the design corrects for it.")
    if dd.get("clipped"):
        out.append(f"- {len(dd['clipped'])} cilia were asked for more turn than a cilium can make and were given "
                   "the most they can.")
    reach = dd.get("reachability")
    if reach is not None:
        floor = tgt.get("speed_floor")
        keep = f"keeping {floor:.0%} of a straight cilium's push" if floor is not None else "at the speed floor"
        coupled = (s.get("coupling") or {}).get("model") == "mean"
        when = ("estimated before designing, for cilia beating in still fluid: in the flow they make together "
                "they turn it further, so a coupled design can reach beyond these figures" if coupled
                else "estimated before designing")
        txt = (f"- What these cilia can make ({when}): one cilium turns its push by up to "
               f"{reach['angle_max_deg']:.1f} deg ({reach['angle_floor_deg']:.1f} deg {keep})")
        if kind in _TWO_SIDED:
            txt += (f"; a pattern that turns the flow both ways ({kind}) holds about {reach['pattern_max_deg']:.1f} "
                    f"deg away from its line")
            if tgt.get("angle") is not None:
                ask = abs(tgt["angle"])
                txt += f" (asked {ask:.3g} deg: " + ("within that" if ask <= reach["pattern_max_deg"] else
                                                      "beyond that, expect a larger residual") + ")"
            if reach.get("width") is not None:
                wm = reach.get("width_min")
                txt += (f"; the narrowest transition across the line at that angle is "
                        + ("wider than 8 spacings" if wm is None else f"about {wm:.3g} {Lu}")
                        + f" (asked {reach['width']:.3g} {Lu})")
        elif tgt.get("angle") is not None:
            ask = abs(tgt["angle"])
            txt += f"; asked {ask:.3g} deg: " + (
                "within reach" if ask <= reach["angle_floor_deg"] else
                "within reach only of cilia that push less" if ask <= reach["angle_max_deg"] else
                "beyond what one cilium can turn")
        out.append(txt + ".")
    tt = dd.get("tolerance")
    if tt is not None:
        out.append(f"- Fabrication: if each cilium's chi_N is off by {tt['sigma']:.0%} at random ({tt['samples']} "
                   f"samples), the flow would be {r(tt['mean_rms'])} rms off on average (sampling error "
                   f"{_g(tt['sampling_error'], 1)}; 10-90%: {_g(tt['p10_rms'])} to {_g(tt['p90_rms'])}), against "
                   f"{r(tt['nominal_rms'])} as designed.")
    return out


def _pathlines(p: dict, dur, Lu: str, Vu: str, standing: bool = False) -> list:
    flow = "the time-resolved flow (the beat included)" if p["model"] == "resolved" else \
        "the long-time mean flow (the beat averaged out)"
    oc = p["outcome"]
    ends = []
    if oc.get("reached end time"):
        ends.append(f"{oc['reached end time']} reached the end")
    if oc.get("left the domain"):
        where = (f"reached the substrate (where the flow stops) or left the region followed ({_g(DOMAIN_MARGIN)} "
                 f"{Lu} beyond the carpet and the seeds, and above the target plane)" if standing else
                 f"left the region followed ({_g(DOMAIN_MARGIN)} {Lu} beyond the carpet and the seeds, where its "
                 f"flow has faded)")
        ends.append(f"{oc['left the domain']} {where}: their lines end there")
    if oc.get("step size underflow"):
        ends.append(f"{oc['step size underflow']} stopped early (the integrator's step size vanished, next to a "
                    "cilium)")
    how = p["duration_from"]
    if how == "scene":
        why = "as the scene's `[output] periods` asks"
    else:
        why = "long enough to cross the carpet" + (f" ({how.split(': ', 1)[1]}, plus 25%)" if ": " in how else "")
    if p.get("model_from", "scene") not in ("scene", "auto"):
        why += f"; {p['model_from'].split(': ', 1)[-1]}, so they follow the mean flow"
    out = [f"- **Path lines** (`pathlines.vtp`, `particles.pvd`): {p['tracers']} tracers followed {flow} for "
           f"{dur(p['duration'])}, {why}: {', '.join(ends) or 'none moved'}."]
    if p.get("points_written", p.get("points")) != p.get("points"):
        out.append(f"- `pathlines.vtp` holds {p['points_written']} of the lines' {p['points']} points (each line "
                   f"evenly thinned, its end kept: a file sized for viewing); `[output] pathline_points = 0` "
                   "writes them all.")
    e = p["end_point_error"]
    if p["model"] == "mean":
        out.append(f"- The mean flow moves their end points by up to {_g(e['max'], 2)} {Lu} (median "
                   f"{_g(e['median'], 2)}) against the time-resolved flow ({e['tracers']} tracers compared): an "
                   "estimate of the model's error.")
    else:
        out.append(f"- Their end points are accurate to about {_g(e['max'], 2)} {Lu} (the largest of "
                   f"{e['tracers']} tracers run again more accurately; median {_g(e['median'], 2)} {Lu}): an "
                   "estimate, not a bound.")
    return out



def _program_state(p: dict) -> list:
    """The lines of a program state's render: which state of which program, and the others."""
    me = p["state"]
    others = ", ".join(f"{q['name']} (chi_E = {q['chi_E']:g}: rms {_g(q['residual_rms'])} rad, "
                       f"{'met' if q['met'] else 'NOT met'})" for q in p["states"] if q["name"] != me)
    return [f"State **{me}** of a program: one layout of curvatures made for several field strengths; this folder "
            f"shows the flow at this state's field. The other states: {others} (their folders are next to this "
            "one; `program.md` above compares them)."]


def program_markdown(p: dict) -> str:
    """``program.md`` from a program render's record (``program.json``): the states' verdicts with
    their error bars, the limiting state, the resting cilia and the switch between states."""
    lines = [f"# {p['scene']}: a program of {len(p['states'])} field states", ""]
    lim = p.get("limiting")
    ok = all(q["met"] for q in p["states"])
    models = {q.get("model", "coupled") for q in p["states"]}
    model = f"the {models.pop()} model" if len(models) == 1 else "each state's own model (see the table)"
    lines.append(f"**Verdict: {'every state met' if ok else 'NOT every state met'}, in {model} of each state's "
                 "field** (one layout of curvatures chi_N for all states; each state's residual is measured with "
                 "the full flow model of that field, its error bar bounds what the model's tolerance can move).")
    lines.append("")
    lines += ["| state | chi_E | weight | rms residual (rad) | error bar (rad) | threshold (rad) | met | cilia at rest |",
              "|---|---:|---:|---:|---:|---:|---|---:|"]
    for q in p["states"]:
        thr = "-" if q["threshold"] is None else _g(q["threshold"])
        lines.append(f"| {q['name']} | {q['chi_E']:g} | {q['weight']:g} | {_g(q['residual_rms'])} | "
                     f"{_g(q['residual_error'], 2)} | {thr} | {'yes' if q['met'] else 'NO'} | {q['resting']} |")
    lines.append("")
    if lim is not None:
        lines.append(f"Limiting state: **{lim['state']}**, its rms residual at {lim['residual_over_threshold']:.2f} "
                     "of its threshold" + (" (above 1: not met)." if lim["residual_over_threshold"] > 1 else "."))
        lines.append("")
    sw = p.get("switch") or []
    if sw:
        lines.append("## The switch")
        lines.append("")
        lines.append("Each state's folder shows its steady beat. The flow while the cilia settle after the field is "
                     "switched is not rendered; how long they take, in beats of the new field (from each cilium's "
                     "Floquet multiplier: an upper estimate for a cilium switched between two beats, whose large "
                     "first deviation decays faster):")
        lines.append("")
        for q in sw:
            st = q.get("statement", "")
            st = st[0].upper() + st[1:] if st else st
            lines.append(f"- To **{q['to']}** (chi_E = {q['chi_E']:g}). {st}")
        lines.append("")
    lines.append("## Files")
    lines.append("")
    lines.append("One folder per state (`" + "/`, `".join(q["name"] for q in p["states"]) + "/`), each a complete "
                 "render: path lines, fields, cilia frames, preview and `open_in_paraview.py` for that field. "
                 "`program.nc` holds the layout (chi_N per cilium, which cilia rest in which state, each state's "
                 "control points and residuals); `program.json` these numbers.")
    lines.append("")
    lines.append(f"Design: {p['message']}")
    return "\n".join(lines) + "\n"
