"""Robust-control side of cdqn: learning-dynamics plant, controller synthesis, runtime
controllers.  Nothing in this package imports torch."""
