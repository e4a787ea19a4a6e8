"""The search space: sampling a specification and writing it into a configuration."""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
from typing import Any

from omegaconf import DictConfig, OmegaConf, read_write

from cdqn.config import TARGET_FIELDS, target_key
from cdqn.tuning.settings import ParamSpec

log = logging.getLogger("cdqn.tune")

RBF_PATH = "env.rbf_centres"
"""A dimension whose choices depend on the observation (:func:`fit_to_observation`)."""
NORMALIZE_PATH = "env.normalize"
"""The [−1, 1] map: not offered for a wide one-hot observation (:func:`fit_to_observation`)."""
EPS_PATH = "train.eps_dec"
"""The ε decrease; its per-episode range depends on the episode budget (:func:`fit_to_budget`)."""
EPS_END_PATH = "train.eps_end"
"""ε's floor; the highest offered sets the per-episode range (:func:`highest_floor`)."""
GAMMA_PATH = "weights.target.gamma_eff"
"""The effective discount of the learning target; bounded by the NTK box (:func:`fit_to_box`)."""


def sample(trial: Any, space: dict[str, ParamSpec]) -> dict[str, Any]:
    """The trial's specification: one value per dimension whose ``when`` holds (Optuna's
    define-by-run suggest API; dimensions are sampled in the order of ``space``)."""
    out: dict[str, Any] = {}
    for name, p in space.items():
        if not _applies(p, out):
            continue
        if p.choices is not None:
            out[name] = trial.suggest_categorical(name, list(p.choices))
        elif p.low is None or p.high is None:  # refused by the settings' check
            raise ValueError(f"{name}: low={p.low}, high={p.high}: need numbers")
        elif p.integer:
            out[name] = trial.suggest_int(name, int(p.low), int(p.high), log=p.log)
        else:
            out[name] = trial.suggest_float(name, float(p.low), float(p.high), log=p.log)
    return out


_ABSENT = object()


def _applies(p: ParamSpec, chosen: dict[str, Any]) -> bool:
    """Whether the dimension ``p`` is sampled given the values ``chosen`` so far (its ``when``)."""
    return not p.when or all(chosen.get(k, _ABSENT) == v for k, v in p.when.items())


def apply(cfg: DictConfig, space: dict[str, ParamSpec], params: dict[str, Any]) -> DictConfig:
    """``cfg`` with the specification ``params`` written into it (:class:`ParamSpec`)."""
    out = copy.deepcopy(cfg)
    name = str(cfg.controller.name)
    with read_write(out):
        for key, value in params.items():
            p = space[key]
            path = _own_target_path(p.path.format(controller=name), out.weights, name)
            if p.width is not None or p.horizon:
                value = written(p, float(value))
            elif p.choices is None and p.scale:
                node = OmegaConf.select(out, path)
                plain = OmegaConf.to_container(node) if OmegaConf.is_config(node) else node
                value = _scaled(plain, float(value))
            OmegaConf.update(out, path, value, merge=False)
    return out


def written(p: ParamSpec, value: float) -> float | list[float]:
    """What the number ``value`` of a ``width`` or ``horizon`` dimension writes at its path:
    the range [c − width/2, c + width/2] (of discounts γ(h) for a horizon), or γ(h)."""
    if p.width is not None:
        lo, hi = value - p.width / 2, value + p.width / 2
        return [discount_of(lo), discount_of(hi)] if p.horizon else [lo, hi]
    return discount_of(value) if p.horizon else value


def lowest(p: ParamSpec, value: float) -> float:
    """The lowest number ``value`` writes (:func:`written`)."""
    out = written(p, value)
    return out[0] if isinstance(out, list) else out


def discount_of(h: float) -> float:
    """The discount of the signed decimal log-horizon ``h`` (:class:`ParamSpec`):
    γ(h) = sign(h)·(1 − 10^(−|h|)); γ(0) = 0, γ(±2) = ±0.99, and γ is increasing in h."""
    return math.copysign(1.0 - 10.0 ** (-abs(h)), h)


def log_horizon_of(gamma: float) -> float:
    """The inverse of :func:`discount_of` on (−1, 1): h = sign(γ)·(−log10(1 − |γ|))."""
    return math.copysign(-math.log10(1.0 - abs(gamma)), gamma)


