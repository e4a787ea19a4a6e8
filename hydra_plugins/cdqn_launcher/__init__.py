"""The cdqn launcher: Hydra's joblib launcher whose workers stop with it on SIGTERM
(:mod:`hydra_plugins.cdqn_launcher.cdqn_launcher`)."""
