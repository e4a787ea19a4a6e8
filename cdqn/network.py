"""The paper's Q-network and its neural tangent kernel in closed form.

The network is the two-layer fully connected ReLU network of the paper (Sec. 6),

.. math::  Q(x) = W_2\\,\\mathrm{relu}(W_1 x + b_1) + b_2 \\in \\mathbb{R}^{|\\mathcal{A}|}.

Its NTK (paper Definition 1) between the outputs ``a`` at ``x`` and ``b`` at ``y`` is the
inner product of the parameter gradients, which for this architecture is, with
``p = W_1 x + b_1``, ``h = relu(p)`` and ``q = W_1 y + b_1``, ``g = relu(q)``,

.. math::  \\Theta((x,a),(y,b)) = [a=b]\\,(h\\cdot g + 1)
           + (x\\cdot y + 1) \\sum_j W_2[a,j]\\,W_2[b,j]\\,[p_j>0]\\,[q_j>0].

The first term is the gradient w.r.t. ``(W_2[a], b_2[a])``, the second w.r.t.
``(W_1, b_1)``.  It costs O(width) per pair and needs no backward pass.

:class:`StackedTwoLayer` holds the parameters of ``K`` such networks stacked along a
leading axis (a population of seeds) and implements the forward pass, the NTK and the
semi-gradient SGD step with the gradients written out by hand:

.. math::  \\partial Q_a/\\partial W_2[a] = h,\\quad \\partial Q_a/\\partial b_2[a] = 1,\\quad
           \\partial Q_a/\\partial b_1 = W_2[a]\\odot[p>0],\\quad
           \\partial Q_a/\\partial W_1 = (W_2[a]\\odot[p>0])\\,x^\\top.

With ``g = W_2[a]\\odot[p>0]`` the NTK's hidden-layer sum is ``g\\cdot(W_2[b]\\odot[q>0])``,
so Θ1, Θ2 and the step share one masked row.  :class:`FastTwoLayer` is the same code on
a stack of one whose arrays are views of a :class:`QNetwork`'s parameters, so a single run
and a member of a population compute bit-identical numbers (every operation acts on each
member's slice alone, through the same kernels).  ``W_1`` is kept input-major (the torch
parameter ``hidden.weight`` has strides ``(1, width)``, the NumPy view ``W_1^\\top`` is
contiguous), so the rank-one update ``W_1 += s\\,g\\,x^\\top`` streams rows of length
``width`` instead of ``width`` rows of length ``n_obs``; the updates of ``W_1``, ``W_2[a]`` and
``b_1`` are BLAS ``ger``/``axpy`` calls that modify the parameters in place, one pass each.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from scipy.linalg.blas import get_blas_funcs
from torch import nn

DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class NetworkSpec:
    """What is needed to rebuild a trained network."""

    n_obs: int
    n_actions: int
    width: int
    dtype: str = "float64"


class QNetwork(nn.Module):
    """Two-layer ReLU Q-network with biases (paper Sec. 6); one output per action."""

    def __init__(self, spec: NetworkSpec) -> None:
        super().__init__()
        if spec.dtype not in DTYPES:
            raise ValueError(f"network.dtype={spec.dtype!r}: allowed {sorted(DTYPES)}")
        self.spec = spec
        dtype = DTYPES[spec.dtype]
        self.hidden = nn.Linear(spec.n_obs, spec.width, bias=True, dtype=dtype)
        self.out = nn.Linear(spec.width, spec.n_actions, bias=True, dtype=dtype)
        # Same values, input-major memory (module docstring): W1ᵀ is contiguous.
        w1 = self.hidden.weight.detach()
        self.hidden.weight = nn.Parameter(w1.t().contiguous().t())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(torch.relu(self.hidden(x)))


def ntk(net: QNetwork, x: torch.Tensor, a: int, y: torch.Tensor, b: int) -> float:
    """Closed-form NTK Θ((x, a), (y, b)) of :class:`QNetwork` (module docstring)."""
    w1, b1 = net.hidden.weight.detach(), net.hidden.bias.detach()
    w2 = net.out.weight.detach()
    p, q = w1 @ x + b1, w1 @ y + b1
    h, g = torch.relu(p), torch.relu(q)
    out_layer = (torch.dot(h, g) + 1.0) if a == b else torch.zeros((), dtype=x.dtype)
    mask = (p > 0) & (q > 0)
    hidden_layer = (torch.dot(x, y) + 1.0) * torch.sum(w2[a] * w2[b] * mask)
    return float(out_layer + hidden_layer)


def ntk_autograd(net: QNetwork, x: torch.Tensor, a: int, y: torch.Tensor, b: int) -> float:
    """NTK by its definition, ∂Q_a(x)/∂θ · ∂Q_b(y)/∂θ, with ``torch.func`` (for tests)."""
    params = {k: v.detach() for k, v in net.named_parameters()}

    def q(p: dict[str, torch.Tensor], inp: torch.Tensor, act: int) -> torch.Tensor:
        return torch.func.functional_call(net, p, (inp,))[act]

    gx = torch.func.grad(q)(params, x, a)
    gy = torch.func.grad(q)(params, y, b)
    return float(sum(torch.sum(gx[k] * gy[k]) for k in params))


class Forward(NamedTuple):
    """Cached forward pass at one input: pre-activation, activation and Q-values."""

    x: np.ndarray
    p: np.ndarray
    h: np.ndarray
    q: np.ndarray


class StackedForward(NamedTuple):
    """Forward passes of ``K`` stacked networks, one input each: shapes ``(K, n_obs)``,
    ``(K, width)``, ``(K, width)``, ``(K, n_actions)``."""

    x: np.ndarray
    p: np.ndarray
    h: np.ndarray
    q: np.ndarray


class TDTerms(NamedTuple):
    """What one controlled step needs from the network, per member (shapes ``(K,)``)."""

    theta1: np.ndarray
    """Θ1 = Θ((s, a), (s, a))."""
    theta2: np.ndarray
    """Θ2 = Θ((s, a), (s', a'))."""
    grad_b1: np.ndarray
    """``∂Q_a(s)/∂b_1 = W_2[a] ⊙ [p > 0]``, shape ``(K, width)``, reused by the step."""


def _rowdot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise inner products of ``(K, n)`` arrays, one BLAS dot per row."""
    return (u[:, None, :] @ v[:, :, None])[:, 0, 0]


