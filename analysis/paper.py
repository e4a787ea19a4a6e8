"""The paper's reported numbers, for ``make_table.py --compare-paper``.

Table ``tab:result_summary`` of Varga, Kulcsár, Haghir Chehreghani, "Deep Q-learning: a
robust control approach" (2022): final scores after 2000 episodes, mean ± std over 10 seeds.
"""

from __future__ import annotations

from typing import NamedTuple


class Score(NamedTuple):
    mean: float
    std: float


PAPER_SCORES: dict[tuple[str, str], Score] = {
    ("h2", "cartpole"): Score(187.92, 2.47),
    ("h2", "acrobot"): Score(-146.44, 45.09),
    ("h2", "mountaincar"): Score(-140.57, 5.07),
    ("hinf_f", "cartpole"): Score(192.59, 7.13),
    ("hinf_f", "acrobot"): Score(-99.93, 3.79),
    ("hinf_f", "mountaincar"): Score(-141.41, 8.38),
    ("hinf", "cartpole"): Score(199.37, 1.21),
    ("hinf", "acrobot"): Score(-111.73, 13.17),
    ("hinf", "mountaincar"): Score(-134.45, 8.63),
    ("ddqn", "cartpole"): Score(197.56, 7.37),
    ("ddqn", "acrobot"): Score(-98.04, 8.58),
    ("ddqn", "mountaincar"): Score(-135.79, 9.41),
}
"""(controller, env) -> the paper's final score."""
PAPER_EPISODES = 2000
PAPER_SEEDS = 10
