"""ERA: realizations of the Markov parameters, and what makes them usable (paper section 2.4).

The eigensystem realization algorithm (Juang & Pappa, *An eigensystem realization algorithm for
modal parameter identification and model reduction*, J. Guid. Control Dyn. 8(5), 1985):
block Hankel matrices :math:`H_0 = [Y_{i+j+1}]`, :math:`H_1 = [Y_{i+j+2}]`, SVD
:math:`H_0 = P S Q^\\top`, and

.. math:: A = S_r^{-1/2} P_r^\\top H_1 Q_r S_r^{-1/2}, \\quad
    B = S_r^{1/2} Q_r^\\top E_m, \\quad C = E_p^\\top P_r S_r^{1/2}, \\quad D = Y_0.

Besides :func:`era` (exact SVD) and :func:`era_truncated` (randomized, for the search):
stabilization (:func:`stabilize`), the output-map refit (:func:`fit_output_map`), the fast
modal simulation used to score many orders at once, and the resampling of a model identified
at a decimated step to the data step (:func:`to_data_rate`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ConfigError, DimensionError
from soft_rom.resources import check_memory

__all__ = ['POWER_ITERATIONS', 'check_hankel_memory', 'era', 'era_from_factors', 'era_truncated',
           'first_order_responses', 'fit_output_map', 'hankel', 'hankel_rank', 'modal_inputs',
           'real_modal_states', 'simulate_states', 'stabilize', 'stabilize_refit',
           'to_data_rate']

Array = NDArray[np.float64]

#: Power iterations of the randomized truncated SVD in the search (:func:`era_truncated`).
POWER_ITERATIONS = 2


def check_hankel_memory(rows: int, cols: int, copies: float = 4.0) -> None:
    """Refuse Hankel matrices of ``rows`` x ``cols`` that would not fit in memory.

    ``copies``: matrices of that size alive at once (``H_0``, ``H_1`` and the SVD's factors
    and workspace). Raises :class:`~soft_rom.errors.ResourceError` before they are built.
    """
    check_memory(8.0 * copies * rows * cols, f'ERA on a {rows} x {cols} Hankel matrix',
                 'Use a shorter Markov horizon (n_markov), decimation, or fewer outputs '
                 '(output_rank).')


def hankel(markov: Array, start: int, rows: int, cols: int) -> Array:
    """Block Hankel matrix ``[Y_{start+i+j}]`` (rows · p, cols · m), from a strided view."""
    _, p, m = markov.shape
    mk = np.ascontiguousarray(markov[start:start + rows + cols - 1])
    s0, s1, s2 = mk.strides
    view = np.lib.stride_tricks.as_strided(mk, shape=(rows, p, cols, m),
                                           strides=(s0, s1, s0, s2), writeable=False)
    return np.ascontiguousarray(view.reshape(rows * p, cols * m))


def hankel_rank(hsv: ArrayLike, *, tol: float = 1e-3) -> int:
    """Default order rule: number of Hankel singular values above ``tol · σ_1``.

    Parameters
    ----------
    hsv : ndarray, shape (s,)
        Hankel singular values, descending.
    tol : float
        Relative threshold (on the scaled data, so independent of units).
    """
    s = np.asarray(hsv, dtype=np.float64).reshape(-1)
    if s.size == 0 or s[0] <= 0:
        raise DimensionError('all Hankel singular values are zero: the outputs do not respond '
                             'to the inputs in these data.')
    return max(int(np.sum(s > tol * s[0])), 1)


def era(markov: ArrayLike, r: int | None = None, *, n_block_rows: int | None = None,
        n_block_cols: int | None = None,
        tol: float = 1e-3, _factors: dict[str, Array] | None = None
        ) -> tuple[Array, Array, Array, Array, Array]:
    """Eigensystem realization from Markov parameters (Juang & Pappa 1985).

    Parameters
    ----------
    markov : ndarray, shape (N + 1, p, m)
        ``markov[0] = D``, ``markov[k] = C A^{k-1} B``.
    r : int, optional
        Order; ``None``: :func:`hankel_rank` with ``tol``.
    n_block_rows, n_block_cols : int, optional
        Block rows/columns of the Hankel matrices; need ``rows + cols <= N``. Default: split
        the ``N`` Markov parameters so that ``H_0`` is about square (``rows · p ≈ cols · m``).

    Returns
    -------
    A : ndarray, shape (r, r)
    B : ndarray, shape (r, m)
    C : ndarray, shape (p, r)
    D : ndarray, shape (p, m)
    hsv : ndarray
        All Hankel singular values of ``H_0`` (to choose ``r``).
    """
    markov = np.asarray(markov, dtype=np.float64)
    if markov.ndim != 3 or markov.shape[0] < 3:
        raise DimensionError(
            f'markov must have shape (N + 1, p, m) with N >= 2; got {markov.shape}.')
    N = markov.shape[0] - 1
    p, m = markov.shape[1:]
    if n_block_rows is None and n_block_cols is None:
        # Balance the Hankel matrix: rows·p ≈ cols·m (square H0, the cheapest SVD for the
        # largest attainable rank).
        n_block_rows = min(max(int(round(N * m / (m + p))), 1), N - 1)
        n_block_cols = N - n_block_rows
    elif n_block_rows is None and n_block_cols is not None:
        n_block_rows = N - int(n_block_cols)
    elif n_block_cols is None and n_block_rows is not None:
        n_block_cols = N - int(n_block_rows)
    assert n_block_rows is not None and n_block_cols is not None
    a, b = int(n_block_rows), int(n_block_cols)
    if a < 1 or b < 1 or a + b > N:
        raise ConfigError(f'Hankel blocks ({a} rows, {b} columns) need 1 <= rows, cols and '
                          f'rows + cols <= {N} (the number of Markov parameters).')
    check_hankel_memory(a * p, b * m)
    H0 = hankel(markov, 1, a, b)
    H1 = hankel(markov, 2, a, b)
    P, s, Qt = np.linalg.svd(H0, full_matrices=False)
    r = hankel_rank(s, tol=tol) if r is None else int(r)
    if not 1 <= r <= s.size or s[r - 1] <= 0:
        raise ConfigError(f'r must be between 1 and the numerical rank of the Hankel matrix '
                          f'({int(np.sum(s > 0))} of {s.size} singular values > 0); got {r}.')
    R = min(max(r, _CACHED_ORDERS), int(np.sum(s > 0)))
    factors = {'M': P[:, :R].T @ H1 @ Qt[:R].T, 's': s, 'Qm': Qt[:R, :m].copy(),
               'Pp': P[:p, :R].copy(), 'D': markov[0].copy()}
    if _factors is not None:
        _factors.update(factors)
    A, B, C, D = era_from_factors(factors, r)
    return A, B, C, D, s


#: Orders whose realizations :func:`era` keeps factors for (``ERAOKID.model_for``).
_CACHED_ORDERS = 200


def era_from_factors(f: dict[str, Array], r: int) -> tuple[Array, Array, Array, Array]:
    """Order-``r`` ERA realization from the factors :func:`era` kept (``r <= R``)."""
    sq = np.sqrt(f['s'][:r])
    A = f['M'][:r, :r] / np.outer(sq, sq)
    B = sq[:, None] * f['Qm'][:r]
    C = f['Pp'][:, :r] * sq[None, :]
    return A, B, C, f['D'].copy()


def era_truncated(markov: Array, rmax: int, *, seed: int = 0
                  ) -> tuple[Array, Array, Array, Array, Array]:
    """ERA of order ``rmax`` from a randomized truncated SVD of ``H_0`` (for the search only).

    Range finder with ``rmax + 20`` columns and two power iterations (fixed seed, so
    deterministic); the leading ``r ≤ rmax`` states are the order-``r`` realization.
    """
    N = markov.shape[0] - 1
    p, m = markov.shape[1:]
    a = min(max(int(round(N * m / (m + p))), 1), N - 1)
    b = N - a
    check_hankel_memory(a * p, b * m, copies=2.5)     # H_0, H_1 and the sketches
    H0 = hankel(markov, 1, a, b)
    H1 = hankel(markov, 2, a, b)
    k = min(rmax + 20, min(H0.shape))
    rng = np.random.default_rng(seed)
    Qm = np.linalg.qr(H0 @ rng.standard_normal((H0.shape[1], k)))[0]
    for _ in range(POWER_ITERATIONS):
        Qm = np.linalg.qr(H0 @ (H0.T @ Qm))[0]
    # SVD of the small (k, n) matrix Qᵀ H0 through the QR of its transpose.
    Qt, Rt = np.linalg.qr((Qm.T @ H0).T)
    Ub, sv, Wt = np.linalg.svd(Rt.T)
    Vt = (Qt @ Wt.T).T
    P = Qm @ Ub
    r = int(min(rmax, int(np.sum(sv > 1e-12 * sv[0]))))
    sq = np.sqrt(sv[:r])
    A = (P[:, :r].T @ H1 @ Vt[:r].T) / np.outer(sq, sq)
    B = sq[:, None] * Vt[:r, :m]
    C = P[:p, :r] * sq[None, :]
    return A, B, C, markov[0].copy(), sv


def stabilize(A: Array) -> Array | None:
    """``A`` with every eigenvalue outside the unit circle reflected inside (``λ → λ/|λ|²``).

    A stable ``A`` is returned as it is. Otherwise ``A' = Re(V diag(λ') V⁻¹)`` (conjugate
    pairs stay conjugate, so ``A'`` is real); ``None`` when the eigenvectors are too ill
    conditioned (``cond(V) > 1e8``) for that to be accurate.
    """
    ev, V = np.linalg.eig(A)
    a = np.abs(ev)
    if np.all(a < 1.0):
        return A
    if np.linalg.cond(V) > 1e8:
        return None
    ev2 = np.where(a >= 1.0, ev / np.maximum(a, 1e-300) * np.minimum(1.0 / a, 1.0 - 1e-9), ev)
    As = np.real(V @ np.diag(ev2) @ np.linalg.inv(V))
    if not np.max(np.abs(np.linalg.eigvals(As))) < 1.0:
        return None
    return np.asarray(As, dtype=np.float64)


def simulate_states(A: Array, B: Array, U: Array) -> Array:
    """States ``x_0 .. x_{K-1}`` from rest, shape (r, K)."""
    K = U.shape[1]
    X = np.empty((A.shape[0], K))
    BU = B @ U
    x = np.zeros(A.shape[0])
    for k in range(K):
        X[:, k] = x
        x = A @ x + BU[:, k]
    return X


def fit_output_map(X: Array, U: Array, Y: Array) -> tuple[Array, Array]:
    """Least-squares ``C, D`` of ``Y ≈ C X + D U`` (ridge ``1e-10 σ_1²``, well posed)."""
    Z = np.concatenate([X, U], axis=0)
    G = Z @ Z.T
    lam = 1e-10 * max(float(np.max(np.diag(G))), 1e-300) * Z.shape[0]
    G[np.diag_indices_from(G)] += lam
    CD = np.linalg.solve(G, Z @ Y.T).T
    r = X.shape[0]
    return CD[:, :r], CD[:, r:]


def stabilize_refit(A: Array, B: Array, C: Array, D: Array, Us: Array, Ys: Array
                     ) -> tuple[Array, Array, Array, bool, bool]:
    """Stabilized ``A`` and least-squares ``C, D`` on the data (``refit=True``).

    Returns ``A, C, D, refitted, stabilized`` (the inputs unchanged when the eigenvectors are
    too ill conditioned to move the unstable eigenvalues).
    """
    As = stabilize(A)
    if As is None:
        return A, C, D, False, False
    X = simulate_states(As, B, Us)
    C2, D2 = fit_output_map(X, Us, Ys)
    return As, C2, D2, True, As is not A


def modal_inputs(A: Array, B: Array, U: Array
                 ) -> tuple[NDArray[np.complex128] | None, NDArray[np.complex128] | None, float]:
    """Eigenvalues of the stabilized ``A`` (:func:`stabilize`) and modal inputs ``V⁻¹ B U``.

    ``(None, None, ρ)`` when ``A`` is unstable and its eigenvectors too ill conditioned.
    """
    ev, V = np.linalg.eig(A)
    a = np.abs(ev)
    rho = float(np.max(a))
    if rho >= 1.0:
        if np.linalg.cond(V) > 1e8:
            return None, None, rho
        ev = np.where(a >= 1.0, ev / a * np.minimum(1.0 / a, 1.0 - 1e-9), ev)
    try:
        G = np.linalg.solve(V, B @ U)
    except np.linalg.LinAlgError:
        return None, None, rho
    return np.asarray(ev, dtype=np.complex128), G, rho


def first_order_responses(ev: NDArray[np.complex128], G: NDArray[np.complex128]
                          ) -> NDArray[np.complex128]:
    """``z_0 = 0``, ``z_{k+1} = λ ⊙ z_k + g_k`` for many modes at once, shape (n, K)."""
    n, K = G.shape
    Z = np.empty((n, K), dtype=np.complex128)
    z = np.zeros(n, dtype=np.complex128)
    for k in range(K):
        Z[:, k] = z
        z = ev * z + G[:, k]
    return Z


def real_modal_states(ev: NDArray[np.complex128], Z: NDArray[np.complex128]) -> Array:
    """Real regressors spanning the states of the modes ``ev`` (responses ``Z``).

    A conjugate pair gives the real and imaginary parts of one of its modes (LAPACK lists a
    pair consecutively), a real mode its response.
    """
    r = ev.size
    X = np.empty((r, Z.shape[1]))
    j = 0
    while j < r:
        if ev[j].imag != 0.0 and j + 1 < r:
            X[j], X[j + 1] = Z[j].real, Z[j].imag
            j += 2
        else:
            X[j] = Z[j].real
            j += 1
    return X


def to_data_rate(A: Array, B: Array, d: int) -> tuple[Array, Array] | None:
    """A model identified at ``d`` times the data step, resampled to the data step.

    ``A_h`` is the real principal ``d``-th root of ``A`` and ``B_h = (Σ_{i<d} A_h^i)⁻¹ B``, so
    that ``d`` steps of ``(A_h, B_h)`` with a constant input reproduce one step of
    ``(A, B)`` exactly (the decimated fit averaged the inputs over each block). The outputs
    are then computed on the data grid, without interpolating states. ``None`` when ``A`` has
    no real principal root (an eigenvalue on the closed negative real axis).
    """
    import scipy.linalg as sla
    if d == 1:
        return A, B
    ev = np.linalg.eigvals(A)
    if np.any((np.abs(ev.imag) <= 1e-12 * np.maximum(np.abs(ev), 1e-300)) & (ev.real <= 0)):
        return None
    Ah = sla.fractional_matrix_power(A, 1.0 / d)
    if np.iscomplexobj(Ah):
        if np.max(np.abs(Ah.imag)) > 1e-9 * max(float(np.max(np.abs(Ah.real))), 1e-300):
            return None
        Ah = Ah.real
    S = np.zeros_like(A)
    P = np.eye(A.shape[0])
    for _ in range(d):
        S += P
        P = P @ Ah
    return np.asarray(Ah, dtype=np.float64), np.asarray(np.linalg.solve(S, B))
