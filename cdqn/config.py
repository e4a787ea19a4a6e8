"""Structured configuration schema.

One dataclass per Hydra config group, registered in Hydra's ConfigStore as
``base_config``; the YAML files under ``conf/`` select and override, this schema
types and validates them.  Each field carries a one-line description with its unit and,
where there is one, the paper's symbol.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore


class ConfigError(ValueError):
    """A configuration value cdqn cannot run with; the message names key, value and what
    is allowed."""


CONTROLLERS = ("h2", "hinf", "hinf_f", "ddqn", "none")
"""Controller names: gain-scheduled H2, dynamic H∞, fixed-structure H∞, Double DQN, none."""


@dataclass
class EnvConfig:
    name: str = "cartpole"
    """Short name used in tags and tables."""
    id: str = "CartPole-v1"
    """Any gymnasium id with a discrete action space."""
    max_episode_steps: int | None = 200
    """Episode cap in environment steps (None: the environment's own limit)."""
    obs_indices: list[int] | None = None
    """Observation features fed to the network (None: all)."""
    solve_threshold: float | None = 195.0
    """Moving-average return (100 episodes) at which the task counts as solved."""


@dataclass
class NetworkConfig:
    width: int = 2500
    """Hidden units of the two-layer ReLU Q-network (paper: 2500)."""
    dtype: str = "float64"
    """Floating-point type of the parameters: float64 or float32."""


@dataclass
class TransferFunctionConfig:
    num: list[float] = field(default_factory=lambda: [1.0])
    """Numerator coefficients, highest power of s first."""
    den: list[float] = field(default_factory=lambda: [1.0])
    """Denominator coefficients, highest power of s first."""


@dataclass
class H2Weights:
    w_x: list[float] = field(default_factory=lambda: [1.0, 30000.0, 10.0])
    """Diagonal of W_x, state weight on [Q1, Q2, x_e] (paper Sec. 4.1)."""
    w_c: float = 20000.0
    """W_c, control weight (paper Sec. 4.1)."""


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


@dataclass
class ThetaBounds:
    theta1: list[float] = field(default_factory=lambda: [200.0, 500.0])
    """Range of Θ1 = Θ((s,a),(s,a)) the robust designs cover."""
    ratio: list[float] = field(default_factory=lambda: [0.8, 1.2])
    """Range of Θ2/Θ1 the robust designs cover."""
    nominal: list[float] = field(default_factory=lambda: [220.0, 222.0])
    """Nominal (Θ1, Θ2) of the design plant."""


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


@dataclass
class ControllerConfig:
    name: str = "hinf"
    """One of h2, hinf, hinf_f, ddqn, none."""
    design: str = "paper"
    """Where the gains come from: paper (research-code values) or synthesize."""
    discretization: str = "zoh"
    """Dynamic H∞ controller discretisation at Δt = α: zoh, tustin or euler."""
    reset_integrator: bool = True
    """Reset the tracking-error integrator x_e at each episode start."""
    reset_state: bool = True
    """Reset the dynamic controller's state at each episode start (paper Sec. 4.2)."""
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
    """Decrease of ε after each random action (research code)."""
    bootstrap_terminal: bool = True
    """Controlled agents bootstrap from max Q(s') at terminal steps too (research code)."""
    q_limit: float = 1e6
    """|Q| above this value ends the run as diverged."""
    fast_path: bool = True
    """Hand-derived gradients for the two-layer network instead of autograd."""
    progress: bool = True
    """Show a progress bar (hidden automatically in multiruns)."""
    signals: bool = True
    """Store the per-step signals (signals/steps.parquet, signals/fft.parquet)."""


@dataclass
class TrackingConfig:
    uri: str = "sqlite:///mlflow.db"
    """MLflow tracking URI; the default is an embedded store in the working folder."""
    experiment: str = "cdqn"
    """MLflow experiment name."""
    log_model: bool = True
    """Store the final network as an MLflow artifact."""


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


def register_configs() -> None:
    """Register the schema in Hydra's ConfigStore as ``base_config``."""
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)


