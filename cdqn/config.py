"""Structured configuration schema.

One dataclass per Hydra config group, registered in Hydra's ConfigStore as
``base_config``; the YAML files under ``conf/`` select and override, this schema
types and validates them.  Each field carries a one-line description with its unit and,
where there is one, the paper's symbol.

Each group's dataclass has a ``check()`` that returns its problems, one line each naming
the key, the value and what is allowed (``network.width=0: must be a positive integer``);
:func:`validate` gathers those of every group (:meth:`Config.check`) into one
:class:`ConfigError`.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

T = TypeVar("T")


def _conf_dir() -> Path:
    """The Hydra config folder: ``cdqn/conf`` in an installed wheel (pyproject.toml copies
    the repository's ``conf/`` there), else ``conf/`` beside the package (a clone, an
    editable install)."""
    package = Path(__file__).resolve().parent
    installed = package / "conf"
    return installed if installed.is_dir() else package.parent / "conf"


CONF_DIR = _conf_dir()
"""The Hydra config folder of every entry point (``python -m cdqn.train``, ...)."""

warnings.filterwarnings(  # the user preset folder on the search path need not exist
    "ignore", message=r"provider=hydra\.searchpath in main, path=.* is not available"
)


AGENT_SETTING = "cdqn.agent"
"""The resolver of an environment setting that depends on the agent (:func:`agent_setting`)."""
AGENT_ENV_KEYS = ("normalize", "rbf_centres")
"""The ``env`` settings an agent's weights may give (``weights.ddqn``), through
:data:`AGENT_SETTING` in the ``env`` group's files."""


def agent_setting(key: str, default: Any, *, _root_: DictConfig) -> Any:
    """``${cdqn.agent:KEY,DEFAULT}``: ``weights.<controller.name>.KEY`` where the weights preset
    gives the selected agent one (Double DQN's ``weights.ddqn.normalize`` and
    ``weights.ddqn.rbf_centres``), else ``DEFAULT``.  The ``env`` group's files set
    ``env.normalize`` and ``env.rbf_centres`` with it, so each group writes only its own keys;
    an environment preset read alone (no ``controller``) takes ``DEFAULT``."""
    name = OmegaConf.select(_root_, "controller.name", default=None)
    if name is None:
        return default
    return OmegaConf.select(_root_, f"weights.{name}.{key}", default=default)


OmegaConf.register_new_resolver(AGENT_SETTING, agent_setting, replace=True)


class ConfigError(ValueError):
    """A configuration value cdqn cannot run with; the message names key, value and what
    is allowed."""


REPLAY_WHEN = ("terminated", "truncated", "any")
"""Episodes that qualify for episodic replay (:class:`ReplayConfig`)."""
EPS_SCHEDULES = ("random_action", "step", "episode")
"""What lowers ε by eps_dec (:class:`cdqn.agents.base.EpsilonGreedy`)."""
EXPERIMENT_TAGS = {"mlflow.experimentKind": "custom_model_development"}
"""Tags of the MLflow experiments cdqn creates: the UI then opens them as model-training
experiments, on the runs table (MLflow 3 opens an untagged new experiment as a GenAI one)."""

CONTROLLERS = ("h2", "hinf", "hinf_f", "ddqn", "none")
"""Controller names: gain-scheduled H2, dynamic H∞, fixed-structure H∞, Double DQN, none."""


