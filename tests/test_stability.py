import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import xarray as xr
from scipy.optimize import brentq, least_squares

from single_cilium import CiliumParams, Filament, Mesh, simulate
from single_cilium.stability import (ResolutionWarning, _hopf_alpha, flutter_boundary, flutter_cutoff,
                                     spectrum, stability, stability_map)

TWO_PI = 2 * np.pi


def test_published_case_flutters(published):
    r = stability(published)
    assert r.regime == "flutter"
    assert r.alpha == pytest.approx(0.4276932, rel=1e-6)
    assert r.beta == pytest.approx(22.8022358, rel=1e-8)
    assert r.period_estimate == pytest.approx(2 * np.pi / r.beta)
    assert r.converged and r.error < 1e-7
    assert r.status == "success" and "change by" in r.message
    assert r.as_dict()["status"] == "success"
    assert r.theta_modes[0, 0] == 0 and np.max(np.abs(r.theta_modes[0])) == pytest.approx(1.0)


def test_leading_eigenvalue_converges_exponentially(published):
    ref = stability(published, degree=16, check=False).omega
    errs = [abs(stability(published, degree=d, check=False).omega - ref) / abs(ref) for d in (4, 5, 6, 7)]
    assert all(a > 5 * b for a, b in zip(errs, errs[1:])), errs  # geometric decay in the degree
    assert abs(stability(published, degree=10, check=False).omega - ref) / abs(ref) < 1e-8


def test_coarse_mesh_warns():
    p = CiliumParams(200, 1, 16 * TWO_PI)  # clamp layer 0.006 wide; first element 0.1
    with pytest.warns(ResolutionWarning, match="raise the degree"):
        r = stability(p, mesh=Mesh.graded(0.05, degree=6), rtol=1e-6)
    assert not r.converged
    assert r.status == "inaccurate" and "raise the degree" in r.message


def test_unchecked_status(published):
    r = stability(published, degree=6, check=False)
    assert r.status == "unchecked" and r.converged and math.isnan(r.error)
    assert "not checked" in r.message


