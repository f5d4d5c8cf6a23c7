"""Exceptions raised by soft_rom.

Every error is also a built-in exception (``ValueError``, ``FileNotFoundError``, ...) so
that callers who do not know this package can still catch it, and every message says what
was expected, what came, and what to do.
"""

from __future__ import annotations

__all__ = [
    'BagError',
    'ClusterError',
    'ConfigError',
    'DatasetError',
    'DimensionError',
    'ModelFileError',
    'NotFittedError',
    'OutputExistsError',
    'ResourceError',
    'SoftRomError',
    'SolverError',
    'show_value',
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


class ClusterError(SoftRomError, ConnectionError):
    """A Dask cluster could not be reached, was lost, or one of its workers failed."""


def show_value(value: object) -> str:
    """``value`` as a YAML file spells it (``abc``, ``[1]``, ``null``), on one short line.

    For messages about configuration values: the user sees what they wrote.
    """
    import yaml

    try:
        text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30).strip()
    except yaml.YAMLError:
        text = repr(value)
    text = text.removesuffix('\n...').removesuffix(' ...').strip()
    return text if len(text) <= 80 else text[:77] + '...'
