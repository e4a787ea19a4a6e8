"""What a cdqn run writes to MLflow: metric keys, tag keys, artifact paths and the columns
of the per-step signal table, named once here.

Training, tuning, the benchmark and ``analysis/`` write and read the store through these
names; the table "What a run records in MLflow" of docs/how_it_works.md lists them
(``tests/test_records.py`` checks the two agree).  Each constant is the string stored, so
stores written before this module existed read the same.
"""

from __future__ import annotations

from typing import Final


class Metric:
    """Metric keys of a run (per-episode ones at step = episode index)."""

    EPISODE_RETURN: Final = "episode_return"
    """Undiscounted return of the episode, Σ_t r(t) (reward units)."""
    RETURN_MA100: Final = "return_ma100"
    """Mean ``episode_return`` of the last 100 episodes, fewer at the start (reward units)."""
    EPISODE_LENGTH: Final = "episode_length"
    """Length of the episode (environment steps)."""
    LOSS_MEAN: Final = "loss_mean"
    """Mean of the episode's finite losses, ½(r + γQ2 + u − Q1)² up to the agent's weight."""
    U_ABS_MEAN: Final = "u_abs_mean"
    """Mean |u(t)| of the episode, the control reward injected into the loss (reward units)."""
    THETA1_MEAN: Final = "theta1_mean"
    """Mean Θ1 = Θ((s, a), (s, a)) of the episode, the NTK of paper Sec. 3."""
    UNSTABLE_FRACTION: Final = "unstable_fraction"
    """Share (0..1) of the episode's steps with Θ1 < γΘ2, the nominal TD dynamics unstable."""
    REPLAY_UPDATES: Final = "replay_updates"
    """Updates of episodic replay after the episode (count; ``cdqn.agents.episodic_replay``)."""
    THETA1_OUTSIDE_BOX: Final = "theta1_outside_box"
    """Share (0..1) of the episode's steps with Θ1 outside the design's NTK box."""
    RATIO_BELOW_BOX: Final = "ratio_below_box"
    """Share (0..1) of the episode's steps with Θ2/Θ1 below the box's ratio range."""
    RATIO_ABOVE_BOX: Final = "ratio_above_box"
    """Share (0..1) of the episode's steps with Θ2/Θ1 above the box's ratio range."""
    FINAL_SCORE: Final = "final_score"
    """Mean return of the last 100 episodes, logged once at the end, step 0 (reward units)."""
    OBJECTIVE: Final = "objective"
    """A tuning trial's objective J, the area under its learning curve (docs/tuning.md)."""
    EVAL_RETURN_MEAN: Final = "eval_return_mean"
    """Mean return of ``python -m cdqn.evaluate``'s greedy episodes (reward units)."""
    EVAL_RETURN_STD: Final = "eval_return_std"
    """Standard deviation of those returns (reward units)."""
    EVAL_RETURN_MIN: Final = "eval_return_min"
    """Smallest of those returns (reward units)."""
    EVAL_RETURN_MAX: Final = "eval_return_max"
    """Largest of those returns (reward units)."""
    EVAL_EPISODES: Final = "eval_episodes"
    """Greedy episodes played by the evaluation (count)."""


EPISODE_METRICS: Final = (
    Metric.EPISODE_RETURN,
    Metric.RETURN_MA100,
    Metric.EPISODE_LENGTH,
    Metric.LOSS_MEAN,
    Metric.U_ABS_MEAN,
    Metric.THETA1_MEAN,
    Metric.UNSTABLE_FRACTION,
    Metric.REPLAY_UPDATES,
    Metric.THETA1_OUTSIDE_BOX,
    Metric.RATIO_BELOW_BOX,
    Metric.RATIO_ABOVE_BOX,
)
"""The per-episode metrics, in the order ``EpisodeStats`` holds them."""