class StackedTwoLayer:
    """``K`` two-layer ReLU Q-networks with stacked parameters and hand-derived forward,
    NTK and semi-gradient SGD step (module docstring).

    Arrays: ``w1t`` ``(K, n_obs, width)`` (``W_1^⊤``), ``b1`` ``(K, width)``, ``w2``
    ``(K, n_actions, width)``, ``b2`` ``(K, n_actions)``; they may be views of torch
    parameters.  Every operation treats each member's slice on its own, so member ``k``'s
    numbers do not depend on ``K`` or on the other members.
    """

    def __init__(self, w1t: np.ndarray, b1: np.ndarray, w2: np.ndarray, b2: np.ndarray) -> None:
        self.w1t, self.b1, self.w2, self.b2 = w1t, b1, w2, b2
        self.dtype = w1t.dtype
        self.rows = np.arange(len(w1t))
        self._blas = get_blas_funcs(("ger", "axpy"), (w1t,))
        """In-place rank-one update and axpy: one pass over each member's parameters."""

    @classmethod
    def from_networks(cls, nets: list[QNetwork]) -> StackedTwoLayer:
        """Copy the parameters of ``nets`` into fresh stacked arrays."""
        return cls(
            np.stack([n.hidden.weight.detach().numpy().T for n in nets]),
            np.stack([n.hidden.bias.detach().numpy() for n in nets]),
            np.stack([n.out.weight.detach().numpy() for n in nets]),
            np.stack([n.out.bias.detach().numpy() for n in nets]),
        )

    def __len__(self) -> int:
        return len(self.w1t)

    def select(self, keep: np.ndarray) -> None:
        """Keep only the members ``keep`` (indices or mask), in that order."""
        self.w1t, self.b1 = self.w1t[keep], self.b1[keep]
        self.w2, self.b2 = self.w2[keep], self.b2[keep]
        self.rows = np.arange(len(self.w1t))

    def copy_to(self, k: int, net: QNetwork) -> None:
        """Write member ``k``'s parameters into ``net``."""
        with torch.no_grad():
            net.hidden.weight.copy_(torch.from_numpy(self.w1t[k].T))
            net.hidden.bias.copy_(torch.from_numpy(self.b1[k]))
            net.out.weight.copy_(torch.from_numpy(self.w2[k]))
            net.out.bias.copy_(torch.from_numpy(self.b2[k]))

    def forward(self, x: np.ndarray) -> StackedForward:
        """``p = W_1 x + b_1``, ``h = relu(p)``, ``Q = W_2 h + b_2`` for inputs ``(K, n_obs)``."""
        x = np.asarray(x, dtype=self.dtype)
        p = (x[:, None, :] @ self.w1t)[:, 0, :] + self.b1
        h = np.maximum(p, 0.0)
        q = (self.w2 @ h[:, :, None])[:, :, 0] + self.b2
        return StackedForward(x, p, h, q)

    def td_terms(
        self, f1: StackedForward, a: np.ndarray, f2: StackedForward, b: np.ndarray
    ) -> TDTerms:
        """Θ1 = Θ((x1,a),(x1,a)), Θ2 = Θ((x1,a),(x2,b)) and ``∂Q_a/∂b_1`` (module docstring)."""
        g = self.w2[self.rows, a] * (f1.p > 0.0)
        g2 = self.w2[self.rows, b] * (f2.p > 0.0)
        theta1 = _rowdot(f1.h, f1.h) + 1.0 + (_rowdot(f1.x, f1.x) + 1.0) * _rowdot(g, g)
        out = np.where(a == b, _rowdot(f1.h, f2.h) + 1.0, 0.0)
        theta2 = out + (_rowdot(f1.x, f2.x) + 1.0) * _rowdot(g, g2)
        return TDTerms(theta1, theta2, g)

    def ntk(
        self, f1: StackedForward, a: np.ndarray, f2: StackedForward, b: np.ndarray
    ) -> np.ndarray:
        """Θ((x1, a), (x2, b)) per member (module docstring)."""
        g = self.w2[self.rows, a] * (f1.p > 0.0)
        g2 = self.w2[self.rows, b] * (f2.p > 0.0)
        out = np.where(a == b, _rowdot(f1.h, f2.h) + 1.0, 0.0)
        return out + (_rowdot(f1.x, f2.x) + 1.0) * _rowdot(g, g2)

    def sgd_step(
        self, f: StackedForward, a: np.ndarray, scale: np.ndarray, grad_b1: np.ndarray
    ) -> None:
        """θ ← θ + scale · ∂Q_a(x)/∂θ per member: the semi-gradient step, scale = α·δ.

        ``grad_b1`` is ``∂Q_a/∂b_1`` at the parameters ``f`` was computed with
        (:attr:`TDTerms.grad_b1`).
        """
        ger, axpy = self._blas
        for k, (s, ak) in enumerate(zip(scale.tolist(), a.tolist(), strict=True)):
            axpy(f.h[k], self.w2[k, ak], a=s)  # W2[a] += s·h        (in place)
            self.b2[k, ak] += s
            ger(s, grad_b1[k], f.x[k], a=self.w1t[k].T, overwrite_a=1)  # W1 += s·g xᵀ
            axpy(grad_b1[k], self.b1[k], a=s)  # b1 += s·g


