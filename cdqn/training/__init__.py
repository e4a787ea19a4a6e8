"""The training side: from a configuration to recorded, checkpointed MLflow runs.

A run reads top to bottom as configuration → building → training loop (single run or
population) → recording and checkpoints; :mod:`cdqn.train` is its command line.  The
modules come in layers, and a module imports only from lower layers (and from the rest of
cdqn: ``config``, ``envs``, ``vector_env``, ``network``, ``ntk_bounds``, ``agents``,
``control``, none of which imports this package; ``tests/test_layering.py`` checks it):

====  =====================================  ==============================================
layer module                                 what it holds
====  =====================================  ==============================================
1     :mod:`~cdqn.training.signals`          the per-step signal table and its spectra
1     :mod:`~cdqn.training.interrupt`        SIGINT/SIGTERM as a stop at the next boundary
1     :mod:`~cdqn.training.result`           what a run or a population returns and prints
1     :mod:`~cdqn.training.batching`         which seeds train as one batch (sweeps too)
1     :mod:`~cdqn.training.divergence`       the divergence check of every run
1     :mod:`~cdqn.training.store`            the tracking store made ready once, under a lock
2     :mod:`~cdqn.training.loop`             the training loop of a single run
2     :mod:`~cdqn.training.member`           a run in training: seed, run, signals, state
3     :mod:`~cdqn.training.population_loop`  the training loop of a population
4     :mod:`~cdqn.training.build`            env, network, controller and agent of a run
5     :mod:`~cdqn.training.tracking`         the MLflow recorder, retries while it is away
5     :mod:`~cdqn.training.sweep`            config hashes, skipping finished runs
5     :mod:`~cdqn.training.callbacks`        Hydra callbacks: job outcomes, sweep summary
6     :mod:`~cdqn.training.checkpoint`       a single run's checkpoints (store and local)
6     :mod:`~cdqn.training.population_checkpoint`  a population member's checkpoints
7     :mod:`~cdqn.training.lifecycle`        a run's life: open, record, checkpoint, close, resume
8     :mod:`~cdqn.training.single`           a single run: train, record, checkpoint, close
8     :mod:`~cdqn.training.population`       a population's runs: the same for K seeds
9     :mod:`~cdqn.training.run`              new run or resume, single or population
====  =====================================  ==============================================
"""

LAYERS: tuple[tuple[str, ...], ...] = (
    ("signals", "interrupt", "result", "batching", "divergence", "store"),
    ("loop", "member"),
    ("population_loop",),
    ("build",),
    ("tracking", "sweep", "callbacks"),
    ("checkpoint", "population_checkpoint"),
    ("lifecycle",),
    ("single", "population"),
    ("run",),
)
"""The modules of the package by layer, lowest first (the table above)."""
