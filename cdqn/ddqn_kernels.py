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

Two compiled loops do it without a ``(B, W)`` temporary:

1. **forward**, per sample, block by block of hidden units: the three passes in one loop
   over the block, each unit's pre-activations a sum of ``n`` written-out products, the
   ``3m`` output sums vectorised partial sums (``fastmath`` ``reassoc``);
2. **backward**, per hidden unit ``j`` (whose parameters only it touches), a loop over the
   samples: ``p_ij`` again (``n`` multiply-adds: cheaper than storing ``B × W`` of them), the
   unit's gradients as ``n + m + 1`` sums over the samples, then its step.

The loops are written out for the network's ``(n, m)`` (source generated from the template
below, written once to a cache folder so that numba caches its machine code on disk) and run
in the network's dtype.  The same compiled :func:`learn` serves a single run (a stack of one)
and every member of a population, so a member computes exactly the numbers of the single run
of its seed.
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

BLOCK = 256
"""Hidden units per block of the forward loop: the block's rows of both networks' parameters
(``2 (n + m + 1)`` rows, 28 KB in float64 on CartPole) stay in L1 while a sample passes."""


def minibatch_macs(batch: int, n_obs: int, n_actions: int, width: int) -> int:
    """Multiply-adds of one minibatch step (module docstring)."""
    return batch * width * (3 * (n_obs + n_actions) + n_obs + 2 * n_actions)


_TEMPLATE = """
import numpy as np
from numba import njit

_JIT = {{"cache": True, "fastmath": {{"reassoc", "contract"}}}}


@njit(**_JIT)
def forward(w1t, b1, w2, tw1t, tb1, tw2, x, y, j0, j1, out, zero):
    b, tb = b1[j0:j1], tb1[j0:j1]
    {fw_rows}
    {fx}
    {fw_acc} = zero
    for jj in range(j1 - j0):
        hs = max(b[jj] + {ps}, zero)
        hn = max(b[jj] + {pn}, zero)
        ht = max(tb[jj] + {pt}, zero)
        {fw_sums}
    {fw_out}


@njit(**_JIT)
def backward(w1t, b1, w2, xs, acts, delta, lr, zero):
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


@njit(**_JIT)
def step(w1t, b1, w2, b2, tw1t, tb1, tw2, tb2, buf_obs, buf_next, buf_actions, buf_rewards,
         buf_terminated, idx, hyper, block):
    lr, discount, zero = hyper[0], hyper[1], hyper[2]
    batch, n_obs, n_act, width = idx.shape[0], w1t.shape[0], w2.shape[0], w1t.shape[1]
    s = np.empty((batch, n_obs), b1.dtype)
    s2 = np.empty((batch, n_obs), b1.dtype)
    xs = np.empty((n_obs, batch), b1.dtype)
    acts = np.empty(batch, np.int64)
    q = np.empty((batch, 3, n_act), b1.dtype)
    for i in range(batch):
        j = idx[i]
        acts[i] = buf_actions[j]
        for k in range(n_obs):
            s[i, k] = buf_obs[j, k]
            s2[i, k] = buf_next[j, k]
            xs[k, i] = s[i, k]
        for a in range(n_act):
            q[i, 0, a], q[i, 1, a], q[i, 2, a] = b2[a], b2[a], tb2[a]
    for j0 in range(0, width, block):
        j1 = min(j0 + block, width)
        for i in range(batch):
            forward(w1t, b1, w2, tw1t, tb1, tw2, s[i], s2[i], j0, j1, q[i], zero)
    delta = np.empty(batch, b1.dtype)
    gb2 = np.zeros(n_act, b1.dtype)
    loss = 0.0
    for i in range(batch):
        j, qi = idx[i], q[i]
        best = 0  # Double DQN: the online network's action at s'_i (first maximum)
        for a in range(1, n_act):
            if qi[1, a] > qi[1, best]:
                best = a
        y = buf_rewards[j] + discount * (1.0 - buf_terminated[j]) * qi[2, best]
        delta[i] = y - qi[0, acts[i]]
        loss += 0.5 * float(delta[i]) * float(delta[i])
        gb2[acts[i]] += delta[i]
    backward(w1t, b1, w2, xs, acts, delta, lr, zero)
    for a in range(n_act):
        b2[a] += lr * gb2[a]
    return loss


@njit(**_JIT)
def learn(w1t, b1, w2, b2, tw1t, tb1, tw2, tb2, buf_obs, buf_next, buf_actions, buf_rewards,
          buf_terminated, idx, members, hyper, block, last_loss):
    for k in range(members.shape[0]):
        if members[k]:
            last_loss[k] = step(w1t[k], b1[k], w2[k], b2[k], tw1t[k], tb1[k], tw2[k], tb2[k],
                                buf_obs[k], buf_next[k], buf_actions[k], buf_rewards[k],
                                buf_terminated[k], idx[k], hyper, block)
"""


