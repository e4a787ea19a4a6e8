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
``width``.  The forward pass, Θ1/Θ2 and the step are three compiled loops (numba) over the
members and hidden units, each one pass over the parameters: no temporaries, no per-call
overhead of a dozen array operations.

**Zero inputs.**  Every product with ``x``, the pass ``p = b_1 + Σ_i x_i W_1ᵀ[i]`` and the
step's ``W_1ᵀ[i] += s x_i g``, runs over the inputs with ``x_i ≠ 0`` only, decided input by
input: a one-hot observation (:class:`cdqn.envs.OneHot`, Taxi's 500 states) costs one row
of ``W_1ᵀ`` instead of 500, a dense one (CartPole) every row as before.  While the
parameters are finite this changes no bit: ``p_j + W_1ᵀ[i, j]·0 = p_j`` and
``W_1ᵀ[i, j] + 0·g_j = W_1ᵀ[i, j]``, and the sums over the other inputs keep their order.
Double DQN's minibatch step does the same per minibatch (:mod:`cdqn.ddqn_kernels`).

**Bundles.**  The kernels take their arrays in small NamedTuples: a network's parameters
(:class:`Params`), a forward pass (:class:`Forward`, :class:`StackedForward`), a deferred
``W_1`` update (:class:`Pending`, :class:`StackedPending`); the agents add theirs.  A
NamedTuple is a tuple: compiled code reads its fields by name from the same arrays, so the
memory and the arithmetic are those of the arrays passed one by one.  The kernels called
from Python take their bundles as plain tuples (``tuple(bundle)``, fields in the bundle's
order) and name them on entry (``Params(*net)``): numba types a plain tuple argument in C,
a NamedTuple in Python, which costs about 2 µs per bundle and call, a tenth of a
population member's step.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from numba import njit
from torch import nn

if TYPE_CHECKING:
    from cdqn.ddqn_kernels import JitOptions


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


def gradient_step(net: nn.Module, loss: torch.Tensor, lr: float) -> None:
    """One step of plain gradient descent on ``loss``, θ ← θ − α ∂L/∂θ (paper Eq.
    theta_update, Sec. 2.1; ``torch.optim.SGD`` without momentum or decay takes the same step,
    ``p.add_(grad, alpha=-lr)``, but its first use imports ``torch._dynamo``, two seconds of
    every run's start).  The gradients are not stored on the parameters (``.grad`` stays None)."""
    params = [p for p in net.parameters() if p.requires_grad]
    grads = torch.autograd.grad(loss, params)
    with torch.no_grad():
        for p, g in zip(params, grads, strict=True):
            p.add_(g, alpha=-lr)


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


class Params(NamedTuple):
    """A network's parameters as the kernels take them: ``w1t`` (``W_1^⊤``, ``(n_obs, width)``),
    ``b1`` ``(width,)``, ``w2`` ``(n_actions, width)``, ``b2`` ``(n_actions,)`` of one
    member, or of a stack with a leading member axis."""

    w1t: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray


class Forward(NamedTuple):
    """Cached forward pass at one input: input, pre-activation ``p`` and Q-values
    (the activation ``relu(p)`` is recomputed where it is needed)."""

    x: np.ndarray
    p: np.ndarray
    q: np.ndarray


class StackedForward(NamedTuple):
    """Forward passes of ``K`` stacked networks, one input each: shapes ``(K, n_obs)``,
    ``(K, width)``, ``(K, n_actions)``."""

    x: np.ndarray
    p: np.ndarray
    q: np.ndarray


class Pending(NamedTuple):
    """One member's deferred ``W_1`` update ``W_1ᵀ[i] += sx_i g`` (:func:`sgd_deferred_row`):
    ``sx = s x`` ``(n_obs,)``, ``g = ∂Q_a/∂b_1`` ``(width,)`` and whether it is still to be
    applied."""

    sx: np.ndarray
    g: np.ndarray
    pending: bool


class StackedPending(NamedTuple):
    """:class:`Pending` of ``K`` members: shapes ``(K, n_obs)``, ``(K, width)``, ``(K,)``."""

    sx: np.ndarray
    g: np.ndarray
    pending: np.ndarray


class TDTerms(NamedTuple):
    """What one controlled step needs from the network, per member (shapes ``(K,)``)."""

    theta1: np.ndarray
    """Θ1 = Θ((s, a), (s, a))."""
    theta2: np.ndarray
    """Θ2 = Θ((s, a), (s', a'))."""
    grad_b1: np.ndarray
    """``∂Q_a(s)/∂b_1 = W_2[a] ⊙ [p > 0]``, shape ``(K, width)``, reused by the step."""


_JIT: JitOptions = {"cache": True, "fastmath": {"reassoc", "contract"}}
"""Compiled once per process (and cached on disk).  ``reassoc`` lets the sums over the
hidden units run as vectorised partial sums: the same code for every member and every
population size, so a member's numbers never depend on ``K`` (``tests/test_fast_path.py``)."""


_BLOCK = 512
"""Hidden units per block of :func:`forward_row`: the block of ``p`` stays in L1 while every
input's row of ``W_1ᵀ`` passes through it."""


@njit(**_JIT)
def member_params(n, k):
    """Member ``k``'s :class:`Params` of a stack's."""
    return Params(n.w1t[k], n.b1[k], n.w2[k], n.b2[k])


@njit(**_JIT)
def member_pass(f, k):
    """Member ``k``'s :class:`Forward` of a :class:`StackedForward`."""
    return Forward(f.x[k], f.p[k], f.q[k])


@njit(**_JIT)
def member_pending(d, k):
    """Member ``k``'s :class:`Pending` of a :class:`StackedPending`."""
    return Pending(d.sx[k], d.g[k], d.pending[k])


@njit(**_JIT)
def forward_row(n, f):
    """One member (:class:`Params` ``n``): ``f.p = b_1 + Σ_i f.x_i W_1ᵀ[i]``,
    ``f.q = W_2 relu(f.p) + b_2``."""
    forward_pending_row(n, f, Pending(f.x, n.b1, False))


@njit(**_JIT)
def forward_pending_row(n, f, d):
    """:func:`forward_row` with, when ``d.pending``, the ``W_1`` part of the last SGD step
    applied on the way (:func:`sgd_deferred_row`): ``W_1ᵀ[i] += sx_i g`` row by row, each
    element updated as :func:`sgd_row` updates it and then multiplied into ``p``, so one
    pass over ``W_1`` does both.  Per hidden unit ``j`` the sum
    ``p_j = b_1[j] + x_0 W_1ᵀ[0, j] + x_1 W_1ᵀ[1, j] + …`` is taken in input order, as
    unblocked, so the blocks change no bit.

    Rows with ``x_i = 0`` and ``sx_i = 0`` are not read (module docstring, zero inputs)."""
    w1t, b1, x, p = n.w1t, n.b1, f.x, f.p
    sx, g, pending = d
    n_obs, width = w1t.shape
    for j0 in range(0, width, _BLOCK):
        n_j = min(j0 + _BLOCK, width) - j0
        pb, bb = p[j0 : j0 + n_j], b1[j0 : j0 + n_j]
        for jj in range(n_j):
            pb[jj] = bb[jj]
        for i in range(n_obs):
            xi, wi = x[i], w1t[i, j0 : j0 + n_j]
            if pending and sx[i] != 0.0:
                si, gb = sx[i], g[j0 : j0 + n_j]
                if xi != 0.0:
                    for jj in range(n_j):
                        w = wi[jj] + si * gb[jj]
                        wi[jj] = w
                        pb[jj] += w * xi
                else:
                    for jj in range(n_j):
                        wi[jj] = wi[jj] + si * gb[jj]
            elif xi != 0.0:
                for jj in range(n_j):
                    pb[jj] += wi[jj] * xi
    output_row(n.w2, n.b2, p, f.q)


@njit(**_JIT)
def apply_pending_row(w1t, sx, g):
    """The deferred ``W_1ᵀ[i] += sx_i g`` of :func:`sgd_deferred_row`, on its own (the rows
    with ``sx_i ≠ 0``)."""
    for i in range(w1t.shape[0]):
        si, wi = sx[i], w1t[i]
        if si == 0.0:
            continue
        for j in range(w1t.shape[1]):
            wi[j] = wi[j] + si * g[j]


@njit(**_JIT)
def output_row(w2, b2, p, q):
    """One member's output layer: ``q = W_2 relu(p) + b_2``."""
    for a in range(w2.shape[0]):
        acc = 0.0
        for j in range(w2.shape[1]):
            acc += w2[a, j] * max(p[j], 0.0)
        q[a] = acc + b2[a]


@njit(**_JIT)
def td_row(w2, f1, f2, a, b, g):
    """One member, passes ``f1`` at ``x1`` and ``f2`` at ``x2``: ``g = W_2[a] ⊙ [p1 > 0]``
    (written into ``g``) and (Θ1, Θ2) of the module docstring with ``h = relu(p1)``,
    ``h' = relu(p2)``; ``Θ2``'s hidden-layer sum is ``Σ_j g_j W_2[b, j] [p2_j > 0]``."""
    x1, p1, x2, p2 = f1.x, f1.p, f2.x, f2.p
    hh = h12 = gg = gg2 = 0.0
    for j in range(w2.shape[1]):
        h1j, h2j = max(p1[j], 0.0), max(p2[j], 0.0)
        gj = w2[a, j] if p1[j] > 0.0 else 0.0
        g[j] = gj
        hh += h1j * h1j
        h12 += h1j * h2j
        gg += gj * gj
        gg2 += gj * w2[b, j] if p2[j] > 0.0 else 0.0
    xx = x12 = 0.0
    for i in range(x1.shape[0]):
        xx += x1[i] * x1[i]
        x12 += x1[i] * x2[i]
    theta1 = hh + 1.0 + (xx + 1.0) * gg
    theta2 = (h12 + 1.0 if a == b else 0.0) + (x12 + 1.0) * gg2
    return theta1, theta2


@njit(**_JIT)
def sgd_row(n, f, a, s, g, f2, nxt):
    """One member, in place: ``W_2[a] += s relu(p)``, ``b_2[a] += s``, ``W_1ᵀ[i] += (s x_i) g``,
    ``b_1 += s g`` with ``g = ∂Q_a/∂b_1`` at ``x`` (the pass ``f``); then the forward pass
    at ``x2`` with the new parameters from the one with the old parameters (``f2``) into
    ``nxt.p, nxt.q``: ``p' = p2 + s (x·x2 + 1) g`` (exact in real arithmetic),
    ``q' = W_2 relu(p') + b_2``.  ``nxt.p`` may be ``f.p`` or ``f2.p`` (each is read before
    it is written)."""
    w1t, b1, w2, b2 = n
    x, p, x2, p2, p_next = f.x, f.p, f2.x, f2.p, nxt.p
    n_obs, width = w1t.shape
    for j in range(width):
        w2[a, j] += s * max(p[j], 0.0)
    b2[a] += s
    xx2 = 0.0
    for i in range(n_obs):
        sx = s * x[i]
        xx2 += x[i] * x2[i]
        if sx != 0.0:  # a row with x_i = 0 (or s = 0) stays as it is
            for j in range(width):
                w1t[i, j] += sx * g[j]
    for j in range(width):
        b1[j] += s * g[j]
    c = s * (xx2 + 1.0)
    for j in range(width):
        p_next[j] = p2[j] + c * g[j]
    output_row(w2, b2, p_next, nxt.q)


@njit(cache=True, fastmath={"contract"})
def _dot_in_order(x, y):
    """``Σ_i x_i y_i`` accumulated in index order (no reassociation: :func:`sgd_row`'s
    outer loop over the inputs sums ``x·x2`` in this order)."""
    acc = 0.0
    for i in range(x.shape[0]):
        acc += x[i] * y[i]
    return acc


@njit(**_JIT)
def sgd_deferred_row(n, f, a, s, f2, nxt, d):
    """:func:`sgd_row` with ``g = d.g`` except for ``W_1``: its update ``W_1ᵀ[i] += sx_i g``
    is left pending (``d.sx = s x`` written; the caller marks it pending) for
    :func:`forward_pending_row` or :func:`apply_pending_row`; the forward pass at ``x2``
    with the new parameters does not read ``W_1``."""
    b1, w2, b2, x, p, g, p_next = n.b1, n.w2, n.b2, f.x, f.p, d.g, nxt.p
    b2[a] += s
    for i in range(x.shape[0]):
        d.sx[i] = s * x[i]
    c = s * (_dot_in_order(x, f2.x) + 1.0)
    wa, p2 = w2[a], f2.p
    # each element's operations as sgd_row's; three loops, as there, since one loop over the
    # six arrays (any of which may alias another for the compiler) is not vectorised
    for j in range(b1.shape[0]):
        wa[j] += s * max(p[j], 0.0)
    for j in range(b1.shape[0]):
        b1[j] += s * g[j]
    for j in range(b1.shape[0]):
        p_next[j] = p2[j] + c * g[j]
    output_row(w2, b2, p_next, nxt.q)


@njit(**_JIT)
def _forward_kernel(net, passes, rows):
    """:func:`forward_row` of the members ``rows`` (bundles as plain tuples: module
    docstring)."""
    n, f = Params(*net), StackedForward(*passes)
    for k in rows:
        forward_row(member_params(n, k), member_pass(f, k))


@njit(**_JIT)
def _td_kernel(w2, passes1, passes2, a, b, g, theta):
    """:func:`td_row` of every member into ``g[k]`` and ``theta[k]``."""
    f1, f2 = StackedForward(*passes1), StackedForward(*passes2)
    for k in range(w2.shape[0]):
        theta[k, 0], theta[k, 1] = td_row(w2[k], member_pass(f1, k), member_pass(f2, k), a[k],
                                          b[k], g[k])  # fmt: skip


@njit(**_JIT)
def _sgd_kernel(net, passes, a, scale, g, passes2, out):
    """:func:`sgd_row` of every member, the pass at ``x2`` with the new parameters into
    ``out``."""
    n, f = Params(*net), StackedForward(*passes)
    f2, nxt = StackedForward(*passes2), StackedForward(*out)
    for k in range(n.w1t.shape[0]):
        sgd_row(member_params(n, k), member_pass(f, k), a[k], scale[k], g[k],
                member_pass(f2, k), member_pass(nxt, k))  # fmt: skip


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
        self.params = Params(w1t, b1, w2, b2)
        """The same arrays as the kernels take them."""
        self.dtype = w1t.dtype
        self.rows = np.arange(len(w1t))

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
        self.params = Params(self.w1t, self.b1, self.w2, self.b2)
        self.rows = np.arange(len(self.w1t))

    def copy_to(self, k: int, net: QNetwork) -> None:
        """Write member ``k``'s parameters into ``net``."""
        with torch.no_grad():
            net.hidden.weight.copy_(torch.from_numpy(self.w1t[k].T))
            net.hidden.bias.copy_(torch.from_numpy(self.b1[k]))
            net.out.weight.copy_(torch.from_numpy(self.w2[k]))
            net.out.bias.copy_(torch.from_numpy(self.b2[k]))

    def forward(self, x: np.ndarray, reuse: StackedForward | None = None) -> StackedForward:
        """``p = W_1 x + b_1``, ``h = relu(p)``, ``Q = W_2 h + b_2`` for inputs ``(K, n_obs)``.

        ``reuse``: a forward pass at the current parameters (from :meth:`sgd_step`); its rows
        whose input equals ``x`` are taken as they are, the others computed into it.
        """
        x = np.ascontiguousarray(x, dtype=self.dtype)
        if reuse is None:
            p, q = np.empty(self.b1.shape, self.dtype), np.empty(self.b2.shape, self.dtype)
            rows = self.rows
        else:
            rows = np.flatnonzero((x != reuse.x).any(axis=1))
            if not len(rows):
                return reuse
            p, q = reuse.p, reuse.q  # rows of ``reuse`` that changed: in place
        _forward_kernel(tuple(self.params), (x, p, q), rows)
        return StackedForward(x, p, q)

    def td_terms(
        self, f1: StackedForward, a: np.ndarray, f2: StackedForward, b: np.ndarray
    ) -> TDTerms:
        """Θ1 = Θ((x1,a),(x1,a)), Θ2 = Θ((x1,a),(x2,b)) and ``∂Q_a/∂b_1`` (module docstring)."""
        g = np.empty_like(f1.p)
        theta = np.empty((len(g), 2), self.dtype)
        _td_kernel(self.w2, tuple(f1), tuple(f2), _int(a), _int(b), g, theta)
        return TDTerms(theta[:, 0], theta[:, 1], g)

    def ntk(
        self, f1: StackedForward, a: np.ndarray, f2: StackedForward, b: np.ndarray
    ) -> np.ndarray:
        """Θ((x1, a), (x2, b)) per member (module docstring)."""
        g = self.w2[self.rows, a] * (f1.p > 0.0)
        g2 = self.w2[self.rows, b] * (f2.p > 0.0)
        h1, h2 = np.maximum(f1.p, 0.0), np.maximum(f2.p, 0.0)
        out = np.where(a == b, np.einsum("kj,kj->k", h1, h2) + 1.0, 0.0)
        return out + (np.einsum("ki,ki->k", f1.x, f2.x) + 1.0) * np.einsum("kj,kj->k", g, g2)

    def sgd_step(
        self,
        f: StackedForward,
        a: np.ndarray,
        scale: np.ndarray,
        grad_b1: np.ndarray,
        f2: StackedForward,
    ) -> StackedForward:
        """θ ← θ + scale · ∂Q_a(x)/∂θ per member, in place: the semi-gradient step with
        scale = α·δ; ``grad_b1`` is ``∂Q_a/∂b_1`` at the parameters ``f`` was computed with
        (:attr:`TDTerms.grad_b1`).  Returns the forward pass at ``f2.x`` with the new
        parameters, updated from ``f2`` (the pass at s' the step was computed with)."""
        scale = np.ascontiguousarray(scale, dtype=self.dtype)
        p, q = np.empty_like(f2.p), np.empty_like(f2.q)
        _sgd_kernel(tuple(self.params), tuple(f), _int(a), scale, grad_b1, tuple(f2),
                    (f2.x, p, q))  # fmt: skip
        return StackedForward(f2.x, p, q)


class Replay(NamedTuple):
    """Stacked replay buffers as :class:`cdqn.agents.replay.StackedReplay` holds them:
    ``obs``, ``next_obs`` ``(K, capacity, n_obs)``, ``actions``, ``rewards``, ``terminated``
    ``(K, capacity)``."""

    obs: np.ndarray
    next_obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray


@njit(**_JIT)
def member_replay(r, k):
    """Member ``k``'s buffer of a :class:`Replay`."""
    return Replay(r.obs[k], r.next_obs[k], r.actions[k], r.rewards[k], r.terminated[k])


def step_settings_array(lr: float, discount: float, dtype: np.dtype) -> np.ndarray:
    """``(α, γ, 0)`` in the network's dtype, as :func:`cdqn.ddqn_kernels.double_dqn_learn`
    takes them."""
    return np.array([lr, discount, 0.0], dtype=dtype)


def _int(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


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

    def forward(self, x: np.ndarray, reuse: Forward | None = None) -> Forward:
        """Forward pass at ``x``; ``reuse`` as in :meth:`StackedTwoLayer.forward`."""
        f = self.stack.forward(
            np.asarray(x, dtype=self.dtype)[None], None if reuse is None else _stacked(reuse)
        )
        return Forward(f.x[0], f.p[0], f.q[0])

    def td_terms(self, f1: Forward, a: int, f2: Forward, b: int) -> tuple[float, float, np.ndarray]:
        """(Θ1, Θ2, ∂Q_a/∂b_1) of one controlled step (:meth:`StackedTwoLayer.td_terms`)."""
        t = self.stack.td_terms(_stacked(f1), np.array([a]), _stacked(f2), np.array([b]))
        return float(t.theta1[0]), float(t.theta2[0]), t.grad_b1

    def ntk(self, f1: Forward, a: int, f2: Forward, b: int) -> float:
        """Θ((x1, a), (x2, b)) from two cached forward passes (module docstring)."""
        return float(self.stack.ntk(_stacked(f1), np.array([a]), _stacked(f2), np.array([b]))[0])

    def sgd_step(
        self, f: Forward, a: int, scale: float, grad_b1: np.ndarray, f2: Forward
    ) -> Forward:
        """θ ← θ + scale · ∂Q_a(x)/∂θ, the semi-gradient step with scale = α·δ; returns the
        forward pass at ``f2.x`` with the new parameters (:meth:`StackedTwoLayer.sgd_step`)."""
        g = self.stack.sgd_step(_stacked(f), np.array([a]), np.array([scale]), grad_b1,
                                _stacked(f2))  # fmt: skip
        return Forward(g.x[0], g.p[0], g.q[0])


def _stacked(f: Forward) -> StackedForward:
    return StackedForward(f.x[None], f.p[None], f.q[None])


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