def _tf_is_proper(tf: TransferFunctionConfig) -> bool:
    num = [float(c) for c in tf.num]
    den = [float(c) for c in tf.den]
    while num and num[0] == 0.0:
        num.pop(0)
    while den and den[0] == 0.0:
        den.pop(0)
    return bool(den) and len(num) <= len(den)


def validate(cfg: Config) -> None:
    """Refuse values cdqn cannot run with, naming the key, the value and what is allowed."""
    checks: list[tuple[bool, str]] = [
        (
            cfg.controller.name in CONTROLLERS,
            f"controller.name={cfg.controller.name!r}: allowed {', '.join(CONTROLLERS)}",
        ),
        (
            cfg.controller.design in ("paper", "synthesize"),
            f"controller.design={cfg.controller.design!r}: allowed paper, synthesize",
        ),
        (
            cfg.controller.discretization in ("zoh", "tustin", "euler"),
            f"controller.discretization={cfg.controller.discretization!r}: "
            "allowed zoh, tustin, euler",
        ),
        (cfg.network.width > 0, f"network.width={cfg.network.width}: must be a positive integer"),
        (
            cfg.network.dtype in ("float64", "float32"),
            f"network.dtype={cfg.network.dtype!r}: allowed float64, float32",
        ),
        (cfg.train.lr > 0, f"train.lr={cfg.train.lr}: the learning rate α must be > 0"),
        (
            0 < cfg.train.discount <= 1,
            f"train.discount={cfg.train.discount}: the discount γ must lie in (0, 1]",
        ),
        (cfg.train.episodes > 0, f"train.episodes={cfg.train.episodes}: must be > 0"),
        (
            0 <= cfg.train.eps_start <= 1,
            f"train.eps_start={cfg.train.eps_start}: ε must lie in [0, 1]",
        ),
        (0 <= cfg.train.eps_end <= 1, f"train.eps_end={cfg.train.eps_end}: ε must lie in [0, 1]"),
        (0 <= cfg.train.eps_dec <= 1, f"train.eps_dec={cfg.train.eps_dec}: must lie in [0, 1]"),
        (cfg.train.q_limit > 0, f"train.q_limit={cfg.train.q_limit}: must be > 0"),
        (
            cfg.controller.batch_size > 0
            and cfg.controller.buffer_size >= cfg.controller.batch_size,
            f"controller.batch_size={cfg.controller.batch_size}, controller.buffer_size="
            f"{cfg.controller.buffer_size}: need 0 < batch_size <= buffer_size",
        ),
        (
            cfg.controller.target_update > 0 and cfg.controller.train_freq > 0,
            "controller.target_update and controller.train_freq must be > 0",
        ),
        (
            len(cfg.weights.h2.w_x) == 3 and all(w >= 0 for w in cfg.weights.h2.w_x),
            f"weights.h2.w_x={list(cfg.weights.h2.w_x)}: need 3 non-negative diagonal entries",
        ),
        (cfg.weights.h2.w_c > 0, f"weights.h2.w_c={cfg.weights.h2.w_c}: must be > 0"),
    ]
    for group in ("hinf", "hinf_f"):
        w = getattr(cfg.weights, group)
        for name in ("w_p", "w_u", "w_r", "w_qhat"):
            tf = getattr(w, name)
            checks.append(
                (
                    _tf_is_proper(tf),
                    f"weights.{group}.{name}=num {list(tf.num)} / den {list(tf.den)}: not a proper "
                    "transfer function (need a non-zero denominator of degree >= the numerator's)",
                )
            )
    tb = cfg.weights.theta_bounds
    for name in ("theta1", "ratio"):
        rng = list(getattr(tb, name))
        checks.append(
            (
                len(rng) == 2 and 0 < rng[0] <= rng[1],
                f"weights.theta_bounds.{name}={rng}: need [lower, upper] with 0 < lower <= upper",
            )
        )
    errors = [msg for ok, msg in checks if not ok]
    if errors:
        raise ConfigError("invalid configuration:\n  - " + "\n  - ".join(errors))