def fit_to_box(space: dict[str, ParamSpec], rho_max: float) -> dict[str, ParamSpec]:
    """``space`` with the effective discounts no design can keep stable over the measured NTK
    boxes left out: a static loop is stable over a box only for γ_eff < 1/ρ_max
    (:func:`cdqn.control.target.stable_over_box`), so a trial whose γ_eff range starts at or
    above it is refused before it trains.  ``rho_max``: the smallest upper Θ2/Θ1 of the
    boxes of the offered observation maps (a value one of them allows stays).  A choice whose
    range starts too high is dropped, and the positive ones dropped give way to the longest
    positive centre the boxes allow (:func:`top_centre`, on a 0.05 grid), so that a task whose
    box rules out the offered positive horizons still has one to learn with; a range's
    ``high`` is lowered to the last centre allowed.  Where no value would remain, the dimension
    is kept as it is (and said so)."""
    from cdqn.control.target import stable_over_box

    out = dict(space)
    for name, p in space.items():
        if p.path != GAMMA_PATH:
            continue
        fitted: ParamSpec | None = p
        if p.choices is not None:
            allowed = [c for c in p.choices if stable_over_box(lowest(p, float(c)), rho_max)]
            top = top_centre(p, rho_max, grid=0.05) if rho_max > 1.0 else None
            cut = any(float(c) > 0 and c not in allowed for c in p.choices)
            if cut and top is not None and top > max([0.0, *map(float, allowed)]):
                allowed.append(top)
            fitted = dataclasses.replace(p, choices=allowed) if allowed else None
        elif p.low is not None and p.high is not None and rho_max > 1.0:
            top = top_centre(p, rho_max)
            fitted = dataclasses.replace(p, high=min(top, p.high)) if top > p.low else None
        if fitted is None:
            log.warning("tune.space.%s: the measured NTK boxes allow γ_eff < 1/ρ_max = %.4g, "
                        "below every value offered; each trial will be refused", name,
                        1.0 / rho_max)  # fmt: skip
        elif fitted != p:
            log.info("tune.space.%s: %s -> %s (the measured NTK boxes allow γ_eff < 1/ρ_max "
                     "= %.4g)", name, p.choices or [p.low, p.high],
                     fitted.choices or [fitted.low, fitted.high], 1.0 / rho_max)  # fmt: skip
            out[name] = fitted
    return out


def top_centre(p: ParamSpec, rho_max: float, grid: float | None = None) -> float:
    """The largest value of the γ_eff dimension ``p`` whose range starts below 1/ρ_max
    (:func:`fit_to_box`): for a horizon, h < log_horizon_of(1/ρ_max) + width/2; rounded down
    to a multiple of ``grid`` when given (a choice's value, as a person would write it)."""
    bound = 1.0 / rho_max
    top = (log_horizon_of(bound) if p.horizon else bound) + (p.width or 0.0) / 2 - 1e-9
    return top if grid is None else round(math.floor(top / grid) * grid, 10)


def fit_to_observation(
    space: dict[str, ParamSpec],
    bounded: bool,
    n_features: int,
    max_features: int,
    one_hot: bool = False,
) -> dict[str, ParamSpec]:
    """``space`` with the dimensions that depend on the observation kept to the choices it
    allows.  Radial basis features (``env.rbf_centres``): none unless every observed feature
    is bounded, and ``n`` centres per feature only where ``n^d <= max_features``.  The
    [−1, 1] map (``env.normalize``) of a one-hot observation (:class:`cdqn.envs.OneHot`):
    only where ``d <= max_features``, since the map sends the d − k zeros of a one-hot
    vector to −1 and the first layer then reads d inputs per sample instead of k (Taxi-v4:
    500 against 1).  A radial-basis dimension left with one choice is dropped (the
    configuration's value stands); the map's keeps its one choice, which may differ from the
    configuration's."""
    out = dict(space)
    for name, p in space.items():
        if p.choices is None or p.path not in (RBF_PATH, NORMALIZE_PATH):
            continue
        if p.path == RBF_PATH:
            allowed = [
                c
                for c in p.choices
                if c is None or (bounded and int(c) ** n_features <= max_features)
            ]
        else:
            allowed = [c for c in p.choices if not (c and one_hot and n_features > max_features)]
        if len(allowed) < len(p.choices):
            log.info("tune.space.%s: choices %s (the observation allows %s)", name,
                     list(p.choices), allowed)  # fmt: skip
        if len(allowed) == 1 and p.path == NORMALIZE_PATH:
            out[name] = dataclasses.replace(p, choices=allowed)
        elif len(allowed) <= 1:
            del out[name]
        else:
            out[name] = dataclasses.replace(p, choices=allowed)
    return out


def highest_floor(space: dict[str, ParamSpec], configured: float) -> float:
    """The highest ε floor (``train.eps_end``) a trial can have: the largest the space offers,
    else ``configured``."""
    offered = [float(v) for p in space.values() if p.path == EPS_END_PATH
               for v in (p.choices or [p.high]) if v is not None]  # fmt: skip
    return max(offered, default=configured)


