"""Exceptions raised by soft_rom, and the warnings it gives.

Every error is also a built-in exception (``ValueError``, ``FileNotFoundError``, ...) so
that callers who do not know this package can still catch it, and every message says what
was expected, what came, and what to do.
"""

from __future__ import annotations

import sys

__all__ = [
    'BagError',
    'ClusterError',
    'ConfigError',
    'DatasetError',
    'DimensionError',
    'ModelFileError',
    'NotFittedError',
    'OutputExistsError',
    'ReferenceReachWarning',
    'ResourceError',
    'SoftRomError',
    'SoftRomWarning',
    'SolverError',
    'UntrustedModelWarning',
    'dask_worker',
    'one_line',
    'show_value',
    'warn',
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


class SoftRomWarning(UserWarning):
    """Base class of the warnings soft_rom gives (``warnings.simplefilter('ignore', ...)``)."""


class UntrustedModelWarning(SoftRomWarning):
    """A model that loads but cannot be trusted is used (``model.trust_issues()`` says why)."""


class ReferenceReachWarning(SoftRomWarning):
    """A reference the controlled model cannot reach within the input bounds."""


def warn(message: str, category: type[Warning]) -> None:
    """``warnings.warn`` pointing at the first caller outside soft_rom (the user's line)."""
    import os
    import warnings
    here = os.path.dirname(os.path.abspath(__file__)) + os.sep
    level, frame = 2, sys._getframe(1)
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(here):
        level += 1
        frame = frame.f_back     # type: ignore[assignment]
    warnings.warn(message, category, stacklevel=level)


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


def one_line(err: BaseException, limit: int = 300) -> str:
    """``'Type: message'`` of ``err`` on one line, at most ``limit`` characters."""
    text = ' '.join(str(err).split())
    if len(text) > limit:
        text = text[:limit - 3] + '...'
    return f'{type(err).__name__}: {text}' if text else type(err).__name__


def dask_worker() -> str | None:
    """Address of the ``dask.distributed`` worker running this code, or ``None``."""
    mod = sys.modules.get('distributed')
    if mod is None:
        return None
    try:
        return str(mod.get_worker().address)
    except Exception:  # noqa: BLE001 - ValueError outside a worker; anything else: not one
        return None