@dataclass
class EnvConfig:
    name: str = "cartpole"
    """Label in run names, tags, tables and studies: a preset's name, or for an id no
    preset names the id's label (:func:`cdqn.envs.adopt`)."""
    id: str = "CartPole-v1"
    """Any gymnasium id with a discrete action space; ``<module>:<Id>`` imports the module
    that registers ``<Id>`` first (as ``gymnasium.make``)."""
    kwargs: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments of the environment's constructor, ``gymnasium.make(id, **kwargs)``
    (empty: its registration's)."""
    max_episode_steps: int | None = 200
    """Episode cap in environment steps (None: the environment's registered limit; an
    environment registered without one needs it set)."""
    obs_indices: list[int] | None = None
    """Observation features fed to the network (None: all)."""
    normalize: bool = False
    """Map every observation feature with finite bounds affinely to [−1, 1]."""
    normalize_scale: list[float] | None = None
    """With normalize: the half-width w of each observed feature's range, [−w, w] instead of
    [−1, 1] (one per feature; null: 1 for all).  Weighs features in the NTK
    (docs/research/learning.md)."""
    rbf_centres: int | None = None
    """Radial basis features: Gaussians centred on a grid of this many points per observed
    feature over the (scaled) observation box, fed to the network instead of the
    observation (null: the observation itself).  Makes the NTK local (docs/research/learning.md)."""
    rbf_width: float = 1.0
    """With rbf_centres: each Gaussian's standard deviation in grid spacings."""
    solve_threshold: float | None = 195.0
    """Moving-average return (100 episodes) at which the task counts as solved."""
    eps_dec: float = 1e-4
    """This environment's decrease of ε, taken by train.eps_dec (research code: 1e-4 per
    random action; Acrobot: 9.3e-4 per episode, 1 to 0.01 at episode 1064;
    docs/research/learning.md, §5)."""
    eps_schedule: str = "random_action"
    """What lowers ε by eps_dec, taken by train.eps_schedule: ``random_action`` (research
    code), ``step`` (every step: linear in steps) or ``episode`` (every episode start)."""

    def check(self) -> list[str]:
        """Problems of the ``env`` group, one line each (empty: none).  The observation
        features (indices, scale, radial grid) are checked against the environment itself
        when it is made (:func:`cdqn.envs.make_env`)."""
        centres, cap = self.rbf_centres, self.max_episode_steps
        return failed(
            [
                (
                    centres is None or centres >= 2,
                    f"env.rbf_centres={centres}: must be >= 2 (centres per feature) or null",
                ),
                (self.rbf_width > 0, f"env.rbf_width={self.rbf_width}: must be > 0"),
                (
                    cap is None or cap > 0,
                    f"env.max_episode_steps={cap}: must be > 0 or null",
                ),
            ]
        )


@dataclass
class NetworkConfig:
    width: int = 2500
    """Hidden units of the two-layer ReLU Q-network (paper: 2500)."""
    dtype: str = "float64"
    """Floating-point type of the parameters: float64 or float32."""

    def check(self) -> list[str]:
        """Problems of the ``network`` group, one line each (empty: none)."""
        return failed(
            [
                (self.width > 0, f"network.width={self.width}: must be a positive integer"),
                (
                    self.dtype in ("float64", "float32"),
                    f"network.dtype={self.dtype!r}: allowed float64, float32",
                ),
            ]
        )


@dataclass
class TransferFunctionConfig:
    num: list[float] = field(default_factory=lambda: [1.0])
    """Numerator coefficients, highest power of s first."""
    den: list[float] = field(default_factory=lambda: [1.0])
    """Denominator coefficients, highest power of s first."""

    def is_proper(self) -> bool:
        """A non-zero denominator of degree >= the numerator's (leading zeros dropped)."""
        num = [float(c) for c in self.num]
        den = [float(c) for c in self.den]
        while num and num[0] == 0.0:
            num.pop(0)
        while den and den[0] == 0.0:
            den.pop(0)
        return bool(den) and len(num) <= len(den)

    def check(self, key: str) -> list[str]:
        """Problems of the weight at ``key`` (e.g. ``weights.hinf.w_p``)."""
        return failed(
            [
                (
                    self.is_proper(),
                    f"{key}=num {list(self.num)} / den {list(self.den)}: not a proper "
                    "transfer function (need a non-zero denominator of degree >= the numerator's)",
                )
            ]
        )


@dataclass
class H2Weights:
    w_x: list[float] = field(default_factory=lambda: [1.0, 30000.0, 10.0])
    """Diagonal of W_x, state weight on [Q1, Q2, x_e] (paper Sec. 4.1)."""
    w_c: float = 20000.0
    """W_c, control weight (paper Sec. 4.1)."""

    def check(self, key: str) -> list[str]:
        """Problems of the H2 weights, one line each (empty: none)."""
        return failed(
            [
                (
                    len(self.w_x) == 3 and all(w >= 0 for w in self.w_x),
                    f"{key}.w_x={list(self.w_x)}: need 3 non-negative diagonal entries",
                ),
                (self.w_c > 0, f"{key}.w_c={self.w_c}: must be > 0"),
            ]
        )


@dataclass
class HinfWeights:
    w_p: TransferFunctionConfig = field(default_factory=TransferFunctionConfig)
    """W_p(s), performance weight on the tracking error (paper Sec. 4.2)."""
    w_u: TransferFunctionConfig = field(default_factory=TransferFunctionConfig)
    """W_u(s), control-effort weight (paper Sec. 4.2)."""
    w_delta: float = 1.0
    """W_Δ, magnitude of the uncertainty weight (constant)."""
    w_r: TransferFunctionConfig = field(default_factory=TransferFunctionConfig)
    """W_r(s), reward (reference) weight."""
    w_qhat: TransferFunctionConfig = field(default_factory=TransferFunctionConfig)
    """W_Q̂(s), weight on the exogenous target Q̂2."""

    def check(self, key: str) -> list[str]:
        """Problems of the H∞ weights at ``key`` (``weights.hinf`` or ``weights.hinf_f``)."""
        problems: list[str] = []
        for name in ("w_p", "w_u", "w_r", "w_qhat"):
            problems += getattr(self, name).check(f"{key}.{name}")
        return problems + failed([(self.w_delta > 0, f"{key}.w_delta={self.w_delta}: must be > 0")])


@dataclass
class ThetaBounds:
    theta1: list[float] = field(default_factory=lambda: [200.0, 500.0])
    """Range of Θ1 = Θ((s,a),(s,a)) the robust designs cover."""
    ratio: list[float] = field(default_factory=lambda: [0.8, 1.2])
    """Range of Θ2/Θ1 the robust designs cover."""
    nominal: list[float] | None = None
    """Nominal (Θ1, Θ2) of the design plant (None: the box centre, √(Θ1_lo·Θ1_hi) and the
    mid ratio; the paper's CartPole design used (220, 222))."""
    measured_on: str | None = None
    """Where the box was measured, when a tuning study measured it (``<env>, seed <n>``);
    None for a box given by hand.  Reports name it as the box's source."""

    def check(self, key: str) -> list[str]:
        """Problems of the NTK box, one line each (empty: none)."""
        checks: list[tuple[bool, str]] = []
        for name in ("theta1", "ratio"):
            rng = list(getattr(self, name))
            checks.append(
                (
                    len(rng) == 2 and 0 < rng[0] <= rng[1],
                    f"{key}.{name}={rng}: need [lower, upper] with 0 < lower <= upper",
                )
            )
        if self.nominal is not None:
            nominal = list(self.nominal)
            checks.append(
                (
                    len(nominal) == 2 and all(v > 0 for v in nominal),
                    f"{key}.nominal={nominal}: need [Θ1, Θ2], both > 0, or null",
                )
            )
        return failed(checks)


@dataclass
class PaperDesign:
    hinf_f: list[float] | None = None
    """Research-code fixed-structure gains (k1, k2, k3), u = -k1 Q1 - k2 Q2 + k3 x_e."""
    hinf_A: list[list[float]] | None = None
    """Research-code dynamic H∞ controller, state matrix."""
    hinf_B: list[list[float]] | None = None
    """Research-code dynamic H∞ controller, input matrix (inputs [x_e, Q1, Q2])."""
    hinf_C: list[list[float]] | None = None
    """Research-code dynamic H∞ controller, output matrix, in cdqn's sign convention."""


@dataclass
class LearningTarget:
    """The learning target a controller keeps (docs/synthesis.md, "Learning target").

    With ``u = −k1 Q1 − k2 Q2 + k3 x_e`` the controlled TD term is
    ``r + (γ − k2) Q2 − (1 + k1) Q1 + k3 x_e = (1 + k1)(r/(1 + k1) + γ_eff Q2 − Q1) + k3 x_e``:
    the fixed point of learning is that of a Bellman equation with the effective discount
    ``γ_eff = (γ − k2)/(1 + k1)``, and ``1 + k1`` scales every SGD step.  Synthesis keeps both
    inside these ranges (for a dynamic controller: its DC gain from [Q1, Q2] to u).
    """

    gamma_eff: list[float] = field(default_factory=lambda: [-1.0, -0.95])
    """[lower, upper] of the effective discount γ_eff = (γ − k2)/(1 + k1), within [−1, 1]."""
    step_scale: list[float] = field(default_factory=lambda: [0.6, 1.0])
    """[lower, upper] of the step scale 1 + k1 (> 0)."""
    rho_cap: float | None = None
    """h2 only (scheduled on Θ1, Θ2): cap γ_eff at rho_cap/ρ at each step, ρ = Θ2/Θ1
    (0 < rho_cap < 1; null: no cap)."""

    def check(self, key: str) -> list[str]:
        """Problems of the ranges, one line each (empty: none)."""
        return _target_problems(key, self.gamma_eff, self.step_scale)


@dataclass
class OwnTarget:
    """A controller's own learning target on one environment: each range set here replaces
    that of ``weights.target`` for this controller's design (null: ``weights.target``'s)."""

    gamma_eff: list[float] | None = None
    step_scale: list[float] | None = None
    rho_cap: float | None = None

    def check(self, key: str) -> list[str]:
        """Problems of the ranges set here (``key``: ``weights.controller_target.<name>``)."""
        return _target_problems(key, self.gamma_eff, self.step_scale)


@dataclass
class ControllerTargets:
    """Per controller, the ranges of its own learning target (:func:`target_of`)."""

    h2: OwnTarget = field(default_factory=OwnTarget)
    hinf: OwnTarget = field(default_factory=OwnTarget)
    hinf_f: OwnTarget = field(default_factory=OwnTarget)

    def check(self, key: str) -> list[str]:
        """Problems of every controller's own ranges, one line each (empty: none)."""
        problems: list[str] = []
        for name in TARGET_CONTROLLERS:
            problems += getattr(self, name).check(f"{key}.{name}")
        return problems


@dataclass
class ReplayConfig:
    """Episodic replay (paper Sec. 4, remark on replay; research code on Acrobot): after an
    episode that qualifies, its final transitions pass again through the same controlled
    update, ``repeats`` times, in temporal order.  Sampled replay (``sample``): after each
    step, transitions drawn from the recent past pass through it too."""

    repeats: int = 0
    """Passes over the replayed transitions after a qualifying episode (0: off)."""
    last: int | None = 1
    """Replay the episode's last this many transitions (1: the final one, as the research
    code; null: the whole episode)."""
    when: str = "terminated"
    """Which episodes qualify: terminated (the MDP ended, e.g. the goal was reached),
    truncated (the time limit), any."""
    min_return: float | None = None
    """Only episodes whose return is at least this qualify (null: no bound)."""
    sample: int = 0
    """Sampled replay, a departure from the paper's online learning (0: off): after each
    environment step, this many transitions drawn uniformly (with replacement) from the last
    ``buffer`` pass through the same controlled update (:mod:`cdqn.agents.replay`)."""
    buffer: int = 50_000
    """Transitions sampled replay draws from (the most recent; Double DQN's buffer size)."""

    def check(self, key: str) -> list[str]:
        """Problems of the replay settings, one line each (empty: none)."""
        return failed(
            [
                (self.repeats >= 0, f"{key}.repeats={self.repeats}: must be >= 0 (0: off)"),
                (self.sample >= 0, f"{key}.sample={self.sample}: must be >= 0 (0: off)"),
                (self.buffer >= 1, f"{key}.buffer={self.buffer}: must be >= 1 (transitions)"),
                (
                    self.last is None or self.last >= 1,
                    f"{key}.last={self.last}: must be >= 1 or null (the whole episode)",
                ),
                (
                    self.when in REPLAY_WHEN,
                    f"{key}.when={self.when!r}: allowed {', '.join(REPLAY_WHEN)}",
                ),
            ]
        )


@dataclass
class IntegratorReset:
    """Per controller: reset x_e at each episode start (true, the research code) or keep it
    across episodes (false: k3·x_e becomes a slowly adapting bias of the TD term)."""

    h2: bool = True
    hinf: bool = True
    hinf_f: bool = True


@dataclass
class DDQNSettings:
    """Double DQN's settings that depend on the environment (docs/ddqn.md)."""

    lr: float | None = None
    """α of Double DQN's SGD step on this environment (null: train.lr, the paper's α)."""
    normalize: bool = False
    """Double DQN's observations: the environment's own (false), or each feature mapped to
    [−1, 1] as env.normalize does (true)."""
    target_update: int = 500
    """Environment steps between Double DQN's target-network copies on this environment."""
    rbf_centres: int | None = None
    """Double DQN's radial basis features (env.rbf_centres; null: the observation itself)."""


@dataclass
class WeightsConfig:
    name: str = "cartpole"
    """Name of this weight set."""
    h2: H2Weights = field(default_factory=H2Weights)
    """Weights of the gain-scheduled H2 (LQR) design."""
    hinf: HinfWeights = field(default_factory=HinfWeights)
    """Weights of the dynamic H∞ design."""
    hinf_f: HinfWeights = field(default_factory=HinfWeights)
    """Weights of the fixed-structure H∞ design."""
    theta_bounds: ThetaBounds = field(default_factory=ThetaBounds)
    """NTK box used by the robust designs when it is not measured."""
    paper: PaperDesign = field(default_factory=PaperDesign)
    """The research code's hand-copied designs, used with controller.design=paper."""
    target: LearningTarget = field(default_factory=LearningTarget)
    """Learning target of the synthesised designs (γ_eff and 1 + k1 ranges)."""
    controller_target: ControllerTargets = field(default_factory=ControllerTargets)
    """Per controller, ranges that replace those of ``target`` for its design alone."""
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    """Episodic replay of the controlled agents."""
    reset_integrator: IntegratorReset = field(default_factory=IntegratorReset)
    """Whether each controlled agent resets the integrator x_e at each episode start on this
    environment (taken by controller.reset_integrator; docs/research/learning.md)."""
    ddqn: DDQNSettings = field(default_factory=DDQNSettings)
    """Double DQN on this environment (controller=ddqn takes controller.lr,
    controller.target_update, env.normalize and env.rbf_centres from here)."""

    def check(self) -> list[str]:
        """Problems of the ``weights`` group, one line each (empty: none): each weight set,
        the learning targets, the replay and the NTK box."""
        return [
            *self.h2.check("weights.h2"),
            *self.hinf.check("weights.hinf"),
            *self.hinf_f.check("weights.hinf_f"),
            *self.target.check("weights.target"),
            *self.controller_target.check("weights.controller_target"),
            *self.replay.check("weights.replay"),
            *self.theta_bounds.check("weights.theta_bounds"),
        ]


@dataclass
class SynthesisConfig:
    plant: str = "gradient_flow"
    """Learning plant of the design and the certificate: gradient_flow (u moves Q1 and Q2,
    B_u = [Θ1, Θ2]: what cdqn's training step does) or paper (B_u = [Θ1, 0], the paper's
    Eq. controlled_Q); see docs/synthesis.md."""
    ntk_bounds: str = "config"
    """Where the NTK box comes from: config (weights.theta_bounds) or measured (rollout)."""
    quantiles: list[float] = field(default_factory=lambda: [0.02, 0.98])
    """Measured box: quantiles of Θ1 and of Θ2/Θ1 over the rollout's transitions."""
    ratio_floor: float = 0.05
    """Measured box: transitions with Θ2/Θ1 below this (Θ2 ≈ 0, Q2 not moved) are left out
    of the ratio range."""
    rollout_steps: int = 3000
    """Measured box: environment steps of the rollout of the initial network."""
    samples: int = 200
    """Plant samples over the box (corners included) for the cover and the designs."""
    seed: int = 0
    """Seed of the plant samples and of the random starts."""
    grid: list[int] = field(default_factory=lambda: [25, 25])
    """Certificate validation grid: points along Θ1 and along Θ2/Θ1 (corners included)."""
    band: list[float] = field(default_factory=lambda: [1.0, 1.0e5])
    """Band [ω_lo, ω_hi] (rad/s of learning time) over which the cover is fitted."""
    cover_order: int = 2
    """Order (pole/zero pairs) of the output-multiplicative cover weight."""
    noise: list[float] = field(default_factory=lambda: [0.2, 0.5])
    """Relative measurement-noise levels on Q1, Q2 (paper: ± 0.2, ± 0.5)."""
    reg_integrator: float = 1.0e-3
    """ε_i of the H∞ plant: integrator 1/s → 1/(s + ε_i), rad/s."""
    reg_control: float = 1.0e-2
    """ε_u of the H∞ plant: extra performance output ε_u·u (D12 full rank)."""
    reg_sensor: float = 1.0e-4
    """ε_s of the H∞ plant: sensor noise on the integrated error (D21 full rank)."""
    reg_process: float = 1.0e-2
    """ε_q of the H∞ plant: process noise into Q1, Q2 (mode at s = 0 reachable)."""
    gamma_tol: float = 1.0e-3
    """Relative tolerance of the γ-bisection."""
    hsv_threshold: float = 1.0e-2
    """Balanced reduction: drop controller states with Hankel singular value below this."""
    decay: float = 0.05
    """Fixed-structure design: every sample's closed loop must satisfy Re λ ≤ −decay."""
    restarts: int = 2
    """Fixed-structure design: random starts after the first one."""
    start: list[float] | None = None
    """Fixed-structure design: first start (k1, k2, k3) (None: H2 gains at the nominal)."""
    margin: float = 1.0e-6
    """Certificate: stable means max Re λ < −margin (rad/s of learning time)."""
    cache: bool = True
    """Reuse a design with the same inputs from cache_dir."""
    cache_dir: str = "~/.cache/cdqn/designs"
    """Folder of cached designs, one sub-folder per hash of the design inputs."""


@dataclass
class ControllerConfig:
    name: str = "hinf"
    """One of h2, hinf, hinf_f, ddqn, none."""
    design: str = "paper"
    """Where the gains come from: paper (research-code values) or synthesize."""
    discretization: str = "zoh"
    """Dynamic H∞ controller discretisation at Δt = α: zoh, tustin or euler."""
    h2_gain_map: str = "paper"
    """H2 only: paper, (k1, k2, k3) = (K1, K2, -K3) of u = -K x_a; research, the research
    code's (-K3, -K2, K1)."""
    reset_integrator: bool = True
    """Reset the tracking-error integrator x_e at each episode start (default: the
    environment's weights.reset_integrator)."""
    reset_state: bool = True
    """Reset the dynamic controller's state at each episode start (paper Sec. 4.2)."""
    synthesis: SynthesisConfig = field(default_factory=SynthesisConfig)
    """Settings of controller synthesis (controller.design=synthesize)."""
    buffer_size: int = 50000
    """DDQN: replay buffer capacity (transitions)."""
    batch_size: int = 32
    """DDQN: minibatch size."""
    learning_starts: int = 1000
    """DDQN: transitions collected before the first update."""
    train_freq: int = 1
    """DDQN: environment steps between updates."""
    target_update: int = 500
    """DDQN: environment steps between target-network copies."""
    discount: float | None = None
    """DDQN: γ of its TD target; null: train.discount (docs/ddqn.md, "What it computes")."""
    lr: float | None = None
    """DDQN: α of its SGD step; null: train.lr (controller=ddqn sets weights.ddqn.lr)."""

    def check(self) -> list[str]:
        """Problems of the ``controller`` group, one line each (empty: none)."""
        name = self.name
        return failed(
            [
                (
                    name in CONTROLLERS,
                    f"controller.name={name!r}: allowed {', '.join(CONTROLLERS)}",
                ),
                (
                    self.design in ("paper", "synthesize"),
                    f"controller.design={self.design!r}: allowed paper, synthesize",
                ),
                (
                    self.discretization in ("zoh", "tustin", "euler"),
                    f"controller.discretization={self.discretization!r}: "
                    "allowed zoh, tustin, euler",
                ),
                (
                    self.h2_gain_map in ("paper", "research"),
                    f"controller.h2_gain_map={self.h2_gain_map!r}: allowed paper, research",
                ),
                *self._ddqn_checks(),
            ]
        )

    def _ddqn_checks(self) -> list[tuple[bool, str]]:
        """Double DQN's settings; its lr and discount are refused on the other agents."""
        return [
            (
                self.learning_starts >= 0,
                f"controller.learning_starts={self.learning_starts}: must be >= 0",
            ),
            (
                0 < self.batch_size <= self.buffer_size,
                f"controller.batch_size={self.batch_size}, controller.buffer_size="
                f"{self.buffer_size}: need 0 < batch_size <= buffer_size",
            ),
            (
                self.target_update > 0 and self.train_freq > 0,
                "controller.target_update and controller.train_freq must be > 0",
            ),
            (
                self.discount is None or 0 < self.discount <= 1,
                f"controller.discount={self.discount}: γ must lie in (0, 1] or be null",
            ),
            (
                self.lr is None or self.lr > 0,
                f"controller.lr={self.lr}: α must be > 0 or null (train.lr)",
            ),
            *(
                (
                    self.name == "ddqn" or value is None,
                    f"controller.{key}={value}: a Double DQN setting (controller=ddqn); "
                    f"{self.name} uses train.{key}",
                )
                for key, value in (("lr", self.lr), ("discount", self.discount))
            ),
        ]


@dataclass
class TrainConfig:
    episodes: int = 2000
    """Training episodes per run."""
    lr: float = 5e-5
    """α, SGD learning rate; one SGD step advances the learning model by Δt = α."""
    discount: float = 1.0
    """γ, discount factor (paper: 1)."""
    eps_start: float = 1.0
    """Initial ε of ε-greedy exploration."""
    eps_end: float = 0.01
    """ε stops decreasing once below this value."""
    eps_dec: float = 1e-4
    """Decrease of ε (default: the environment's env.eps_dec)."""
    eps_schedule: str = "random_action"
    """ε falls by eps_dec after each ``random_action`` (research code), after each ``step``
    (linear in steps) or at the start of each ``episode`` (linear in episodes), floored at
    eps_end (default: the environment's env.eps_schedule)."""
    bootstrap_terminal: bool = False
    """Bootstrap from max Q(s') at terminal steps too (the research code's behaviour); by
    default only truncated steps (the time limit) bootstrap, terminal ones do not."""
    q_limit: float = 1e6
    """|Q| above this value ends the run as diverged."""
    fast_path: bool = True
    """Hand-derived gradients for the two-layer network instead of autograd."""
    progress: bool = True
    """Show a progress bar (hidden automatically in multiruns)."""
    signals: bool = True
    """Store the per-step signals (signals/steps.parquet, signals/fft.parquet)."""
    checkpoint_every: int = 100
    """Episodes between checkpoints stored in the run (0: only when interrupted)."""
    keep_checkpoints: bool = False
    """Keep the resume checkpoints of a run that FINISHED (default: deleted at the end)."""
    population: int = 1
    """Seeds trained together in one process as one batch: seed, seed+1, …, seed+K−1, each
    its own MLflow run (cdqn.training.population)."""

    def check(self) -> list[str]:
        """Problems of the ``train`` group, one line each (empty: none)."""
        schedule = self.eps_schedule
        return failed(
            [
                (self.lr > 0, f"train.lr={self.lr}: the learning rate α must be > 0"),
                (
                    0 < self.discount <= 1,
                    f"train.discount={self.discount}: the discount γ must lie in (0, 1]",
                ),
                (self.episodes > 0, f"train.episodes={self.episodes}: must be > 0"),
                (
                    0 <= self.eps_start <= 1,
                    f"train.eps_start={self.eps_start}: ε must lie in [0, 1]",
                ),
                (0 <= self.eps_end <= 1, f"train.eps_end={self.eps_end}: ε must lie in [0, 1]"),
                (0 <= self.eps_dec <= 1, f"train.eps_dec={self.eps_dec}: must lie in [0, 1]"),
                (
                    schedule in EPS_SCHEDULES,
                    f"train.eps_schedule={schedule!r} (env.eps_schedule unless set): "
                    f"allowed {', '.join(EPS_SCHEDULES)}",
                ),
                (self.q_limit > 0, f"train.q_limit={self.q_limit}: must be > 0"),
                (
                    self.checkpoint_every >= 0,
                    f"train.checkpoint_every={self.checkpoint_every}: must be >= 0 (0: off)",
                ),
                (
                    self.population >= 1,
                    f"train.population={self.population}: the number of seeds must be >= 1",
                ),
            ]
        )


@dataclass
class TrackingConfig:
    uri: str = "sqlite:///mlflow.db"
    """MLflow tracking URI; the default is an embedded store in the working folder."""
    experiment: str = "cdqn"
    """MLflow experiment name."""
    log_model: bool = True
    """Store the final network as an MLflow artifact."""
    timeout: float = 10.0
    """Seconds a tracking server gets to answer the start-up check."""
    skip_finished: bool = False
    """Skip a run whose configuration and seed already have a FINISHED run in the store,
    continue one that was KILLED from its checkpoint (restarted sweeps; cdqn.training.sweep)."""
    retry_s: float = 300.0
    """Seconds a metric, tag or artifact write is retried (with backoff) while the store
    does not answer; past them the run checkpoints locally and stops (resume later)."""
    local_checkpoints: str = "checkpoints"
    """Folder for checkpoints of runs whose tracking store went away
    (``<folder>/<run_id>/state.pt``); relative to the working folder."""

    def check(self) -> list[str]:
        """Problems of the ``tracking`` group, one line each (empty: none)."""
        return failed(
            [
                (bool(self.uri.strip()), "tracking.uri='': give an MLflow tracking URI"),
                (bool(self.experiment.strip()), "tracking.experiment='': give an experiment name"),
                (self.timeout > 0, f"tracking.timeout={self.timeout}: must be > 0 seconds"),
                (self.retry_s >= 0, f"tracking.retry_s={self.retry_s}: must be >= 0 seconds"),
            ]
        )


SQLITE = "sqlite:///"
"""The scheme of an SQLite database URI (MLflow's store, Optuna's storage)."""


def sqlite_file(uri: str) -> Path | None:
    """The database file of a ``sqlite:///<path>`` URI (``sqlite:////abs/path``: an absolute
    one, else relative to the working folder); None for any other URI."""
    return Path(uri[len(SQLITE) :]) if uri.startswith(SQLITE) else None


def resolve_tracking_uri(uri: str) -> str:
    """Make a relative ``sqlite:///`` store or a plain path absolute, so that every launcher
    process and the analysis scripts open the same store; other URIs are returned as given."""
    if (path := sqlite_file(uri)) is not None and not path.is_absolute():
        return SQLITE + str(path.resolve())
    if "://" not in uri and not uri.startswith("file:"):
        return Path(uri).resolve().as_uri()
    return uri


@dataclass
class Config:
    env: EnvConfig = field(default_factory=EnvConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    weights: WeightsConfig = field(default_factory=WeightsConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    seed: int = 0
    """Seed of network initialisation, exploration and environment."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Free-form user notes, logged as parameters."""
    resume: str | None = None
    """MLflow run id to continue from its last checkpoint (``python -m cdqn.train resume=<id>``)."""

    def check(self) -> list[str]:
        """Problems of the whole configuration, one line each (empty: none): each group's
        :meth:`check` in turn, then the run's own settings (seed, resume).  No rule relates
        two groups: every check reads one group's values, and a message that names another
        key (``train.eps_schedule``'s default from ``env.eps_schedule``, the agents that use
        ``train.lr``) only points to it."""
        return [
            *self.controller.check(),
            *self.network.check(),
            *self.train.check(),
            *self.env.check(),
            *self.tracking.check(),
            *self.weights.check(),
            *failed(
                [
                    (self.seed >= 0, f"seed={self.seed}: must be >= 0 (a non-negative integer)"),
                    (
                        self.resume is None or bool(str(self.resume).strip()),
                        "resume='': give the MLflow run id of the run to continue, resume=<run_id>",
                    ),
                ]
            ),
        ]


@dataclass
class EvaluateConfig:
    """``python -m cdqn.evaluate run_id=<id> episodes=100``: greedy evaluation of a run."""

    run_id: str = MISSING
    """MLflow run id of the trained network."""
    episodes: int = 100
    """Evaluation episodes."""
    seed: int = 1_000_000
    """Seed of the first evaluation episode; episode i uses seed + i (unlike any training seed)."""
    log: bool = True
    """Log the evaluation to the run (metrics eval_return_*, artifact evaluation/)."""
    tracking: TrackingConfig = field(default_factory=TrackingConfig)

    def check(self) -> list[str]:
        """Problems of an evaluation's settings, one line each (empty: none)."""
        return (
            failed(
                [
                    (bool(self.run_id.strip()), "run_id='': give the MLflow run id, run_id=<id>"),
                    (self.episodes > 0, f"episodes={self.episodes}: must be > 0"),
                    (self.seed >= 0, f"seed={self.seed}: must be >= 0"),
                ]
            )
            + self.tracking.check()
        )


@dataclass
class SynthesizeConfig(Config):
    """``python -m cdqn.synthesize env=<env> controller=<hinf|hinf_f|h2> out=<dir>``."""

    out: str = "synthesis"
    """Folder for controller.json, report.txt, closed_loop_sv.csv and the plots."""


TARGET_FIELDS = ("gamma_eff", "step_scale", "rho_cap")
"""The ranges of a learning target (:class:`LearningTarget`)."""
TARGET_CONTROLLERS = ("h2", "hinf", "hinf_f")
"""The controllers whose designs keep a learning target (:class:`ControllerTargets`)."""
BOXED_CONTROLLERS = ("hinf", "hinf_f")
"""The designs certified over an NTK box (the gain-scheduled H2 design sees Θ1, Θ2 at every
step instead)."""


def target_key(weights: Any, controller: str, name: str) -> str:
    """Configuration key of range ``name`` of the learning target that the design of
    ``controller`` keeps: ``weights.controller_target.<controller>.<name>`` when that is set,
    else ``weights.target.<name>``."""
    if _own_range(weights, controller, name) is None:
        return f"weights.target.{name}"
    return f"weights.controller_target.{controller}.{name}"


def target_of(weights: Any, controller: str) -> dict[str, Any]:
    """The learning target the design of ``controller`` keeps, ``{range: value}``: its own
    ranges where set, the environment's ``weights.target`` for the others (:func:`target_key`)."""
    out: dict[str, Any] = {}
    for name in TARGET_FIELDS:
        own = _own_range(weights, controller, name)
        out[name] = getattr(weights.target, name) if own is None else own
    return out


def _own_range(weights: Any, controller: str, name: str) -> Any:
    own = getattr(getattr(weights, "controller_target", None), controller, None)
    return None if own is None else getattr(own, name, None)


def register_configs() -> None:
    """Register the schema in Hydra's ConfigStore as ``base_config``."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(name="base_evaluate", node=EvaluateConfig)
    cs.store(name="base_synthesize", node=SynthesizeConfig)


def of_kind(value: object, kind: type[T]) -> T:
    """``value``, which is a ``kind`` (an internal invariant: :class:`TypeError` if not)."""
    if not isinstance(value, kind):
        raise TypeError(f"a {type(value).__name__} where a {kind.__name__} belongs")
    return value


def to_schema(cfg: DictConfig, kind: type[T]) -> T:
    """``cfg`` as its schema's dataclass ``kind`` (``OmegaConf.to_object``)."""
    return of_kind(OmegaConf.to_object(cfg), kind)


def to_plain(cfg: DictConfig) -> dict[str, Any]:
    """``cfg`` as plain dicts and lists, interpolations resolved."""
    return of_kind(OmegaConf.to_container(cfg, resolve=True), dict)


def merged(*cfgs: Any) -> DictConfig:
    """``OmegaConf.merge`` of configurations whose first is a mapping (so is the result)."""
    return of_kind(OmegaConf.merge(*cfgs), DictConfig)


def validate(cfg: Config) -> None:
    """Refuse values cdqn cannot run with, naming the key, the value and what is allowed:
    every problem of :meth:`Config.check` (each group's ``check()``) in one
    :class:`ConfigError`."""
    raise_problems(cfg.check())


def validate_evaluate(cfg: EvaluateConfig) -> None:
    """Refuse evaluation settings cdqn cannot run with (same message style as :func:`validate`)."""
    raise_problems(cfg.check())


def failed(checks: Iterable[tuple[bool, str]]) -> list[str]:
    """The messages of the rules that do not hold, in order; each rule is ``(holds, message)``,
    the message naming the key, the value and what is allowed."""
    return [msg for ok, msg in checks if not ok]


def raise_problems(problems: list[str]) -> None:
    """Raise one :class:`ConfigError` listing ``problems``, one per line; nothing when empty."""
    if problems:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(problems))


def _target_problems(
    key: str, gamma_eff: list[float] | None, step_scale: list[float] | None
) -> list[str]:
    """Problems of a learning target's ranges at ``key`` (unset ranges: none)."""
    checks: list[tuple[bool, str]] = []
    if gamma_eff is not None:
        g_eff = list(gamma_eff)
        checks.append(
            (
                len(g_eff) == 2 and g_eff[0] <= g_eff[1],
                f"{key}.gamma_eff={g_eff}: need [lower, upper] with lower <= upper",
            )
        )
    if step_scale is not None:
        scale = list(step_scale)
        checks.append(
            (
                len(scale) == 2 and 0 < scale[0] <= scale[1],
                f"{key}.step_scale={scale}: need [lower, upper] with 0 < lower <= upper",
            )
        )
    return failed(checks)
