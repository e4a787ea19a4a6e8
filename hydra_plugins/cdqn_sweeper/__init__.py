"""The cdqn sweeper: Hydra's basic sweep, with jobs that differ only in ``seed`` trained as
populations (:mod:`hydra_plugins.cdqn_sweeper.cdqn_sweeper`)."""
