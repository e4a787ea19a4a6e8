"""Certificate on both learning plants, the structural zero of the gradient-flow plant, and the
sign facts of the research code's designs."""

from __future__ import annotations

import control
import numpy as np
import pytest

from cdqn.control.box import NTKBox
from cdqn.control.certificate import (
    ControllerMatrices,
    certify,
    closed_loop_batch,
    discrete_loop_batch,
    max_real_poles,
)
from cdqn.control.errors import DesignError
from cdqn.control.plant import conserved_direction, static_closed_loop

PAPER_BOX = NTKBox((200.0, 500.0), (0.8, 1.2), (220.0, 222.0))
RESEARCH_GAINS = (-0.379, 2.82, 0.1937)
RESEARCH_A = np.array([[-20470.0, 13550.0], [-13130.0, -2.394]])
RESEARCH_B = np.array([[155.7, 53.97, 55.91], [-1.744, -0.6808, 0.179]])
RESEARCH_C = np.array([[174.1, -1.881]])  # MATLAB's u = +K y, the plant's +u
PAPER_PLANT_DESIGN = (2.075, -2.078, -0.00363)
"""(k1, k2, k3) certified on the paper's plant for the CartPole box [100, 800] × [0.8, 1.2]."""
CARTPOLE_BOX = NTKBox((100.0, 800.0), (0.8, 1.2), (282.8, 282.8))


def test_research_fixed_gains_on_the_paper_plant_unstable_stable_negated() -> None:
    poles = np.linalg.eigvals(static_closed_loop(220.0, 222.0, 1.0, RESEARCH_GAINS, "paper"))
    assert poles.real.max() == pytest.approx(390.57, abs=0.5)
    negated = tuple(-k for k in RESEARCH_GAINS)
    assert np.linalg.eigvals(static_closed_loop(220.0, 222.0, 1.0, negated, "paper")).real.max() < 0
    cert = certify(
        ControllerMatrices.static(*negated),
        PAPER_BOX,
        PAPER_BOX.sample(200, 0),
        (25, 25),
        1.0,
        lr=5e-5,
        plant="paper",
    )
    assert cert.passed


def test_research_dynamic_controller_fails_where_theta2_exceeds_theta1() -> None:
    K = ControllerMatrices(RESEARCH_A, RESEARCH_B, RESEARCH_C, np.zeros((1, 3)))
    grid = PAPER_BOX.grid(13, 17)
    re = max_real_poles(grid, 1.0, K, "paper")
    ratio = grid[:, 1] / grid[:, 0]
    assert np.all(re[ratio <= 0.95] < 0)  # stabilises the Θ2 < Θ1 part
    assert np.all(ratio[re >= 0] > 1.0)  # what it leaves unstable lies in Θ2 > Θ1
    assert np.mean(re[ratio >= 1.05] > 0) > 0.9
    cert = certify(K, PAPER_BOX, PAPER_BOX.sample(200, 0), (25, 25), 1.0, plant="paper")
    assert not cert.passed and 0.4 < cert.share_stable_grid < 0.8
    # in the research code's runtime sign (its loss uses −u) no point of the box is stable
    K_neg = ControllerMatrices(RESEARCH_A, RESEARCH_B, -RESEARCH_C, np.zeros((1, 3)))
    cert = certify(K_neg, PAPER_BOX, PAPER_BOX.sample(50, 0), (9, 9), 1.0, plant="paper")
    assert cert.share_stable == 0.0


def test_norm_of_unstable_loop_is_finite_so_stability_is_checked_explicitly() -> None:
    A = static_closed_loop(220.0, 222.0, 1.0, RESEARCH_GAINS, "paper")
    sys = control.ss(A, np.eye(3)[:, :1], np.eye(3)[:1], 0.0)
    assert np.isfinite(float(control.norm(sys, p="inf")))  # an L∞ value, no complaint
    cert = certify(
        ControllerMatrices.static(*RESEARCH_GAINS),
        PAPER_BOX,
        PAPER_BOX.sample(20, 0),
        (5, 5),
        1.0,
        plant="paper",
    )
    assert not cert.passed
    assert "unstable" in cert.reason() and cert.worst_pole > 300


def test_discrete_check_catches_too_large_gains() -> None:
    """Stable in continuous time, unstable as SGD steps at Δt = α."""
    K = ControllerMatrices.static(100.0, -100.2, -0.1)
    cert = certify(K, PAPER_BOX, PAPER_BOX.sample(20, 0), (5, 5), 1.0, lr=5e-5, plant="paper")
    assert cert.share_stable == 1.0 and not cert.passed
    assert "Δt = α" in cert.reason()
    K = ControllerMatrices.static(200.0, 1.0, 0.5)  # gradient flow: α (1+k1) Θ1 > 2
    cert = certify(K, PAPER_BOX, PAPER_BOX.sample(20, 0), (5, 5), 1.0, lr=5e-5)
    assert cert.share_stable == 1.0 and not cert.passed
    assert "Δt = α" in cert.reason()


def _random_controllers(rng: np.random.Generator):
    yield ControllerMatrices.static(*rng.normal(size=3))
    n = 2
    yield ControllerMatrices(
        -np.diag(rng.uniform(1, 10, n)),
        rng.normal(size=(n, 3)),
        rng.normal(size=(1, n)),
        rng.normal(size=(1, 3)),
    )


