"""NTK bounds of the actual network and environment (paper Sec. 3, Remark "Boundedness of
the parametric uncertainty", Fig. NTK_range).

The initial network is rolled out under the configured ε-greedy exploration, without
learning; on every transition ``(s, a, s')`` the closed-form NTK
(:meth:`cdqn.network.FastTwoLayer.ntk`) gives

.. math::  \\Theta_1 = \\Theta((s,a),(s,a)),\\qquad
           \\Theta_2 = \\Theta((s,a),(s',a')),\\quad a' = \\arg\\max_b Q(s', b),

and the box is the ``[q_lo, q_hi]`` quantile range of Θ1 and of ρ = Θ2/Θ1, rounded outward
to two significant digits (Θ1) and to ``RATIO_STEP`` (ρ) so that networks of the same kind
share one design (and one cache entry).  The nominal point is the median (Θ1, ρ).

The ratio's rounding is fine because ρ_max bounds the learning target: a static design is
stable over the box only for γ_eff < 1/ρ_max (:func:`cdqn.control.target.check_target`),
and on normalised observations ρ often stays within 1 ± 0.002, where a goal task needs
γ_eff ≈ 0.99.  Rounded to 0.005, such a box keeps γ_eff up to 0.995.

Transitions whose greedy next action differs from ``a`` have Θ2 ≈ 0 at initialisation (the
output-layer term vanishes and the hidden-layer term averages out): about half of them.
They leave Q2 unmoved by the update (Q̇2 = Θ2·(…) ≈ 0) and are left out of the ratio range
(``ratio_floor``); their share is reported.  At Θ2 = 0 exactly Q2 does not move at all: on the
paper's plant its mode (eigenvalue 0) is uncontrollable, so no controller makes that point
asymptotically stable; on the gradient-flow plant it is the conserved quantity
``Θ2 Q1 − Θ1 Q2 = −Θ1 Q2`` that every loop keeps constant (:mod:`cdqn.control.plant`).

This module uses torch; :mod:`cdqn.control` does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from cdqn.agents.base import EpsilonGreedy
from cdqn.config import BOXED_CONTROLLERS, Config, TrainConfig
from cdqn.control.box import NTKBox
from cdqn.control.errors import DesignError
from cdqn.envs import make_env
from cdqn.network import FastTwoLayer, QNetwork

RATIO_STEP = 0.005
"""Outward rounding of the measured Θ2/Θ1 range (module docstring)."""


@dataclass
class MeasuredBounds:
    """The measured box and the NTK samples it summarises."""

    box: NTKBox
    samples: np.ndarray
    """Rows (Θ1, Θ2) of every transition of the rollout."""
    quantiles: tuple[float, float]
    """Quantiles of Θ1 and Θ2/Θ1 that define the box."""
    share_below_floor: float = 0.0
    """Share of transitions with Θ2/Θ1 below the ratio floor (left out of the ratio range)."""


def _round_out(lo: float, hi: float, step: float | None) -> tuple[float, float]:
    if step is None:  # two significant digits, outward

        def down(x: float) -> float:
            e = 10.0 ** (math.floor(math.log10(x)) - 1)
            return float(math.floor(x / e) * e)

        def up(x: float) -> float:
            e = 10.0 ** (math.floor(math.log10(x)) - 1)
            return float(math.ceil(x / e) * e)

        return down(lo), up(hi)
    return round(math.floor(lo / step) * step, 10), round(math.ceil(hi / step) * step, 10)


def rollout_ntk(
    env: gym.Env, net: QNetwork, train: TrainConfig, steps: int, seed: int
) -> np.ndarray:
    """(Θ1, Θ2) on ``steps`` transitions of the initial network under ε-greedy exploration."""
    fast = FastTwoLayer(net)
    explorer = EpsilonGreedy(train, net.spec.n_actions, np.random.default_rng(seed + 7919))
    out = np.empty((steps, 2))
    obs, _ = env.reset(seed=seed + 7919)
    for t in range(steps):
        f1 = fast.forward(obs)
        explored = explorer.explore()
        action = int(np.argmax(f1.q)) if explored is None else explored
        next_obs, _, terminated, truncated, _ = env.step(action)
        f2 = fast.forward(next_obs)
        a2 = int(np.argmax(f2.q))
        out[t] = fast.ntk(f1, action, f1, action), fast.ntk(f1, action, f2, a2)
        obs = next_obs
        if terminated or truncated:
            obs, _ = env.reset()
    return out


def summarise(
    samples: np.ndarray, quantiles: tuple[float, float], ratio_floor: float = 0.05
) -> NTKBox:
    """The rounded quantile box of NTK samples (module docstring); the ratio range is taken
    over the transitions with ``Θ2/Θ1 ≥ ratio_floor``."""
    q_lo, q_hi = quantiles
    if not 0 <= q_lo < q_hi <= 1:
        raise DesignError(f"synthesis.quantiles={[q_lo, q_hi]}: need 0 <= lower < upper <= 1")
    t1 = samples[:, 0]
    rho_all = samples[:, 1] / t1
    rho = rho_all[rho_all >= ratio_floor]
    if rho.size == 0:
        raise DesignError(
            f"infeasible NTK box: no transition has Θ2/Θ1 >= synthesis.ratio_floor={ratio_floor}"
        )
    t1_lo, t1_hi = (float(v) for v in np.quantile(t1, [q_lo, q_hi]))
    r_lo, r_hi = (float(v) for v in np.quantile(rho, [q_lo, q_hi]))
    if t1_lo <= 0 or r_lo <= 0:
        raise DesignError(
            f"infeasible NTK box: measured Θ1 in [{t1_lo:.4g}, {t1_hi:.4g}], Θ2/Θ1 in "
            f"[{r_lo:.4g}, {r_hi:.4g}]; the designs need Θ1 > 0 and Θ2/Θ1 > 0 over the box "
            "(narrow synthesis.quantiles or give the box in weights.theta_bounds)"
        )
    theta1 = _round_out(t1_lo, t1_hi, None)
    ratio = _round_out(r_lo, r_hi, RATIO_STEP)
    t1_nom = float(np.clip(np.median(t1), *theta1))
    r_nom = float(np.clip(np.median(rho), *ratio))
    return NTKBox(theta1, ratio, (t1_nom, t1_nom * r_nom), source="measured")


def measure_bounds(
    env: gym.Env,
    net: QNetwork,
    train: TrainConfig,
    steps: int,
    quantiles: tuple[float, float],
    seed: int,
    ratio_floor: float = 0.05,
) -> MeasuredBounds:
    """Roll out ``net`` in ``env`` and summarise the NTK as a box (module docstring)."""
    samples = rollout_ntk(env, net, train, steps, seed)
    rho = samples[:, 1] / samples[:, 0]
    box = summarise(samples, quantiles, ratio_floor)
    return MeasuredBounds(box, samples, quantiles, float(np.mean(rho < ratio_floor)))


def measured_box(conf: Config, net: QNetwork) -> NTKBox | None:
    """The run's measured NTK box when ``controller.design=synthesize`` and
    ``controller.synthesis.ntk_bounds=measured`` for a synthesised controller, else None.

    The rollout uses its own environment instance and random stream and does not change
    the network, so the run's own random streams are untouched."""
    ctrl = conf.controller
    if ctrl.design != "synthesize" or ctrl.name not in BOXED_CONTROLLERS:
        return None
    syn = ctrl.synthesis
    if syn.ntk_bounds == "config":
        return None
    if syn.ntk_bounds != "measured":
        raise DesignError(
            f"controller.synthesis.ntk_bounds={syn.ntk_bounds!r}: allowed config, measured"
        )
    env = make_env(conf.env)
    try:
        measured = measure_bounds(
            env,
            net,
            conf.train,
            syn.rollout_steps,
            (float(syn.quantiles[0]), float(syn.quantiles[1])),
            conf.seed,
            syn.ratio_floor,
        )
    finally:
        env.close()
    return measured.box
