"""Exceptions raised by soft_rom.

Every error is also a built-in exception (``ValueError``, ``FileNotFoundError``, ...) so
that callers who do not know this package can still catch it, and every message says what
was expected, what came, and what to do.
"""

from __future__ import annotations

__all__ = [
    'BagError',
    'ConfigError',
    'DatasetError',
    'DimensionError',
    'ModelFileError',
    'NotFittedError',
    'OutputExistsError',
    'ResourceError',
    'SoftRomError',
    'SolverError',
]


class SoftRomError(Exception):
    """Base class of every error raised on purpose by soft_rom."""


class DimensionError(SoftRomError, ValueError):
    """An array has the wrong shape or the wrong number of channels/samples."""


class ConfigError(SoftRomError, ValueError):
    """A configuration file, hyperparameter or node parameter is invalid."""


class NotFittedError(SoftRomError, AttributeError):
    """A learner was used before ``fit`` was called."""


class SolverError(SoftRomError, RuntimeError):
    """A numerical solver failed (did not converge, infeasible, ...)."""


class ModelFileError(SoftRomError, ValueError):
    """A model file is missing, corrupt, hostile or of an unknown format version."""


class DatasetError(SoftRomError, ValueError):
    """A training set on disk is missing, corrupt, or inconsistent."""


class BagError(SoftRomError, ValueError):
    """A ROS 2 bag cannot be read/written or does not match the configured contract."""


class OutputExistsError(SoftRomError, FileExistsError):
    """An output exists and may not be replaced (no ``--overwrite``, or not soft_rom's)."""


class ResourceError(SoftRomError, MemoryError):
    """A run was refused before it started: it would not fit in memory or on disk."""
