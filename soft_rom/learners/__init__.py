"""Learners: hyperparameters in ``__init__``, ``fit(...) -> self``, a frozen ``model_``."""
