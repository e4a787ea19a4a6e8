"""Uncertainty cover: overbounds the sampled relative errors at every grid frequency."""

from __future__ import annotations

import numpy as np
import pytest

from cdqn.control.box import NTKBox
from cdqn.control.errors import DesignError
from cdqn.control.uncertainty import fit_cover, noise_cover, relative_errors

PAPER_BOX = NTKBox((200.0, 500.0), (0.8, 1.2), (316.2, 316.2))


@pytest.mark.parametrize("plant", ["gradient_flow", "paper"])
@pytest.mark.parametrize("order", [0, 1, 2])
def test_cover_overbounds_every_grid_frequency(order: int, plant: str) -> None:
    samples = PAPER_BOX.sample(200, seed=0)
    cover = fit_cover(samples, PAPER_BOX.nominal, 1.0, (1.0, 1e5), order, plant=plant)
    errors = relative_errors(samples, PAPER_BOX.nominal, 1.0, cover.omega, plant)
    w = cover.weight.mag(cover.omega)
    assert np.all(w[None, :] >= errors), "the cover must lie above every sample everywhere"
    assert cover.margin >= 1.0
    # stable and minimum phase
    den_roots = np.roots(cover.weight.den) if len(cover.weight.den) > 1 else np.zeros(0)
    num_roots = np.roots(cover.weight.num) if len(cover.weight.num) > 1 else np.zeros(0)
    assert np.all(den_roots.real < 0) and np.all(num_roots.real < 0)


def test_cover_is_tight_in_the_mean() -> None:
    samples = PAPER_BOX.sample(200, seed=0)
    c2 = fit_cover(samples, PAPER_BOX.nominal, 1.0, (1.0, 1e5), 2)
    c0 = fit_cover(samples, PAPER_BOX.nominal, 1.0, (1.0, 1e5), 0)
    gap2 = np.mean(np.log(c2.weight.mag(c2.omega) / c2.bound))
    gap0 = np.mean(np.log(c0.weight.mag(c0.omega) / c0.bound))
    assert gap2 < gap0  # a dynamic weight follows the 1/ω growth the constant cannot


@pytest.mark.parametrize("plant", ["gradient_flow", "paper"])
def test_relative_error_grows_at_low_frequency_near_ratio_one_over_gamma(plant: str) -> None:
    """With γ = 1 a plant with Θ2 = Θ1 has a pole (paper: a double pole) at 0: σ̄(E) ~ 1/ω."""
    omega = np.array([1e-3, 1e-2, 1e-1])
    err = relative_errors(np.array([[300.0, 300.0]]), (300.0, 240.0), 1.0, omega, plant)[0]
    assert err[0] > 5 * err[1] > 25 * err[2]


def test_gradient_flow_relative_error_is_the_smallest_multiplicative_one() -> None:
    """The gradient-flow plant P = g [1, 1] has rank one; E = (g_i − g_0) g_0ᴴ/‖g_0‖² gives
    P_i = (I + E) P_0 exactly, with σ̄(E) = ‖g_i − g_0‖/‖g_0‖."""
    from cdqn.control.plant import io_freqresp, io_plant

    omega = np.array([1.0, 30.0, 1e3])
    pts = np.array([[250.0, 280.0], [450.0, 400.0]])
    P = io_freqresp(pts, 1.0, omega)
    P0 = io_freqresp(np.array([PAPER_BOX.nominal]), 1.0, omega)[0]
    err = relative_errors(pts, PAPER_BOX.nominal, 1.0, omega)
    for i in range(len(pts)):
        for w in range(len(omega)):
            g, g0 = P[i, w, :, 0], P0[w, :, 0]
            E = np.outer(g - g0, g0.conj()) / np.vdot(g0, g0).real
            np.testing.assert_allclose((np.eye(2) + E) @ P0[w], P[i, w], rtol=1e-10, atol=1e-14)
            assert np.linalg.svd(E, compute_uv=False)[0] == pytest.approx(err[i, w], rel=1e-10)
        # the closed form equals the state-space frequency response (the mode at 0 cancels)
        A, B = io_plant(*pts[i], 1.0)
        H = np.linalg.solve(1j * omega[1] * np.eye(2) - A, B)
        np.testing.assert_allclose(H, P[i, 1], rtol=1e-10)


def test_noise_cover_is_the_constant_levels() -> None:
    w1, w2 = noise_cover((0.2, 0.5))
    assert w1.mag(np.array([1.0, 1e6]))[1] == pytest.approx(0.2)
    assert w2.mag(np.array([1e-3]))[0] == pytest.approx(0.5)


def test_cover_errors() -> None:
    samples = PAPER_BOX.sample(20, seed=0)
    with pytest.raises(DesignError, match="synthesis.band"):
        fit_cover(samples, PAPER_BOX.nominal, 1.0, (10.0, 1.0), 2)
    with pytest.raises(DesignError, match="cover order"):
        fit_cover(samples, PAPER_BOX.nominal, 1.0, (1.0, 10.0), -1)
    with pytest.raises(DesignError, match="noise"):
        noise_cover((0.2,))