def fit_to_budget(
    space: dict[str, ParamSpec], episodes: int, share: float, eps_span: float
) -> dict[str, ParamSpec]:
    """``space`` with the per-episode ε decrease (``train.eps_dec`` when
    ``eps_schedule=episode``) kept to schedules that reach their floor no earlier than
    ``share`` of the ``episodes``: ε falls by ``eps_span`` (start − the highest floor) in
    ``eps_span / eps_dec`` episodes, so ``eps_dec ≤ eps_span / (share · episodes)``.

    A schedule that stops exploring early leaves the seeds that have not met the reward by
    then on their first policy, and three tuning seeds rarely show it (FrozenLake-v1,
    docs/research/tuning.md).  The bound is the same for every agent of a study."""
    out = dict(space)
    if share <= 0 or episodes <= 0:
        return out
    bound = eps_span / (share * episodes)
    for name, p in space.items():
        per_episode = p.when is not None and p.when.get("eps_schedule") == "episode"
        if p.path != EPS_PATH or not per_episode or p.high is None or p.low is None:
            continue
        if bound < p.high:
            high = max(float(p.low), bound)
            log.info("tune.space.%s: high %g -> %g (ε at its floor after %.0f%% of %d "
                     "episodes at the earliest)", name, p.high, high, 100 * share,
                     episodes)  # fmt: skip
            out[name] = dataclasses.replace(p, high=high)
    return out


def fitted_specification(
    space: dict[str, ParamSpec], params: dict[str, Any], searched: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    """``params``, a specification another study found in its space ``searched`` (name →
    the dimension's fields, as a preset records them), as values this ``space`` offers, for
    a trial to start from.  Dimensions go in the order of ``space``: those whose ``when``
    holds, that ``params`` gives, and that write the same quantity in both spaces (``path``,
    ``horizon``, ``scale`` and whether a ``width`` makes a range); a choice not offered
    becomes the nearest offered number (a continuous γ_eff centre, 6 radial basis centres
    where only 4 fit), or is left out when no choice is a number; a number is clipped into
    [low, high].  Dimensions left out are sampled as in any trial."""
    out: dict[str, Any] = {}
    for name, p in space.items():
        if not _applies(p, out):
            continue
        value = params.get(name, _ABSENT)
        if value is _ABSENT or value is None and p.choices is None:
            continue
        other = searched.get(name, {})
        if (
            other.get("path"),
            bool(other.get("horizon")),
            bool(other.get("scale")),
            other.get("width") is None,
        ) != (p.path, p.horizon, p.scale, p.width is None):
            continue  # fmt: skip
        if p.choices is not None:
            numbers = [c for c in p.choices if _is_number(c)]
            if any(value == c and type(value) is type(c) for c in p.choices):
                out[name] = value
            elif _is_number(value) and numbers:
                out[name] = min(numbers, key=lambda c: abs(float(c) - float(value)))
        elif p.low is not None and p.high is not None and _is_number(value):
            clipped = min(max(float(value), float(p.low)), float(p.high))
            out[name] = int(round(clipped)) if p.integer else clipped
    return out


def with_each_input_map(
    space: dict[str, ParamSpec], params: dict[str, Any]
) -> list[dict[str, Any]]:
    """``params`` with each other choice of the [−1, 1] map (``env.normalize``) that ``space``
    offers, for a warm start to try a preset's specification on each observation map.

    The map is what transfers least between environments: it changes the NTK box the design
    is certified on (one-hot CliffWalking-v1 raw: Θ1 ≈ 19, Θ2/Θ1 ∈ [0.585, 1]; mapped:
    Θ1 ≈ 430, Θ2/Θ1 ∈ [0.89, 1], the states nearly one input), and the same specification
    learns under one map and not the other (docs/research/tuning.md).  Empty where
    ``params`` leaves the map to the sampler or the space offers one choice."""
    out: list[dict[str, Any]] = []
    for name, p in space.items():
        if p.path != NORMALIZE_PATH or p.choices is None or name not in params:
            continue
        out += [params | {name: c} for c in p.choices if c != params[name]]
    return out


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _own_target_path(path: str, weights: Any, controller: str) -> str:
    """``weights.target.<range>`` names that range of the tuned controller's learning target:
    ``weights.controller_target.<controller>.<range>`` where the environment sets it."""
    head = "weights.target."
    if not path.startswith(head) or path[len(head) :] not in TARGET_FIELDS:
        return path
    return target_key(weights, controller, path[len(head) :])


def _scaled(value: Any, factor: float) -> Any:
    if isinstance(value, list):
        return [_scaled(v, factor) for v in value]
    return float(value) * factor
