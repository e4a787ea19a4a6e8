"""The learning target a controller keeps: effective discount and step scale.

A controller changes the fixed point of the learning update, not only its stability.  With
the static law ``u = −k1 Q1 − k2 Q2 + k3 x_e`` (paper Sec. 4.1, 4.3) the TD term of a step is

.. math::  r + (\\gamma - k_2) Q_2 - (1 + k_1) Q_1 + k_3 x_e
           = (1 + k_1)\\Big(\\frac{r}{1 + k_1} + \\gamma_{\\rm eff} Q_2 - Q_1\\Big) + k_3 x_e,
           \\qquad \\gamma_{\\rm eff} = \\frac{\\gamma - k_2}{1 + k_1},

so learning settles where ``Q1 = r/(1+k1) + γ_eff Q2`` (``x_e`` integrates the TD error at
``Δt = α``; reset every episode, or kept across episodes as a slowly adapting bias,
``controller.reset_integrator``): a Bellman equation with the *effective discount* ``γ_eff``,
while ``1 + k1`` (the *step scale*) multiplies every SGD step, ``α(1 + k1)Θ1`` being the
step's gain on Q1.  A robust design that leaves these free trades them for robustness: on
the gradient-flow plant the worst-case H∞ objective is smallest for ``γ_eff → 0`` (the
agent learns the immediate reward only).  So they are design inputs (``weights.target``, or
a controller's own ``weights.controller_target.<controller>``):

* static designs (``hinf_f``, ``h2``) keep ``(γ_eff, 1 + k1)`` in the target box;
* a dynamic design keeps its DC gain from ``[Q1, Q2]`` to ``u``,
  ``K(0) = D − C A^{-1} B``, in the box: ``k1 = −K(0)_{Q1}``, ``k2 = −K(0)_{Q2}``.

Stability over the NTK box bounds what a target may ask: on the gradient-flow plant the fast
mode of the static loop is ``(1 + k1) Θ1 (γ_eff ρ − 1)`` with ``ρ = Θ2/Θ1``, stable only where
``γ_eff ρ < 1``, i.e. ``γ_eff < 1/ρ_max`` for a positive effective discount
(:func:`check_target`).  A gain-scheduled controller sees ρ at every step and can keep
``γ_eff ρ ≤ c < 1`` pointwise (``weights.target.rho_cap = c``): the effective discount is then
the target's where ρ is small and lower only where the step's loop would otherwise be unstable.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from cdqn.config import TARGET_FIELDS, target_key, target_of
from cdqn.control.box import NTKBox
from cdqn.control.errors import DesignError
from cdqn.control.kernels import project_target

if TYPE_CHECKING:
    from cdqn.control.certificate import ControllerMatrices


@dataclass(frozen=True)
class TargetBox:
    """Ranges of the effective discount γ_eff and of the step scale 1 + k1."""

    gamma_eff: tuple[float, float]
    step_scale: tuple[float, float]
    rho_cap: float | None = None
    """Scheduled controllers (h2): cap γ_eff at ``rho_cap/ρ`` at each step (ρ = Θ2/Θ1)."""
    keys: tuple[tuple[str, str], ...] = field(default=(), compare=False)
    """``(range, configuration key)`` of each range (:meth:`of_controller`); a range not
    listed came from ``weights.target``."""

    @classmethod
    def of_controller(cls, weights: Any, controller: str) -> TargetBox:
        """The target the design of ``controller`` keeps: the ranges of
        ``weights.controller_target.<controller>`` that are set, ``weights.target``'s for the
        others (:func:`cdqn.config.target_of`)."""
        box = cls.of(target_of(weights, controller))
        keys = tuple((n, target_key(weights, controller, n)) for n in TARGET_FIELDS)
        return cls(box.gamma_eff, box.step_scale, box.rho_cap, keys)

    def key(self, name: str) -> str:
        """Configuration key of range ``name`` (for the errors that name it)."""
        return dict(self.keys).get(name, f"weights.target.{name}")

    @classmethod
    def of(cls, cfg: Any) -> TargetBox:
        """From ``weights.target`` (a :class:`cdqn.config.LearningTarget` or a dict)."""

        def get(key: str) -> Any:
            return cfg.get(key) if isinstance(cfg, dict) else getattr(cfg, key)

        g, s = get("gamma_eff"), get("step_scale")
        cap = (
            get("rho_cap")
            if (isinstance(cfg, dict) and "rho_cap" in cfg) or hasattr(cfg, "rho_cap")
            else None
        )
        return cls(
            (float(g[0]), float(g[1])),
            (float(s[0]), float(s[1])),
            None if cap is None else float(cap),
        )

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "gamma_eff": list(self.gamma_eff),
            "step_scale": list(self.step_scale),
        }
        if self.rho_cap is not None:
            out["rho_cap"] = self.rho_cap
        return out

    def centre(self) -> tuple[float, float]:
        """(γ_eff, 1 + k1) at the centre of the box."""
        return (0.5 * sum(self.gamma_eff), 0.5 * sum(self.step_scale))

    def distance(self, k1: float, k2: float, discount: float) -> float:
        """0 inside the box, else the distance of (γ_eff, 1 + k1) from it (γ_eff measured in
        units of its range's width, at least 1)."""
        scale = 1.0 + k1
        if scale <= 0.0:
            return 1.0 + self.step_scale[0] - scale
        g = (discount - k2) / scale
        d_s = max(self.step_scale[0] - scale, scale - self.step_scale[1], 0.0)
        width = max(self.gamma_eff[1] - self.gamma_eff[0], 1.0)
        d_g = max(self.gamma_eff[0] - g, g - self.gamma_eff[1], 0.0) / width
        return d_s + d_g

    def array(self) -> np.ndarray:
        """``[γ_eff lo, γ_eff hi, 1 + k1 lo, 1 + k1 hi, ρ cap (0: none)]``, as the compiled
        kernels take it."""
        cap = 0.0 if self.rho_cap is None else self.rho_cap
        return np.array([*self.gamma_eff, *self.step_scale, cap], dtype=float)

    def project(self, k1: float, k2: float, discount: float) -> tuple[float, float]:
        """(k1, k2) moved into the box in the (γ_eff, 1 + k1) coordinates
        (:func:`cdqn.control.kernels.project_target`)."""
        p1, p2 = project_target(float(k1), float(k2), float(discount), self.array(), 0.0)
        return float(p1), float(p2)

    def gains(self, gamma_eff: float, step_scale: float, discount: float) -> tuple[float, float]:
        """(k1, k2) of a point (γ_eff, 1 + k1)."""
        return step_scale - 1.0, discount - gamma_eff * step_scale


def dc_gain(K: ControllerMatrices) -> np.ndarray:
    """``K(0) = D − C A^{-1} B`` from ``[x_e, Q1, Q2]`` to ``u`` (``D`` for a static gain);
    ``inf`` entries where ``A`` is singular (an integrator in the controller)."""
    D = np.asarray(K.D, float).reshape(3)
    if K.nstates == 0:
        return D.copy()
    try:
        return D - (K.C @ np.linalg.solve(K.A, K.B)).reshape(3)
    except np.linalg.LinAlgError:
        return np.full(3, np.inf)


def learning_target(K: ControllerMatrices, discount: float, box: NTKBox, lr: float) -> dict:
    """What a design keeps at DC: ``k1, k2, k3`` (u = −k1 Q1 − k2 Q2 + k3 x_e at DC),
    ``gamma_eff``, ``step_scale`` = 1 + k1, and ``max_step_gain`` = the largest
    ``α (1 + k1) Θ1`` over the box (the SGD step's gain on Q1; near 2 the discrete loop
    reaches its edge)."""
    k3, mk1, mk2 = dc_gain(K)
    k1, k2 = -float(mk1), -float(mk2)
    scale = 1.0 + k1
    g = (discount - k2) / scale if scale != 0 else float("nan")
    return {
        "k1": k1,
        "k2": k2,
        "k3": float(k3),
        "gamma_eff": float(g),
        "step_scale": float(scale),
        "max_step_gain": float(lr * scale * box.theta1[1]),
    }


def stable_over_box(gamma_eff: float, rho_max: float) -> bool:
    """Whether a static loop at effective discount ``γ_eff`` can be stable over a box whose
    ratio Θ2/Θ1 reaches ``ρ_max``: its fast mode ``(1 + k1) Θ1 (γ_eff ρ − 1)`` is stable for
    every ρ of the box only if ``γ_eff ρ_max < 1`` (module docstring)."""
    return gamma_eff * rho_max < 1.0


def check_target(target: TargetBox, box: NTKBox, scheduled: bool = False) -> None:
    """Refuse a target outside ``|γ_eff| ≤ 1`` (the effective Bellman operator expands
    beyond it) and one no controller can keep stable over the box (module docstring): the
    whole γ_eff range at or above ``1/ρ_max`` (for a ``scheduled`` controller with a ρ cap,
    a cap ≥ 1)."""
    lo, hi = target.gamma_eff
    if lo < -1.0 or hi > 1.0:
        raise DesignError(
            f"{target.key('gamma_eff')}={list(target.gamma_eff)}: need -1 <= γ_eff <= 1; the "
            "effective Bellman operator r/(1 + k1) + γ_eff·max Q(s') is a contraction only for "
            "|γ_eff| < 1, and learning that once solved CartPole with γ_eff = −2.5 collapsed "
            "when its episodes stopped terminating (docs/research/learning.md)"
        )
    rho_max = box.ratio[1]
    if scheduled and target.rho_cap is not None:
        if not 0.0 < target.rho_cap < 1.0:
            raise DesignError(
                f"{target.key('rho_cap')}={target.rho_cap}: need 0 < rho_cap < 1 (γ_eff·ρ is "
                "capped there at every step; at 1 or above the step's loop is unstable)"
            )
        return
    if not stable_over_box(target.gamma_eff[0], rho_max):
        raise DesignError(
            f"{target.key('gamma_eff')}={list(target.gamma_eff)} conflicts with the NTK box "
            f"(Θ2/Θ1 up to {rho_max:g}): the learning loop is stable over the box only for "
            f"γ_eff < 1/ρ_max = {1.0 / rho_max:.4g}; lower the effective discount or narrow "
            "the box's ratio range (weights.theta_bounds.ratio)"
        )
