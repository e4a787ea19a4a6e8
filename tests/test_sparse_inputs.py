"""Inputs with zeros (one-hot encoded states, mixed vectors): the kernels that multiply ``x``
into ``W_1`` read only the nonzero inputs, and compute what the dense products compute: bit
for bit in the row kernels, within rounding in Double DQN's minibatch step, and what torch
autograd computes from the definitions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from numba import njit

from cdqn.bench import nonzero_inputs
from cdqn.config import EnvConfig
from cdqn.ddqn_kernels import BLOCK, kernels, sparse_learn, sparse_members
from cdqn.envs import make_env
from cdqn.network import (
    _JIT,
    FastTwoLayer,
    Forward,
    NetworkSpec,
    Params,
    Pending,
    QNetwork,
    Replay,
    apply_pending_row,
    forward_pending_row,
    ntk_autograd,
    output_row,
    sgd_row,
)
from tests.test_ddqn_kernels import fast_and_autograd_agents
from tests.test_ddqn_population import BASE as DDQN_BASE
from tests.test_ddqn_population import _population, _single

KINDS = ("one-hot", "two-hot", "mixed", "zero", "dense")


def _input(kind: str, n: int, gen: np.random.Generator) -> np.ndarray:
    """One input of ``kind``: a one-hot vector, two ones (a ``Tuple`` of two ``Discrete``),
    normal values with about 85 % zeros, all zeros, or normal values."""
    x = np.zeros(n)
    if kind == "one-hot":
        x[gen.integers(n)] = 1.0
    elif kind == "two-hot":
        x[gen.integers(n // 2)] = x[n // 2 + gen.integers(n - n // 2)] = 1.0
    elif kind == "mixed":
        x = gen.normal(size=n) * (gen.random(n) < 0.15)
    elif kind == "dense":
        x = gen.normal(size=n)
    return x


@njit(**_JIT)
def _dense_forward_pending(w1t, b1, w2, b2, x, p, q, sx, g, pending):
    """The pass and the pending ``W_1`` update over every input, zero or not, unblocked."""
    for j in range(w1t.shape[1]):
        p[j] = b1[j]
    for i in range(w1t.shape[0]):
        for j in range(w1t.shape[1]):
            if pending:
                w1t[i, j] = w1t[i, j] + sx[i] * g[j]
            p[j] += w1t[i, j] * x[i]
    output_row(w2, b2, p, q)


@njit(**_JIT)
def _dense_w1_step(w1t, x, s, g):
    """``W_1ᵀ[i] += (s x_i) g`` over every input."""
    for i in range(w1t.shape[0]):
        sx = s * x[i]
        for j in range(w1t.shape[1]):
            w1t[i, j] += sx * g[j]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    ("n_obs", "width", "dtype"),
    [(500, 700, np.float64), (45, 33, np.float64), (36, 40, np.float32)],
)
def test_row_kernels_equal_the_dense_products_bit_for_bit(
    kind: str, n_obs: int, width: int, dtype: type
) -> None:
    """The pass (with and without a pending update), the pending update on its own and the
    SGD step leave the numbers of the products over every input, in either dtype; rows of
    zero inputs are not changed."""
    gen = np.random.default_rng(n_obs)
    for _ in range(5):
        w1t, b1, w2, b2 = (
            gen.normal(size=s).astype(dtype) for s in ((n_obs, width), width, (3, width), 3)
        )
        x, x_prev = (_input(kind, n_obs, gen).astype(dtype) for _ in range(2))
        g, s = gen.normal(size=width).astype(dtype), dtype(1e-3 * gen.normal())
        sx = s * x_prev
        for pending in (False, True):
            w_fast, w_ref = w1t.copy(), w1t.copy()
            p, q = np.empty(width, dtype), np.empty(3, dtype)
            p_ref, q_ref = np.empty(width, dtype), np.empty(3, dtype)
            forward_pending_row(Params(w_fast, b1, w2, b2), Forward(x, p, q),
                                Pending(sx, g, pending))  # fmt: skip
            _dense_forward_pending(w_ref, b1, w2, b2, x, p_ref, q_ref, sx, g, pending)
            assert np.array_equal(p, p_ref) and np.array_equal(q, q_ref)
            assert np.array_equal(w_fast, w_ref)
        w_fast, w_ref = w1t.copy(), w1t.copy()
        apply_pending_row(w_fast, sx, g)
        _dense_forward_pending(w_ref, b1, w2, b2, x, p_ref, q_ref, sx, g, True)
        assert np.array_equal(w_fast, w_ref)
        assert np.array_equal(w_fast[x_prev == 0.0], w1t[x_prev == 0.0])

        fast, ref = [a.copy() for a in (w1t, b1, w2, b2)], [a.copy() for a in (w1t, b1, w2, b2)]
        f = np.empty(width, dtype), np.empty(3, dtype)
        forward_pending_row(Params(*fast), Forward(x_prev, *f), Pending(sx, g, False))
        sgd_row(Params(*fast), Forward(x_prev, *f), 1, s, g, Forward(x, p, q),
                Forward(x, np.empty(width, dtype), np.empty(3, dtype)))  # fmt: skip
        _dense_w1_step(ref[0], x_prev, s, g)
        assert np.array_equal(fast[0], ref[0])


def _autograd_step(net: QNetwork, x: np.ndarray, a: int, scale: float) -> list[torch.Tensor]:
    """``θ + scale ∂Q_a(x)/∂θ`` by torch autograd."""
    params = dict(net.named_parameters())
    q = net(torch.as_tensor(x))[a]
    grads = torch.autograd.grad(q, list(params.values()))
    return [(p + scale * gp).detach() for p, gp in zip(params.values(), grads, strict=True)]


@pytest.mark.parametrize("kind", ["one-hot", "two-hot", "mixed"])
def test_q_values_td_terms_ntk_and_step_equal_autograd(kind: str) -> None:
    """On inputs with zeros, the fast path's Q-values, Θ1, Θ2, NTK and SGD step (the updated
    parameters and the pass at s' after it) equal torch's forward pass, the NTK by its
    definition (:func:`cdqn.network.ntk_autograd`) and an autograd step."""
    torch.manual_seed(2)
    n_obs, n_actions = 60, 4
    net = QNetwork(NetworkSpec(n_obs, n_actions, 300))
    fast = FastTwoLayer(net)
    gen = np.random.default_rng(3)
    for _ in range(6):
        x, y = _input(kind, n_obs, gen), _input(kind, n_obs, gen)
        fx, fy = fast.forward(x), fast.forward(y)
        with torch.no_grad():
            for f, v in ((fx, x), (fy, y)):
                np.testing.assert_allclose(f.q, net(torch.as_tensor(v)).numpy(), rtol=1e-12)
        a, b = int(gen.integers(n_actions)), int(np.argmax(fy.q))
        theta1, theta2, grad_b1 = fast.td_terms(fx, a, fy, b)
        tx, ty = torch.as_tensor(x), torch.as_tensor(y)
        assert theta1 == pytest.approx(ntk_autograd(net, tx, a, tx, a), rel=1e-12)
        assert theta2 == pytest.approx(ntk_autograd(net, tx, a, ty, b), rel=1e-12)
        assert fast.ntk(fx, a, fy, b) == pytest.approx(theta2, rel=1e-13)
        scale = 1e-2 * gen.normal()
        expected = _autograd_step(net, x, a, scale)
        w1_before = fast.w1.copy()
        after = fast.sgd_step(fx, a, scale, grad_b1, fy)
        for got, want in zip(net.parameters(), expected, strict=True):
            torch.testing.assert_close(got.detach(), want, rtol=1e-12, atol=1e-14)
        assert np.array_equal(fast.w1[:, x == 0.0], w1_before[:, x == 0.0])
        np.testing.assert_allclose(after.q, fast.forward(y).q, rtol=1e-11)


@pytest.mark.parametrize(
    ("kind", "dtype"), [("one-hot", "float64"), ("two-hot", "float32"), ("mixed", "float64")]
)
def test_minibatch_step_over_nonzero_inputs_equals_autograd(kind: str, dtype: str) -> None:
    """Double DQN's minibatch steps on inputs with zeros (taken over their nonzero inputs)
    and torch autograd's leave the same losses and networks after 60 updates."""
    n_obs, n_actions = (40, 3) if kind != "mixed" else (60, 2)
    base, agents = fast_and_autograd_agents(n_obs, n_actions, dtype, lr=1e-2)
    rel_loss, rtol, atol = {"float64": (1e-9, 1e-10, 1e-12), "float32": (2e-4, 2e-4, 2e-6)}[dtype]
    gen = np.random.default_rng(2)
    obs = _input(kind, n_obs, gen)
    for t in range(60):
        nxt = _input(kind, n_obs, gen)
        done = t % 17 == 16
        recs = [agent.update(obs, t % n_actions, 1.0, nxt, done) for agent in agents]
        assert recs[0].loss == pytest.approx(recs[1].loss, rel=rel_loss, nan_ok=True)
        obs = _input(kind, n_obs, gen) if done else nxt
    replay, size = agents[0].replay, agents[0].buffer.size
    sparse = np.zeros(1, dtype=np.bool_)
    everything = np.arange(size)[None]
    assert sparse_members(replay.obs, replay.next_obs, everything, ~sparse, n_actions, sparse)
    for p_fast, p_auto in zip(agents[0].net.parameters(), agents[1].net.parameters(), strict=True):
        torch.testing.assert_close(p_fast, p_auto, rtol=rtol, atol=atol)
    assert not torch.equal(agents[0].net.hidden.weight, base.hidden.weight)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_sparse_and_unrolled_minibatch_kernels_take_the_same_step(dtype: type) -> None:
    """On one minibatch with zeros, the kernel over the nonzero inputs and the kernel written
    out for the shape give the same loss and parameters, to rounding; the choice of route:
    a dense minibatch goes to the unrolled kernel, one with mostly zeros to the loop."""
    n, m, width, batch, cap = 40, 3, 300, 16, 100
    gen = np.random.default_rng(0)
    params = [gen.normal(size=s).astype(dtype) for s in ((2, n, width), (2, width), (2, m, width),
                                                          (2, m))]  # fmt: skip
    target = [a.copy() for a in params]
    zeros = np.stack([gen.random((cap, n)) < 0.9, np.zeros((cap, n), bool)])
    obs = np.where(zeros, 0.0, gen.normal(size=(2, cap, n)))
    nxt = np.where(zeros, 0.0, gen.normal(size=(2, cap, n)))
    buf = (gen.integers(m, size=(2, cap)), gen.normal(size=(2, cap)),
           (gen.random((2, cap)) < 0.2).astype(float))  # fmt: skip
    idx = gen.integers(cap, size=(2, batch))
    hyper = np.array([1e-2, 0.99, 0.0], dtype)
    sparse = np.empty(2, dtype=np.bool_)
    assert sparse_members(obs, nxt, idx, np.ones(2, np.bool_), m, sparse) == 1
    assert sparse.tolist() == [True, False]
    member = np.array([True, False])
    results = []
    for learn in (sparse_learn, kernels(n, m).learn):
        p, loss = [a.copy() for a in params], np.empty(2)
        learn(Params(*p), Params(*target), Replay(obs, nxt, *buf), idx, member, hyper, BLOCK,
              loss)  # fmt: skip
        results.append((p, loss[0]))
    (p_sparse, l_sparse), (p_dense, l_dense) = results
    rtol = 1e-12 if dtype == np.float64 else 2e-5
    assert l_sparse == pytest.approx(l_dense, rel=rtol)
    for a, b, before in zip(p_sparse, p_dense, params, strict=True):
        np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol)
        assert not np.array_equal(a[0], before[0]) and np.array_equal(a[1], before[1])


