"""Tests of the error metrics."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.errors import DimensionError
from soft_rom.metrics import (
    output_errors,
    relative_deviation_error,
    relative_error,
    relative_error_from_squares,
)


def test_relative_errors_known_values() -> None:
    Y = np.array([[3.0, 3.0], [4.0, 4.0]])
    Yh = Y + np.array([[0.0, 0.3], [0.4, 0.0]])
    assert relative_error(Y, Yh) == pytest.approx(0.5 / np.sqrt(50.0))
    y_ref = np.array([3.0, 3.0])
    assert relative_deviation_error(Y, Yh, y_ref) == pytest.approx(0.5 / np.sqrt(2.0))
    both = output_errors(Y, Yh, y_ref)
    assert set(both) == {'relative_error', 'relative_deviation_error'}


def test_shape_mismatch() -> None:
    with pytest.raises(DimensionError):
        relative_error(np.ones((2, 3)), np.ones((3, 2)))


def test_zero_reference_and_pooled_squares() -> None:
    zero = np.zeros((2, 3))
    assert np.isnan(relative_error(zero, zero))
    assert relative_error(zero, zero, if_zero=0.0) == 0.0
    assert np.isnan(relative_error_from_squares(1.0, 0.0))
    # Pooling two pieces by their squared norms equals the error of the concatenation.
    rng = np.random.default_rng(0)
    Y1, Y2 = rng.standard_normal((3, 5)), rng.standard_normal((3, 7))
    E1, E2 = 0.1 * rng.standard_normal((3, 5)), 0.1 * rng.standard_normal((3, 7))
    pooled = relative_error_from_squares(float(np.sum(E1 ** 2) + np.sum(E2 ** 2)),
                                         float(np.sum(Y1 ** 2) + np.sum(Y2 ** 2)))
    whole = relative_error(np.hstack([Y1, Y2]), np.hstack([Y1 + E1, Y2 + E2]))
    assert pooled == pytest.approx(whole, rel=1e-12)


def test_deviation_error_names_a_transposed_prediction() -> None:
    """A prediction of another shape is named, as relative_error does.

    ``Y_hat`` (k, p) against ``Y`` (p, k) was numpy's broadcast ValueError, and a ``Y_hat``
    of one row (or 1-D) was broadcast against ``y_ref`` to p rows and scored silently.
    """
    Y = np.ones((3, 5))
    with pytest.raises(DimensionError, match=r'Y and Y_hat must have the same shape; got '
                                             r'\(3, 5\), \(5, 3\)'):
        relative_deviation_error(Y, Y.T, np.zeros(3))
    with pytest.raises(DimensionError, match='same shape'):
        output_errors(Y, Y.T, np.zeros(3))
    for one_row in (np.ones(5), np.ones((1, 5))):
        with pytest.raises(DimensionError, match=r'same shape; got \(3, 5\), \(1, 5\)'):
            relative_deviation_error(Y, one_row, np.zeros(3))
