"""The CUDA backend (ciliary_carpet.stokes.cuda): its kernels under numba's CUDA simulator against the
CPU kernels (dense and ranged, every kernel, fp64 to 1e-12, fp32 within its stated bound), and the
clear error where no GPU is usable.

numba's simulator must be chosen before ``numba.cuda`` is first imported, and under it numba
reports a GPU, which would send every :class:`Auto` sum of the other tests to the (slow)
simulator. So :func:`test_simulator_suite` runs this file again in a child process with
``NUMBA_ENABLE_CUDASIM=1``, where the simulator tests below are defined (about 15 s); in the main
process only the no-GPU behaviour is tested.
"""
import os
import subprocess
import sys

import numpy as np
import pytest

from ciliary_carpet.stokes import cuda as cc
from ciliary_carpet.stokes import (
    Auto,
    Blake,
    Cuda,
    CudaUnavailableError,
    Direct,
    RegularisedBlake,
    RegularisedStokeslet,
    Stokeslet,
    Wall,
    backend_named,
    stokeslet_velocity,
    stokeslet_velocity_ranges,
)

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
KERNELS = [Stokeslet(), Blake(Wall(-0.2)), RegularisedStokeslet(0.05), RegularisedBlake(0.05, Wall(-0.2))]
KIDS = ["free", "wall", "regularised", "regularised-wall"]


def case(m, n, seed=0, offset=0.0):
    """Random targets and sources in [-1, 1]^2 x [0, 1.5] (+ offset in x, y), a target on a source
    and one on the wall z = -0.2."""
    rng = np.random.default_rng(seed)
    T = rng.uniform(-1, 1, (m, 3))
    S = rng.uniform(-1, 1, (n, 3))
    T[:, 2] = rng.uniform(-0.2, 1.5, m)
    S[:, 2] = rng.uniform(0.0, 1.5, n)
    T[:, :2] += offset
    S[:, :2] += offset
    T[3] = S[5]
    T[4, 2] = -0.2
    return T, S, rng.standard_normal((n, 3))


