"""The closed-form NTK of the two-layer ReLU network equals its autograd definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cdqn.network import FastTwoLayer, NetworkSpec, QNetwork, ntk, ntk_autograd


@pytest.mark.parametrize("seed", range(5))
def test_closed_form_ntk_equals_autograd_definition(seed: int) -> None:
    torch.manual_seed(seed)
    gen = np.random.default_rng(seed)
    n_obs, n_actions, width = int(gen.integers(1, 7)), int(gen.integers(2, 5)), 200
    net = QNetwork(NetworkSpec(n_obs, n_actions, width, "float64"))
    fast = FastTwoLayer(net)
    for _ in range(6):
        x = torch.randn(n_obs, dtype=torch.float64)
        y = x + 0.3 * torch.randn(n_obs, dtype=torch.float64)  # near pairs share ReLU masks
        a, b = (int(v) for v in gen.integers(n_actions, size=2))
        for left, right in ((a, a), (a, b), (b, a)):
            reference = ntk_autograd(net, x, left, y, right)
            assert ntk(net, x, left, y, right) == pytest.approx(reference, rel=1e-12, abs=1e-12)
            fx, fy = fast.forward(x.numpy()), fast.forward(y.numpy())
            assert fast.ntk(fx, left, fy, right) == pytest.approx(reference, rel=1e-12, abs=1e-12)


def test_theta1_is_a_squared_gradient_norm() -> None:
    torch.manual_seed(0)
    net = QNetwork(NetworkSpec(4, 2, 64, "float64"))
    x = torch.randn(4, dtype=torch.float64)
    net.zero_grad()
    net(x)[1].backward()
    norm2 = sum(float(torch.sum(p.grad**2)) for p in net.parameters())
    assert ntk(net, x, 1, x, 1) == pytest.approx(norm2, rel=1e-12)
