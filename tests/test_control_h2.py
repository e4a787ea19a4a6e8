"""H2: the per-step LQR gains equal python-control's ``lqr`` (slycot SB02MD)."""

from __future__ import annotations

import control
import numpy as np
import pytest

from cdqn.control.h2 import h2_gains, lqr_gain
from cdqn.control.plant import augmented_plant

W_X = {
    "cartpole": ([1.0, 30000.0, 10.0], 20000.0),
    "acrobot": ([1.0, 100.0, 80.0], 30.0),
    "mountaincar": ([1.0, 10.0, 100.0], 1000.0),
}


@pytest.mark.parametrize("env", sorted(W_X))
@pytest.mark.parametrize("theta", [(220.0, 222.0), (200.0, 160.0), (500.0, 600.0), (316.0, 316.0)])
def test_h2_gains_equal_control_lqr(env: str, theta: tuple[float, float]) -> None:
    w_x, w_c = W_X[env]
    plant = augmented_plant(*theta, 1.0)
    K, _, _ = control.lqr(plant.A, plant.B_u.reshape(3, 1), np.diag(w_x), np.array([[w_c]]))
    K = np.asarray(K).ravel()
    np.testing.assert_allclose(lqr_gain(plant.A, plant.B_u, np.asarray(w_x), w_c), K, rtol=1e-7)
    k1, k2, k3 = h2_gains(*theta, 1.0, np.asarray(w_x), w_c)
    np.testing.assert_allclose([k1, k2, -k3], K, rtol=1e-6)
