import math

import numpy as np
import pytest

from single_cilium import CiliumParams, PhysicalCilium


@pytest.mark.parametrize("field,kwargs", [
    ("eta", dict(chi_E=1.0, eta=-1.0)),
    ("eta", dict(chi_E=1.0, eta=0.0)),
    ("chi_E", dict(chi_E=math.nan, eta=1.0)),
    ("chi_N", dict(chi_E=1.0, eta=1.0, chi_N=math.inf)),
    ("chi_E", dict(chi_E="abc", eta=1.0)),
])
def test_invalid_params_name_the_field(field, kwargs):
    with pytest.raises(ValueError, match=field):
        CiliumParams(**kwargs)


def test_params_are_frozen_floats():
    p = CiliumParams(200, 1, 3)
    assert isinstance(p.chi_E, float) and p.chi_N == 3.0
    with pytest.raises(AttributeError):
        p.eta = 2.0
    assert p.mirrored() == CiliumParams(200, 1, -3)


def test_physical_round_trip():
    # a 100 um hydrogel filament, tau = 2 s, B = 1e-15 N m^2 in water-like drag
    L, tau, B, mu = 100e-6, 2.0, 1e-15, 2e-3
    p = CiliumParams.from_physical(L, tau, B, mu, target_curvature=2e6, natural_curvature=1e6)
    assert p.chi_E == pytest.approx(200.0)
    assert p.chi_N == pytest.approx(100.0)
    assert p.eta == pytest.approx(mu * L**4 / (tau * B))
    phys = p.to_physical(L, tau, B)
    assert phys.drag_coefficient == pytest.approx(mu, rel=1e-14)
    assert phys.target_curvature == pytest.approx(2e6)
    back = phys.to_params()
    assert (back.chi_E, back.eta, back.chi_N) == pytest.approx((p.chi_E, p.eta, p.chi_N), rel=1e-14)
    assert phys.force_scale == pytest.approx(B / L**2)
    assert phys.velocity_scale == pytest.approx(L / tau)


@pytest.mark.parametrize("name", ["length", "relaxation_time", "bending_stiffness", "drag_coefficient"])
def test_physical_rejects_nonpositive(name):
    kw = dict(length=1e-4, relaxation_time=1.0, bending_stiffness=1e-15, drag_coefficient=1e-3,
              target_curvature=1.0)
    kw[name] = -1.0
    with pytest.raises(ValueError, match=name):
        PhysicalCilium(**kw)


@pytest.mark.parametrize("value", [1 + 0j, np.complex128(2.0), np.complex64(1 + 1j)])
def test_the_shared_validator_refuses_complex_numbers(value):
    """float() of a numpy complex keeps the real part with only a warning; the one finite-number
    validator (single_cilium.checks) refuses it by name, and the parameters with it."""
    from single_cilium.checks import finite
    with pytest.raises(ValueError, match="x must be a real number"):
        finite("x", value)
    with pytest.raises(ValueError, match="eta must be a real number"):
        CiliumParams(200.0, value, 0.0)
