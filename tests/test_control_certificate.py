"""Certificate and the sign facts of the research code's designs."""

from __future__ import annotations

import control
import numpy as np
import pytest

from cdqn.control.box import NTKBox
from cdqn.control.certificate import ControllerMatrices, certify, max_real_poles
from cdqn.control.errors import DesignError
from cdqn.control.plant import static_closed_loop

PAPER_BOX = NTKBox((200.0, 500.0), (0.8, 1.2), (220.0, 222.0))
RESEARCH_GAINS = (-0.379, 2.82, 0.1937)
RESEARCH_A = np.array([[-20470.0, 13550.0], [-13130.0, -2.394]])
RESEARCH_B = np.array([[155.7, 53.97, 55.91], [-1.744, -0.6808, 0.179]])
RESEARCH_C = np.array([[174.1, -1.881]])  # MATLAB's u = +K y, the plant's +u


def test_research_fixed_gains_unstable_in_loss_convention_stable_negated() -> None:
    poles = np.linalg.eigvals(static_closed_loop(220.0, 222.0, 1.0, RESEARCH_GAINS))
    assert poles.real.max() == pytest.approx(390.57, abs=0.5)
    negated = tuple(-k for k in RESEARCH_GAINS)
    assert np.linalg.eigvals(static_closed_loop(220.0, 222.0, 1.0, negated)).real.max() < 0
    cert = certify(
        ControllerMatrices.static(*negated),
        PAPER_BOX,
        PAPER_BOX.sample(200, 0),
        (25, 25),
        1.0,
        lr=5e-5,
    )
    assert cert.passed


def test_research_dynamic_controller_fails_where_theta2_exceeds_theta1() -> None:
    K = ControllerMatrices(RESEARCH_A, RESEARCH_B, RESEARCH_C, np.zeros((1, 3)))
    grid = PAPER_BOX.grid(13, 17)
    re = max_real_poles(grid, 1.0, K)
    ratio = grid[:, 1] / grid[:, 0]
    assert np.all(re[ratio <= 0.95] < 0)  # stabilises the Θ2 < Θ1 part
    assert np.all(ratio[re >= 0] > 1.0)  # what it leaves unstable lies in Θ2 > Θ1
    assert np.mean(re[ratio >= 1.05] > 0) > 0.9
    cert = certify(K, PAPER_BOX, PAPER_BOX.sample(200, 0), (25, 25), 1.0)
    assert not cert.passed and 0.4 < cert.share_stable_grid < 0.8
    # in the research code's runtime sign (its loss uses −u) no point of the box is stable
    K_neg = ControllerMatrices(RESEARCH_A, RESEARCH_B, -RESEARCH_C, np.zeros((1, 3)))
    assert certify(K_neg, PAPER_BOX, PAPER_BOX.sample(50, 0), (9, 9), 1.0).share_stable == 0.0


def test_norm_of_unstable_loop_is_finite_so_stability_is_checked_explicitly() -> None:
    A = static_closed_loop(220.0, 222.0, 1.0, RESEARCH_GAINS)
    sys = control.ss(A, np.eye(3)[:, :1], np.eye(3)[:1], 0.0)
    assert np.isfinite(float(control.norm(sys, p="inf")))  # an L∞ value, no complaint
    cert = certify(
        ControllerMatrices.static(*RESEARCH_GAINS), PAPER_BOX, PAPER_BOX.sample(20, 0), (5, 5), 1.0
    )
    assert not cert.passed
    assert "unstable" in cert.reason() and cert.worst_pole > 300


def test_discrete_check_catches_too_large_gains() -> None:
    """Stable in continuous time, unstable as SGD steps at Δt = α."""
    K = ControllerMatrices.static(100.0, -100.2, -0.1)
    cert = certify(K, PAPER_BOX, PAPER_BOX.sample(20, 0), (5, 5), 1.0, lr=5e-5)
    assert cert.share_stable == 1.0 and not cert.passed
    assert "Δt = α" in cert.reason()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"theta1": (0.0, 500.0)}, "Θ1 > 0"),
        ({"theta1": (500.0, 200.0)}, "lower <= upper"),
        ({"ratio": (-0.1, 1.2)}, "ratio"),
        ({"nominal": (100.0, 100.0)}, "outside theta1"),
        ({"nominal": (300.0, 600.0)}, "outside ratio"),
    ],
)
def test_box_errors(kwargs: dict, match: str) -> None:
    args = {"theta1": (200.0, 500.0), "ratio": (0.8, 1.2), "nominal": (300.0, 300.0)} | kwargs
    with pytest.raises(DesignError, match=match):
        NTKBox(**args)
