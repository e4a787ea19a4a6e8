"""Tuning an agent for an environment: an Optuna study whose trials are populations
(``python -m cdqn.tune``, docs/tuning.md).

* :mod:`~cdqn.tuning.settings` — the ``tune.*`` schema and its checks, the episode budget;
* :mod:`~cdqn.tuning.space` — sampling a specification and writing it into a configuration;
* :mod:`~cdqn.tuning.objective` — J, the area under the learning curves;
* :mod:`~cdqn.tuning.pruner` — the episode-median pruner;
* :mod:`~cdqn.tuning.trial` — one trial: certify, train, report, record;
* :mod:`~cdqn.tuning.study` — the study: its trials, the preset, the evaluation;
* :mod:`~cdqn.tuning.evaluation` — fresh seeds and the tuned agents side by side;
* :mod:`~cdqn.tuning.presets` — the preset of the best trial;
* :mod:`~cdqn.tuning.tracker`, :mod:`~cdqn.tuning.storage`, :mod:`~cdqn.tuning.report` —
  MLflow runs, the Optuna storage and its lock, plots and the printed summary.
"""
