"""Cost and interpolation error of a thrust table over the background flow (benchmarks/README.md).

    python benchmarks/bench_table_flow.py                     # sections build, continuation: ~15 minutes
    python benchmarks/bench_table_flow.py --quick             # the two coarser grids only
    python benchmarks/bench_table_flow.py --sections shipped  # the shipped table: ~3 minutes on 2 cores

All at chi_E = 200, eta = 1, degree 8, 64 steps per period, Floquet multipliers and error
estimates on every row, on the default process pool over the machine's cores (the machine is
shared: the load average is printed with each timing):

1. Build time against the grid: the flow grid ``U_par x U_perp`` (each ``linspace(-2, 2, m)``,
   spacing 4 / (m - 1)) and the chi_N grid (``linspace(0, 1.05 max cutoff, n)``, the cutoffs
   of all flows added).
2. Interpolation error against fresh cycles (``limit_cycle``, same discretisation) at flows off
   the grid and chi_N at fractions of that flow's cutoff (and just above it, and negative chi_N,
   served by the mirror image): the thrust vector ``|F - F_fresh|``, period (relative), thrust
   angle, shape ``x``; and the table's own estimate (``interpolation_error``): the largest ratio
   of the error to the estimate (below 1: the estimate holds).
3. Continuation in the flow: a flow's cycle at chi_N = 100 started from the neighbouring flow's
   cycle (spacing 1) against the Hopf mode.
4. (``--sections shipped``) The shipped table (``ThrustTable.default(flow=True)``: U in
   [-1.5, 1.5]^2 at spacing 0.5, chi_N spacing 10, stored by ``tablefile.compact``) against fresh
   cycles at flows off its grid (cell centres, next to grid lines, |U| = 0.8-1.2, the outer cells)
   x chi_N at fractions of that flow's cutoff (and just above it, and negative chi_N): the errors
   of the thrust (absolute and relative to |F|), its angle, the period, the shape x, the ratio of
   the thrust's error to the table's estimate (``thrust_interpolation_error``) and that estimate's
   two parts; and the same points on the full-resolution original (``--original``, where it
   exists) with the largest difference of any scalar from the shipped table's.

A run of some sections writes them to ``--out`` in place of that file's blocks of the same
sections (marked ``<!-- section: NAME -->``), new ones at the top, and keeps the rest of the file.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from single_cilium import CiliumParams
from single_cilium.cycle import CycleError, limit_cycle
from single_cilium.stability import flutter_cutoff
from single_cilium.table import ThrustTable, build_table
from single_cilium.tablefile import SAFETY, SCALARS

KW = dict(degree=8, n_phase=64)
OFF_GRID = [(-1.3, -0.4), (0.7, 1.6), (-0.2, 0.3), (1.4, -1.7), (0.3, -0.7)]  # off every grid below
FRACTIONS = [0.0, 0.25, 0.5, 0.75, 0.9, 1.04]


def load() -> str:
    return "load average " + " / ".join(f"{v:.1f}" for v in os.getloadavg())


def chi_N_grid(n: int, top: float) -> np.ndarray:
    return np.linspace(0.0, top, n)


def fresh_points():
    """(chi_N, U_par, U_perp, fresh cycle) at the off-grid flows (negative chi_N: the mirror)."""
    pts = []
    for up, uq in OFF_GRID:
        cut = flutter_cutoff(200.0, 1.0, degree=8, background=(uq, up)).chi_N_cutoff
        for f in FRACTIONS:
            cN = f * cut
            c = limit_cycle(CiliumParams(200.0, 1.0, cN, (uq, up)), **KW, error_estimate=False, floquet=False)
            pts.append((cN, up, uq, c))
    for cN, up, uq in [(-60.0, 0.7, 1.6), (-120.0, -1.3, -0.4)]:  # U_perp -> -U_perp under the mirror
        c = limit_cycle(CiliumParams(200.0, 1.0, cN, (uq, up)), **KW, error_estimate=False, floquet=False)
        pts.append((cN, up, uq, c))
    return pts


def errors(t, pts) -> dict:
    out = {"F": 0.0, "F_branch_rel": 0.0, "T": 0.0, "angle": 0.0, "x": 0.0, "ratio": 0.0, "est": 0.0,
           "flutter_mismatch": 0}
    for cN, up, uq, c in pts:
        r = t.at(cN, U_par=up, U_perp=uq)
        F = np.array([float(r.thrust_x), float(r.thrust_y)])
        e = float(np.hypot(*(F - c.thrust)))
        est = float(t.interpolation_error("thrust_norm", cN, U_par=up, U_perp=uq))
        out["F"] = max(out["F"], e)
        out["est"] = max(out["est"], est)
        if e > 1e-7:  # above the rows' Newton tolerance (at a row the estimate is 0)
            out["ratio"] = max(out["ratio"], e / est if est > 0 else np.inf)
        out["flutter_mismatch"] += int(bool(r.flutter) != c.flutter)
        if c.flutter and bool(r.flutter):
            out["F_branch_rel"] = max(out["F_branch_rel"], e / c.thrust_norm)
            out["T"] = max(out["T"], abs(float(r.period) / c.period - 1))
            out["angle"] = max(out["angle"], abs(float(r.thrust_angle) - c.thrust_angle))
            if cN > 0:  # a mirrored cycle starts at the mirror image of phase 0, not a fresh cycle's phase 0
                x = c.mesh.interpolate(c.data.x.values.T, t.ds.s.values).T
                out["x"] = max(out["x"], float(np.max(np.abs(r.x.values - x))))
    return out


def continuation() -> list[str]:
    rows = []
    for up in (-1.0, 0.0, 1.0, 2.0):
        p = CiliumParams(200.0, 1.0, 100.0, (0.0, up))
        nb = limit_cycle(CiliumParams(200.0, 1.0, 100.0, (0.0, up - 1.0)), **KW)
        t0 = time.perf_counter()
        hopf = limit_cycle(p, **KW)
        th = time.perf_counter() - t0
        t0 = time.perf_counter()
        seeded = limit_cycle(p, **KW, seed=nb)
        ts = time.perf_counter() - t0
        rows.append(f"| {up:g} | {hopf.work['newton']} | {th:.2f} | {seeded.work['newton']} | {ts:.2f} | "
                    f"{abs(seeded.period / hopf.period - 1):.1e} |")
    return rows


# ---------------------------------------------------------------------------------- 4. the shipped table
ORIGINAL = "/work/flowtable/flow200_7.nc"  # the full-resolution build the shipped file was compacted from
#: off the shipped grid (spacing 0.5): (U_par, U_perp, what it probes)
SHIPPED_FLOWS = [
    (0.25, 0.25, "cell centre"),
    (0.75, -0.25, "cell centre"),
    (-0.75, 0.75, "cell centre"),
    (-1.25, -1.25, "centre of a corner cell"),
    (1.25, -0.75, "centre of an outer cell"),
    (0.52, -0.03, "next to both grid lines"),
    (-0.98, 0.27, "next to U_par = -1"),
    (0.03, 0.98, "next to both grid lines"),
    (0.6, 0.6, "abs(U) = 0.85"),
    (0.85, 0.35, "abs(U) = 0.92"),
    (-0.35, -0.85, "abs(U) = 0.92"),
    (-0.65, -0.65, "abs(U) = 0.92"),
    (0.1, -1.1, "abs(U) = 1.10"),
    (1.1, 0.45, "abs(U) = 1.19"),
    (-1.4, 1.4, "next to the edge"),
    (1.4, -1.35, "next to the edge"),
]
SHIPPED_FRACTIONS = [0.0, 0.25, 0.5, 0.75, 0.9, 0.99, 1.04]
#: negative chi_N (served by the mirror image U_perp -> -U_perp): (fraction of the cutoff, U_par, U_perp)
SHIPPED_NEGATIVE = [(0.5, 0.25, 0.25), (0.9, 0.85, 0.35), (0.75, -0.35, -0.85), (0.99, -0.75, 0.75),
                    (0.25, 0.52, -0.03), (0.5, 1.25, -0.75), (0.9, 0.6, 0.6), (0.99, -1.4, 1.4)]
SMALL_F = 0.1  #: |F| below this: the relative error is not reported (the thrust nearly cancels)
CARPET_U = 0.9  #: the flows a carpet sustains: |U| below this


def est_parts(t: ThrustTable, cN: float, up: float, uq: float) -> dict:
    """The thrust's estimate (FlowGrid.interpolation_error) taken apart: ``U`` = SAFETY x the
    change from the quadratic to the cubic interpolant in U over the cell, ``chi_N`` the grid
    flows' own chi_N part (each the norm of its thrust_x, thrust_y parts); and two variants of the
    estimate: ``factor1`` with 1 in place of SAFETY, ``point`` with the change at the point alone
    in place of the largest over its cell."""
    fg = t._flow
    a, up_, uq_, _, _ = fg._points(cN, up, uq)
    names = ["thrust_x", "thrust_y"]
    full, on, used = fg._evaluate(names, a, up_, uq_)
    low = fg._evaluate(names, a, up_, uq_, lower=True)[0]
    ch = fg._U_change(names, a, up_, uq_, on)
    ec = []
    for n in names:
        e = 0.0
        for w, x, tt in used:
            if w[0] != 0:
                e += abs(float(w[0])) * float(tt.interpolation_error(n, (x if on[0] else a)[:1])[0])
        ec.append(e)
    cell = [float(ch[n][0]) for n in names]
    point = [abs(float(full[n][0] - low[n][0])) for n in names]
    return {"U": SAFETY * float(np.hypot(*cell)), "chi_N": float(np.hypot(*ec)),
            "factor1": float(np.hypot(cell[0] + ec[0], cell[1] + ec[1])),
            "point": float(np.hypot(SAFETY * point[0] + ec[0], SAFETY * point[1] + ec[1]))}


def shipped_points() -> list[dict]:
    """Fresh cycles at the shipped section's points."""
    cut = {}

    def cutoff(up, uq):
        if (up, uq) not in cut:
            cut[(up, uq)] = flutter_cutoff(200.0, 1.0, degree=8, background=(uq, up)).chi_N_cutoff
        return cut[(up, uq)]

    todo = [(f, up, uq, what) for up, uq, what in SHIPPED_FLOWS for f in SHIPPED_FRACTIONS]
    todo += [(-f, up, uq, "negative chi_N") for f, up, uq in SHIPPED_NEGATIVE]
    pts = []
    for f, up, uq, what in todo:
        c_ = cutoff(up, -uq if f < 0 else uq)  # chi_N < 0: the mirror image's cutoff
        cN = f * c_
        p = CiliumParams(200.0, 1.0, cN, (uq, up))
        try:
            c = limit_cycle(p, **KW, error_estimate=False, floquet=False)
        except CycleError:  # next to the cutoff of a strong flow the Hopf mode can be too far: the last fraction's
            c = limit_cycle(p, **KW, error_estimate=False, floquet=False, seed=pts[-1]["fresh"])
        pts.append(dict(frac=f, cN=cN, up=up, uq=uq, what=what, cut=c_, fresh=c))
    return pts