class Signal:
    """Columns of ``signals/steps.parquet`` (one row per environment step) and of
    ``signals/fft.parquet``."""

    EPISODE: Final = "episode"
    """Episode index, from 0."""
    STEP: Final = "step"
    """Step within the episode, from 0."""
    REWARD: Final = "reward"
    """Environment reward r(t)."""
    Q1: Final = "q1"
    """Q1 = Q(s, a) before the update."""
    Q2: Final = "q2"
    """Q2 = max_a' Q(s', a') before the update."""
    U: Final = "u"
    """Control reward u(t) injected into the loss (0 without a controller)."""
    X_E: Final = "x_e"
    """Integrated tracking error x_e = ∫ (r + γ Q̂2 − Q1) dt, Δt = α."""
    THETA1: Final = "theta1"
    """Θ1 = Θ((s, a), (s, a)), the NTK on the updated pair."""
    THETA2: Final = "theta2"
    """Θ2 = Θ((s, a), (s', a')), the NTK between the pair and its greedy successor."""
    LOSS: Final = "loss"
    """TD loss of the step (NaN before the first update)."""
    FREQ: Final = "freq"
    """Frequency of a spectrum row, cycles per unit of learning time (Δt = α)."""


STEP_COLUMNS: Final = (
    Signal.EPISODE,
    Signal.STEP,
    Signal.REWARD,
    Signal.Q1,
    Signal.Q2,
    Signal.U,
    Signal.X_E,
    Signal.THETA1,
    Signal.THETA2,
    Signal.LOSS,
)
"""Columns of ``signals/steps.parquet``, in the order of the in-memory signal table."""
FFT_COLUMNS: Final = (Signal.FREQ, Signal.REWARD, Signal.Q1, Signal.Q2)
"""Columns of ``signals/fft.parquet``: one-sided amplitude spectra of r, Q1 and Q2."""


def column(name: str) -> int:
    """Index of signal column ``name`` in :data:`STEP_COLUMNS`."""
    return STEP_COLUMNS.index(name)


SERIES_PREFIX: Final = "signals/"
"""Prefix of the per-step series' metric keys (MLflow groups charts by it)."""
SPECTRUM_PREFIX: Final = "spectrum/"
"""Prefix of the amplitude spectra's metric keys (step = round(1000 ω))."""
SERIES: Final = ("u", "q1", "q2", "theta1", "theta2_over_theta1")
"""Per-step series logged as ``signals/<name>``: span means of u, Q1, Q2, Θ1 and Θ2/Θ1."""
BOX_SERIES: Final = ("theta1_box_lower", "theta1_box_upper", "ratio_box_lower", "ratio_box_upper")
"""The design's NTK box logged as ``signals/<name>``: Θ1 and Θ2/Θ1 bounds."""
SPECTRA: Final = FFT_COLUMNS[1:]
"""Spectra logged as ``spectrum/<name>``: amplitudes of r, Q1 and Q2."""
SERIES_METRICS: Final = (
    *(SERIES_PREFIX + s for s in SERIES + BOX_SERIES),
    *(SPECTRUM_PREFIX + s for s in SPECTRA),
)
"""Every metric key of the series and spectra written when a run closes."""


