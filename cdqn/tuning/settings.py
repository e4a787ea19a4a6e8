"""The schema of ``python -m cdqn.tune`` (``tune.*``) and its checks."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from cdqn.config import TARGET_CONTROLLERS, Config, ConfigError, register_configs, validate

TUNABLE = ("h2", "hinf", "hinf_f", "ddqn")
"""Agents a study can tune: the three synthesised designs and Double DQN."""


@dataclass
class ParamSpec:
    """One dimension of the search space.

    ``choices``: a categorical value at ``path``.  ``width``: the centre c of a range is
    sampled in [low, high] (or from ``choices``) and ``path`` becomes
    [c − width/2, c + width/2] (γ_eff, 1 + k1).
    ``scale``: a factor f in [low, high] multiplies every number at ``path`` (a weight's
    magnitude, e.g. ``weights.{controller}.w_p.num``).  Otherwise a number in [low, high]
    (``integer``: a whole one).  ``{controller}`` in ``path`` is the controller's name.
    ``when``: the dimension is sampled only in trials whose other dimensions take these
    values (``{eps_schedule: episode}``); other trials leave ``path`` as configured.
    ``horizon``: the number h (and ``width``) is a signed decimal log-horizon, written as the
    discount γ(h) = sign(h)·(1 − 10^(−|h|)), so that 1/(1 − |γ|) = 10^|h| steps
    (:func:`cdqn.tuning.space.discount_of`); with ``width`` the range is
    [γ(h − width/2), γ(h + width/2)].  Uniform in h, the discounts near ±1, where a goal task
    learns, are as likely as those near 0."""

    path: str = "???"
    low: float | None = None
    high: float | None = None
    log: bool = False
    """Sample on a log scale."""
    width: float | None = None
    scale: bool = False
    integer: bool = False
    choices: list[Any] | None = None
    when: dict[str, Any] | None = None
    horizon: bool = False


@dataclass
class PrunerConfig:
    kind: str = "median"
    """median (:class:`EpisodeMedianPruner`: J over the episodes so far against the median of
    the complete trials' at the same episode) or none."""
    startup_trials: int = 3
    """Trials that complete before any is pruned."""
    warmup_episodes: int | None = None
    """Episodes before a trial can be pruned (null: half of the episode budget, at least
    50: the first episodes are mostly random play, and J_n there says little)."""
    interval: int = 25
    """Episodes between the intermediate values reported to Optuna."""


@dataclass
class TuneSettings:
    study: str = "cdqn"
    """Optuna study name (also the MLflow parent run's name)."""
    storage: str = "sqlite:///optuna.db"
    """Optuna storage; an SQLite file survives a restart and the study continues."""
    trials: int = 20
    """Trials of the study that train (a resumed study runs the missing ones); a specification
    refused before training (infeasible) does not count, up to ``trials`` of them."""
    seeds: int = 3
    """Population size K of a trial."""
    seed: int = 100
    """First seed of every trial's population (seed … seed+K−1, the same for all trials)."""
    episodes: int | None = None
    """Training episodes per member (trials and evaluation); null: ``steps`` divided by the
    environment's episode cap, within [min_episodes, max_episodes]."""
    steps: int = 300_000
    """With episodes null: the environment steps per member the episode budget is sized on
    (episodes at the cap), so that a study's cost follows the environment's own scale."""
    min_episodes: int = 100
    """With episodes null: the fewest episodes per member."""
    max_episodes: int = 2000
    """With episodes null: the most episodes per member."""
    time_limit: float | None = 1800.0
    """Wall time of the whole study, evaluation included, seconds (null: none): a worker
    starts no trial that, with the evaluation, would end past it (:mod:`cdqn.tuning.clock`)."""
    trial_share: float | None = 0.25
    """The most wall time one trial trains, as a share of ``time_limit`` (null: no cap): a
    trial still training then stops and is pruned, so that any complete trial and its
    evaluation fit the limit (:mod:`cdqn.tuning.clock`)."""
    eval_seeds: int = 10
    """Fresh seeds of the final evaluation of the best specification (0: none)."""
    eval_seed: int = 1000
    """First seed of the evaluation; its seeds must not overlap the trials' seeds."""
    recheck_trials: int = 3
    """The best complete trials (by J) trained again on ``recheck_seeds`` more seeds before
    the study chooses one (:meth:`cdqn.tuning.study.Study.choose`); 0 or 1: the best by J."""
    recheck_seeds: int = 4
    """Seeds of each recheck: ``recheck_seed`` … ``recheck_seed + recheck_seeds − 1``."""
    recheck_seed: int = 200
    """First seed of the rechecks; disjoint from the trials' and the evaluation's seeds."""
    explore_share: float = 0.2
    """The per-episode ε schedule reaches its floor no earlier than this share of the
    episodes (:func:`cdqn.tuning.space.fit_to_budget`); 0: the space's range as written."""
    max_rbf_features: int = 256
    """The radial-basis dimension offers n centres per feature only where n^d stays within
    this: the network's first layer, and the time of a trial, grow with the features."""
    eval_processes: int = 0
    """Processes the evaluation's seeds are split over, trained side by side (0: one per
    core)."""
    baseline: str | None = None
    """A controller (e.g. ddqn) trained, untuned, on the evaluation seeds beside the best
    design."""
    sampler_seed: int = 0
    """Seed of Optuna's TPE sampler."""
    sampler_startup: int = 10
    """Trials the TPE sampler draws at random (the warm start's among them) before it models
    the trials so far (Optuna's ``n_startup_trials``)."""
    sampler_multivariate: bool = False
    """TPE models the dimensions jointly (Optuna's ``multivariate`` and ``group``, for the
    dimensions that exist only under another's value) rather than one by one."""
    worker: int = 0
    """Index of this process among the study's parallel workers (``-m tune.worker=0,1``);
    worker 0 waits for the others' trials and writes the plots, preset and evaluation."""
    pruner: PrunerConfig = field(default_factory=PrunerConfig)
    space: dict[str, ParamSpec] = field(default_factory=dict)
    """The search space, name → :class:`ParamSpec` (conf/space/<controller>.yaml)."""
    warm_start: list[str] = field(default_factory=list)
    """Environments (names of studies' environments) whose tuned presets for the same agent,
    ``tuned_<name>-<agent>``, give a new study its first trials: their specifications, fitted
    to this study's space (:func:`cdqn.tuning.space.fitted_specification`); looked up in
    ``preset_dir``, then among the shipped presets."""
    preset: str | None = None
    """Name of the weights preset written for the best trial (null: tuned_<study>)."""
    preset_dir: str = "presets"
    """Folder of user presets; the preset goes to <preset_dir>/weights/<name>.yaml."""


@dataclass
class TuneConfig(Config):
    tune: TuneSettings = field(default_factory=TuneSettings)


register_configs()
ConfigStore.instance().store(name="base_tune", node=TuneConfig)


def episode_budget(t: TuneSettings, cap: int | None) -> int:
    """Episodes per member: ``tune.episodes``, else ``tune.steps / cap`` clamped to
    ``[tune.min_episodes, tune.max_episodes]`` (``cap``: the environment's episode cap,
    :func:`cdqn.envs.make.episode_cap`)."""
    if t.episodes is not None:
        return t.episodes
    if not cap:
        return t.max_episodes
    return int(min(t.max_episodes, max(t.min_episodes, t.steps // cap)))


def trial_cap(t: TuneSettings) -> float | None:
    """T_cap, the most seconds a trial trains: ``trial_share · time_limit`` (None without
    either)."""
    if t.time_limit is None or t.trial_share is None:
        return None
    return t.trial_share * t.time_limit


def warmup(p: PrunerConfig, episodes: int) -> int:
    """The pruner's warm-up in episodes: ``tune.pruner.warmup_episodes``, else half of
    ``episodes`` (at least 50).  A study lets ε reach its floor as late as
    ``tune.explore_share`` of the episodes, and J_n counts every episode from the first: at a
    quarter of the episodes a trial that explores that long is still mostly random play, and
    on Acrobot-v1 the median rule pruned there the one specification that ended best on its
    seeds (docs/research/tuning.md, 2026-11-30 (sixth))."""
    return p.warmup_episodes if p.warmup_episodes is not None else max(50, episodes // 2)


def validate_tune(conf: TuneConfig) -> None:
    """The training configuration's rules and the study's: one line per problem."""
    validate(conf)
    t = conf.tune
    errors: list[str] = []
    if conf.controller.name not in TUNABLE:
        allowed = ", ".join(TUNABLE)
        errors.append(f"controller={conf.controller.name}: tune searches {allowed}")
    if conf.controller.name in TARGET_CONTROLLERS and conf.controller.design != "synthesize":
        errors.append(
            f"controller.design={conf.controller.design}: tune needs controller.design=synthesize"
        )
    for key, value, lo in (("trials", t.trials, 1), ("seeds", t.seeds, 1),
                           ("episodes", t.episodes if t.episodes is not None else 1, 1),
                           ("steps", t.steps, 1), ("min_episodes", t.min_episodes, 1),
                           ("max_episodes", t.max_episodes, t.min_episodes),
                           ("eval_seeds", t.eval_seeds, 0),
                           ("recheck_trials", t.recheck_trials, 0),
                           ("recheck_seeds", t.recheck_seeds, 0),
                           ("eval_processes", t.eval_processes, 0),
                           ("max_rbf_features", t.max_rbf_features, 1),
                           ("pruner.interval", t.pruner.interval, 1), ("worker", t.worker, 0),
                           ("sampler_startup", t.sampler_startup, 1)):  # fmt: skip
        if value < lo:
            errors.append(f"tune.{key}={value}: must be an integer >= {lo}")
    if not 0 <= t.explore_share <= 1:
        errors.append(f"tune.explore_share={t.explore_share}: must be a share in [0, 1]")
    if t.time_limit is not None and not t.time_limit >= 0:
        errors.append(f"tune.time_limit={t.time_limit}: must be a number of seconds >= 0, or null "
                      "for no limit")  # fmt: skip
    if t.trial_share is not None and not 0 < t.trial_share <= 1:
        errors.append(f"tune.trial_share={t.trial_share}: must be a share in (0, 1], or null "
                      "for no cap")  # fmt: skip
    if t.pruner.kind not in ("median", "none"):
        errors.append(f"tune.pruner.kind={t.pruner.kind}: allowed median, none")
    trial = set(range(t.seed, t.seed + t.seeds))
    fresh = set(range(t.eval_seed, t.eval_seed + t.eval_seeds))
    if trial & fresh:
        last = t.eval_seed + t.eval_seeds - 1
        errors.append(
            f"tune.eval_seed={t.eval_seed}: evaluation seeds {t.eval_seed}..{last}"
            f" overlap the trials' seeds {t.seed}..{t.seed + t.seeds - 1}; choose fresh seeds"
        )
    again = set(range(t.recheck_seed, t.recheck_seed + t.recheck_seeds))
    if t.recheck_trials > 1 and again & (trial | fresh):
        last = t.recheck_seed + t.recheck_seeds - 1
        errors.append(
            f"tune.recheck_seed={t.recheck_seed}: recheck seeds {t.recheck_seed}..{last} overlap "
            "the trials' or the evaluation's seeds; choose seeds of their own"
        )
    if not t.space:
        errors.append("tune.space: empty; give at least one dimension")
    errors += warm_start_errors(t, conf.controller.name)
    for name, p in t.space.items():
        errors += [f"tune.space.{name}: {e}" for e in _spec_errors(p, conf)]
        for other in p.when or {}:
            if other not in t.space:
                errors.append(f"tune.space.{name}.when: {other!r} is no dimension of tune.space")
    if errors:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(errors))


def warm_start_preset(name: str, agent: str) -> str:
    """The preset of ``tune.warm_start`` entry ``name`` for ``agent``."""
    return f"tuned_{name}-{agent}"


def warm_start_errors(t: TuneSettings, agent: str) -> list[str]:
    """One line per ``tune.warm_start`` entry that names no preset with a specification."""
    from cdqn.tuning.presets import specification_of

    errors = []
    for name in t.warm_start:
        try:
            specification_of(warm_start_preset(name, agent), t.preset_dir)
        except ConfigError as err:
            errors.append(f"tune.warm_start: {name}: {err}")
    return errors


def _spec_errors(p: ParamSpec, conf: Config) -> list[str]:
    path = p.path.format(controller=conf.controller.name)
    if OmegaConf.select(OmegaConf.structured(conf), path, default="__missing__") == "__missing__":
        return [f"path={p.path!r} names no configuration key"]
    if p.choices is not None:
        return [] if p.choices else ["choices=[]: give at least one"]
    if p.low is None or p.high is None or not p.low < p.high:
        return [f"low={p.low}, high={p.high}: need numbers with low < high"]
    if p.log and p.low <= 0:
        return [f"low={p.low}: a log scale needs low > 0"]
    return []