def shipped_errors(t: ThrustTable, p: dict, parts: bool = True) -> dict:
    c, cN, up, uq = p["fresh"], p["cN"], p["up"], p["uq"]
    r = t.at(cN, U_par=up, U_perp=uq)
    F = np.array([float(r.thrust_x), float(r.thrust_y)])
    e = float(np.hypot(*(F - c.thrust)))
    est = float(r.thrust_interpolation_error)
    out = dict(row=r, F=e, Fn=c.thrust_norm, rel=e / c.thrust_norm if c.thrust_norm >= SMALL_F else np.nan,
               est=est, ratio=e / est if est > 0 else np.inf, flutter_ok=bool(r.flutter) == c.flutter,
               T=np.nan, angle=np.nan, x=np.nan)
    if c.flutter and bool(r.flutter):
        out["T"] = abs(float(r.period) / c.period - 1)
        out["angle"] = abs((float(r.thrust_angle) - c.thrust_angle + np.pi) % (2 * np.pi) - np.pi)
        if cN >= 0:  # a mirrored cycle starts at the mirror image of phase 0, not a fresh cycle's phase 0
            step = c.data.sizes["phase"] // r.sizes["phase"]
            assert np.allclose(c.data.phase.values[::step], r.phase.values)
            x = c.mesh.interpolate(c.data.x.values.T, t.ds.s.values).T[::step]
            out["x"] = float(np.max(np.abs(r.x.values - x)))
    elif not c.flutter and not bool(r.flutter):
        out["angle"] = abs((float(r.thrust_angle) - c.thrust_angle + np.pi) % (2 * np.pi) - np.pi)
    if parts:
        d = est_parts(t, cN, up, uq)
        out["eU"], out["eC"] = d["U"], d["chi_N"]
        out["ratio1"] = e / d["factor1"] if d["factor1"] > 0 else np.inf
        out["ratio_pt"] = e / d["point"] if d["point"] > 0 else np.inf
    return out


