"""Controllers as used during training: ``reset()`` and ``step(...) -> u``.

All of them return ``u`` in the convention of :mod:`cdqn.control.plant`,
``Q̇1 = Θ1 (r + γ Q̂2 − Q1 + u)``.  One training step advances the learning model by
``Δt = α`` (the learning rate), so dynamic controllers run in discrete time at ``Δt = α``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import scipy.linalg

from cdqn.control.kernels import scheduled_lqr_step, state_space_step, static_gain_u


class RuntimeController(Protocol):
    """What an agent needs from a controller."""

    loss_weight: float
    """Factor ``1/(1+k1)`` of the paper's static-gain loss (1 for other controllers)."""

    def reset(self) -> None: ...

    def step(self, x_e: float, q1: float, q2: float, theta1: float, theta2: float) -> float: ...


class NoControl:
    """u = 0: plain semi-gradient deep Q-learning."""

    loss_weight = 1.0

    def reset(self) -> None:
        pass

    def step(self, x_e: float, q1: float, q2: float, theta1: float, theta2: float) -> float:
        return 0.0


class StaticGain:
    """``u = −k1 Q1 − k2 Q2 + k3 x_e`` (paper Sec. 4.3, fixed-structure H∞)."""

    def __init__(self, k1: float, k2: float, k3: float) -> None:
        if k1 <= -1.0:
            raise ValueError(f"k1={k1}: the loss 1/(2(1+k1))(...)^2 needs k1 > -1")
        self.k1, self.k2, self.k3 = float(k1), float(k2), float(k3)
        self.loss_weight = 1.0 / (1.0 + self.k1)

    def reset(self) -> None:
        pass

    def step(self, x_e: float, q1: float, q2: float, theta1: float, theta2: float) -> float:
        return static_gain_u(self.k1, self.k2, self.k3, x_e, q1, q2)


class ScheduledLQR:
    """Gain-scheduled H2: the LQR gains re-solved at every step's (Θ1, Θ2) (paper Sec. 4.1).

    ``gain_map="paper"`` applies ``u = −K x_a`` as the paper writes it,
    ``(k1, k2, k3) = (K_1, K_2, −K_3)``.  ``gain_map="research"`` applies the research
    code's assignment ``(k1, k2, k3) = (−K_3, −K_2, K_1)``, which is not the LQR's closed
    loop on the model but is what produced the paper's H2 results.  ``target``
    (``[γ_eff lo, γ_eff hi, 1 + k1 lo, 1 + k1 hi]``, :mod:`cdqn.control.target`) moves every
    step's (k1, k2) into the learning target.

    Where no stabilising LQR exists at a step's (Θ1, Θ2) (e.g. Θ2 = 0 leaves Q2
    uncontrollable), the previous step's gains are kept and ``unsolved_steps`` counts it.
    """

    def __init__(
        self,
        discount: float,
        w_x: list[float],
        w_c: float,
        gain_map: str = "paper",
        target: np.ndarray | None = None,
    ) -> None:
        if gain_map not in ("paper", "research"):
            raise ValueError(f"controller.h2_gain_map={gain_map!r}: allowed paper, research")
        self.discount = float(discount)
        self.w_x = np.asarray(w_x, dtype=float)
        self.w_c = float(w_c)
        self.research_map = gain_map == "research"
        self.target = np.zeros(0) if target is None else np.asarray(target, dtype=float)
        self._gains = np.zeros(3)
        self.loss_weight = 1.0
        self.unsolved_steps = 0

    @property
    def gains(self) -> tuple[float, float, float]:
        """The gains (k1, k2, k3) of the last step that had an LQR solution."""
        k1, k2, k3 = (float(g) for g in self._gains)
        return k1, k2, k3

    def reset(self) -> None:
        pass

    def step(self, x_e: float, q1: float, q2: float, theta1: float, theta2: float) -> float:
        u, self.loss_weight, solved = scheduled_lqr_step(
            theta1, theta2, self.discount, self.w_x, self.w_c, self.research_map, self.target,
            self._gains, x_e, q1, q2,
        )  # fmt: skip
        if not solved:
            self.unsolved_steps += 1
        return u


def discretize(
    A: np.ndarray, B: np.ndarray, dt: float, method: str
) -> tuple[np.ndarray, np.ndarray]:
    """(A_d, B_d) of ``ẋ = A x + B v`` at step ``dt``.

    ``zoh``: ``A_d = e^{A dt}``, ``B_d = ∫_0^dt e^{Aτ} dτ B`` (exact for piecewise-constant
    inputs); ``tustin``: bilinear ``A_d = (I − A dt/2)^{-1}(I + A dt/2)``,
    ``B_d = (I − A dt/2)^{-1} B dt``; ``euler``: ``A_d = I + A dt``, ``B_d = B dt``
    (the research code's integration, unstable once ``|λ| dt`` approaches 2).
    """
    n, m = B.shape
    if method == "zoh":
        M = np.zeros((n + m, n + m))
        M[:n, :n], M[:n, n:] = A * dt, B * dt
        E = scipy.linalg.expm(M)
        return E[:n, :n], E[:n, n:]
    if method == "tustin":
        lhs = np.eye(n) - A * dt / 2
        return np.linalg.solve(lhs, np.eye(n) + A * dt / 2), np.linalg.solve(lhs, B * dt)
    if method == "euler":
        return np.eye(n) + A * dt, B * dt
    raise ValueError(f"controller.discretization={method!r}: allowed zoh, tustin, euler")


class StateSpace:
    """Dynamic controller ``ẋ_c = A x_c + B v``, ``u = C x_c + D v``, ``v = [x_e, Q1, Q2]``.

    Run in discrete time at ``Δt = α``: ``u_k = C x_k + D v_k``, ``x_{k+1} = A_d x_k + B_d v_k``.
    The state is reset at each episode start when ``reset_state`` (paper Sec. 4.2).
    """

    loss_weight = 1.0

    def __init__(
        self,
        A: np.ndarray,
        B: np.ndarray,
        C: np.ndarray,
        D: np.ndarray | None,
        dt: float,
        method: str = "zoh",
        reset_state: bool = True,
    ) -> None:
        A, B = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(B, float))
        self.C = np.ascontiguousarray(np.asarray(C, float).reshape(-1))
        no_d = D is None or np.size(D) == 0
        self.D = np.zeros(3) if no_d else np.ascontiguousarray(np.asarray(D, float).ravel())
        if B.shape != (A.shape[0], 3) or self.C.shape != (A.shape[0],):
            raise ValueError(
                f"controller matrices must be A n×n, B n×3, C 1×n; got {A.shape}, {B.shape}, "
                f"{self.C.shape}"
            )
        self.Ad, self.Bd = (np.ascontiguousarray(m) for m in discretize(A, B, dt, method))
        self.reset_state = reset_state
        self.x = np.zeros(A.shape[0])

    def reset(self) -> None:
        if self.reset_state:
            self.x[:] = 0.0

    def step(self, x_e: float, q1: float, q2: float, theta1: float, theta2: float) -> float:
        return state_space_step(self.Ad, self.Bd, self.C, self.D, self.x, x_e, q1, q2)