class FastTwoLayer:
    """:class:`StackedTwoLayer` on a stack of one whose arrays are views of a
    :class:`QNetwork`'s parameters.

    A step taken here is seen by the module (and by ``state_dict``) without copies.
    """

    def __init__(self, net: QNetwork) -> None:
        w1t = net.hidden.weight.detach().numpy().T
        if not w1t.flags.c_contiguous:
            raise ValueError(
                "FastTwoLayer needs hidden.weight in QNetwork's input-major layout "
                "(strides (1, width)); build the network with QNetwork(spec)"
            )
        self.stack = StackedTwoLayer(
            w1t[None],
            net.hidden.bias.detach().numpy()[None],
            net.out.weight.detach().numpy()[None],
            net.out.bias.detach().numpy()[None],
        )
        self.w1 = w1t.T
        self.b1 = self.stack.b1[0]
        self.w2 = self.stack.w2[0]
        self.b2 = self.stack.b2[0]
        self.dtype = self.stack.dtype

    def forward(self, x: np.ndarray) -> Forward:
        f = self.stack.forward(np.asarray(x, dtype=self.dtype)[None])
        return Forward(f.x[0], f.p[0], f.h[0], f.q[0])

    def td_terms(self, f1: Forward, a: int, f2: Forward, b: int) -> tuple[float, float, np.ndarray]:
        """(Θ1, Θ2, ∂Q_a/∂b_1) of one controlled step (:meth:`StackedTwoLayer.td_terms`)."""
        t = self.stack.td_terms(_stacked(f1), np.array([a]), _stacked(f2), np.array([b]))
        return float(t.theta1[0]), float(t.theta2[0]), t.grad_b1

    def ntk(self, f1: Forward, a: int, f2: Forward, b: int) -> float:
        """Θ((x1, a), (x2, b)) from two cached forward passes (module docstring)."""
        return float(self.stack.ntk(_stacked(f1), np.array([a]), _stacked(f2), np.array([b]))[0])

    def sgd_step(self, f: Forward, a: int, scale: float, grad_b1: np.ndarray | None = None) -> None:
        """θ ← θ + scale · ∂Q_a(x)/∂θ, the semi-gradient step with scale = α·δ."""
        if grad_b1 is None:
            grad_b1 = (self.w2[a] * (f.p > 0.0))[None]
        self.stack.sgd_step(_stacked(f), np.array([a]), np.array([scale]), grad_b1)

    def forward_batch(self, x: np.ndarray) -> Forward:
        """Forward passes at the rows of ``x`` ``(B, n_obs)``: fields of shape ``(B, ·)``.

        ``p`` is not kept (``p > 0`` iff ``h > 0``); the field holds ``h``.
        """
        x = np.asarray(x, dtype=self.dtype)
        h = x @ self.stack.w1t[0]
        h += self.b1
        np.maximum(h, 0.0, out=h)
        q = h @ self.w2.T
        q += self.b2
        return Forward(x, h, h, q)

    def minibatch_step(
        self, f: Forward, actions: np.ndarray, target: np.ndarray, lr: float
    ) -> float:
        """One SGD step on ``L = ½ Σ_i (target_i − Q_{a_i}(x_i))²`` (targets held constant)
        from the batch forward pass ``f``; returns ``L`` before the step.

        With ``δ_i = target_i − Q_{a_i}(x_i)`` and ``G`` the ``(B, n_actions)`` matrix with
        ``G[i, a_i] = δ_i``, ``−∂L/∂θ`` is (module docstring, summed over the batch)

        .. math::  \\Delta W_2 = G^\\top H,\\ \\Delta b_2 = \\textstyle\\sum_i G_i,\\quad
                   D = (G W_2)\\odot[P>0],\\ \\Delta W_1^\\top = X^\\top D,\\
                   \\Delta b_1 = \\textstyle\\sum_i D_i,

        all taken at the current parameters, then ``θ ← θ + lr·Δθ`` (torch's SGD step on L).
        """
        rows = np.arange(len(actions))
        delta = target - f.q[rows, actions]
        g = np.zeros_like(f.q)
        g[rows, actions] = delta
        d = g @ self.w2
        d *= f.h > 0.0
        self.w2 += lr * (g.T @ f.h)
        self.b2 += lr * g.sum(axis=0)
        self.stack.w1t[0] += lr * (f.x.T @ d)
        self.b1 += lr * d.sum(axis=0)
        return 0.5 * float(delta @ delta)


def _stacked(f: Forward) -> StackedForward:
    return StackedForward(f.x[None], f.p[None], f.h[None], f.q[None])


def save_network(net: QNetwork, directory: Path) -> None:
    """Write ``q_network.pt`` (state dict) and ``spec.json`` into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), directory / "q_network.pt")
    (directory / "spec.json").write_text(json.dumps(asdict(net.spec)))


def load_network(directory: Path) -> QNetwork:
    """Inverse of :func:`save_network`."""
    spec = NetworkSpec(**json.loads((Path(directory) / "spec.json").read_text()))
    net = QNetwork(spec)
    net.load_state_dict(torch.load(Path(directory) / "q_network.pt", weights_only=True))
    return net