def _mx(v) -> float:
    v = np.asarray([x for x in v if np.isfinite(x)], dtype=float)
    return float(v.max()) if v.size else np.nan


def shipped(say, original: str) -> None:
    t0 = time.perf_counter()
    t = ThrustTable.default(flow=True)
    ds = t.ds
    say(f"shipped table loaded in {time.perf_counter() - t0:.1f} s: U_par x U_perp = {ds.sizes['U_par']} x "
        f"{ds.sizes['U_perp']} over {t.U_range}, chi_N {ds.sizes['chi_N']} rows (0-190 at spacing 10 and every "
        f"flow's cutoff), {ds.sizes['phase']} phase samples, s {ds.sizes['s']}; storage: {ds.attrs.get('storage')}\n")
    t0 = time.perf_counter()
    pts = shipped_points()
    say(f"fresh cycles (limit_cycle degree 8, 64 steps, no Floquet, no error estimate; the cutoff by flutter_cutoff, "
        f"degree 8) at {len(pts)} points: {time.perf_counter() - t0:.0f} s ({load()})\n")
    t0 = time.perf_counter()
    errs = [shipped_errors(t, p) for p in pts]
    say(f"table lookups (at(), with its estimate) and the estimate's parts: {time.perf_counter() - t0:.0f} s\n")
    orig = None
    if original and Path(original).exists():
        t0 = time.perf_counter()
        o = ThrustTable.load(original)
        orig = [shipped_errors(o, p, parts=False) for p in pts]
        say(f"full-resolution original {original} ({o.ds.sizes['phase']} phase samples, {o.ds.x.dtype} fields): "
            f"loaded and read at the same points in {time.perf_counter() - t0:.0f} s\n")

    say("Errors against fresh cycles of the same discretisation. 'err F' = |F - F_fresh| (absolute; F the mean thrust "
        f"vector, |F| {min(p['fresh'].thrust_norm for p in pts):.2f}-{max(p['fresh'].thrust_norm for p in pts):.1f} "
        f"here), 'err F / |F|' where |F_fresh| >= {SMALL_F} (the thrust of a flow nearly cancels "
        "elsewhere), 'T' the period (relative), 'angle' the thrust angle [rad], 'x' the shape (max over the stored "
        "phase samples and s; chi_N >= 0 only: a mirrored cycle starts at the mirror image of phase 0), 'est.' the "
        "table's thrust_interpolation_error at the point, 'err / est.' their ratio (below 1: the estimate holds), "
        f"'est. U' and 'est. chi_N' its two parts (SAFETY = {SAFETY:g} x the largest change from the quadratic to the "
        "cubic interpolant in U over the cell; the grid flows' own chi_N estimate). Fractions: chi_N / the flow's "
        f"cutoff in {SHIPPED_FRACTIONS} (1.04: above the cutoff, the steady force) and {len(SHIPPED_NEGATIVE)} "
        "negative chi_N.\n")

    def summary(sel, E):
        ee = [E[i] for i in sel]
        return (f"{_mx(e['F'] for e in ee):.1e} | {_mx(e['rel'] for e in ee):.1e} | "
                f"{_mx(e['T'] for e in ee):.1e} | {_mx(e['angle'] for e in ee):.1e} | {_mx(e['x'] for e in ee):.1e} | "
                f"{min(e['est'] for e in ee):.1e}-{max(e['est'] for e in ee):.1e} | "
                f"{_mx(e['ratio'] for e in ee):.2f} |")

    on = [i for i, p in enumerate(pts) if abs(p["frac"]) <= 1]
    slow = [i for i in on if np.hypot(pts[i]["up"], pts[i]["uq"]) < CARPET_U]
    off = [i for i, p in enumerate(pts) if abs(p["frac"]) > 1]
    say("### Summary (max per column)\n")
    say("| table | points | err F | err F / abs(F) | err T (rel) | err angle [rad] | err x | est. (range) | "
        "err / est. |")
    say("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, E in (("shipped", errs),) + ((("original", orig),) if orig else ()):
        say(f"| {name} | flutter branch, all flows ({len(on)}) | " + summary(on, E))
        say(f"| {name} | flutter branch, abs(U) < {CARPET_U} ({len(slow)}) | " + summary(slow, E))
        say(f"| {name} | above the cutoff ({len(off)}) | " + summary(off, E))
    say("\n### The estimate's margin (shipped table): the largest err / est. of the estimate as it is and of two "
        "variants\n")
    say("| points | err / est. (SAFETY 2, over the cell) | with SAFETY 1 | SAFETY 2, the change at the point alone | "
        "est. / err, median |")
    say("|---|---:|---:|---:|---:|")
    subsets = [(f"flutter branch, all flows ({len(on)})", on),
               (f"flutter branch, abs(U) < {CARPET_U} ({len(slow)})", slow),
               (f"above the cutoff ({len(off)})", off)]
    for name, sel in subsets:
        ee = [errs[i] for i in sel]
        say(f"| {name} | {_mx(e['ratio'] for e in ee):.2f} | {_mx(e['ratio1'] for e in ee):.2f} | "
            f"{_mx(e['ratio_pt'] for e in ee):.2f} | {float(np.median([e['est'] / e['F'] for e in ee])):.0f} |")
    bad = [i for i, e in enumerate(errs) if not e["flutter_ok"]]
    if bad:
        say("\nflutter flag differs from the fresh cycle's at " + ", ".join(
            f"(chi_N {pts[i]['cN']:.1f}, U_par {pts[i]['up']:g}, U_perp {pts[i]['uq']:g})" for i in bad))
    if orig:
        dif = 0.0
        for e, g in zip(errs, orig):
            for k in SCALARS + ("thrust_interpolation_error",):
                a, b = float(e["row"][k]), float(g["row"][k])
                if not (np.isnan(a) and np.isnan(b)):
                    dif = max(dif, abs(a - b))
        dx = 0.0
        for e, g in zip(errs, orig):
            if e["row"].flutter:
                xo = g["row"].x.values[::g["row"].sizes["phase"] // e["row"].sizes["phase"]]
                dx = max(dx, float(np.max(np.abs(e["row"].x.values - xo))))
        xs, xo = t.ds.x.values, o.ds.x.values[..., ::o.ds.sizes["phase"] // t.ds.sizes["phase"], :]
        ok = np.isfinite(xo)
        say(f"\nshipped against the original at the same points: largest difference of any scalar (and of the "
            f"estimate) {dif:.1e}; of the shape x at the shared phase samples {dx:.1e} (the stored rounding at the "
            f"rows: {float(np.max(np.abs(xs[ok] - xo[ok]))):.1e}, amplified by the interpolation's weights).")
    say("\n### Per flow (max over its chi_N >= 0; negative chi_N in the per-point table)\n")
    say("| U_par | U_perp | abs(U) | probes | cutoff: table - fresh | err F | err F / abs(F) | err T | err angle | "
        "err x | est. | err / est. | est. U | est. chi_N |")
    say("|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for up, uq, what in SHIPPED_FLOWS:
        sel = [i for i, p in enumerate(pts) if (p["up"], p["uq"]) == (up, uq) and p["frac"] >= 0]
        ee = [errs[i] for i in sel]
        dc = t.cutoff(U_par=up, U_perp=uq) - pts[sel[0]]["cut"]
        say(f"| {up:g} | {uq:g} | {np.hypot(up, uq):.2f} | {what} | {dc:.1e} | {_mx(e['F'] for e in ee):.1e} | "
            f"{_mx(e['rel'] for e in ee):.1e} | {_mx(e['T'] for e in ee):.1e} | {_mx(e['angle'] for e in ee):.1e} | "
            f"{_mx(e['x'] for e in ee):.1e} | {_mx(e['est'] for e in ee):.1e} | {_mx(e['ratio'] for e in ee):.2f} | "
            f"{_mx(e['eU'] for e in ee):.1e} | {_mx(e['eC'] for e in ee):.1e} |")
    say("\n### Per point\n")
    say("| chi_N / cutoff | chi_N | U_par | U_perp | abs(F) | err F | err F / abs(F) | err T | err angle | err x | "
        "est. | err / est. | est. U | est. chi_N |")
    say("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for p, e in zip(pts, errs):
        say(f"| {p['frac']:g} | {p['cN']:.2f} | {p['up']:g} | {p['uq']:g} | {e['Fn']:.3f} | {e['F']:.1e} | "
            f"{e['rel']:.1e} | {e['T']:.1e} | {e['angle']:.1e} | {e['x']:.1e} | {e['est']:.1e} | {e['ratio']:.2f} | "
            f"{e['eU']:.1e} | {e['eC']:.1e} |" + ("" if e["flutter_ok"] else " flutter flag differs"))


SECTIONS = ("build", "continuation", "shipped")


def write(out: Path, blocks: dict[str, list[str]], title: str) -> None:
    """The run's blocks in place of the file's blocks of the same names (marked
    ``<!-- section: NAME -->`` ... ``<!-- end: NAME -->``), new ones at the top (after the title
    line); the rest of the file kept."""
    old = out.read_text().splitlines() if out.exists() else [title]
    for name, lines in blocks.items():
        b, e = f"<!-- section: {name} -->", f"<!-- end: {name} -->"
        new = [b, ""] + lines + ["", e]
        if b in old and e in old:
            i, j = old.index(b), old.index(e)
            old = old[:i] + new + old[j + 1:]
        else:
            k = 1 if old and old[0].startswith("# ") else 0
            old = old[:k] + [""] + new + old[k:]
    out.write_text("\n".join(old).rstrip("\n") + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the coarse grids only")
    ap.add_argument("--sections", default="build,continuation",
                    help=f"comma-separated, of {', '.join(SECTIONS)} (default build,continuation: sections 1-3)")
    ap.add_argument("--original", default=ORIGINAL, help="the full-resolution table the shipped one was compacted "
                    "from (section shipped; skipped where it does not exist)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "bench_table_flow.md"))
    args = ap.parse_args()
    sections = [x.strip() for x in args.sections.split(",") if x.strip()]
    if not sections or any(x not in SECTIONS for x in sections):
        ap.error(f"--sections: comma-separated names of {', '.join(SECTIONS)}, got {args.sections!r}")
    lines: list[str] = []
    blocks: dict[str, list[str]] = {}

    def say(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "single_cilium", "benchmarks/bench_table_flow.py"],
                           capture_output=True, text=True).stdout.strip()
    cpu = platform.processor() or platform.machine()
    title = "# Thrust table over the background flow"
    print(title + "\n")

    def preamble(what: str) -> None:
        say(f"- python {sys.version.split()[0]}, numpy {np.__version__}; code git {rev}"
            f"{' (with uncommitted changes in single_cilium or this script)' if dirty else ' (clean)'}; "
            f"{os.cpu_count()} cores ({cpu}), shared with other work; {load()} at start")
        say(f"- chi_E = 200, eta = 1; degree 8, 64 steps per period; {what}\n")

    limit_cycle(CiliumParams(200, 1, 50.0), **KW)  # warm-up (numba caches)
    if "shipped" in sections:
        t0 = time.perf_counter()
        say("## 4. The shipped table against fresh cycles\n")
        preamble("the shipped table: ThrustTable.default(flow=True)")
        shipped(say, args.original)
        say(f"\n(section: {time.perf_counter() - t0:.0f} s; {load()} at the end)")
        blocks["shipped"], lines[:] = list(lines), []
    if "build" in sections or "continuation" in sections:
        say("## 1-3. Tables over the flow grids: build time, interpolation error, continuation\n")
        preamble("Floquet multipliers and error estimates on every row; default process pool")
        if "build" in sections:
            build(say, args.quick)
        if "continuation" in sections:
            _continuation(say)
        blocks["build"] = list(lines)
    write(Path(args.out), blocks, title)


def build(say, quick: bool) -> None:
    cuts = [flutter_cutoff(200.0, 1.0, degree=8, background=(uq, up)).chi_N_cutoff
            for up in (-2.0, 2.0) for uq in (-2.0, 2.0)]
    top = min(1.05 * max(cuts), 0.95 * 200.0)  # short of the coiled limit, where the steady state turns steep
    cases = [(3, 20), (5, 20)] if quick else [(3, 20), (5, 20), (5, 39), (9, 20)]
    t0 = time.perf_counter()
    pts = fresh_points()
    say(f"fresh cycles at {len(pts)} points: {time.perf_counter() - t0:.1f} s ({load()})\n")
    say("### 1-2. Build time and interpolation error against fresh cycles\n")
    say(f"chi_N grid linspace(0, {top:.1f}, n) (1.05 x the largest cutoff over the corners of [-2, 2]^2, at most "
        "0.95 chi_E) plus each "
        "flow's cutoff; flows linspace(-2, 2, m) in each component. Errors: max over the points "
        f"({len(OFF_GRID)} off-grid flows x chi_N / cutoff in {FRACTIONS}, and 2 negative chi_N); F absolute "
        "(|Fbar| is 0.2-3.5 here), the rest on the flutter branch; 'est.' the largest estimate, 'err / est.' the "
        "largest ratio of the error to the table's estimate at the same point; x: the shape at chi_N > 0 (a mirrored "
        "cycle starts at the mirror image of phase 0).\n")
    say("| flows m x m (spacing) | chi_N n (spacing) | rows computed | wall [s] | load | err F | err F / abs(F) | "
        "err T (rel) | err angle [rad] | err x | est. | err / est. |")
    say("|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for m, n in cases:
        U = np.linspace(-2.0, 2.0, m)
        grid = chi_N_grid(n, top)
        t0 = time.perf_counter()
        t = build_table(200.0, 1.0, grid, U_par=U, U_perp=U)
        wall = time.perf_counter() - t0
        rows = int((t.ds.regime.values != 5).sum())
        e = errors(t, pts)
        say(f"| {m} x {m} ({4 / (m - 1):g}) | {n} ({top / (n - 1):.1f}) | {rows} | {wall:.0f} | {load()[13:]} | "
            f"{e['F']:.1e} | {e['F_branch_rel']:.1e} | {e['T']:.1e} | {e['angle']:.1e} | {e['x']:.1e} | "
            f"{e['est']:.1e} | {e['ratio']:.2f} |" + (f" flutter flag differs at {e['flutter_mismatch']} points"
                                                       if e["flutter_mismatch"] else ""))


def _continuation(say) -> None:
    say("\n### 3. Continuation in the flow (chi_N = 100, U_perp = 0; seed: the cycle at U_par - 1)\n")
    say("| U_par | Newton steps from the Hopf mode | wall [s] | seeded from U_par - 1 | wall [s] | period change |")
    say("|---:|---:|---:|---:|---:|---:|")
    for r in continuation():
        say(r)
    say(f"\n({load()})")


if __name__ == "__main__":
    main()
