"""What every agent provides to the trainer, and the shared ε-greedy exploration."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numba import njit

from cdqn.config import TrainConfig

if TYPE_CHECKING:
    from cdqn.agents.episodic_replay import Transitions
    from cdqn.network import QNetwork
    from cdqn.vector_env import VectorStep


class StepRecord(NamedTuple):
    """Signals of one training step (paper notation)."""

    loss: float
    q1: float
    """Q1 = Q(s, a) before the update."""
    q2: float
    """Q2 = max_a' Q(s', a') before the update."""
    u: float
    """Control reward u(t) injected into the loss (0 without a controller)."""
    x_e: float
    """Integrated tracking error x_e = ∫ (r + γ Q̂2 − Q1) dt, Δt = α."""
    theta1: float
    """Θ1 = Θ((s, a), (s, a))."""
    theta2: float
    """Θ2 = Θ((s, a), (s', a'))."""


class Agent(Protocol):
    """A learning agent driven by :func:`cdqn.training.loop.train`."""

    @property
    def epsilon(self) -> float: ...

    def act(self, obs: np.ndarray) -> int: ...

    def update(
        self, obs: np.ndarray, action: int, reward: float, next_obs: np.ndarray, terminated: bool
    ) -> StepRecord: ...

    def start_episode(self) -> None: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class MemberControllers(Protocol):
    """The controllers of a population's members (none for Double DQN)."""

    def state(self, i: int) -> np.ndarray | None:
        """Member ``i``'s controller state, checked for divergence; None without one."""
        ...


class LoopState(NamedTuple):
    """What the population loop hands a :class:`PopulationAgent`'s step, per member:
    episode ``ep`` ``(K,)``, step ``t`` (the agent counts the step), return ``ret`` (the
    agent adds the reward), the signal ``rows`` ``(K, 10)`` to write, and the divergence
    test's ``q_limit`` (:mod:`cdqn.training.divergence`)."""

    ep: np.ndarray
    t: np.ndarray
    ret: np.ndarray
    rows: np.ndarray
    q_limit: float


class PopulationAgent(Protocol):
    """K members of one agent stepped together (``train.population``), driven by
    :func:`cdqn.training.population_loop.train_population`; member ``i`` learns exactly what
    the single :class:`Agent` of its seed learns.  Implemented by
    :class:`cdqn.agents.controlled_population.ControlledPopulation` and
    :class:`cdqn.agents.ddqn_population.DDQNPopulation`."""

    flags: np.ndarray
    """Per member, after :meth:`update`: why it needs the loop's attention (0: it does not)."""
    loss_seen: np.ndarray
    """Per member: a finite loss was recorded in the current episode."""

    @property
    def controller(self) -> MemberControllers: ...

    @property
    def epsilon(self) -> np.ndarray: ...

    def start_episode(self, i: int) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...

    def update(self, actions: np.ndarray, step: VectorStep, loop: LoopState) -> int: ...

    def select(self, keep: np.ndarray) -> None: ...

    def network(self, i: int) -> QNetwork: ...

    def state_dict(self, i: int) -> dict[str, Any]: ...

    def load_state_dict(self, i: int, state: dict[str, Any]) -> None: ...


@runtime_checkable
class ReplayAgent(Agent, Protocol):
    """An agent that can learn again from an episode's last transitions (episodic replay)."""

    def replay(self, tail: Transitions, repeats: int) -> Iterator[StepRecord]: ...


class EpsilonGreedy:
    """ε-greedy: start at ``eps_start`` and lower ε by ``eps_dec``, floored at ``eps_end``,
    after each random action (``eps_schedule=random_action``, the research code: ε falls
    while it is ≥ ``eps_end``, so as the agent explores), after each step
    (``eps_schedule=step``: ε_t = max(eps_end, eps_start − eps_dec·t), linear in steps as
    in DQN) or at the start of each episode (``eps_schedule=episode``: episode ``e``,
    counted from 0, acts with ε = max(eps_end, eps_start − eps_dec·(e + 1)), however long
    its episodes are).  Step ``t`` acts at random with probability ε_t.  Under the episode
    schedule every step draws both the uniform and the random action, so that decisions can
    be drawn ahead of the episode ends that set ε (:class:`ExplorationPlan`)."""

    def __init__(self, cfg: TrainConfig, n_actions: int, rng: np.random.Generator) -> None:
        self.epsilon = cfg.eps_start
        self.eps_end = cfg.eps_end
        self.eps_dec = cfg.eps_dec
        self.per_step = cfg.eps_schedule == "step"
        self.per_episode = cfg.eps_schedule == "episode"
        self.n_actions = n_actions
        self.rng = rng

    def start_episode(self) -> None:
        """``eps_schedule=episode``: lower ε by ``eps_dec`` (down to ``eps_end``)."""
        if self.per_episode and self.epsilon > self.eps_end:
            self.epsilon = max(self.eps_end, self.epsilon - self.eps_dec)

    def explore(self) -> int | None:
        """A random action with probability ε (and decay ε), else None."""
        if self.per_episode:
            u, action = self.rng.random(), int(self.rng.integers(self.n_actions))
            return None if u > self.epsilon else action
        epsilon = self.epsilon
        if self.per_step and epsilon > self.eps_end:
            self.epsilon = max(self.eps_end, epsilon - self.eps_dec)
        if self.rng.random() > epsilon:
            return None
        if not self.per_step and epsilon >= self.eps_end:
            self.epsilon = epsilon - self.eps_dec
        return int(self.rng.integers(self.n_actions))


@njit(cache=True)
def explore_ahead(rng, epsilon, eps_end, eps_dec, per_step, n_actions, out):
    """The next ``len(out)`` decisions of :meth:`EpsilonGreedy.explore` from ``rng`` and
    ``epsilon`` (``per_step``: ``eps_schedule=step``): ``out[i]`` is the random action of
    step ``i`` or −1 (greedy).  Returns ε after them.

    Exploration depends on nothing but its generator and ε, so its decisions can be drawn
    ahead.  numba's ``Generator.random``/``integers`` advance the NumPy generator's own
    bit generator with NumPy's algorithms, so the draws, and the generator's state after
    them, are those of ``len(out)`` calls of ``explore`` (``tests/test_population.py``).
    """
    for i in range(out.shape[0]):
        eps = epsilon
        if per_step and epsilon > eps_end:
            epsilon = max(eps_end, epsilon - eps_dec)
        if rng.random() > eps:
            out[i] = -1
            continue
        if not per_step and epsilon >= eps_end:
            epsilon -= eps_dec
        out[i] = rng.integers(0, n_actions)
    return epsilon


@njit(cache=True)
def draw_ahead(rng, n_actions, uniform, action):
    """The next ``len(uniform)`` draws of :meth:`EpsilonGreedy.explore` under
    ``eps_schedule=episode`` from ``rng``: the uniform that is compared with ε, and the
    random action, of each step (the same generator order as ``explore``)."""
    for i in range(uniform.shape[0]):
        uniform[i] = rng.random()
        action[i] = rng.integers(0, n_actions)


@njit(cache=True)
def decide(uniform, action, epsilon, out):
    """One step's decisions under ``eps_schedule=episode`` from draws made ahead
    (:func:`draw_ahead`): member ``k`` takes its random action where its uniform is at most
    its ε (as :meth:`EpsilonGreedy.explore`), else −1 (greedy)."""
    for k in range(out.shape[0]):
        out[k] = action[k] if uniform[k] <= epsilon[k] else -1
