"""H2: the per-step LQR gains equal python-control's ``lqr`` (slycot SB02MD), on the paper's
plant and on the minimal part of the gradient-flow plant."""

from __future__ import annotations

import control
import numpy as np
import pytest

from cdqn.control.certificate import ControllerMatrices, max_real_poles
from cdqn.control.h2 import h2_gains, h2_gains_plant, lqr_gain
from cdqn.control.plant import augmented_plant, reduction_basis

W_X = {
    "cartpole": ([1.0, 30000.0, 10.0], 20000.0),
    "acrobot": ([1.0, 100.0, 80.0], 30.0),
    "mountaincar": ([1.0, 10.0, 100.0], 1000.0),
}


@pytest.mark.parametrize("env", sorted(W_X))
@pytest.mark.parametrize("theta", [(220.0, 222.0), (200.0, 160.0), (500.0, 600.0), (316.0, 316.0)])
def test_h2_gains_equal_control_lqr(env: str, theta: tuple[float, float]) -> None:
    w_x, w_c = W_X[env]
    plant = augmented_plant(*theta, 1.0, "paper")
    K, _, _ = control.lqr(plant.A, plant.B_u.reshape(3, 1), np.diag(w_x), np.array([[w_c]]))
    K = np.asarray(K).ravel()
    np.testing.assert_allclose(lqr_gain(plant.A, plant.B_u, np.asarray(w_x), w_c), K, rtol=1e-7)
    k1, k2, k3 = h2_gains(*theta, 1.0, np.asarray(w_x), w_c)
    np.testing.assert_allclose([k1, k2, -k3], K, rtol=1e-6)


@pytest.mark.parametrize("env", sorted(W_X))
@pytest.mark.parametrize("theta", [(220.0, 222.0), (200.0, 160.0), (500.0, 600.0)])
def test_h2_gains_on_the_gradient_flow_plant(env: str, theta: tuple[float, float]) -> None:
    w_x, w_c = W_X[env]
    gains = h2_gains_plant(*theta, 1.0, np.asarray(w_x), w_c, "gradient_flow")
    assert gains == h2_gains_plant(*theta, 1.0, np.asarray(w_x), w_c, "gradient_flow")
    assert h2_gains_plant(*theta, 1.0, np.asarray(w_x), w_c, "paper") == h2_gains(
        *theta, 1.0, np.asarray(w_x), w_c
    )
    p = augmented_plant(*theta, 1.0, "gradient_flow")
    N = reduction_basis(np.array([theta]), 3)[0]
    K_r, _, _ = control.lqr(
        N.T @ p.A @ N, (N.T @ p.B_u).reshape(2, 1), N.T @ np.diag(w_x) @ N, np.array([[w_c]])
    )
    k1, k2, k3 = gains
    np.testing.assert_allclose(np.array([k1, k2, -k3]) @ N, np.asarray(K_r).ravel(), rtol=1e-6)
    pole = max_real_poles(np.array([theta]), 1.0, ControllerMatrices.static(*gains))[0]
    assert pole < 0
