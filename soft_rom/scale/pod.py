"""POD of snapshot sets larger than memory, streamed from disk in a few passes.

Two methods, both centring on ``q_ref`` on the fly and both returning, besides the basis,
the *coordinates* of every snapshot in the leading ``l`` modes (so that the projection
:math:`\\hat{Q} = V_r^T (Q - q_{ref})` costs no extra read):

``'randomized'`` (default; Halko, Martinsson, Tropp 2011, alg. 4.4 + 5.1)
    A randomized range finder over *column blocks* (the training set's storage layout):
    pass 1 forms :math:`Y = X \\Omega` with a Gaussian :math:`\\Omega \\in
    \\mathbb{R}^{K \\times (l + o)}`; each of ``power_iters`` passes replaces ``Y`` by
    :math:`X X^T \\mathrm{orth}(Y)`; the last pass computes :math:`B = Q_b^T X` and an SVD of
    the small ``B`` gives modes :math:`W = Q_b U_B` and coordinates
    :math:`Z = \\Sigma_B V_B^T = W^T X`. Cost: ``2 + power_iters`` reads of the data and
    :math:`O(n K l)` flops; memory :math:`O(n l)` plus two blocks.
``'gram'`` (method of snapshots; Sirovich 1987)
    The Gram matrix :math:`G = X^T X = \\sum_{\\text{row blocks}} X_b^T X_b` in one pass
    over *row blocks*, its eigendecomposition gives the exact singular values and right
    singular vectors, the coordinates :math:`Z = \\Sigma V^T` need no read, and the modes
    :math:`X V \\Sigma^{-1}` one more pass (optional). Exact to rounding (the squaring
    costs accuracy only in modes with :math:`\\sigma_i / \\sigma_1 \\lesssim 10^{-7}`), but
    :math:`O(n K^2)` flops and :math:`K^2` memory: for 12,000 snapshots 1.2 GB and ~3 min
    of BLAS-3 on 2 cores; it needs storage chunked in rows (memmap or zarr chunks with
    fewer than ``n`` rows), and a row block spans whole chunks: with the training set's
    ``(32768, 32)`` chunks that is ``32768 x K`` values (3.1 GB at K = 12,000).

Choice: for moderate ``K`` the Gram method is cheaper and exact; for many snapshots its
``K^2`` memory and ``n K^2`` flops are out of reach while the randomized passes stay
I/O-bound, so ``'randomized'`` is this class's default and the streaming reducer
(:class:`soft_rom.reduce.StreamingReducer`) takes ``'gram'`` while it fits in memory. The
measurements are in ``docs/methods.md`` (POD).

Reference: Sharma et al., *Data-driven Model Reduction for Soft Robots via Lagrangian
Operator Inference*, section 2.2 (POD of the centred snapshots; ``r`` for 95 % energy).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg as sla

from soft_rom.data import all_finite
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.scale import kernels
from soft_rom.scale.blocks import (
    column_plan,
    DEFAULT_BLOCK_BYTES,
    Executor,
    LocalExecutor,
    row_plan,
    SnapshotSet,
)

__all__ = ['StreamingPOD', 'as_snapshot_set']

Array = NDArray[np.float64]

_METHODS = ('randomized', 'gram')


def as_snapshot_set(snapshots: Any, q_ref: ArrayLike | None = None) -> SnapshotSet:
    """Wrap one array, a sequence of arrays or of Episodes, or a SnapshotSet.

    Parameters
    ----------
    snapshots : SnapshotSet, array-like (n, k), or sequence of arrays / Episodes
        Episodes must have full states ``Q`` (possibly lazy).
    q_ref : array_like, shape (n,), optional
        Reference configuration (ignored when ``snapshots`` is already a SnapshotSet).
    """
    if isinstance(snapshots, SnapshotSet):
        return snapshots
    if hasattr(snapshots, 'shape'):
        return SnapshotSet([snapshots], q_ref)
    arrays, names = [], []
    for i, s in enumerate(snapshots):
        if hasattr(s, 'Q') and hasattr(s, 'U'):  # an Episode
            if s.Q is None:
                raise DimensionError(
                    f'episode {s.name or i!r} has no full states Q; POD needs snapshots '
                    '(ERA/OKID alone can be fitted from inputs and outputs).')
            arrays.append(s.Q)
            names.append(s.name or f'ep{i + 1}')
        else:
            arrays.append(s)
            names.append(f'ep{i + 1}')
    return SnapshotSet(arrays, q_ref, names)


def _fix_signs(W: Array, Z: Array) -> tuple[Array, Array]:
    """Make the largest-magnitude entry of every mode positive (as :class:`soft_rom.basis.POD`)."""
    idx = np.argmax(np.abs(W), axis=0)
    signs = np.sign(W[idx, np.arange(W.shape[1])])
    signs[signs == 0] = 1.0
    return W * signs, Z * signs[:, None]


class StreamingPOD:
    """Out-of-core POD basis builder (implements :class:`soft_rom.basis.BasisBuilder`).

    .. math:: X = Q - q_{ref} 1^T \\approx W_l \\Sigma_l V_l^T, \\qquad
        V_r = W_l[:, :r], \\qquad \\hat{Q} = V_r^T X = \\Sigma_r V_r^T

    Parameters
    ----------
    r : int, optional
        Number of modes in :attr:`basis_`; if ``None`` chosen by ``energy``.
    energy : float
        Fraction of :math:`\\|X\\|_F^2` to capture when ``r`` is ``None`` (default 0.95).
        The total energy is measured exactly in the first pass.
    method : {'randomized', 'gram'}
        See the module docstring.
    n_coords : int, optional
        Number ``l`` of leading modes whose coordinates are kept (:attr:`coords_`); used by
        DMDc, which needs more than ``r`` directions. Default ``max(r + 20, 2 r)``, or
        100 when ``r`` is ``None``.
    oversample : int
        Extra sketch columns for ``'randomized'`` (default 10).
    power_iters : int
        Power iterations for ``'randomized'`` (default 1; each is one more read).
    compute_basis : bool
        For ``'gram'``: form the modes (one more pass). If ``False``, :attr:`basis_` is
        not set and only the coordinates are available.
    block_cols, block_rows : int, optional
        Block sizes; default :data:`~soft_rom.scale.blocks.DEFAULT_BLOCK_BYTES` per block,
        rounded to whole storage chunks.
    seed : int
        Seed of the Gaussian test matrix (results are reproducible).
    memory_limit : int, optional
        Bytes that ``'gram'`` may hold (Gram matrix, row blocks); it refuses to start
        beyond (default 4 GiB; ``None``: no limit).
    executor : Executor, optional
        Where passes run: default :class:`~soft_rom.scale.blocks.LocalExecutor`; a
        :class:`~soft_rom.scale.dask_backend.DaskExecutor` runs them on a cluster.
    progress : callable, optional
        ``progress(n_done)`` after each block (e.g. ``tqdm.update``) for the local executor.

    Attributes
    ----------
    basis_ : ndarray, shape (n, r)
        Orthonormal modes, sign fixed so the largest-magnitude entry is positive.
    singular_values_ : ndarray, shape (l,)
        Leading singular values of ``X`` (descending).
    energy_ : ndarray, shape (l,)
        Cumulative energy fraction :math:`\\sum_{i\\le j}\\sigma_i^2 / \\|X\\|_F^2`.
    total_energy_ : float
        :math:`\\|X\\|_F^2`.
    r_ : int
    q_ref_ : ndarray, shape (n,)
    coords_ : list of ndarray, each shape (l, k_i)
        Coordinates :math:`W_l^T (Q_i - q_{ref})` of every episode's snapshots.
    reduced_ : list of ndarray, each shape (r, k_i)
        :math:`\\hat{Q}_i = V_r^T (Q_i - q_{ref})` (the first ``r`` rows of ``coords_``).
    modes_ : ndarray, shape (n, l)
        All ``l`` modes (when computed).
    n_passes_ : int
        Number of reads of the whole data set this fit made.
    """

    def __init__(self, r: int | None = None, energy: float = 0.95, *,
                 method: str = 'randomized', n_coords: int | None = None,
                 oversample: int = 10, power_iters: int = 1, compute_basis: bool = True,
                 block_cols: int | None = None, block_rows: int | None = None,
                 block_bytes: int = DEFAULT_BLOCK_BYTES, seed: int = 0,
                 memory_limit: int | None = 4 * 2 ** 30,
                 executor: Executor | None = None,
                 progress: Callable[[int], Any] | None = None) -> None:
        self.r = r
        self.energy = energy
        self.method = method
        self.n_coords = n_coords
        self.oversample = oversample
        self.power_iters = power_iters
        self.compute_basis = compute_basis
        self.block_cols = block_cols
        self.block_rows = block_rows
        self.block_bytes = block_bytes
        self.seed = seed
        self.memory_limit = memory_limit
        self.executor = executor
        self.progress = progress

    # -- helpers ------------------------------------------------------------------------
    def _l(self, n: int, K: int) -> int:
        if self.n_coords is not None:
            l = int(self.n_coords)
        elif self.r is not None:
            l = max(int(self.r) + 20, 2 * int(self.r))
        else:
            l = 100
        if self.r is not None and l < int(self.r):
            raise ConfigError(f'n_coords ({l}) must be at least r ({self.r}).')
        return max(1, min(l, n, K))

    def _select(self, s: Array, total: float) -> int:
        if total <= 0 or s.size == 0 or s[0] <= 0:
            raise DimensionError('the centred snapshots are all zero: the body never moved '
                                 'away from q_ref, so there is nothing to reduce.')
        if self.r is not None:
            r = int(self.r)
            if not 1 <= r <= s.size:
                raise ConfigError(f'r must be between 1 and {s.size} (modes computed); got {r}.')
            return r
        if not 0.0 < self.energy <= 1.0:
            raise ConfigError(f'energy must be in (0, 1]; got {self.energy!r}.')
        cum = np.cumsum(s ** 2) / total
        if cum[-1] < self.energy - 1e-12:
            raise ConfigError(
                f'the {s.size} leading modes computed capture {cum[-1]:.4f} of the energy, '
                f'less than the {self.energy} asked for; raise n_coords or give r.')
        return int(np.searchsorted(cum, self.energy - 1e-12) + 1)

    # -- fitting ------------------------------------------------------------------------
    def fit(self, snapshots: Any, q_ref: ArrayLike | None = None) -> StreamingPOD:
        """Compute the basis and the reduced coordinates by streaming the snapshots.

        Parameters
        ----------
        snapshots : SnapshotSet, array (n, k), or sequence of arrays / Episodes
            Absolute snapshots; lazy arrays (zarr, memmap) are read in blocks.
        q_ref : array_like, shape (n,), optional
            Reference configuration (default zeros, or that of a SnapshotSet).

        Returns
        -------
        self : StreamingPOD
        """
        if self.method not in _METHODS:
            raise ConfigError(f'method must be one of {_METHODS}; got {self.method!r}.')
        snaps = as_snapshot_set(snapshots, q_ref)
        ex = self.executor if self.executor is not None else LocalExecutor(self.progress)
        n, K = snaps.n, snaps.n_total
        l = self._l(n, K)
        W: Array | None
        if self.method == 'randomized':
            W, s, Z, total, passes = self._randomized(snaps, ex, l)
        else:
            W, s, Z, total, passes = self._gram(snaps, ex, l)
        if not np.isfinite(total) or not all_finite(s):
            raise DimensionError('snapshots contain NaN or Inf; clean them before POD.')
        r = self._select(s, total)
        if W is not None:
            W, Z = _fix_signs(W, Z)
            self.modes_ = W
            self.basis_ = W[:, :r]
        self.singular_values_ = s
        self.total_energy_ = float(total)
        self.energy_ = np.cumsum(s ** 2) / total
        self.q_ref_ = snaps.q_ref.copy()
        self.r_ = r
        self.n_passes_ = passes
        self.episode_names_ = list(snaps.names)
        cuts = np.cumsum(snaps.lengths)[:-1]
        self.coords_ = [np.ascontiguousarray(z) for z in np.split(Z, cuts, axis=1)]
        self.reduced_ = [np.ascontiguousarray(z[:r]) for z in self.coords_]
        return self

    def _randomized(self, snaps: SnapshotSet, ex: Executor,
                    l: int) -> tuple[Array, Array, Array, float, int]:
        n, K = snaps.n, snaps.n_total
        width = min(l + max(int(self.oversample), 0), n, K)
        plan = column_plan(snaps, block_cols=self.block_cols, block_bytes=self.block_bytes)
        omega = np.random.default_rng(self.seed).standard_normal((K, width))
        per = [(omega[b.offset:b.offset + b.n_cols],) for b in plan]
        Y, total = ex.sum(snaps, plan, kernels.sketch, per)
        Qb = np.linalg.qr(Y)[0]
        del Y
        for _ in range(max(int(self.power_iters), 0)):
            Qb = np.linalg.qr(ex.sum(snaps, plan, kernels.power, None, (Qb,)))[0]
        B = np.concatenate(ex.collect(snaps, plan, kernels.project, None, (Qb,)), axis=1)
        Ub, s, Vt = np.linalg.svd(B, full_matrices=False)
        W = Qb @ Ub[:, :l]
        Z = s[:l, None] * Vt[:l]
        return W, s[:l], Z, float(total), 2 + max(int(self.power_iters), 0)

    def _gram(self, snaps: SnapshotSet, ex: Executor,
              l: int) -> tuple[Array | None, Array, Array, float, int]:
        chunks = snaps.storage_chunks()
        if chunks is not None and chunks[0] >= snaps.n and snaps.n * snaps.n_total * 8 > (
                4 * self.block_bytes):
            raise ConfigError(
                'the Gram POD reads row blocks, but these snapshots are stored in chunks of '
                f'full height {chunks}: every chunk would be read once per row block. Use the '
                'randomized POD (reads column blocks) or store Q in row-split chunks.')
        K = snaps.n_total
        plan = row_plan(snaps, block_rows=self.block_rows, block_bytes=self.block_bytes)
        rows = max(b.rows[1] - b.rows[0] for b in plan)
        need = 8 * (2 * rows * K + 2 * K * K)  # two row blocks (read-ahead), G and a term
        if self.memory_limit is not None and need > self.memory_limit:
            raise ConfigError(
                f'the Gram POD would hold about {need / 2 ** 30:.1f} GiB ({K} snapshots, row '
                f'blocks of {rows} rows), over its memory limit of '
                f'{self.memory_limit / 2 ** 30:.1f} GiB; use the randomized POD (memory O(n l)) '
                'or raise the limit.')
        G = ex.sum(snaps, plan, kernels.gram_rows)
        total = float(np.trace(G))
        lam, V = sla.eigh(G, subset_by_index=[K - l, K - 1])
        lam, V = lam[::-1], V[:, ::-1]
        s = np.sqrt(np.clip(lam, 0.0, None))
        keep = s > s[0] * K * np.finfo(float).eps if s[0] > 0 else np.zeros(s.size, bool)
        keep[0] = True
        s, V = s[keep], V[:, keep]
        Z = s[:, None] * V.T
        if not self.compute_basis:
            return None, s, Z, total, 1
        W = np.concatenate(ex.collect(snaps, plan, kernels.modes_rows, None, (V / s,)), axis=0)
        return W, s, Z, total, 2

    # -- use ----------------------------------------------------------------------------
    def _check(self) -> None:
        if not hasattr(self, 'basis_'):
            raise NotFittedError('this StreamingPOD has no basis: call fit(snapshots, q_ref) '
                                 'first (with compute_basis=True for method="gram").')

    def project(self, Q: Any, *, executor: Executor | None = None) -> Array:
        """Reduced coordinates ``V_rᵀ (Q - q_ref)`` of new snapshots, streamed; returns (r, k)."""
        self._check()
        snaps = as_snapshot_set(Q, self.q_ref_)
        if snaps.n != self.basis_.shape[0]:
            raise DimensionError(f'Q has {snaps.n} states; the basis has {self.basis_.shape[0]}.')
        ex = executor if executor is not None else (self.executor or LocalExecutor())
        plan = column_plan(snaps, block_cols=self.block_cols, block_bytes=self.block_bytes)
        return np.concatenate(ex.collect(snaps, plan, kernels.project, None, (self.basis_,)),
                              axis=1)

    def reconstruct(self, Qhat: ArrayLike) -> Array:
        """Full states ``q_ref + V_r Qhat`` from reduced coordinates (r, k); returns (n, k)."""
        from soft_rom.basis import reconstruct
        self._check()
        return reconstruct(Qhat, self.basis_, self.q_ref_)

