"""Cost against error of the linear-stability computations (see benchmarks/README.md).

    python benchmarks/bench_stability.py [--quick]

1. One leading eigenvalue at (chi_E, eta, chi_N) = (200, 1, 16*2pi) at several degrees, by
   - QZ on the Galerkin pencil (J, M)                     (ours: single_cilium.stability.spectrum)
   - a standard dense eigensolver on M^-1 J               (the "invert the mass" alternative)
   - shift-invert Arnoldi (ARPACK eigs, 6 eigenvalues) at a shift 1 % off the answer (what a
     continuation step with a good predictor could use)
   error against degree 20 (QZ).
2. The flutter cutoff chi_N at (200, 1), to 1e-10 relative.
3. One Hopf boundary (chi_N = 16*2pi, chi_E in [90, 300], eta in [0.1, 2.5]).
4. The 106 x 49 map at chi_N = 16*2pi on the machine's cores.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import scipy.linalg as sla
from scipy.sparse.linalg import eigs

from single_cilium import CiliumParams, Filament, Mesh
from cilia_runtime.blas import single_threaded_blas
from single_cilium.stability import _leading, _pencil, flutter_boundary, flutter_cutoff, spectrum, stability_map


def best_time(fn, repeat=5):
    out, best = None, np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    lines = []

    def emit(s=""):
        print(s)
        lines.append(s)

    emit("# bench_stability")
    emit(f"- machine: {os.cpu_count()} cores, {platform.machine()}, Python {platform.python_version()}, "
         f"numpy {np.__version__}, scipy {scipy.__version__}; one BLAS thread for single solves")
    p = CiliumParams(200, 1, 16 * 2 * np.pi)
    with single_threaded_blas():
        ref = _leading(spectrum(p, Mesh.for_params(p, 20)))
        emit(f"- reference: degree 20, omega = {ref.real:.12f} + {ref.imag:.12f} i")
        emit("")
        emit("## 1. Leading eigenvalue: cost and error (relative to the reference)")
        emit("")
        emit("| degree | size | QZ pencil (ours) [ms] | error | eig(M^-1 J) [ms] | error | shift-invert eigs [ms] | error |")
        emit("|---:|---:|---:|---:|---:|---:|---:|---:|")
        for deg in ((6, 10) if args.quick else (4, 6, 8, 10, 12, 16)):
            mesh = Mesh.for_params(p, deg)
            # ours, end to end: mesh, assembly, discrete equilibrium, QZ
            w, t_qz = best_time(lambda: spectrum(p, Mesh.for_params(p, deg)))
            e_qz = abs(_leading(w) - ref) / abs(ref)
            J, M, _ = _pencil(Filament(p, mesh))
            w2, t_std = best_time(lambda: sla.eigvals(np.linalg.solve(M, J)))
            w2 = w2[np.lexsort((-w2.imag, -w2.real))]
            e_std = abs(_leading(w2) - ref) / abs(ref)
            shift = ref * 1.01
            Jc, Mc = J.astype(complex), M.astype(complex)
            w3, t_si = best_time(lambda: eigs(Jc, k=6, M=Mc, sigma=shift, which="LM", return_eigenvectors=False))
            e_si = np.min(np.abs(w3 - ref)) / abs(ref)
            emit(f"| {deg} | {J.shape[0]} | {t_qz * 1e3:.2f} | {e_qz:.1e} | {t_std * 1e3:.2f} | {e_std:.1e} | "
                 f"{t_si * 1e3:.2f} | {e_si:.1e} |")
        emit("")
        emit("(QZ column: end to end, including mesh, assembly and the discrete equilibrium; the other two: "
             "the eigensolver alone on the same pencil.)")
        emit("")
        emit("## 2. Flutter cutoff at (chi_E, eta) = (200, 1)")
        c, t_c = best_time(lambda: flutter_cutoff(200, 1), repeat=1 if args.quick else 3)
        emit(f"chi_N_cutoff = {c.chi_N_cutoff:.12g} (= {c.chi_N_cutoff / (2 * np.pi):.8g} * 2pi), beta = "
             f"{c.beta:.8g}, error estimate {c.error:.1e} (degree 6 vs 10), {c.n_eigensolves} eigensolves, "
             f"{t_c:.2f} s")
    emit("")
    emit("## 3. Hopf boundary, chi_N = 16*2pi, chi_E in [90, 300], eta in [0.1, 2.5]")
    t0 = time.perf_counter()
    b = flutter_boundary(16 * 2 * np.pi, chi_E=(90, 300), eta=(0.1, 2.5))
    t_b = time.perf_counter() - t0
    npts = sum(len(x) for x in b.branches)
    emit(f"{b.message}, {npts} points, {b.n_eigensolves} eigensolves, {t_b:.2f} s "
         f"({t_b / max(npts, 1) * 1e3:.0f} ms per point)")
    emit("")
    shape = (22, 10) if args.quick else (106, 49)
    emit(f"## 4. Stability map {shape[0]} x {shape[1]}, chi_N = 16*2pi, on {os.cpu_count()} processes")
    t0 = time.perf_counter()
    ds = stability_map(16 * 2 * np.pi, chi_E=np.linspace(90, 300, shape[0]), eta=np.linspace(0.1, 2.5, shape[1]))
    t_m = time.perf_counter() - t0
    counts = {name: int((ds.regime == k).sum()) for k, name in enumerate(("stable", "flutter", "divergence", "coiled"))}
    emit(f"{t_m:.1f} s for {ds.regime.size} points ({counts}); coiled points are not computed")
    out = Path(__file__).parent / "results" / ("bench_stability_quick.md" if args.quick else "bench_stability.md")
    out.parent.mkdir(exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