def test_ddqn_population_on_one_hot_states_steps_as_single_runs() -> None:
    """On CliffWalking (one-hot states), each member of a Double DQN population equals the
    single run of its seed, bit for bit: signals, returns and networks."""
    overrides = [*DDQN_BASE, "env.id=CliffWalking-v1", "env.max_episode_steps=60",
                 "train.episodes=30"]  # fmt: skip
    members, _ = _population(overrides, [3, 4])
    for m in members:
        returns, rows, state = _single([*overrides, f"seed={m.seed}"])
        assert m.status == "FINISHED" and m.returns == returns
        assert np.array_equal(m.signals.state(), rows, equal_nan=True)
        assert np.isfinite(rows[:, 9]).sum() > 20  # it learned
        for key in ("net", "target"):
            for name, value in state[key].items():
                assert torch.equal(m.cfg[key][name], value), (key, name)


@pytest.mark.parametrize(
    ("env_id", "nonzero"), [("Taxi-v4", 1), ("Blackjack-v1", 3), ("CartPole-v1", 4)]
)
def test_benchmark_counts_the_nonzero_inputs(env_id: str, nonzero: int) -> None:
    """The benchmark's limit counts the first layer over the inputs the kernels read: one
    per ``Discrete`` part of a one-hot observation, every input of a dense one."""
    env = make_env(EnvConfig(id=env_id, max_episode_steps=20))
    assert nonzero_inputs(env) == nonzero


@pytest.mark.parametrize(
    ("n", "kind", "expected"),
    [(16, "one-hot", True), (48, "one-hot", True), (36, "dense", False), (8, "dense", False)],
)
def test_the_route_follows_the_minibatchs_zeros(n: int, kind: str, expected: bool) -> None:
    """One-hot minibatches take the loop over nonzeros (FrozenLake's 16 inputs too, where the
    products through BLAS would be the dearer route); dense ones, such as radial features,
    do not."""
    gen = np.random.default_rng(3)
    obs = np.stack([np.stack([_input(kind, n, gen) for _ in range(64)])])
    nxt = np.stack([np.stack([_input(kind, n, gen) for _ in range(64)])])
    sparse = np.empty(1, dtype=np.bool_)
    sparse_members(obs, nxt, gen.integers(64, size=(1, 32)), np.ones(1, np.bool_), 4, sparse)
    assert bool(sparse[0]) is expected
