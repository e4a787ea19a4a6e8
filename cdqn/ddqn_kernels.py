"""Double DQN's minibatch step on the two-layer ReLU network, compiled for each shape.

One SGD step on :math:`\\mathcal L = \\tfrac12 \\sum_i \\delta_i^2`,

.. math::  \\delta_i = r_i + \\gamma (1-d_i)\\,\\bar Q(s'_i, \\arg\\max_a Q(s'_i, a)) - Q(s_i, a_i),

targets held constant, ``θ ← θ + α Σ_i δ_i ∂Q_{a_i}(s_i)/∂θ`` with the per-sample gradients
of :mod:`cdqn.network` (``∂Q_a/∂W_2[a] = h``, ``∂Q_a/∂b_1 = W_2[a] ⊙ [p > 0]``,
``∂Q_a/∂W_1 = (∂Q_a/∂b_1) x^⊤``), all at the parameters before the step.  It is the
arithmetic of these matrix products (``B`` samples, ``n`` inputs, ``m`` actions, width ``W``):

* forward: ``Q(s_i, ·)``, ``Q(s'_i, ·)``, ``Q̄(s'_i, ·)``: ``3 B W (n + m)`` multiply-adds;
* backward: ``∂L/∂W_2`` (``B W m``), ``∂L/∂h`` (``B W m``), ``∂L/∂W_1`` (``B W n``):
  ``B W (n + 2m)`` (:func:`minibatch_macs`).

Two compiled loops do it, block by block of hidden units, without a ``(B, W)`` temporary:

1. **forward**, two samples per pass over the block (one with more than
   :data:`FW_CHUNK_INPUTS` inputs): the three passes in one loop over the block, each
   unit's pre-activations a sum of ``n`` written-out products, the ``3m`` output sums
   vectorised partial sums (``fastmath`` ``reassoc``);
2. **backward**, vectorised over the block's hidden units (each touches only its own
   parameters), :data:`CHUNK` samples per pass: ``p_ij`` again (``n`` multiply-adds:
   cheaper than storing ``B × W`` of them), the unit's gradients as ``n + m + 1`` sums over
   the samples, added in sample order and held in registers, then its step.  With more
   inputs and actions than :data:`UNIT_MAJOR_SIZE`, per unit a loop over the samples takes
   them (partial sums over the samples).

The loops are written out for the network's ``(n, m)`` (source generated from the template
below, written once to a cache folder so that numba caches its machine code on disk) and run
in the network's dtype.  The same compiled ``learn`` serves a single run (a stack of one)
and every member of a population, so a member computes exactly the numbers of the single run
of its seed.

**Many inputs.**  From :data:`DENSE_INPUTS` inputs (Mountain car's 36 radial features,
LunarLander's 8) a dense minibatch goes through :func:`dense_step`: the same step as matrix
products through BLAS (``np.dot``, on one thread), which run near one thread's peak where
the written-out loops, with ``n`` products per pre-activation, reach a fifth of it.

**Inputs with zeros.**  A minibatch whose inputs (the ``s_i`` and ``s'_i``) are mostly zero,
such as one-hot encoded states (:class:`cdqn.envs.OneHot`: one 1 among Taxi's 500 inputs),
takes the same step through :func:`sparse_step`, a loop (not written out per shape)
over each sample's nonzero inputs: a pre-activation costs ``nnz(s_i)`` multiply-adds instead
of ``n``, and ``∂L/∂W_1`` is summed only for the inputs nonzero in some ``s_i`` (the others'
is 0, and their rows of ``W_1`` are not touched).  Its sums over the samples and hidden units
run in another order than the unrolled kernel's, so the two agree to rounding
(``tests/test_sparse_inputs.py``).  :func:`learn` chooses per member and minibatch
(:func:`sparse_members`), from the minibatch alone, so a member and the single run of its
seed still take the same route; the unrolled kernel of a shape is generated and compiled
only when a minibatch with more nonzeros comes.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, NamedTuple, TypedDict

import numpy as np
from numba import njit
from threadpoolctl import threadpool_limits

from cdqn.network import (
    Params,
    Replay,
    member_params,
    member_replay,
    step_settings_array,
)

if TYPE_CHECKING:
    from cdqn.network import FastTwoLayer, StackedTwoLayer

BLOCK = 256
"""Hidden units per block of the forward loop: the block's rows of both networks' parameters
(``2 (n + m + 1)`` rows, 28 KB in float64 on CartPole) stay in L1 while a sample passes."""


def minibatch_macs(batch: int, n_obs: int, n_actions: int, width: int) -> int:
    """Multiply-adds of one minibatch step (module docstring)."""
    return batch * width * (3 * (n_obs + n_actions) + n_obs + 2 * n_actions)


class JitOptions(TypedDict):
    """The options given to ``numba.njit``."""

    cache: bool
    fastmath: set[str]


_JIT: JitOptions = {"cache": True, "fastmath": {"reassoc", "contract"}}


@njit(**_JIT)
def td_errors(q, acts, idx, replay, discount, delta, gb2):
    """``δ_i`` (module docstring) from the passes ``q[i] = (Q(s_i, ·), Q(s'_i, ·),
    Q̄(s'_i, ·))`` and the rewards and terminations of the transitions ``idx`` of one
    member's ``replay`` into ``delta``; ``Σ_i δ_i [a_i = a]`` added to ``gb2[a]``; returns
    the loss ``½ Σ_i δ_i²``."""
    buf_rewards, buf_terminated = replay.rewards, replay.terminated
    loss = 0.0
    for i in range(acts.shape[0]):
        j, qi = idx[i], q[i]
        best = 0  # Double DQN: the online network's action at s'_i (first maximum)
        for a in range(1, qi.shape[1]):
            if qi[1, a] > qi[1, best]:
                best = a
        y = buf_rewards[j] + discount * (1.0 - buf_terminated[j]) * qi[2, best]
        delta[i] = y - qi[0, acts[i]]
        loss += 0.5 * float(delta[i]) * float(delta[i])
        gb2[acts[i]] += delta[i]
    return loss


SPARSE_COST = 4
"""Cost of a multiply-add of :func:`sparse_step` relative to the unrolled kernel's, an upper
bound: measured on one core (width 2500, 32 samples), a minibatch of 36 inputs a quarter
nonzero takes 0.97 ms against 3.3 ms unrolled (a ratio of 1.0 per multiply-add), one of
one-hot states of 500 takes 0.53 ms against about 150 ms.  With 4, a minibatch goes the
sparse route where under a sixth (36 inputs) to a quarter (many) of its inputs are nonzero,
as with one-hot states; Mountain car's radial features (none exactly zero) stay dense
(written out below :data:`DENSE_INPUTS` inputs, :func:`dense_step` from it)."""


DENSE_INPUTS = 8
"""From this many network inputs a dense minibatch goes through :func:`dense_step`.  Measured
on one core (width 2500, 32 samples, float64, CPU µs per minibatch step, written out /
BLAS): 4 inputs 188 / 202, 6: 278 / 228, 8: 363 / 274, 16: 767 / 460, 36: 2 573 / 684."""

DENSE_COST = 1.4
"""The route through :func:`dense_step` at the cost :func:`sparse_members` gives the written-out
kernel, times this: measured on one core with one-hot minibatches, 408 µs against the loop's
325 at 16 inputs (1.4 times the model), 804 against 329 at 48 (1.1 times)."""


@njit(cache=True)
def sparse_members(buf_obs, buf_next, idx, members, n_actions, sparse):
    """Per member ``k`` of ``members``: whether :func:`sparse_step` is the cheaper route for
    its minibatch (the transitions ``idx[k]``), into ``sparse[k]``; returns how many members
    it is for.  Per sample and hidden unit, the unrolled kernel does ``4n + 5m``
    multiply-adds (:func:`minibatch_macs`), the loop ``4 nnz + 5m`` with ``nnz`` the mean
    number of nonzero inputs of the ``s_i`` and ``s'_i``, each :data:`SPARSE_COST` times as
    dear; from :data:`DENSE_INPUTS` inputs the dense route costs :data:`DENSE_COST` times the
    unrolled kernel's count."""
    count = 0
    batch, n_obs = idx.shape[1], buf_obs.shape[2]
    dense = 2 * batch * (4 * n_obs + 5 * n_actions) * (DENSE_COST if n_obs >= DENSE_INPUTS else 1.0)
    for k in range(members.shape[0]):
        nnz = 0
        if members[k]:
            for j in idx[k]:
                for c in range(n_obs):
                    nnz += (buf_obs[k, j, c] != 0.0) + (buf_next[k, j, c] != 0.0)
        loop = SPARSE_COST * (4 * nnz + 10 * batch * n_actions)  # × 2 batch, as unrolled
        sparse[k] = members[k] and loop <= dense
        count += sparse[k]
    return count


@njit(cache=True)
def _nonzeros(buf, idx, like):
    """The nonzero inputs of the rows ``idx`` of ``buf``, row by row in input order:
    ``(ptr, col, val)``, row ``i``'s being ``col[ptr[i]:ptr[i+1]]`` with the values
    ``val[ptr[i]:ptr[i+1]]`` in ``like``'s dtype."""
    ptr = np.empty(idx.shape[0] + 1, np.int64)
    col = np.empty(idx.shape[0] * buf.shape[1], np.int64)
    val = np.empty(idx.shape[0] * buf.shape[1], like.dtype)
    t = 0
    for i in range(idx.shape[0]):
        ptr[i] = t
        row = buf[idx[i]]
        for c in range(row.shape[0]):
            if row[c] != 0.0:
                col[t], val[t] = c, row[c]
                t += 1
    ptr[idx.shape[0]] = t
    return ptr, col[:t], val[:t]


class Passes(NamedTuple):
    """One array per pass of a sample: ``Q(s_i, ·)`` (``s``), ``Q(s'_i, ·)`` (``s2``) and
    ``Q̄(s'_i, ·)`` (``target``)."""

    s: np.ndarray
    s2: np.ndarray
    target: np.ndarray


@njit(**_JIT)
def _sparse_forward(online, target, s, nxt, i, j0, j1, out, h, zero):
    """Sample ``i``'s three passes (``Q(s_i, ·)``, ``Q(s'_i, ·)``, ``Q̄(s'_i, ·)``) over the
    hidden units ``j0:j1`` of the networks ``online`` and ``target``, added to ``out``: the
    pre-activations (into the :class:`Passes` ``h``) over the nonzero inputs of
    ``s = (ptr, col, val)`` and ``nxt`` only, then ``relu`` and the output sums."""
    w1t, b1, w2, tw1t, tb1, tw2 = online.w1t, online.b1, online.w2, target.w1t, target.b1, target.w2
    ps, pn, pt = h
    n = j1 - j0
    for jj in range(n):
        ps[jj], pn[jj], pt[jj] = b1[j0 + jj], b1[j0 + jj], tb1[j0 + jj]
    ptr, col, val = s
    for t in range(ptr[i], ptr[i + 1]):
        w, x = w1t[col[t], j0:j1], val[t]
        for jj in range(n):
            ps[jj] += w[jj] * x
    ptr, col, val = nxt
    for t in range(ptr[i], ptr[i + 1]):
        w, u, y = w1t[col[t], j0:j1], tw1t[col[t], j0:j1], val[t]
        for jj in range(n):
            pn[jj] += w[jj] * y
            pt[jj] += u[jj] * y
    for jj in range(n):
        ps[jj], pn[jj], pt[jj] = max(ps[jj], zero), max(pn[jj], zero), max(pt[jj], zero)
    for a in range(w2.shape[0]):
        v, u = w2[a, j0:j1], tw2[a, j0:j1]
        qs = qn = qt = zero
        for jj in range(n):
            qs += v[jj] * ps[jj]
            qn += v[jj] * pn[jj]
            qt += u[jj] * pt[jj]
        out[0, a] += qs
        out[1, a] += qn
        out[2, a] += qt


@njit(**_JIT)
def _sparse_backward(online, s, pos, used, acts, delta, lr, zero, block):
    """The backward pass and step of the module docstring, block by block of the hidden
    units of the network ``online`` (``W_1``, ``b_1``, ``W_2``), over the nonzero inputs
    ``s = (ptr, col, val)`` of the ``s_i``: per sample, ``p_ij`` again and the gradients it
    adds (``∂L/∂W_1[j, c]`` for the inputs ``used`` that are nonzero in some ``s_i``, ``pos``
    mapping each nonzero to its place in ``used``), vectorised over the block's units; then
    the block's step.  A unit with ``p_ij ≤ 0`` adds an exact zero, so each unit's sums are
    those of a loop over its active samples, in sample order."""
    w1t, b1, w2 = online.w1t, online.b1, online.w2
    ptr, col, val = s
    width = w1t.shape[1]
    g = np.empty(block, b1.dtype)
    sb = np.empty(block, b1.dtype)
    e = np.empty((w2.shape[0], block), b1.dtype)
    acc = np.empty((used.shape[0], block), b1.dtype)
    for j0 in range(0, width, block):
        n = min(block, width - j0)
        sb[:] = zero
        e[:, :] = zero
        acc[:, :] = zero
        for i in range(acts.shape[0]):
            for jj in range(n):
                g[jj] = b1[j0 + jj]
            for t in range(ptr[i], ptr[i + 1]):
                w, x = w1t[col[t], j0 : j0 + n], val[t]
                for jj in range(n):
                    g[jj] += w[jj] * x
            d, ea, va = delta[i], e[acts[i]], w2[acts[i], j0 : j0 + n]
            for jj in range(n):
                active = g[jj] > zero
                ea[jj] += d * g[jj] if active else zero
                g[jj] = d * va[jj] if active else zero
                sb[jj] += g[jj]
            for t in range(ptr[i], ptr[i + 1]):
                a, x = acc[pos[t]], val[t]
                for jj in range(n):
                    a[jj] += x * g[jj]
        for jj in range(n):
            b1[j0 + jj] += lr * sb[jj]
        for u in range(used.shape[0]):
            w, a = w1t[used[u], j0 : j0 + n], acc[u]
            for jj in range(n):
                w[jj] += lr * a[jj]
        for a in range(w2.shape[0]):
            w, ea = w2[a, j0 : j0 + n], e[a]
            for jj in range(n):
                w[jj] += lr * ea[jj]


@njit(cache=True)
def _inputs_used(col, n_obs):
    """The distinct inputs in ``col`` (first appearance order) and each entry's place
    among them."""
    place = np.full(n_obs, -1, np.int64)
    used = np.empty(min(n_obs, col.shape[0]), np.int64)
    pos = np.empty(col.shape[0], np.int64)
    n = 0
    for t in range(col.shape[0]):
        c = col[t]
        if place[c] < 0:
            place[c], used[n] = n, c
            n += 1
        pos[t] = place[c]
    return pos, used[:n]


@njit(**_JIT)
def sparse_step(online, target, replay, idx, hyper, block):
    """One member's minibatch step (module docstring) over the nonzero inputs of its
    minibatch, the transitions ``idx`` of its ``replay``; returns the loss before the
    step."""
    lr, discount, zero = hyper[0], hyper[1], hyper[2]
    w1t, b1, w2, b2 = online
    batch, n_act, width = idx.shape[0], w2.shape[0], w1t.shape[1]
    s, nxt = _nonzeros(replay.obs, idx, b1), _nonzeros(replay.next_obs, idx, b1)
    acts = np.empty(batch, np.int64)
    q = np.empty((batch, 3, n_act), b1.dtype)
    for i in range(batch):
        acts[i] = replay.actions[idx[i]]
        for a in range(n_act):
            q[i, 0, a], q[i, 1, a], q[i, 2, a] = b2[a], b2[a], target.b2[a]
    h = Passes(np.empty(block, b1.dtype), np.empty(block, b1.dtype), np.empty(block, b1.dtype))
    for j0 in range(0, width, block):
        j1 = min(j0 + block, width)
        for i in range(batch):
            _sparse_forward(online, target, s, nxt, i, j0, j1, q[i], h, zero)
    delta = np.empty(batch, b1.dtype)
    gb2 = np.zeros(n_act, b1.dtype)
    loss = td_errors(q, acts, idx, replay, discount, delta, gb2)
    pos, used = _inputs_used(s[1], w1t.shape[0])
    _sparse_backward(online, s, pos, used, acts, delta, lr, zero, block)
    for a in range(n_act):
        b2[a] += lr * gb2[a]
    return loss


@njit(**_JIT)
def sparse_learn(online, target, replay, idx, members, hyper, block, last_loss):
    """:func:`sparse_step` of each member ``k`` with ``members[k]`` (the generated
    ``learn``'s interface: :func:`learn`'s, the bundles as plain tuples)."""
    net, tgt, buf = Params(*online), Params(*target), Replay(*replay)
    for k in range(members.shape[0]):
        if members[k]:
            last_loss[k] = sparse_step(member_params(net, k), member_params(tgt, k),
                                       member_replay(buf, k), idx[k], hyper, block)  # fmt: skip


@njit(**_JIT)
def dense_step(online, target, replay, idx, hyper):
    """One member's minibatch step (module docstring) as matrix products through BLAS
    (``np.dot``): ``P = [s; s'] W_1^⊤`` and ``P̄ = s' W̄_1^⊤`` with ``b_1`` and ``relu`` in
    place, the outputs ``H W_2^⊤``, then ``∂L/∂W_1 = sᵀ G`` with
    ``G_ij = δ_i W_2[a_i, j] [p_ij > 0]``; returns the loss before the step.  The ``(2B, W)``
    activations are held, which the unrolled kernel avoids; past :data:`DENSE_INPUTS` inputs
    the products' speed (near one thread's peak) outweighs it."""
    lr, discount, zero = hyper[0], hyper[1], hyper[2]
    w1t, b1, w2, b2 = online
    batch, n_obs, n_act, width = idx.shape[0], w1t.shape[0], w2.shape[0], w1t.shape[1]
    x = np.empty((2 * batch, n_obs), b1.dtype)  # the s_i, then the s'_i
    acts = np.empty(batch, np.int64)
    for i in range(batch):
        j = idx[i]
        acts[i] = replay.actions[j]
        x[i], x[batch + i] = replay.obs[j], replay.next_obs[j]
    h = np.dot(x, w1t)
    ht = np.dot(x[batch:], target.w1t)
    for i in range(2 * batch):
        for j in range(width):
            h[i, j] = max(h[i, j] + b1[j], zero)
    for i in range(batch):
        for j in range(width):
            ht[i, j] = max(ht[i, j] + target.b1[j], zero)
    out, out_t = np.dot(h, w2.T), np.dot(ht, target.w2.T)
    q = np.empty((batch, 3, n_act), b1.dtype)
    for i in range(batch):
        for a in range(n_act):
            q[i, 0, a], q[i, 1, a] = b2[a] + out[i, a], b2[a] + out[batch + i, a]
            q[i, 2, a] = target.b2[a] + out_t[i, a]
    delta = np.empty(batch, b1.dtype)
    gb2 = np.zeros(n_act, b1.dtype)
    loss = td_errors(q, acts, idx, replay, discount, delta, gb2)
    g = np.empty((batch, width), b1.dtype)
    e = np.zeros((n_act, width), b1.dtype)
    sb = np.zeros(width, b1.dtype)
    for i in range(batch):
        d, va, ea, hi, gi = delta[i], w2[acts[i]], e[acts[i]], h[i], g[i]
        for j in range(width):
            gi[j] = d * va[j] if hi[j] > zero else zero
            ea[j] += d * hi[j]
            sb[j] += gi[j]
    gw1 = np.dot(np.ascontiguousarray(x[:batch].T), g)
    for k in range(n_obs):
        for j in range(width):
            w1t[k, j] += lr * gw1[k, j]
    for j in range(width):
        b1[j] += lr * sb[j]
    for a in range(n_act):
        for j in range(width):
            w2[a, j] += lr * e[a, j]
        b2[a] += lr * gb2[a]
    return loss


@njit(**_JIT)
def dense_learn(online, target, replay, idx, members, hyper, last_loss):
    """:func:`dense_step` of each member ``k`` with ``members[k]`` (:func:`learn`'s
    interface, the bundles as plain tuples)."""
    net, tgt, buf = Params(*online), Params(*target), Replay(*replay)
    for k in range(members.shape[0]):
        if members[k]:
            last_loss[k] = dense_step(member_params(net, k), member_params(tgt, k),
                                      member_replay(buf, k), idx[k], hyper)  # fmt: skip


@functools.cache
def _blas_on_one_thread() -> None:
    """BLAS on one thread, once per process: a job's step runs on one core, as a sweep that
    runs one job per core expects (and as :mod:`cdqn.bench` measures)."""
    threadpool_limits(1, user_api="blas")


def learn(
    online: Params,
    target: Params,
    replay: Replay,
    idx: np.ndarray,
    members: np.ndarray,
    hyper: np.ndarray,
    block: int,
    last_loss: np.ndarray,
) -> None:
    """One minibatch step of each member ``k`` with ``members[k]`` of the stacked networks
    ``online`` (their targets ``target``), on the transitions ``idx[k]`` of its buffer in
    ``replay``; its loss before the step into ``last_loss[k]``.  Through
    :func:`sparse_learn` where the minibatch's zeros make it the cheaper route
    (:func:`sparse_members`), else through the kernel written out for the shape
    (:func:`kernels`); both take the bundles as plain tuples (:mod:`cdqn.network`,
    bundles)."""
    args = (tuple(online), tuple(target), tuple(replay), idx)
    sparse = np.empty_like(members)
    if sparse_members(replay.obs, replay.next_obs, idx, members, online.w2.shape[1], sparse):
        sparse_learn(*args, sparse, hyper, block, last_loss)
        members = members & ~sparse
        if not members.any():
            return
    if online.w1t.shape[1] >= DENSE_INPUTS:
        _blas_on_one_thread()
        dense_learn(*args, members, hyper, last_loss)
    else:
        compiled = kernels(online.w1t.shape[1], online.w2.shape[1])
        compiled.learn(*args, members, hyper, block, last_loss)


_TEMPLATE = """
import numpy as np
from numba import njit

from cdqn.ddqn_kernels import td_errors
from cdqn.network import Params, Replay, member_params, member_replay

_JIT = {{"cache": True, "fastmath": {{"reassoc", "contract"}}}}


@njit(**_JIT)
def forward(online, target, s, s2, j0, j1, q, zero):
    w1t, b1, w2, tw1t, tb1, tw2 = online.w1t, online.b1, online.w2, target.w1t, target.b1, target.w2
    b, tb = b1[j0:j1], tb1[j0:j1]
    {fw_rows}
    i = 0
    while i + {fw_chunk} <= s.shape[0]:
        {fw_scalars}
        for jj in range(j1 - j0):
            {fw_body}
        {fw_out}
        i += {fw_chunk}
    while i < s.shape[0]:
        {fw1_scalars}
        for jj in range(j1 - j0):
            {fw1_body}
        {fw1_out}
        i += 1


{backward}

@njit(**_JIT)
def step(online, target, replay, idx, hyper, block):
    lr, discount, zero = hyper[0], hyper[1], hyper[2]
    w1t, b1, w2, b2 = online
    buf_obs, buf_next, buf_actions, tb2 = replay.obs, replay.next_obs, replay.actions, target.b2
    batch, n_obs, n_act, width = idx.shape[0], w1t.shape[0], w2.shape[0], w1t.shape[1]
    s = np.empty((batch, n_obs), b1.dtype)
    s2 = np.empty((batch, n_obs), b1.dtype)
    acts = np.empty(batch, np.int64)
    q = np.empty((batch, 3, n_act), b1.dtype)
    for i in range(batch):
        j = idx[i]
        acts[i] = buf_actions[j]
        for k in range(n_obs):
            s[i, k] = buf_obs[j, k]
            s2[i, k] = buf_next[j, k]
        for a in range(n_act):
            q[i, 0, a], q[i, 1, a], q[i, 2, a] = b2[a], b2[a], tb2[a]
    for j0 in range(0, width, block):
        j1 = min(j0 + block, width)
        forward(online, target, s, s2, j0, j1, q, zero)
    delta = np.empty(batch, b1.dtype)
    gb2 = np.zeros(n_act, b1.dtype)
    loss = td_errors(q, acts, idx, replay, discount, delta, gb2)
    backward(online, s, acts, delta, lr, zero, block)
    for a in range(n_act):
        b2[a] += lr * gb2[a]
    return loss


@njit(**_JIT)
def learn(online, target, replay, idx, members, hyper, block, last_loss):
    net, tgt, buf = Params(*online), Params(*target), Replay(*replay)
    for k in range(members.shape[0]):
        if members[k]:
            last_loss[k] = step(member_params(net, k), member_params(tgt, k),
                                member_replay(buf, k), idx[k], hyper, block)
"""

_UNIT_PASS = """
@njit(**_JIT)
def {name}(online, s, acts, delta, i, j0, j1, acc, zero):
    w1t, b1, w2 = online.w1t, online.b1, online.w2
    {rows}
    {scalars}
    for jj in range(j1 - j0):
        {load}
        {body}
        {store}
"""
"""One pass of the unit-major backward loop over a block: ``chunk`` (:data:`CHUNK`
samples) and ``single`` (one)."""

_BACKWARD_UNITS = """
@njit(**_JIT)
def backward(online, s, acts, delta, lr, zero, block):
    w1t, b1, w2 = online.w1t, online.b1, online.w2
    batch, width = acts.shape[0], w1t.shape[1]
    acc = np.empty(({n_acc}, block), b1.dtype)
    for j0 in range(0, width, block):
        j1 = min(j0 + block, width)
        acc[:, : j1 - j0] = zero
        i = 0
        while i + {chunk} <= batch:
            chunk(online, s, acts, delta, i, j0, j1, acc, zero)
            i += {chunk}
        while i < batch:
            single(online, s, acts, delta, i, j0, j1, acc, zero)
            i += 1
        for jj in range(j1 - j0):
            j = j0 + jj
            {bw_step}
"""

_BACKWARD_SAMPLES = """
@njit(**_JIT)
def backward(online, s, acts, delta, lr, zero, block):
    w1t, b1, w2 = online.w1t, online.b1, online.w2
    xs = np.empty((s.shape[1], s.shape[0]), b1.dtype)
    for i in range(s.shape[0]):
        for k in range(s.shape[1]):
            xs[k, i] = s[i, k]
    {bw_cols}
    for j in range(w1t.shape[1]):
        bj = b1[j]
        {bw_params}
        {bw_acc} = zero
        for i in range(acts.shape[0]):
            ai, d = acts[i], delta[i]
            p = bj + {bw_p}
            hd = d * max(p, zero)
            g = d * ({bw_wa}) if p > zero else zero
            sb += g
            {bw_sums}
        b1[j] += lr * sb
        {bw_step}
"""

UNIT_MAJOR_SIZE = 6
"""Up to this many inputs and actions together the backward loop runs over the hidden units
with the unit's ``n + m + 1`` sums in registers (:data:`_BACKWARD_UNITS`); with more, it
runs over the samples per unit (:data:`_BACKWARD_SAMPLES`): the unit-major loop reads and
writes ``2n + m + 2`` rows, and past a few of them LLVM, given no aliasing information,
leaves it scalar (measured: CartPole's 4 + 2 vectorise, Acrobot's 6 + 3 do not)."""

FW_CHUNK_INPUTS = 8
"""Up to this many inputs the forward loop takes two samples per pass over a block."""

CHUNK = 4
"""Samples per pass of the unit-major backward loop over a block of hidden units."""


def _source(n_obs: int, n_actions: int) -> str:
    """The template written out for ``n_obs`` inputs and ``n_actions`` actions."""
    obs, act = range(n_obs), range(n_actions)
    units = n_obs + n_actions <= UNIT_MAJOR_SIZE
    fw_chunk = 2 if n_obs <= FW_CHUNK_INPUTS else 1
    fields: dict[str, object] = {
        "fw_rows": "; ".join(
            [f"W{k}, T{k} = w1t[{k}, j0:j1], tw1t[{k}, j0:j1]" for k in obs]
            + [f"V{a}, U{a} = w2[{a}, j0:j1], tw2[{a}, j0:j1]" for a in act]
        ),
        "fw_chunk": fw_chunk,
    }
    for prefix, samples in (("fw", range(fw_chunk)), ("fw1", range(1))):
        fields |= _forward_fields(prefix, samples, n_obs, n_actions)
    if units:
        bw = {"n_acc": 1 + n_obs + n_actions, "chunk": CHUNK, "bw_step": "\n            ".join(
            ["b1[j] += lr * acc[0, jj]"]
            + [f"w1t[{k}, j] += lr * acc[{1 + k}, jj]" for k in obs]
            + [f"w2[{a}, j] += lr * acc[{1 + n_obs + a}, jj]" for a in act]
        )}  # fmt: skip
        passes = [
            _UNIT_PASS.format(name=name, **_backward_fields(samples, n_obs, n_actions))
            for name, samples in (("chunk", range(CHUNK)), ("single", range(1)))
        ]
        backward = "\n\n".join([*passes, _BACKWARD_UNITS.format(**bw)])
    else:
        backward = _BACKWARD_SAMPLES.format(**_samples_fields(n_obs, n_actions))
    return _TEMPLATE.format(**fields, backward=backward.strip("\n"))


def _samples_fields(n_obs: int, n_actions: int) -> dict[str, str]:
    """:data:`_BACKWARD_SAMPLES` written out: per hidden unit ``j`` a loop over the samples
    with ``p_ij`` again and the unit's ``n + m + 1`` sums."""
    obs, act = range(n_obs), range(n_actions)
    return {
        "bw_cols": "; ".join(f"X{k} = xs[{k}]" for k in obs),
        "bw_params": "; ".join(
            [f"w{k}j = w1t[{k}, j]" for k in obs] + [f"v{a}j = w2[{a}, j]" for a in act]
        ),
        "bw_acc": " = ".join(["sb"] + [f"s{k}" for k in obs] + [f"e{a}" for a in act]),
        "bw_p": " + ".join(f"w{k}j * X{k}[i]" for k in obs),
        "bw_wa": "v0j" if n_actions == 1 else _select(n_actions),
        "bw_sums": "\n            ".join(
            [f"s{k} += X{k}[i] * g" for k in obs]
            + [f"e{a} += hd if ai == {a} else zero" for a in act]
        ),
        "bw_step": "\n        ".join(
            [f"w1t[{k}, j] += lr * s{k}" for k in obs] + [f"w2[{a}, j] += lr * e{a}" for a in act]
        ),
    }


def _select(n_actions: int) -> str:
    """``W_2[a_i, j]`` as a chain of selects (vectorises, unlike a gather)."""
    expr = f"v{n_actions - 1}j"
    for a in range(n_actions - 2, -1, -1):
        expr = f"v{a}j if ai == {a} else ({expr})"
    return expr


def _forward_fields(prefix: str, samples: range, n_obs: int, n_actions: int) -> dict[str, str]:
    """The forward loop's body over the samples ``i + u``, ``u`` in ``samples``: per hidden
    unit the three pre-activations of each sample and the output sums."""
    obs, act = range(n_obs), range(n_actions)

    def terms(w: str, x: str) -> str:
        return " + ".join(f"{w}{k}[jj] * {x}_{k}" for k in obs)

    scalars, body, out = [], [], []
    for u in samples:
        scalars += [
            "; ".join(f"x{u}_{k}, y{u}_{k} = s[i + {u}, {k}], s2[i + {u}, {k}]" for k in obs),
            " = ".join([f"{v}{u}_{a}" for v in ("qs", "qn", "qt") for a in act] + ["zero"]),
        ]
        body += [
            f"hs{u} = max(b[jj] + {terms('W', f'x{u}')}, zero)",
            f"hn{u} = max(b[jj] + {terms('W', f'y{u}')}, zero)",
            f"ht{u} = max(tb[jj] + {terms('T', f'y{u}')}, zero)",
            *[
                f"qs{u}_{a} += V{a}[jj] * hs{u}; qn{u}_{a} += V{a}[jj] * hn{u}; "
                f"qt{u}_{a} += U{a}[jj] * ht{u}"
                for a in act
            ],
        ]
        out += [
            f"q[i + {u}, {r}, {a}] += {v}{u}_{a}"
            for r, v in enumerate(("qs", "qn", "qt"))
            for a in act
        ]
    return {
        f"{prefix}_scalars": "\n        ".join(scalars),
        f"{prefix}_body": "\n            ".join(body),
        f"{prefix}_out": "; ".join(out),
    }


def _backward_fields(samples: range, n_obs: int, n_actions: int) -> dict[str, str]:
    """The backward loop's body over the samples ``i + u``, ``u`` in ``samples``: the
    unit's sums ``acc`` (``Σ g``, ``Σ x_k g``, ``Σ h [a_i = a]`` δ-weighted) loaded, each
    sample's ``h = relu(p)`` and terms added in sample order, stored."""
    obs, act = range(n_obs), range(n_actions)
    names = ["sb"] + [f"s{k}" for k in obs] + [f"e{a}" for a in act]
    body = []
    for u in samples:
        body += [
            f"h{u} = max(b[jj] + {' + '.join(f'W{k}[jj] * x{u}_{k}' for k in obs)}, zero)",
            f"g{u} = d{u} * R{u}[jj] if h{u} > zero else zero",
            f"hd{u} = d{u} * h{u}",
            f"sb += g{u}",
            *[f"s{k} += x{u}_{k} * g{u}" for k in obs],
            *[f"e{a} += hd{u} if a{u} == {a} else zero" for a in act],
        ]
    scalars = []
    for u in samples:
        scalars += [
            f"a{u}, d{u} = acts[i + {u}], delta[i + {u}]",
            f"R{u} = w2[a{u}, j0:j1]",
            *[f"x{u}_{k} = s[i + {u}, {k}]" for k in obs],
        ]
    return {
        "rows": "; ".join(
            [f"A{r} = acc[{r}]" for r in range(len(names))]
            + ["b = b1[j0:j1]"]
            + [f"W{k} = w1t[{k}, j0:j1]" for k in obs]
        ),
        "scalars": "\n    ".join(scalars),
        "load": "; ".join(f"{v} = A{r}[jj]" for r, v in enumerate(names)),
        "body": "\n        ".join(body),
        "store": "; ".join(f"A{r}[jj] = {v}" for r, v in enumerate(names)),
    }


def _cache_dir() -> Path:
    """Where the generated modules (and numba's cache of them) live: ``CDQN_KERNEL_DIR``,
    else ``$XDG_CACHE_HOME/cdqn/kernels`` (``~/.cache/cdqn/kernels``)."""
    if "CDQN_KERNEL_DIR" in os.environ:
        return Path(os.environ["CDQN_KERNEL_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cdqn" / "kernels"


@functools.cache
def kernels(n_obs: int, n_actions: int) -> ModuleType:
    """The compiled module for ``n_obs`` inputs and ``n_actions`` actions: ``learn``
    (``members`` of stacked networks, each its minibatch ``idx[k]`` from its buffer) and the
    loops it calls (module docstring)."""
    source = _source(n_obs, n_actions)
    digest = hashlib.sha256(source.encode()).hexdigest()[:12]
    name = f"ddqn_o{n_obs}_a{n_actions}_{digest}"
    for folder in (_cache_dir(), Path(tempfile.gettempdir()) / f"cdqn-kernels-{os.getuid()}"):
        path = folder / f"{name}.py"
        try:
            if not path.exists() or path.read_text() != source:
                folder.mkdir(parents=True, exist_ok=True)
                tmp = folder / f".{name}.{os.getpid()}.tmp"
                tmp.write_text(source)
                os.replace(tmp, path)  # atomic: concurrent runs never read a partial file
            break
        except OSError:
            continue
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # numba's disk cache imports it by this name
    spec.loader.exec_module(module)
    return module


def double_dqn_learn(
    online: StackedTwoLayer,
    target: StackedTwoLayer,
    replay: Replay,
    idx: np.ndarray,
    members: np.ndarray,
    hyper: np.ndarray,
    last_loss: np.ndarray,
) -> None:
    """One Double DQN minibatch step of each member ``k`` with ``members[k]``, on the
    transitions ``idx[k]`` of its buffer; its loss before the step into ``last_loss[k]``.

    .. math::  \\mathcal L = \\tfrac12 \\sum_i \\delta_i^2,\\qquad
               \\delta_i = r_i + \\gamma (1-d_i)\\,\\bar Q(s'_i, \\arg\\max_a Q(s'_i, a))
               - Q(s_i, a_i),

    targets held constant; ``−∂L/∂θ = Σ_i δ_i ∂Q_{a_i}(s_i)/∂θ`` with the per-sample
    gradients of :mod:`cdqn.network`'s docstring, all at the current parameters, then
    ``θ ← θ + α·(−∂L/∂θ)`` (torch's SGD step on L), written out by hand in :func:`learn`.
    ``hyper``: :func:`cdqn.network.step_settings_array`.
    """
    learn(online.params, target.params, replay, idx, members, hyper, BLOCK, last_loss)


def double_dqn_step(
    online: FastTwoLayer,
    target: FastTwoLayer,
    obs: np.ndarray,
    actions: np.ndarray,
    rewards: np.ndarray,
    next_obs: np.ndarray,
    terminated: np.ndarray,
    discount: float,
    lr: float,
) -> float:
    """One SGD step of Double DQN on the minibatch given (:func:`double_dqn_learn`);
    returns the loss before the step."""
    replay = Replay(
        np.asarray(obs, dtype=np.float64)[None],
        np.asarray(next_obs, dtype=np.float64)[None],
        np.ascontiguousarray(actions, dtype=np.int64)[None],
        np.asarray(rewards, dtype=np.float64)[None],
        np.asarray(terminated, dtype=np.float64)[None],
    )
    loss = np.empty(1)
    double_dqn_learn(
        online.stack, target.stack, replay, np.arange(len(actions))[None],
        np.ones(1, dtype=np.bool_), step_settings_array(lr, discount, online.dtype), loss,
    )  # fmt: skip
    return float(loss[0])
