"""Examples never rot: each is imported and its result checked."""
import importlib.util
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_flutter_onset():
    ex = load("flutter_onset")
    # the oscillation period is close to 2 pi / beta with beta ~ 22.81 (fit in test_dynamics)
    assert ex.period == pytest.approx(2 * 3.141592653589793 / 22.81, rel=5e-3)
    assert 0.2 < ex.growth_rate < 0.8
    assert ex.sim.error < 3e-4