@pytest.mark.parametrize("chi_N", [0.0, 8 * TWO_PI, 16 * TWO_PI])
def test_nonlinear_growth_matches_the_eigenvalue(chi_N):
    """A 1e-7 perturbation along the leading mode grows at alpha and turns at beta (to 1e-5)."""
    p = CiliumParams(200, 1, chi_N)
    mesh = Mesh.for_params(p, 10)
    fil = Filament(p, mesh)
    w, V = spectrum(p, mesh, vectors=True)
    v = np.real(V[:, 0] / V[np.argmax(np.abs(V[: fil.n - 1, 0])), 0])
    y0 = fil.equilibrium_state()
    th0, ka0 = fil.split(y0 + 1e-7 * v)
    sim = simulate(p, 1.0, state=(th0, ka0), mesh=mesh, rtol=1e-13, n_out=201, error_estimate=False)
    t = sim.data.time.values
    x = sim.data.theta.values[:, -1] - fil.split(y0)[0][-1]

    def resid(ab):
        basis = np.stack([np.exp(ab[0] * t) * np.cos(ab[1] * t), np.exp(ab[0] * t) * np.sin(ab[1] * t)], 1)
        c, *_ = np.linalg.lstsq(basis, x, rcond=None)
        return (basis @ c - x) / np.abs(x).max()

    fit = least_squares(resid, [w[0].real, abs(w[0].imag)], xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    assert fit[0] == pytest.approx(w[0].real, rel=1e-5, abs=1e-5 * abs(w[0]))
    assert fit[1] == pytest.approx(abs(w[0].imag), rel=1e-5)


def test_tiny_natural_curvature_removes_flutter_only_for_negative_field():
    neg0 = stability(CiliumParams(-50, 1, 0.0), check=False)
    neg = stability(CiliumParams(-50, 1, 0.01 * TWO_PI), check=False)
    assert neg0.regime == "flutter" and neg.regime == "stable"
    pos0 = stability(CiliumParams(150, 1, 0.0), check=False)
    pos = stability(CiliumParams(150, 1, 0.01 * TWO_PI), check=False)
    assert pos0.regime == pos.regime == "flutter"
    assert abs(pos.omega - pos0.omega) < 1e-5 * abs(pos0.omega)


def test_raising_chi_N_lowers_the_frequency(published):
    betas = [stability(CiliumParams(200, 1, k * TWO_PI), check=False).beta for k in (0, 8, 16, 24)]
    assert np.all(np.diff(betas) < 0)


@pytest.mark.parametrize("chi_E", [60.0, 90.0])
def test_coiled_filaments_are_stable(chi_E):
    r = stability(CiliumParams(chi_E, 1, 16 * TWO_PI), degree=8, check=False)
    assert r.alpha < -0.1


def test_flutter_cutoff():
    c = flutter_cutoff(200, 1)
    assert 150 < c.chi_N_cutoff < 180 and c.beta > 0 and c.error < 1e-6
    a_below = _hopf_alpha(spectrum(CiliumParams(200, 1, c.chi_N_cutoff * (1 - 1e-6)),
                                   Mesh.for_params(CiliumParams(200, 1, c.chi_N_cutoff), 10)))[0]
    a_above = _hopf_alpha(spectrum(CiliumParams(200, 1, c.chi_N_cutoff * (1 + 1e-6)),
                                   Mesh.for_params(CiliumParams(200, 1, c.chi_N_cutoff), 10)))[0]
    assert a_below > 0 > a_above
    none = flutter_cutoff(50, 1)
    assert math.isnan(none.chi_N_cutoff) and "no flutter" in none.message


def test_boundary_agrees_with_sign_changes_on_grid_lines():
    chi_N = 16 * TWO_PI
    b = flutter_boundary(chi_N, chi_E=(150, 250), eta=(0.3, 1.5), degree=8, step=0.08)
    assert b.branches, b.message
    pts = np.vstack(b.branches)
    for br in b.branches:  # every point on alpha = 0
        for eta, cE, beta in br[:: max(1, len(br) // 5)]:
            a, bt = _hopf_alpha(spectrum(CiliumParams(cE, eta, chi_N), Mesh.for_params(CiliumParams(cE, eta, chi_N), 8)))
            assert abs(a) < 1e-8 and bt == pytest.approx(beta)
    for cE in (175.0, 225.0):  # crossings found independently along lines of constant chi_E
        def a(eta):
            p = CiliumParams(cE, eta, chi_N)
            return _hopf_alpha(spectrum(p, Mesh.for_params(p, 8)))[0]
        etas = np.linspace(0.3, 1.5, 13)
        vals = [a(e) for e in etas]
        for i in np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0]:
            root = brentq(a, etas[i], etas[i + 1], xtol=1e-10)
            d = np.min(np.hypot((pts[:, 0] - root) / 1.2, (pts[:, 1] - cE) / 100.0))
            assert d < 0.05, (cE, root, d)  # the traced curve passes there (within a step)


def test_empty_window_gives_a_message():
    b = flutter_boundary(0.0, chi_E=(20, 60), eta=(0.5, 1.0), degree=6)
    assert b.branches == [] and "no Hopf boundary" in b.message


def test_stability_map(tmp_path):
    chi_N = 16 * TWO_PI
    with ThreadPoolExecutor(2) as ex:
        ds = stability_map(chi_N, chi_E=[90.0, 200.0, 300.0], eta=[0.5, 1.0], degree=8, executor=ex)
    assert ds.regime.sel(chi_E=90.0).values.tolist() == [3, 3]  # coiled, not computed
    r = stability(CiliumParams(200, 1, chi_N), degree=8, check=False)
    assert ds.alpha.sel(chi_E=200.0, eta=1.0) == pytest.approx(r.alpha, rel=1e-12)
    assert ds.regime.sel(chi_E=200.0, eta=1.0) == 1
    assert ds.frequency.sel(chi_E=200.0, eta=1.0) == pytest.approx(r.beta / TWO_PI)
    from cilia_runtime.files import write_netcdf
    write_netcdf(ds, tmp_path / "map.nc")
    back = xr.open_dataset(tmp_path / "map.nc", engine="h5netcdf")
    assert back.alpha.attrs["units"] == "1" and back.attrs["chi_N"] == chi_N


@pytest.mark.parametrize("kw,match", [
    (dict(chi_E=[], eta=[1.0]), "chi_E grid"),
    (dict(chi_E=[200.0, 100.0], eta=[1.0]), "increasing"),
    (dict(chi_E=[200.0], eta=[np.nan]), "NaN"),
    (dict(chi_E=[200.0], eta=[-1.0, 1.0]), "eta"),
])
def test_bad_grids(kw, match):
    with pytest.raises(ValueError, match=match):
        stability_map(0.0, **kw)


def test_bad_windows():
    with pytest.raises(ValueError, match="eta window"):
        flutter_boundary(0.0, chi_E=(10, 20), eta=(-1, 1))
    with pytest.raises(ValueError, match="chi_E window"):
        flutter_boundary(0.0, chi_E=(20, 10), eta=(0.1, 1))


@pytest.mark.parametrize("p", [
    CiliumParams(100.53 * 1.001, 1, 100.53),   # chi_E close to chi_N: slow equilibrium transition
    CiliumParams(-50, 1, 0.01 * TWO_PI),       # chi_E < 0, small chi_N: the equilibrium folds over
    CiliumParams(1000, 1, 16 * TWO_PI),        # thin clamp layer (QZ meets infinite eigenvalues)
    CiliumParams(200, 0.05, 16 * TWO_PI),
    CiliumParams(200, 20, 16 * TWO_PI),
], ids=["chiE~chiN", "folded", "chiE=1000", "eta=0.05", "eta=20"])
def test_hard_cases_converge(p, recwarn):
    r = stability(p)
    assert r.converged and r.error < 1e-6, r.message
    assert np.all(np.isfinite(r.eigenvalues)) and np.isfinite(r.alpha)
    assert not [w for w in recwarn if issubclass(w.category, ResolutionWarning)]
    ref = stability(p, degree=16, check=False)
    assert abs(r.omega - ref.omega) <= 1e-6 * abs(ref.omega)  # and the estimate was honest