def _source(n_obs: int, n_actions: int) -> str:
    """The template written out for ``n_obs`` inputs and ``n_actions`` actions."""
    obs, act = range(n_obs), range(n_actions)

    def terms(w: str, x: str) -> str:
        return " + ".join(f"{w}{k}[jj] * {x}{k}" for k in obs)

    fw_acc = [f"{v}{a}" for v in ("qs", "qn", "qt") for a in act]
    sums = [f"qs{a} += V{a}[jj] * hs; qn{a} += V{a}[jj] * hn; qt{a} += U{a}[jj] * ht" for a in act]
    wa = "v0j" if n_actions == 1 else _select(n_actions)
    fields = {
        "fw_rows": "; ".join(
            [f"W{k}, T{k} = w1t[{k}, j0:j1], tw1t[{k}, j0:j1]" for k in obs]
            + [f"V{a}, U{a} = w2[{a}, j0:j1], tw2[{a}, j0:j1]" for a in act]
        ),
        "fx": "; ".join(f"x{k}, y{k} = x[{k}], y[{k}]" for k in obs),
        "fw_acc": " = ".join(fw_acc),
        "ps": terms("W", "x"),
        "pn": terms("W", "y"),
        "pt": terms("T", "y"),
        "fw_sums": "\n        ".join(sums),
        "fw_out": "; ".join(
            f"out[{r}, {a}] += {v}{a}" for r, v in enumerate(("qs", "qn", "qt")) for a in act
        ),
        "bw_cols": "; ".join(f"X{k} = xs[{k}]" for k in obs),
        "bw_params": "; ".join(
            [f"w{k}j = w1t[{k}, j]" for k in obs] + [f"v{a}j = w2[{a}, j]" for a in act]
        ),
        "bw_acc": " = ".join(["sb"] + [f"s{k}" for k in obs] + [f"e{a}" for a in act]),
        "bw_p": " + ".join(f"w{k}j * X{k}[i]" for k in obs),
        "bw_wa": wa,
        "bw_sums": "\n            ".join(
            [f"s{k} += X{k}[i] * g" for k in obs]
            + [f"e{a} += hd if ai == {a} else zero" for a in act]
        ),
        "bw_step": "\n        ".join(
            [f"w1t[{k}, j] += lr * s{k}" for k in obs] + [f"w2[{a}, j] += lr * e{a}" for a in act]
        ),
    }
    return _TEMPLATE.format(**fields)


def _select(n_actions: int) -> str:
    """``W_2[a_i, j]`` as a chain of selects (vectorises, unlike a gather)."""
    expr = f"v{n_actions - 1}j"
    for a in range(n_actions - 2, -1, -1):
        expr = f"v{a}j if ai == {a} else ({expr})"
    return expr


def _cache_dir() -> Path:
    """Where the generated modules (and numba's cache of them) live: ``CDQN_KERNEL_DIR``,
    else ``$XDG_CACHE_HOME/cdqn/kernels`` (``~/.cache/cdqn/kernels``)."""
    if "CDQN_KERNEL_DIR" in os.environ:
        return Path(os.environ["CDQN_KERNEL_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cdqn" / "kernels"


@functools.cache
def kernels(n_obs: int, n_actions: int) -> ModuleType:
    """The compiled module for ``n_obs`` inputs and ``n_actions`` actions: :func:`learn`
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
