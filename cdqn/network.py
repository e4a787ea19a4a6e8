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

:class:`FastTwoLayer` holds NumPy views that share memory with the torch parameters and
implements the forward pass, the NTK and the semi-gradient SGD step with the gradients
written out by hand:

.. math::  \\partial Q_a/\\partial W_2[a] = h,\\quad \\partial Q_a/\\partial b_2[a] = 1,\\quad
           \\partial Q_a/\\partial b_1 = W_2[a]\\odot[p>0],\\quad
           \\partial Q_a/\\partial W_1 = (W_2[a]\\odot[p>0])\\,x^\\top.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
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


class FastTwoLayer:
    """Hand-derived forward, NTK and SGD step on NumPy views of a :class:`QNetwork`.

    The views share memory with the torch parameters, so a step taken here is seen by
    the module (and by ``state_dict``) without copies.
    """

    def __init__(self, net: QNetwork) -> None:
        self.w1 = net.hidden.weight.detach().numpy()
        self.b1 = net.hidden.bias.detach().numpy()
        self.w2 = net.out.weight.detach().numpy()
        self.b2 = net.out.bias.detach().numpy()
        self.dtype = self.w1.dtype

    def forward(self, x: np.ndarray) -> Forward:
        x = np.asarray(x, dtype=self.dtype)
        p = self.w1 @ x + self.b1
        h = np.maximum(p, 0.0)
        return Forward(x, p, h, self.w2 @ h + self.b2)

    def ntk(self, f1: Forward, a: int, f2: Forward, b: int) -> float:
        """Θ((x1, a), (x2, b)) from two cached forward passes (module docstring)."""
        out_layer = float(f1.h @ f2.h) + 1.0 if a == b else 0.0
        mask = (f1.p > 0) & (f2.p > 0)
        hidden = (float(f1.x @ f2.x) + 1.0) * float(np.sum(self.w2[a] * self.w2[b] * mask))
        return out_layer + hidden

    def sgd_step(self, f: Forward, a: int, scale: float) -> None:
        """θ ← θ + scale · ∂Q_a(x)/∂θ, the semi-gradient step with scale = α·δ."""
        g = self.w2[a] * (f.p > 0)  # ∂Q_a/∂b1, taken before W2 changes
        self.w2[a] += scale * f.h
        self.b2[a] += scale
        self.w1 += np.outer(scale * g, f.x)
        self.b1 += scale * g


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
