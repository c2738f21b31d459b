"""Throughput of the velocity sums on an NVIDIA GPU (ciliary_carpet.stokes.cuda.Cuda) beside the CPU.

    python benchmarks/bench_gpu.py [--sizes 2e4 1e5 4e5] [--cpu-targets 20000] [--tune] [--out FILE]

For M = N random points in the unit cube (z + 0.01 with the wall, the wall at z = 0) and standard
normal forces, the dense sum u_i = 1/(8 pi mu) sum_j G(x_i, xi_j) f_j in free space (Stokeslet)
and with the wall (Blake), on the GPU in fp64, fp32 and fp32-acc64:

- kernel pairs/s: M N / (best time of the kernel alone, inputs already on the GPU, after a
  warm-up that compiles it);
- end-to-end pairs/s: M N / (best time of ``Cuda.dense``: copies to and from the GPU included);
- error: max_i |u_i - u_i^ref| / max_i |u_i^ref|, the reference being the fp64 GPU result for
  the fp32 rows, and Direct on the first ``--cpu-targets`` targets for the fp64 rows;
- CPU: Direct (numba, all cores) on the first ``--cpu-targets`` targets and all N sources, in the
  same run (its pairs/s does not depend on M); the ratio is GPU kernel pairs/s over it.

``--tune`` first times the dense free-space fp64 and fp32 kernels at the smallest size for blocks
of 64 / 128 / 256 threads and 1 / 2 / 4 targets per thread, and uses the fastest shape.

Exits with status 2 and a message naming what is missing when no GPU is usable, and under numba's
CUDA simulator (its timings mean nothing). Writes ``results/bench_gpu.md`` (device, driver, table).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np

from ciliary_carpet.stokes import cuda as cc
from ciliary_carpet.stokes import Blake, Direct, Stokeslet, Wall
from ciliary_carpet.stokes.kernel import INV_8PI

sys.path.insert(0, str(Path(__file__).parent))
from bench_flow import best_time as best  # noqa: E402 -- one timing helper for every benchmark

RESULTS = Path(__file__).parent / "results"


def device_lines(cuda) -> list[str]:
    dev = cuda.get_current_device()
    name = dev.name.decode() if isinstance(dev.name, bytes) else str(dev.name)
    lines = [f"- device: {name}, compute capability {dev.compute_capability}"]
    try:
        from numba.cuda.cudadrv.driver import driver

        v = driver.get_version()
        lines.append(f"- CUDA driver API version {v[0]}.{v[1]}; CUDA runtime {cuda.runtime.get_version()}")
    except Exception as exc:  # noqa: BLE001 -- only for the header
        lines.append(f"- CUDA driver version: unknown ({exc})")
    impl = getattr(cuda, "implementation", "?")
    lines.append(f"- numba {numba.__version__}, numba.cuda implementation: {impl}")
    return lines


def kernel_time(cuda, backend: cc.Cuda, kernel, T, S, F, repeat=3) -> float:
    """Best time of the dense kernel alone (inputs on the GPU)."""
    dt = np.float64 if backend.precision == "fp64" else np.float32
    o = cc._origin(kernel, T, S)
    dT, dS, dF = (cuda.to_device(cc._soa(a, dt, oo)) for a, oo in ((T, o), (S, o), (F, None)))
    out = cuda.device_array((3, T.shape[0]))
    k = cc._dense_kernel(kernel.code, backend.precision, backend.threads, backend.targets_per_thread)
    blocks = -(-T.shape[0] // (backend.threads * backend.targets_per_thread))

    def run():
        k[blocks, backend.threads](dT, dS, dF, dt(kernel.eps ** 2), INV_8PI, out)
        cuda.synchronize()

    run()  # compile
    return best(run, repeat)[1]


def case(n, wall, seed=0):
    rng = np.random.default_rng(seed)
    T, S = rng.random((n, 3)), rng.random((n, 3))
    if wall:
        T[:, 2] += 0.01
        S[:, 2] += 0.01
    return T, S, rng.standard_normal((n, 3))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[2e4, 1e5, 4e5])
    ap.add_argument("--cpu-targets", type=int, default=20000, help="targets of the CPU Direct timing")
    ap.add_argument("--tune", action="store_true", help="pick the block shape first (module docstring)")
    ap.add_argument("--out", default=str(RESULTS / "bench_gpu.md"))
    a = ap.parse_args(argv)
    from numba.core import config

    if config.ENABLE_CUDASIM:
        print("bench_gpu: NUMBA_ENABLE_CUDASIM=1 selects numba's CUDA simulator, whose timings mean nothing; "
              "unset it and run on a machine with an NVIDIA GPU", file=sys.stderr)
        return 2
    if not cc.cuda_available():
        print(f"bench_gpu: no GPU to measure: {cc.cuda_status()}", file=sys.stderr)
        return 2
    cuda = cc.cuda
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    head = ["# bench_gpu: dense Stokeslet sums on the GPU beside numba Direct on the CPU", "",
            *device_lines(cuda),
            f"- host: {os.cpu_count()} cores ({platform.processor() or platform.machine()}), numba CPU threads "
            f"{numba.get_num_threads()}, load average at start {load}",
            "- M = N random points in the unit cube, standard normal forces; time = best of 3 after a warm-up", ""]
    shape = {"threads": 128, "targets_per_thread": 2}
    lines = []
    if a.tune:
        n = int(min(a.sizes))
        T, S, F = case(n, False)
        lines += [f"## block shape (free space, N = M = {n:.3g})", "", "| threads | targets/thread | fp64 pairs/s | "
                  "fp32 pairs/s |", "|---|---|---|---|"]
        rates = {}
        for th in (64, 128, 256):
            for p in (1, 2, 4):
                r = [n * n / kernel_time(cuda, cc.Cuda(pr, th, p), Stokeslet(), T, S, F) for pr in ("fp64", "fp32")]
                rates[(th, p)] = r
                lines.append(f"| {th} | {p} | {r[0]:.3g} | {r[1]:.3g} |")
                print(lines[-1], flush=True)
        th, p = max(rates, key=lambda k: rates[k][0])
        shape = {"threads": th, "targets_per_thread": p}
        lines += ["", f"fastest fp64 shape used below: {th} threads, {p} targets per thread", ""]
    lines += [f"## dense sums ({shape['threads']} threads per block, {shape['targets_per_thread']} targets per thread)",
              "", "| kernel | N = M | precision | kernel pairs/s | end-to-end pairs/s | error | CPU Direct pairs/s | "
              "GPU / CPU |", "|---|---|---|---|---|---|---|---|"]
    for n in (int(x) for x in a.sizes):
        for wall in (False, True):
            kernel = Blake(Wall(0.0)) if wall else Stokeslet()
            T, S, F = case(n, wall)
            m_cpu = min(n, a.cpu_targets)
            Direct().dense(kernel, T[:min(m_cpu, 100)], S[:100], F[:100], 1.0)  # compile
            ref_cpu, t_cpu = best(lambda: Direct().dense(kernel, T[:m_cpu], S, F, 1.0), 2)
            cpu_rate = m_cpu * n / t_cpu
            u64 = None
            for prec in cc.PRECISIONS:
                b = cc.Cuda(prec, **shape)
                tk = kernel_time(cuda, b, kernel, T, S, F)
                u, te = best(lambda: b.dense(kernel, T, S, F, 1.0))
                if prec == "fp64":
                    u64 = u
                    err = np.max(np.abs(u[:m_cpu] - ref_cpu)) / np.max(np.abs(ref_cpu))
                else:
                    err = np.max(np.abs(u - u64)) / np.max(np.abs(u64))
                row = (f"| {'wall' if wall else 'free'} | {n:.3g} | {prec} | {n * n / tk:.3g} | {n * n / te:.3g} | "
                       f"{err:.1e} | {cpu_rate:.3g} | {n * n / tk / cpu_rate:.3g} |")
                lines.append(row)
                print(row, flush=True)
    lines += ["", "error: fp64 rows against Direct (first CPU targets), fp32 rows against the fp64 GPU result; "
              f"CPU Direct timed on the first {a.cpu_targets} targets and all sources in the same run."]
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text("\n".join(head + lines) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
