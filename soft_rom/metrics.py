"""Error metrics (plain functions), as in the paper's eq. (err): the package's only error code.

Both are reported everywhere: the paper's relative error on absolute outputs, and the same
on deviations from ``y_ref`` (more telling, since absolute coordinates dominate the norm).
:func:`relative_error_from_squares` gives the same ratio from squared norms accumulated
piece by piece (errors pooled over episodes or segments).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from soft_rom.data import as_signal
from soft_rom.errors import DimensionError

__all__ = ['output_errors', 'relative_deviation_error', 'relative_error',
           'relative_error_from_squares']


def relative_error(Y: ArrayLike, Y_hat: ArrayLike, *, if_zero: float = math.nan) -> float:
    """Relative output error ``||Y - Ŷ||_F / ||Y||_F`` (Sharma et al., eq. err).

    Parameters
    ----------
    Y, Y_hat : ndarray, shape (p, k)
        Reference and approximation, absolute coordinates.
    if_zero : float
        Returned when ``||Y||_F = 0`` (default NaN: the ratio is undefined). Fits that
        report how well they reproduce their own data pass 0.0 (an all-zero target fitted
        by an all-zero map).
    """
    Y = as_signal('Y', Y)
    Y_hat = as_signal('Y_hat', Y_hat)
    if Y.shape != Y_hat.shape:
        raise DimensionError(f'Y and Y_hat must have the same shape; got {Y.shape}, '
                             f'{Y_hat.shape}.')
    den = np.linalg.norm(Y)
    return float(np.linalg.norm(Y - Y_hat) / den) if den > 0 else float(if_zero)


def relative_error_from_squares(err_sq: float, ref_sq: float, *,
                                if_zero: float = math.nan) -> float:
    """Relative error ``sqrt(err_sq / ref_sq)`` from squared Frobenius norms.

    For errors pooled over pieces (episodes, train/test segments): ``err_sq`` is the sum of
    :math:`\\|Y_i - \\hat Y_i\\|_F^2` and ``ref_sq`` that of :math:`\\|Y_i\\|_F^2` (or of the
    deviations from ``y_ref``).

    Parameters
    ----------
    err_sq, ref_sq : float
        Squared norms (non-negative).
    if_zero : float
        Returned when ``ref_sq`` is 0 (default NaN), as in :func:`relative_error`.
    """
    return float(np.sqrt(err_sq / ref_sq)) if ref_sq > 0 else float(if_zero)


def relative_deviation_error(Y: ArrayLike, Y_hat: ArrayLike, y_ref: ArrayLike, *,
                             if_zero: float = math.nan) -> float:
    """Relative error on deviations: ``||Y - Ŷ||_F / ||Y - y_ref 1ᵀ||_F``.

    Parameters
    ----------
    Y, Y_hat : ndarray, shape (p, k)
    y_ref : ndarray, shape (p,)
    if_zero : float
        Returned when the deviations are all zero (default NaN), as in :func:`relative_error`.
    """
    Y = as_signal('Y', Y)
    Y_hat = as_signal('Y_hat', Y_hat)
    if Y.shape != Y_hat.shape:      # before ``- y_ref``, which broadcasts or fails in numpy
        raise DimensionError(f'Y and Y_hat must have the same shape; got {Y.shape}, '
                             f'{Y_hat.shape}.')
    y_ref = np.asarray(y_ref, dtype=np.float64).reshape(-1, 1)
    if y_ref.shape[0] != Y.shape[0]:
        raise DimensionError(f'y_ref must have {Y.shape[0]} entries; got {y_ref.shape[0]}.')
    return relative_error(Y - y_ref, Y_hat - y_ref, if_zero=if_zero)


def output_errors(Y: ArrayLike, Y_hat: ArrayLike, y_ref: ArrayLike) -> dict[str, float]:
    """Both metrics as ``{'relative_error': ..., 'relative_deviation_error': ...}``."""
    return {'relative_error': relative_error(Y, Y_hat),
            'relative_deviation_error': relative_deviation_error(Y, Y_hat, y_ref)}