def test_every_gradient_flow_loop_has_the_structural_zero_and_the_reduction_removes_it() -> None:
    """For any controller reading [x_e, Q1, Q2], [Θ2, −Θ1, 0, …] is a left eigenvector at 0
    (continuous time) and at 1 (one SGD step); the certified loop has the other eigenvalues."""
    rng = np.random.default_rng(0)
    pts = CARTPOLE_BOX.sample(6, 1)
    for K in _random_controllers(rng):
        full = closed_loop_batch(pts, 0.9, K, reduce=False)
        red = closed_loop_batch(pts, 0.9, K)
        phi = discrete_loop_batch(pts, 0.9, K, 5e-5, "zoh", reduce=False)
        phi_red = discrete_loop_batch(pts, 0.9, K, 5e-5, "zoh")
        for i, (t1, t2) in enumerate(pts):
            ell = np.zeros(full.shape[1])
            ell[:2] = conserved_direction(t1, t2)
            scale = np.abs(full[i]).max()
            np.testing.assert_allclose(ell @ full[i], 0.0, atol=1e-12 * scale * t1)
            np.testing.assert_allclose(ell @ phi[i], ell, rtol=1e-12, atol=1e-9 * t1)
            ev_full = np.sort_complex(np.linalg.eigvals(full[i]))
            ev_red = np.linalg.eigvals(red[i])
            zero = np.argmin(np.abs(ev_full))
            assert abs(ev_full[zero]) < 1e-8 * scale
            rest = np.delete(ev_full, zero)
            np.testing.assert_allclose(np.sort_complex(ev_red), rest, rtol=1e-7, atol=1e-7 * scale)
            mod = np.sort(np.abs(np.linalg.eigvals(phi[i])))
            one = np.argmin(np.abs(mod - 1.0))
            np.testing.assert_allclose(
                np.sort(np.abs(np.linalg.eigvals(phi_red[i]))), np.delete(mod, one), rtol=1e-9
            )
    assert conserved_direction(300.0, 300.0, "paper") is None


def test_paper_plant_has_no_structural_zero() -> None:
    K = ControllerMatrices.static(0.379, -2.82, -0.1937)
    pts = PAPER_BOX.sample(5, 0)
    red = closed_loop_batch(pts, 1.0, K, plant="paper")
    assert red.shape == (5, 3, 3)
    np.testing.assert_array_equal(red, closed_loop_batch(pts, 1.0, K, plant="paper", reduce=False))


def test_research_gains_certified_on_the_gradient_flow_plant() -> None:
    """The research code's gains, unstable on the paper plant, are stable on the plant training
    realises over the whole measured CartPole box; the paper-plant design is not."""
    samples = CARTPOLE_BOX.sample(200, 0)
    cert = certify(
        ControllerMatrices.static(*RESEARCH_GAINS), CARTPOLE_BOX, samples, (25, 25), 1.0, lr=5e-5
    )
    assert cert.passed and cert.plant == "gradient_flow"
    assert cert.worst_pole == pytest.approx(-0.0691, abs=1e-3)
    assert cert.to_dict()["plant"] == "gradient_flow"
    paper = certify(
        ControllerMatrices.static(*RESEARCH_GAINS),
        CARTPOLE_BOX,
        samples,
        (25, 25),
        1.0,
        plant="paper",
    )
    assert not paper.passed and paper.share_stable == 0.0
    for gains, pole in ((PAPER_PLANT_DESIGN, 494.9), (tuple(-k for k in RESEARCH_GAINS), 2564.1)):
        cert = certify(ControllerMatrices.static(*gains), CARTPOLE_BOX, samples, (25, 25), 1.0)
        assert not cert.passed and cert.worst_pole == pytest.approx(pole, abs=0.5)
        ok = certify(
            ControllerMatrices.static(*gains), CARTPOLE_BOX, samples, (25, 25), 1.0, plant="paper"
        )
        assert ok.passed


def test_gradient_flow_static_loop_routh_hurwitz() -> None:
    """Stable iff (1+k1) Θ1 > (γ−k2) Θ2 and k3 > 0; k3 = 0 leaves a double zero, which the
    reduction keeps (the certificate fails)."""
    t1, t2 = 300.0, 330.0
    for gains, stable in (
        ((0.0, 0.0, 0.1), False),  # γΘ2 > Θ1: the uncontrolled TD mode is unstable
        ((0.2, 0.0, 0.1), True),
        ((0.2, 0.0, -0.1), False),
        ((-0.379, 2.82, 0.1937), True),
        ((0.2, 0.0, 0.0), False),
    ):
        re = max_real_poles(np.array([[t1, t2]]), 1.0, ControllerMatrices.static(*gains))[0]
        assert bool(re < -1e-9) is stable, gains
    re0 = max_real_poles(np.array([[t1, t2]]), 1.0, ControllerMatrices.static(0.2, 0.0, 0.0))[0]
    assert abs(re0) < 1e-9


def test_research_dynamic_controller_on_the_gradient_flow_plant() -> None:
    """In cdqn's sign (its Python loss) stable for Θ2/Θ1 ≤ 1, unstable at 1.2."""
    K = ControllerMatrices(RESEARCH_A, RESEARCH_B, -RESEARCH_C, np.zeros((1, 3)))
    pts = np.array([[300.0, 300.0 * r] for r in (0.8, 0.9, 1.0, 1.2)])
    re = max_real_poles(pts, 1.0, K)
    assert np.all(re[:3] < 0) and re[3] > 10


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