class Tag:
    """Tag keys of a run (values are strings)."""

    ENV: Final = "env"
    """Environment preset name (``env.name``)."""
    ENV_ID: Final = "env_id"
    """Gymnasium id of the environment (``env.id``)."""
    CONTROLLER: Final = "controller"
    """Agent: ``h2``, ``hinf``, ``hinf_f`` or ``ddqn`` (``controller.name``)."""
    SEED: Final = "seed"
    """Seed of the run (decimal integer)."""
    GIT_COMMIT: Final = "git_commit"
    """Commit of the cdqn source tree, ``+dirty`` with local changes."""
    DESIGN_SOURCE: Final = "design_source"
    """Where the controller came from: ``paper``, ``synthesized``, ``scheduled`` or ``none``."""
    CONFIG_HASH: Final = "config_hash"
    """SHA-256 of the resolved configuration (a sweep skips seeds already FINISHED)."""
    POPULATION: Final = "population"
    """Seeds of the population the run was a member of, ``<first>-<last>``."""
    POPULATION_ID: Final = "population_id"
    """Identifier shared by the members of one population (what ``resume=`` finds)."""
    FAILURE_REASON: Final = "failure_reason"
    """Why the run FAILED (divergence, error, store outage)."""
    PREVIOUS_FAILURE_REASON: Final = "previous_failure_reason"
    """The ``failure_reason`` of a run before it was resumed."""
    RESUMED_FROM_EPISODE: Final = "resumed_from_episode"
    """Episode a resumed run continued from."""
    RESUME_COUNT: Final = "resume_count"
    """Times the run was resumed."""
    HOST: Final = "host"
    """Host of the process training the run."""
    PID: Final = "pid"
    """Process id of the process training the run."""
    DESIGN_GAMMA_EFF: Final = "design_gamma_eff"
    """Effective discount γ_eff = (γ − k2)/(1 + k1) the design keeps."""
    DESIGN_STEP_SCALE: Final = "design_step_scale"
    """Step scale 1 + k1 of the design."""
    DESIGN_MAX_STEP_GAIN: Final = "design_max_step_gain"
    """Largest α(1 + k1)Θ1 over the NTK box."""
    DESIGN_WORST_POLE: Final = "design_worst_pole"
    """Largest closed-loop pole magnitude of the certificate."""
    EVAL_SEED: Final = "eval_seed"
    """Seed of the first greedy episode of the latest evaluation."""
    STUDY: Final = "study"
    """Name of the tuning study (``tune.study``)."""
    KIND: Final = "kind"
    """Role of a tuning run: ``tune`` (parent), ``trial``, ``recheck``, ``evaluation``, ..."""
    TRIAL_STATUS: Final = "trial_status"
    """How a tuning trial ended: complete, pruned or failed."""
    STOPPED: Final = "stopped"
    """On a study's parent run: why it started no further trial (``tune.time_limit``)."""
    START_FROM: Final = "start_from"
    """On a tuning trial: the preset whose specification it trained (``tune.warm_start``)."""


class Artifact:
    """Artifact paths of a run (folders end in ``/``)."""

    CONFIG: Final = "config.yaml"
    """The run's resolved configuration (without the ``hydra`` section)."""
    SIGNALS: Final = "signals/"
    """Folder of the per-step signal tables."""
    STEPS: Final = "signals/steps.parquet"
    """One row per environment step, columns :data:`STEP_COLUMNS`."""
    FFT: Final = "signals/fft.parquet"
    """Amplitude spectra, columns :data:`FFT_COLUMNS`."""
    DESIGN: Final = "design/"
    """Folder of the controller design (report, plots)."""
    DESIGN_RECORD: Final = "design/controller.json"
    """The controller design: gains or matrices, bounds, certificate."""
    MODEL: Final = "model/"
    """The final network (``q_network.pt``, ``spec.json``)."""
    CHECKPOINT: Final = "checkpoint/"
    """Resume checkpoints (removed when the run finishes unless ``train.keep_checkpoints``)."""
    EVALUATION: Final = "evaluation/"
    """Folder of evaluations: ``returns-seed<seed>-n<episodes>.csv`` of ``cdqn.evaluate``."""
    EVALUATION_RETURNS: Final = "evaluation/returns.json"
    """A tuning evaluation's return curves, per seed."""
    EVALUATION_SEEDS: Final = "evaluation/seeds.json"
    """What each seed of a tuning evaluation did (:mod:`cdqn.tuning.diagnosis`)."""


def folder(path: str) -> str:
    """Artifact folder ``path`` without its trailing ``/`` (as MLflow's calls take it)."""
    return path.rstrip("/")


def names(space: type) -> tuple[str, ...]:
    """The values of the constants of ``space`` (:class:`Metric`, :class:`Tag`, ...)."""
    return tuple(v for k, v in vars(space).items() if k.isupper() and isinstance(v, str))
