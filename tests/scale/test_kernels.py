"""The block kernels (soft_rom.scale.kernels) compute the products they name."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.scale import kernels


def test_kernels_are_the_products_they_name():
    rng = np.random.default_rng(5)
    X, omega, W = rng.standard_normal((40, 7)), rng.standard_normal((7, 3)), \
        np.linalg.qr(rng.standard_normal((40, 4)))[0]
    Y, sq = kernels.sketch(X, omega)
    assert np.allclose(Y, X @ omega, rtol=0, atol=1e-12)
    assert sq == pytest.approx(float(np.sum(X * X)), rel=1e-14)
    assert np.allclose(kernels.power(X, W), X @ X.T @ W, rtol=0, atol=1e-12)
    assert np.allclose(kernels.project(X, W), W.T @ X, rtol=0, atol=1e-12)
    assert np.allclose(kernels.gram_rows(X), X.T @ X, rtol=0, atol=1e-12)
    assert np.allclose(kernels.modes_rows(X, omega), X @ omega, rtol=0, atol=1e-12)
