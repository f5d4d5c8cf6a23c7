"""Proper orthogonal decomposition (POD) bases for the reduced states.

A basis builder turns full-order snapshots ``Q`` (nodal positions, ``(n, k)``) centred on the
reference configuration ``q_ref`` into an orthonormal basis ``V`` of shape ``(n, r)``; reduced
coordinates are ``q̂ = Vᵀ (q - q_ref)`` and ``q ≈ q_ref + V q̂``.

Builders are objects behind the small :class:`BasisBuilder` protocol, so that an out-of-core
builder (for data that do not fit in memory, see :mod:`soft_rom.scale`) plugs into
:class:`soft_rom.learners.lopinf.LOpInf` in place of the in-memory :class:`POD`.

Snapshots may be lazy arrays (anything with ``.shape`` and numpy-style column slicing
``Q[:, a:b]``, e.g. zarr arrays); they are read in column blocks by :func:`project`.

The in-memory POD takes its SVD on the coordinates of the snapshots in a basis of their
range (:func:`snapshot_range`, to ``RANGE_TOL``) when the snapshots have a decaying spectrum
(a smooth body: the eel's 4,000 snapshots of 5,145 states have numerical rank 229 at 1e-10),
and on the snapshots themselves otherwise: the same basis to rounding, at a fraction of the
cost.

Reference: Sharma et al., *Data-driven Model Reduction for Soft Robots via Lagrangian
Operator Inference*, section 2.2 (POD of the centred snapshot matrix).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import all_finite
from soft_rom.errors import ConfigError, DimensionError, NotFittedError

__all__ = ['BasisBuilder', 'DEFAULT_BLOCK_COLUMNS', 'POD', 'project', 'RANGE_TOL', 'reconstruct',
           'select_rank', 'snapshot_range']

Array = NDArray[np.float64]

#: Number of snapshot columns read at a time from (possibly lazy) snapshot arrays.
DEFAULT_BLOCK_COLUMNS = 2048
#: Relative Frobenius residual to which :func:`snapshot_range` finds the snapshots' range
#: for the in-memory SVDs (POD, DMDc): 1e-3 of DMDc's rank guard (1e-10).
RANGE_TOL = 1e-13


@runtime_checkable
class BasisBuilder(Protocol):
    """What :class:`~soft_rom.learners.lopinf.LOpInf` needs from a basis builder.

    Attributes (after ``fit``)
    --------------------------
    basis_ : ndarray, shape (n, r)
        Orthonormal columns.
    singular_values_ : ndarray, shape (s,)
        Singular values of the centred snapshot matrix, descending (all that were
        computed, not only the ``r`` kept).
    """

    basis_: Array
    singular_values_: Array

    def fit(self, snapshots: Sequence[Any], q_ref: ArrayLike) -> BasisBuilder:
        """Build the basis from one or several (n, k_i) snapshot arrays centred on q_ref."""
        ...


def select_rank(singular_values: ArrayLike, *, r: int | None = None,
                energy: float = 0.95) -> int:
    """Choose the reduced dimension from the singular values.

    Parameters
    ----------
    singular_values : array_like, shape (s,)
        Descending singular values.
    r : int, optional
        Explicit dimension; wins over ``energy``. Must satisfy ``1 <= r <= s``.
    energy : float
        Fraction in ``(0, 1]`` of :math:`\\sum_i \\sigma_i^2` to capture: the smallest ``r``
        with :math:`\\sum_{i\\le r}\\sigma_i^2 / \\sum_i \\sigma_i^2 \\ge` ``energy``.
    """
    s = np.asarray(singular_values, dtype=np.float64).reshape(-1)
    if s.size == 0 or not np.any(s > 0):
        raise DimensionError('the centred snapshots are all zero: the body never moved away '
                             'from q_ref, so there is nothing to reduce.')
    if r is not None:
        r = int(r)
        if not 1 <= r <= s.size:
            raise ConfigError(f'r must be between 1 and {s.size} (number of singular values '
                              f'available); got {r}.')
        return r
    if not 0.0 < energy <= 1.0:
        raise ConfigError(f'energy must be in (0, 1]; got {energy!r}.')
    cum = np.cumsum(s ** 2) / np.sum(s ** 2)
    return min(int(np.searchsorted(cum, energy - 1e-12)) + 1, int(s.size))


def snapshot_range(arrays: Sequence[Array], tol: float, *, start: int = 512,
                   seed: int = 0) -> Array | None:
    """An orthonormal basis of the columns of ``arrays``, to relative precision ``tol``.

    A randomized range finder (Halko, Martinsson & Tropp, *SIAM Review* 53(2), 2011,
    algorithm 4.1, without power iterations): ``W = orth(A Ω)`` with a Gaussian ``Ω`` of
    ``k`` columns from a fixed seed, grown by half until the residual
    ``‖A - W Wᵀ A‖_F ≤ tol ‖A‖_F`` is checked to hold. Snapshots of a smooth body have a
    fast-decaying spectrum (the eel's 4,000 snapshots of 5,145 states: numerical rank 229
    at 1e-10, residual 2e-14 with 640 columns), so the SVDs can then be taken on ``Wᵀ A``
    at a fraction of their cost on ``A``. Noisy snapshots have no such range: after two tries
    whose residuals, extrapolated geometrically, would not reach ``tol`` within half of
    ``min(n, K)`` columns, it gives up (on the eel with 1 µm of noise: after 2 tries, instead
    of 4).

    Parameters
    ----------
    arrays : sequence of ndarray, each shape (n, k_i)
        The snapshots (columns of ``A``), e.g. one array per episode.
    tol : float
        Relative Frobenius residual to reach.
    start : int
        Columns of the first try.
    seed : int
        Seed of ``Ω`` (fixed: the same basis on every run).

    Returns
    -------
    W : ndarray, shape (n, k), or None
        ``None`` when ``A`` is too small to gain (``min(n, K) < 2 start``) or the residual
        needs (or, extrapolated, would need) more than half of ``min(n, K)`` columns: take
        the SVDs of ``A`` itself.
    """
    n = int(arrays[0].shape[0])
    K = sum(int(a.shape[1]) for a in arrays)
    norm2 = sum(float(np.vdot(a, a)) for a in arrays)
    if min(n, K) < 2 * start or norm2 == 0.0:
        return None
    rng = np.random.default_rng(seed)
    k = int(start)
    limit, before = min(n, K) // 2, None
    while k <= limit:
        sketch = np.zeros((n, k))
        for a in arrays:
            sketch += a @ rng.standard_normal((a.shape[1], k))
        W = np.linalg.qr(sketch)[0]
        residual2 = 0.0
        for a in arrays:
            for j in range(0, a.shape[1], 512):
                block = a[:, j:j + 512]
                r = block - W @ (W.T @ block)
                residual2 += float(np.vdot(r, r))
        if residual2 <= tol * tol * norm2:
            return W
        if before is not None and not _reaches(before, (k, residual2), tol * tol * norm2,
                                               limit):
            return None                 # noise, not a decaying spectrum: the full SVD
        before, k = (k, residual2), k + k // 2
    return None


def _reaches(first: tuple[int, float], second: tuple[int, float], target: float,
             limit: int) -> bool:
    """Whether a residual decaying geometrically reaches ``target`` within ``limit`` columns.

    ``first`` and ``second`` are two tries, ``(columns, squared residual)``.
    """
    (k1, e1), (k2, e2) = first, second
    if e2 <= 0.0 or e2 >= e1:
        return e2 <= target
    per_column = np.log(e2 / e1) / (k2 - k1)
    return bool(k2 + np.log(target / e2) / per_column <= limit)


def project(Q: Any, basis: ArrayLike, q_ref: ArrayLike, *,
            block_columns: int = DEFAULT_BLOCK_COLUMNS) -> Array:
    """Reduced coordinates ``Vᵀ (Q - q_ref)``, reading ``Q`` in column blocks.

    Parameters
    ----------
    Q : array_like or lazy array, shape (n, k)
        Snapshots; only ``.shape`` and ``Q[:, a:b]`` are used, so zarr/dask arrays work.
    basis : ndarray, shape (n, r)
    q_ref : ndarray, shape (n,)
    block_columns : int
        Columns read per block.

    Returns
    -------
    Qhat : ndarray, shape (r, k)
    """
    V = np.asarray(basis, dtype=np.float64)
    ref = np.asarray(q_ref, dtype=np.float64).reshape(-1)
    shape = getattr(Q, 'shape', None)
    if shape is None:
        Q = np.asarray(Q, dtype=np.float64)
        shape = Q.shape
    if len(shape) != 2 or shape[0] != V.shape[0] or ref.size != V.shape[0]:
        raise DimensionError(f'cannot project snapshots of shape {tuple(shape)} on a basis of '
                             f'shape {V.shape} with q_ref of length {ref.size}: the number of '
                             'full-order coordinates must agree.')
    k = int(shape[1])
    out = np.empty((V.shape[1], k))
    step = max(int(block_columns), 1)
    for a in range(0, k, step):
        b = min(a + step, k)
        block = np.asarray(Q[:, a:b], dtype=np.float64)
        out[:, a:b] = V.T @ (block - ref[:, None])
    return out


def reconstruct(Qhat: ArrayLike, basis: ArrayLike, q_ref: ArrayLike) -> Array:
    """Full states ``q_ref + V Qhat`` from reduced coordinates.

    Parameters
    ----------
    Qhat : ndarray, shape (r, k) or (r,)
    basis : ndarray, shape (n, r)
    q_ref : ndarray, shape (n,)

    Returns
    -------
    ndarray, shape (n, k) or (n,)
    """
    V = np.asarray(basis, dtype=np.float64)
    Qhat = np.asarray(Qhat, dtype=np.float64)
    one_d = Qhat.ndim == 1
    Q2 = Qhat.reshape(-1, 1) if one_d else Qhat
    if Q2.shape[0] != V.shape[1]:
        raise DimensionError(f'Qhat must have {V.shape[1]} rows; got shape {Qhat.shape}.')
    out = np.asarray(q_ref, dtype=np.float64)[:, None] + V @ Q2
    return out[:, 0] if one_d else out


class POD:
    """In-memory POD basis by thin SVD of the centred snapshot matrix.

    .. math:: [Q_1 - q_{ref}, \\dots, Q_E - q_{ref}] = V \\Sigma W^T, \\qquad
        V_r = V[:, :r]

    Parameters
    ----------
    r : int, optional
        Reduced dimension; if ``None`` it is chosen by ``energy``.
    energy : float
        Fraction of the squared singular values to capture when ``r`` is ``None``
        (default 0.95, as in the paper).
    block_columns : int
        Columns read per block from lazy snapshot arrays.

    Attributes
    ----------
    basis_ : ndarray, shape (n, r)
        Orthonormal POD modes; the sign of each mode is fixed so that its entry of largest
        magnitude is positive (results do not depend on LAPACK's sign choice).
    singular_values_ : ndarray, shape (min(n, k),)
        All singular values, descending.
    energy_ : ndarray, shape (min(n, k),)
        Cumulative energy fraction :math:`\\sum_{i\\le j}\\sigma_i^2/\\sum_i\\sigma_i^2`.
    q_ref_ : ndarray, shape (n,)
    r_ : int
        Number of modes kept.
    """

    def __init__(self, r: int | None = None, energy: float = 0.95, *,
                 block_columns: int = DEFAULT_BLOCK_COLUMNS) -> None:
        self.r = r
        self.energy = energy
        self.block_columns = block_columns

    def fit(self, snapshots: Sequence[Any] | Any, q_ref: ArrayLike) -> POD:
        """Compute the basis.

        Parameters
        ----------
        snapshots : array or sequence of arrays, each shape (n, k_i)
            One or several episodes' snapshots (absolute), possibly lazy.
        q_ref : ndarray, shape (n,)
            Reference configuration subtracted from every snapshot.

        Returns
        -------
        self : POD
        """
        V, s = self.svd(snapshots, q_ref)
        return self.fit_svd(V, s, q_ref)

    def svd(self, snapshots: Sequence[Any] | Any, q_ref: ArrayLike) -> tuple[Array, Array]:
        """The thin SVD ``(V, s)`` of the centred snapshots, read in column blocks.

        Parameters
        ----------
        snapshots : array or sequence of arrays, each shape (n, k_i)
        q_ref : ndarray, shape (n,)

        Returns
        -------
        V : ndarray, shape (n, min(n, k))
        s : ndarray, shape (min(n, k),)
        """
        parts: list[Any] = [snapshots] if hasattr(snapshots, 'shape') else list(snapshots)
        if not parts:
            raise DimensionError('POD.fit needs at least one snapshot array.')
        ref = np.asarray(q_ref, dtype=np.float64).reshape(-1)
        blocks = []
        for i, Q in enumerate(parts):
            shape = getattr(Q, 'shape', None)
            if shape is None:
                Q = np.asarray(Q, dtype=np.float64)
                shape = Q.shape
            if len(shape) != 2 or shape[0] != ref.size:
                raise DimensionError(f'snapshot array {i} must have shape ({ref.size}, k) to '
                                     f'match q_ref; got {tuple(shape)}.')
            step = max(int(self.block_columns), 1)
            for a in range(0, int(shape[1]), step):
                blocks.append(np.asarray(Q[:, a:a + step], dtype=np.float64) - ref[:, None])
        X = np.concatenate(blocks, axis=1)
        if not all_finite(X):
            raise DimensionError('snapshots contain NaN or Inf; clean them before POD.')
        W = snapshot_range([X], RANGE_TOL)
        if W is None:
            V, s, _ = np.linalg.svd(X, full_matrices=False)
            return V, s
        # the SVD of the coordinates on a basis of the range (snapshot_range): the same
        # singular values and vectors, to ~RANGE_TOL, without an SVD of the n rows
        Vw, s, _ = np.linalg.svd(W.T @ X, full_matrices=False)
        return W @ Vw, s

    def fit_svd(self, V: ArrayLike, s: ArrayLike, q_ref: ArrayLike) -> POD:
        """The basis from a thin SVD of the centred snapshots, already computed.

        :meth:`fit` ends here; a caller that needs several truncations of the same snapshots
        (:class:`~soft_rom.reduce.InMemoryPOD` with ``share_svd``) computes the SVD once.

        Parameters
        ----------
        V : ndarray, shape (n, k)
            Left singular vectors, in the order of ``s``.
        s : ndarray, shape (k,)
            Singular values, descending.
        q_ref : ndarray, shape (n,)

        Returns
        -------
        self : POD
        """
        V = np.asarray(V, dtype=np.float64)
        s = np.asarray(s, dtype=np.float64).reshape(-1)
        ref = np.asarray(q_ref, dtype=np.float64).reshape(-1)
        r = select_rank(s, r=self.r, energy=self.energy)
        V = V[:, :r]
        idx = np.argmax(np.abs(V), axis=0)
        signs = np.sign(V[idx, np.arange(r)])
        signs[signs == 0] = 1.0
        self.basis_ = V * signs
        self.singular_values_ = s
        self.energy_ = np.cumsum(s ** 2) / np.sum(s ** 2)
        self.q_ref_ = ref.copy()
        self.r_ = r
        return self

    def _check(self) -> None:
        if not hasattr(self, 'basis_'):
            raise NotFittedError('this POD is not fitted yet: call fit(snapshots, q_ref) first.')

    def project(self, Q: Any) -> Array:
        """Reduced coordinates ``Vᵀ (Q - q_ref)``; ``Q`` (n, k) may be lazy. Returns (r, k)."""
        self._check()
        return project(Q, self.basis_, self.q_ref_, block_columns=self.block_columns)

    def reconstruct(self, Qhat: ArrayLike) -> Array:
        """Full states ``q_ref + V Qhat`` from reduced coordinates (r, k); returns (n, k)."""
        self._check()
        return reconstruct(Qhat, self.basis_, self.q_ref_)