def csr(m, n, seed=0):
    """A random list of source ranges per target: some targets with none, empty and repeated
    ranges."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 4, m)
    counts[0] = 0
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    lo = rng.integers(0, n, ptr[-1])
    hi = np.minimum(n, lo + rng.integers(0, 40, ptr[-1]))
    ranges = np.column_stack([lo, hi]).astype(np.int64)
    ranges[1] = ranges[0]
    return ptr, ranges


def terms(ptr, ranges):
    """The number of sources each target sums."""
    per = ranges[:, 1] - ranges[:, 0]
    return np.array([per[ptr[i]:ptr[i + 1]].sum() for i in range(len(ptr) - 1)])


# ------------------------------------------------------------------------ without a GPU
@pytest.fixture
def fresh_probe():
    cc._probe.cache_clear()
    yield
    cc._probe.cache_clear()


@pytest.mark.skipif(SIM or cc.cuda_available(), reason="a GPU (or the simulator) is usable here")
def test_no_gpu_is_a_clear_error_before_any_work(tmp_path, capsys):
    from ciliary_carpet.cli import main

    msg = "backend 'cuda' cannot run here: .*(NVIDIA driver|no GPU|NVVM).*pip install 'cilia-flow\\[gpu\\]'"
    with pytest.raises(CudaUnavailableError, match=msg):
        Cuda()
    with pytest.raises(CudaUnavailableError, match=msg):
        backend_named("cuda-fp32")
    assert isinstance(Auto().choose(10, 10), Direct)  # nothing else changes
    assert Auto().describe().startswith("auto: direct")
    out = tmp_path / "out"
    scene = os.path.join(os.path.dirname(__file__), "..", "designs", "shear_layer.toml")
    assert main(["--backend", "cuda", "render", scene, "-o", str(out)]) == 2
    assert "backend 'cuda' cannot run here" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.skipif(SIM, reason="the simulator is the CUDA target in this process")
def test_missing_numba_cuda_names_the_package(monkeypatch, fresh_probe):
    import numba

    monkeypatch.delattr(numba, "cuda", raising=False)
    monkeypatch.setitem(sys.modules, "numba.cuda", None)  # as if numba had no CUDA target
    with pytest.raises(CudaUnavailableError, match="install numba-cuda with pip install 'cilia-flow\\[gpu\\]'"):
        Cuda()
    assert not cc.cuda_available()


def test_scene_backend_key(tmp_path):
    from ciliary_carpet.scenes.scene import SceneError, load_scene

    p = tmp_path / "s.toml"
    p.write_text('backend = "cuda-fp32"\n')
    assert load_scene(p).backend == "cuda-fp32"  # checked when a render starts, not when read
    p.write_text('backend = "gpu"\n')
    with pytest.raises(SceneError, match="backend.*'cuda'"):
        load_scene(p)


def test_parameters_are_validated():
    with pytest.raises(ValueError, match="precision must be one of fp64, fp32, fp32-acc64"):
        Cuda("fp16")
    with pytest.raises(ValueError, match="threads must be a multiple of 32"):
        Cuda(threads=48)
    with pytest.raises(ValueError, match="targets_per_thread"):
        Cuda(targets_per_thread=0)
    with pytest.raises(ValueError, match="unknown backend 'gpu'"):
        backend_named("gpu")


def _ptx_compiler():
    """numba-cuda's ``compile_ptx`` when it and NVVM are installed (``pip install cilia-flow[gpu]``),
    else None; no GPU is needed to compile."""
    if SIM:
        return None
    try:
        import numba_cuda  # noqa: F401 -- the NVIDIA package, not numba's built-in target
        from numba.cuda.cudadrv import nvvm
        from numba import cuda
    except ImportError:
        return None
    return cuda if nvvm.is_available() else None


@pytest.mark.skipif(_ptx_compiler() is None, reason="needs numba-cuda and NVVM: pip install cilia-flow[gpu]")
@pytest.mark.parametrize("precision", ["fp64", "fp32", "fp32-acc64"])
def test_kernels_compile_for_the_gpu(precision, monkeypatch):
    """Every kernel compiles to sm_90 (H100) PTX without a GPU; the pairs stay in registers (no
    local memory), use one hardware reciprocal square root per distance, and in fp32 no fp64
    arithmetic but the final scaling (and the fp64 sums of fp32-acc64)."""
    import re

    import numba.cuda.dispatcher as disp
    from numba import types as nt

    cuda = _ptx_compiler()

    class Sm90:
        compute_capability = (9, 0)

    monkeypatch.setattr(disp, "get_current_device", lambda: Sm90())  # device functions: sm_90
    monkeypatch.setattr(cc, "cuda", cuda)
    monkeypatch.setattr(cc, "_require", lambda: cuda)
    ft = nt.float64 if precision == "fp64" else nt.float32
    a2, o2 = nt.Array(ft, 2, "C"), nt.Array(nt.float64, 2, "C")
    for code in (0, 1, 2):
        d = cc._dense_kernel.__wrapped__(code, precision, 128, 2)
        r = cc._ranged_kernel.__wrapped__(code, precision, 128)
        for fn, sig, n_out in ((d, (a2, a2, a2, ft, nt.float64, o2), 6),
                               (r, (a2, a2, a2, nt.Array(nt.int64, 1, "C"), nt.Array(nt.int64, 2, "C"), ft,
                                    nt.float64, o2), 3)):
            ptx, _ = cuda.compile_ptx(fn.py_func, sig, cc=(9, 0), fastmath=precision != "fp64")
            assert ".local" not in ptx
            ops = re.findall(r"^\s+((?:add|sub|mul|fma|div|rcp|sqrt|rsqrt)\S*)", ptx, re.M)
            assert not [o for o in ops if o.startswith(("div", "rcp", "sqrt"))]
            assert any(o.startswith("rsqrt.approx") for o in ops)
            f64 = [o for o in ops if o.endswith(".f64") and not o.startswith("rsqrt")]
            if precision == "fp32":
                assert len(f64) <= n_out, f64  # out = scale * u only
            elif precision == "fp64":
                assert not [o for o in ops if o.endswith(".f32")]


@pytest.mark.slow
def test_simulator_suite():
    """The simulator tests of this file, in a child process (module docstring; about 25 s: in the
    slow set, which CI runs)."""
    if SIM:
        pytest.skip("this is the child process")
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", __file__],
                       env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-3000:]
    assert " passed" in r.stdout and "failed" not in r.stdout


# ------------------------------------------------------------------------ under the simulator
if SIM:

    @pytest.mark.parametrize("kernel", KERNELS, ids=KIDS)
    def test_dense_matches_direct(kernel):
        """Two blocks (the second partial) of 32 threads x 2 targets, three source tiles (the
        last partial); a coincident pair and a target on the wall."""
        T, S, F = case(70, 75, seed=1)
        ref = Direct().dense(kernel, T, S, F, 0.7)
        u = stokeslet_velocity(T, S, F, 0.7, kernel=kernel, backend=Cuda(threads=32, targets_per_thread=2))
        assert u.shape == (70, 3) and u.dtype == np.float64
        assert np.max(np.abs(u - ref)) <= 1e-12 * np.max(np.abs(ref))
        for precision in ("fp32", "fp32-acc64"):
            u = Cuda(precision, threads=32, targets_per_thread=3).dense(kernel, T, S, F, 0.7)
            err = np.max(np.abs(u - ref), axis=1)
            bound = cc.fp32_error_bound(kernel, T, S, F, 0.7, precision=precision)
            assert np.all(err <= bound), np.max(err / bound)
            assert np.max(err) > 1e-10 * np.max(np.abs(ref))  # fp32 arithmetic did run

    @pytest.mark.parametrize("kernel", KERNELS, ids=KIDS)
    def test_ranged_matches_direct(kernel):
        """Two warps per block, a partial last block, targets without ranges, empty and repeated
        ranges."""
        T, S, F = case(7, 60, seed=2)
        ptr, ranges = csr(7, 60, seed=3)
        ref = Direct().ranged(kernel, T, S, F, ptr, ranges, 1.3)
        u = stokeslet_velocity_ranges(T, S, F, ptr, ranges, 1.3, kernel=kernel, backend=Cuda(threads=64))
        assert np.max(np.abs(u - ref)) <= 1e-12 * np.max(np.abs(ref))
        assert np.all(u[0] == 0)
        n = terms(ptr, ranges)
        for precision in ("fp32", "fp32-acc64"):
            u = Cuda(precision, threads=64).ranged(kernel, T, S, F, ptr, ranges, 1.3)
            err = np.max(np.abs(u - ref), axis=1)
            bound = cc.fp32_error_bound(kernel, T, S, F, 1.3, precision=precision, terms=n)
            assert np.all(err <= bound), np.max(err / bound)

    def test_fp32_far_from_the_origin_keeps_its_bound():
        """Points 1e3 away from the origin: shifted to their centre before rounding, the fp32 sum
        keeps the accuracy it has near the origin (without the shift, 1e3 * 2^-24 ~ 6e-5 of
        error in every distance)."""
        k = Stokeslet()
        T, S, F = case(40, 50, seed=4)
        Tf, Sf, _ = case(40, 50, seed=4, offset=1e3)
        near = Cuda("fp32").dense(k, T, S, F, 1.0) - Direct().dense(k, T, S, F, 1.0)
        ref = Direct().dense(k, Tf, Sf, F, 1.0)
        far = Cuda("fp32").dense(k, Tf, Sf, F, 1.0) - ref
        assert np.max(np.abs(far)) < 10 * np.max(np.abs(near))
        assert np.all(np.max(np.abs(far), axis=1) <= cc.fp32_error_bound(k, Tf, Sf, F))

    def test_selection_under_the_simulator():
        assert cc.cuda_available()
        assert isinstance(Auto().choose(10, 10), Cuda)
        assert Auto().describe().startswith("auto: cuda (fp64")
        assert backend_named("cuda-fp32-acc64") == Cuda("fp32-acc64")
        T, S, F = case(20, 30, seed=5)
        ptr, ranges = csr(6, 30, seed=6)
        k = KERNELS[3]
        assert np.allclose(stokeslet_velocity(T, S, F, kernel=k, backend=Auto()),
                           Direct().dense(k, T, S, F, 1.0), rtol=0, atol=1e-13)
        assert np.allclose(stokeslet_velocity_ranges(T[:6], S, F, ptr, ranges, kernel=k, backend=Auto()),
                           Direct().ranged(k, T[:6], S, F, ptr, ranges, 1.0), rtol=0, atol=1e-13)

    def test_carpet_flow_on_the_gpu_matches_the_cpu():
        """A 2 x 2 carpet above a wall (regularised Blake kernel, dense and ranged sums, point
        and resolved levels): instantaneous and mean flows on Cuda agree with Direct."""
        from ciliary_carpet.carpet import layout
        from ciliary_carpet.carpet.carpet import Carpet, CycleMean, Instant
        from single_cilium.table import ThrustTable

        rng = np.random.default_rng(7)
        bases, chi = layout.square(2, 2, 2.0), rng.uniform(-100, 100, 4)
        pts = np.column_stack([rng.uniform(-1, 3, 4), rng.uniform(-1, 3, 4), rng.uniform(0.05, 1.0, 4)])
        kw = dict(phases=layout.random_phases(4, 0), wall=0.5)
        a = Carpet(bases, chi, ThrustTable.default(), backend=Direct(), **kw)
        b = Carpet(bases, chi, ThrustTable.default(), backend=Cuda(), **kw)
        for f in (lambda c: c.evaluate(pts, Instant(0.3)), lambda c: c.evaluate(pts, CycleMean())):
            ua, ub = f(a).velocity, f(b).velocity
            assert np.max(np.abs(ua - ub)) <= 1e-12 * np.max(np.abs(ua))

    def test_empty_sums_are_zero():
        T, S, F = case(8, 9)
        z = np.zeros((0, 3))
        assert Cuda().dense(Stokeslet(), z, S, F, 1.0).shape == (0, 3)
        assert np.all(Cuda().dense(Stokeslet(), T, z, z, 1.0) == 0)
        assert np.all(Cuda().ranged(Stokeslet(), T, S, F, np.zeros(9, np.int64), np.zeros((0, 2), np.int64),
                                    1.0) == 0)
