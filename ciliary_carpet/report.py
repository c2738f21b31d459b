"""The render's summary in words (``summary.md``)."""
from __future__ import annotations


def _markdown(s: dict) -> str:
    lines = [f"# {s['scene']}", "", f"- source: `{s['source']}`", f"- cilia: {s['n_cilia']}",
             f"- flow tolerance: {s['tolerance']:g}", f"- units: {s['units']}", f"- flow sums: {s['backend']}"]
    if "design" in s:
        dd = s["design"]
        lines.append(f"- design ({dd['kind']} target, {dd['control_points']} control points): rms residual "
                     f"{dd['residual_rms']:.3g} {dd['residual_unit']} (+- {dd['residual_error']:.1g}), worst "
                     f"{dd['residual_max']:.3g}; local layout {dd['local_rms']:.3g}; returned the {dd['returned']} "
                     f"layout; {dd['cilia_near_cutoff']} of {s['n_cilia']} cilia near the flutter cutoff; "
                     f"{dd['work']['iterations']} L-BFGS-B iterations, {dd['work']['checks']} full-model checks")
        if "met" in dd:
            worst = ", ".join(f"#{w['index']} at ({w['x']:.3g}, {w['y']:.3g}): {w['residual']:.3g}" for w in dd["worst"])
            lines.append(f"- target {'met' if dd['met'] else 'NOT met: the closest flow the cilia make'} (rms "
                         f"{dd['residual_rms']:.3g} against [target] residual = {dd['residual_threshold']:g}); "
                         f"worst control points {worst}")
        if "reachability" in dd:
            lines.append(f"- reachability (estimated up front): {dd['reachability']['text']}")
        if "tolerance" in dd:
            tt = dd["tolerance"]
            lines.append(f"- fabrication tolerance (relative chi_N error sigma = {tt['sigma']:g}, {tt['samples']} "
                         f"samples): expected rms residual {tt['mean_rms']:.3g} +- {tt['sampling_error']:.1g} "
                         f"(spread {tt['std_rms']:.2g}; 10-90%: {tt['p10_rms']:.3g}..{tt['p90_rms']:.3g}); "
                         f"nominal {tt['nominal_rms']:.3g}")
    if "mean_field" in s:
        m = s["mean_field"]
        fid = ", ".join(f"{k} {v:.1%}" for k, v in m["fidelity"].items())
        lines.append(f"- mean field: {m['points']} points, fidelity {fid}, max error bound {m['max_error_bound']:.2e}")
    if "pathlines" in s:
        p = s["pathlines"]
        out = ", ".join(f"{v} {k}" for k, v in p["outcome"].items() if v)
        lines.append(f"- path lines: {p['tracers']} tracers, {p['model']} flow, over {p['duration']:.4g} "
                     f"({p['periods']:.3g} beats; {p['duration_from']}): {out}; {p['stopped_early']} stopped early")
        e = p["end_point_error"]
        lines.append(f"- path-line end-point error (estimated, {e['tracers']} tracers against {e['reference']}): "
                     f"max {e['max']:.2g}, median {e['median']:.2g}")
    if "mixing" in s:
        mx = s["mixing"]
        top = "n/a" if mx["ftle_max"] is None else f"{mx['ftle_max']:.3g}"
        lines.append(f"- mixing: number {mx['mixing_number']:.3g} (mean log-stretching over {mx['duration']:.4g}, "
                     f"{mx['model']} flow; FTLE max {top}, defined on {mx['defined_fraction']:.0%} of the grid)")
    lines += ["", "| stage | seconds |", "|---|---|"] + [f"| {k} | {v:.2f} |" for k, v in s["seconds"].items()]
    return "\n".join(lines) + "\n"
