"""Tests of the error metrics."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.errors import DimensionError
from soft_rom.metrics import output_errors, relative_deviation_error, relative_error


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
