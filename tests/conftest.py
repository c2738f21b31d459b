import numpy as np
import pytest

from single_cilium import CiliumParams

TWO_PI = 2 * np.pi


@pytest.fixture
def published():
    """The published nonlinear case: chi_E = 200, eta = 1, chi_N = 16 * 2 pi."""
    return CiliumParams(200.0, 1.0, 16 * TWO_PI)
