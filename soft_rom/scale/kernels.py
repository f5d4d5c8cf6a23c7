"""Block kernels of the streaming passes (module-level so that Dask can ship them).

Each kernel receives a *centred* block ``X`` of the snapshot matrix (column block
``(n, c)`` or row block ``(rows, K)``) followed by its arguments, and returns a small result.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def sketch(X: Array, omega: Array) -> tuple[Array, float]:
    """Range sketch ``X Ω`` of a column block and its squared Frobenius norm."""
    return X @ omega, float(np.einsum('ij,ij->', X, X))


def power(X: Array, Qb: Array) -> Array:
    """One power-iteration term ``X (Xᵀ Q_b)`` of a column block."""
    return X @ (X.T @ Qb)


def project(X: Array, W: Array) -> Array:
    """Coordinates ``Wᵀ X`` of a column block in an orthonormal frame ``W`` (n, l)."""
    return W.T @ X


def gram_rows(X: Array) -> Array:
    """Contribution ``Xᵀ X`` (K, K) of a row block to the snapshot Gram matrix."""
    return X.T @ X


def modes_rows(X: Array, V_scaled: Array) -> Array:
    """Rows of the POD modes ``X V Σ⁻¹`` from a row block (method of snapshots)."""
    return X @ V_scaled
