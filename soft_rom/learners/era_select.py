"""Well-posed OKID and data-driven ERA/OKID settings.

**Why regularize OKID.** The observer regression ``Y = Θ Φ`` (:func:`soft_rom.learners.era.
okid_markov`) has ``m + l (m + p)`` unknowns per output and a data matrix whose rows are
lagged copies of smooth, densely sampled signals: its singular values fall over many decades,
and on nearly noise-free data the least-squares residual stays small while the coefficients
along the weak directions are whatever rounding makes them (on the eel: Markov parameters
changing by 59 % between 1 and 2 BLAS threads and by 900 % under a 1e-9 perturbation of the
outputs, with the same 1.6e-6 residual). Those directions are not determined by the data.

**The formulation.** Ridge (Tikhonov) least squares on the scaled data,

.. math:: \\Theta = \\arg\\min \\|Y - \\Theta\\Phi\\|_F^2 + \\lambda \\|\\Theta\\|_F^2, \\qquad
    \\lambda = \\rho\\, \\sigma_1(\\Phi)^2,

solved from one SVD of ``Φ`` (``Θ = Y V diag(s/(s²+λ)) Uᵀ``). Its conditioning is
``(σ_1² + λ)/λ ≤ 1/ρ + 1``, so results are reproducible (thread counts, rounding, tiny
perturbations) when ``ρ`` is not tiny; the directions it damps are those with
``σ_i < √ρ σ_1``, i.e. where an output error of relative size ``√ρ`` (a noise level) would
already dominate the coefficient. ``ρ`` is therefore tied to the noise level of the data: it
is never below ``RIDGE_FLOOR`` (``1e-5 ≈ (3e-3)²``: a relative output precision of 0.3 %,
about as good as measured soft-robot poses get; on the eel it keeps the Markov parameters
within 1e-8 under a 1e-9 output perturbation, where ``1e-6`` gives 1.5e-8) and is chosen
from ``RIDGE_GRID`` by the criterion below.

**The criterion.** Every candidate ``(l, ρ)`` is fitted on the head of the training episode
(``1 - holdout``, default 80 %); its ERA model (a randomized truncated SVD of the Hankel
matrix, for speed) is simulated from rest over the whole episode for every even order up to
``r_max``, unstable realizations rejected, and scored by the relative output error on the
held-out tail: the quantity the ROM is used for (prediction on new times). The best
``(l, ρ, r)`` is refitted on the whole episode with the exact ERA. The Markov horizon is
``n_markov = min(K // 3, MAX_MARKOV)``: long enough for the slow modes of a soft body at
1 kHz, with two thirds of the samples left as OKID equations.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError

__all__ = ['MAX_MARKOV', 'OBSERVER_GRID', 'RIDGE_FLOOR', 'RIDGE_GRID', 'default_n_markov',
           'fir_response', 'okid_regression', 'ridge_markov', 'select_okid']

Array = NDArray[np.float64]

#: Smallest relative ridge weight (a relative output precision of about 3e-3).
RIDGE_FLOOR = 1e-5
#: Candidate relative ridge weights ``ρ``.
RIDGE_GRID = (1e-5, 1e-4, 1e-3)
#: Candidate observer orders (those that fit the data are tried).
OBSERVER_GRID = (8, 16, 32, 64)
#: Cap of the automatic Markov horizon.
MAX_MARKOV = 500


def default_n_markov(K: int) -> int:
    """Automatic Markov horizon: a third of the samples, at most :data:`MAX_MARKOV`."""
    return int(max(min(K // 3, MAX_MARKOV), 3))


def okid_regression(U: Array, Y: Array, lo: int) -> tuple[Array, Array]:
    """The OKID data matrix ``Φ`` (n_unknowns, K - l) and target ``Y[:, l:]``."""
    m, K = U.shape
    p = Y.shape[0]
    n_unknowns = m + lo * (m + p)
    rows = K - lo
    V = np.concatenate([U, Y], axis=0)
    Phi = np.empty((n_unknowns, rows))
    Phi[:m] = U[:, lo:]
    for i in range(1, lo + 1):
        a = m + (i - 1) * (m + p)
        Phi[a:a + m + p] = V[:, lo - i:K - i]
    return Phi, Y[:, lo:]


def markov_from_observer(theta: Array, m: int, p: int, lo: int, nm: int) -> Array:
    """System Markov parameters ``(nm + 1, p, m)`` from the observer coefficients."""
    D = theta[:, :m]
    Y1 = [theta[:, m + (i - 1) * (m + p): m + (i - 1) * (m + p) + m] for i in range(1, lo + 1)]
    Y2 = [theta[:, m + (i - 1) * (m + p) + m: m + i * (m + p)] for i in range(1, lo + 1)]
    markov = np.zeros((nm + 1, p, m))
    markov[0] = D
    for k in range(1, nm + 1):
        acc = Y1[k - 1].copy() if k <= lo else np.zeros((p, m))
        for i in range(1, min(k, lo) + 1):
            acc += Y2[i - 1] @ markov[k - i]
        markov[k] = acc
    return markov


def ridge_markov(U: Array, Y: Array, lo: int, nm: int, rhos: tuple[float, ...]
                 ) -> list[tuple[Array, dict[str, Any]]]:
    """Ridge OKID for several ``ρ`` from one SVD; ``[(markov, info), ...]``."""
    m, p = U.shape[0], Y.shape[0]
    Phi, T = okid_regression(U, Y, lo)
    Uo, s, Vt = np.linalg.svd(Phi, full_matrices=False)
    TV = T @ Vt.T                                   # (p, n_unknowns)
    den = float(np.linalg.norm(T))
    out = []
    for rho in rhos:
        if not (np.isfinite(rho) and rho > 0):
            raise ConfigError(f'OKID ridge weight must be > 0; got {rho!r}.')
        lam = float(rho) * float(s[0]) ** 2
        theta = (TV * (s / (s ** 2 + lam))[None, :]) @ Uo.T
        resid = float(np.linalg.norm(T - theta @ Phi))
        markov = markov_from_observer(theta, m, p, lo, nm)
        out.append((markov, {'residual': resid / den if den > 0 else 0.0,
                             'ridge': float(rho), 'n_unknowns': int(Phi.shape[0]),
                             'effective_rank': int(np.sum(s ** 2 > lam)),
                             'condition': float((s[0] ** 2 + lam) / (s[-1] ** 2 + lam))}))
    return out


def fir_response(markov: Array, U: Array) -> Array:
    """``ŷ_k = Σ_{i=0}^{N} Y_i u_{k-i}`` (response from rest), shape (p, K)."""
    N = markov.shape[0] - 1
    p, m = markov.shape[1:]
    K = U.shape[1]
    Yh = np.zeros((p, K))
    for i in range(min(N, K - 1) + 1):
        Yh[:, i:] += markov[i] @ U[:, :K - i]
    return Yh


def _rel(a: Array, b: Array) -> float:
    return float(np.linalg.norm(a - b) / max(float(np.linalg.norm(b)), 1e-300))


def era_truncated(markov: Array, rmax: int, *, seed: int = 0
                  ) -> tuple[Array, Array, Array, Array, Array]:
    """ERA of order ``rmax`` from a randomized truncated SVD of ``H_0`` (for the search only).

    Range finder with ``rmax + 20`` columns and two power iterations (fixed seed, so
    deterministic); the leading ``r ≤ rmax`` states are the order-``r`` realization.
    """
    from soft_rom.learners.era import _hankel
    N = markov.shape[0] - 1
    p, m = markov.shape[1:]
    a = min(max(int(round(N * m / (m + p))), 1), N - 1)
    b = N - a
    H0 = _hankel(markov, 1, a, b)
    H1 = _hankel(markov, 2, a, b)
    k = min(rmax + 20, min(H0.shape))
    rng = np.random.default_rng(seed)
    Qm = np.linalg.qr(H0 @ rng.standard_normal((H0.shape[1], k)))[0]
    for _ in range(2):
        Qm = np.linalg.qr(H0 @ (H0.T @ Qm))[0]
    Ub, sv, Vt = np.linalg.svd(Qm.T @ H0, full_matrices=False)
    P = Qm @ Ub
    r = int(min(rmax, int(np.sum(sv > 1e-12 * sv[0]))))
    sq = np.sqrt(sv[:r])
    A = (P[:, :r].T @ H1 @ Vt[:r].T) / np.outer(sq, sq)
    B = sq[:, None] * Vt[:r, :m]
    C = P[:p, :r] * sq[None, :]
    return A, B, C, markov[0].copy(), sv


def select_okid(Us: Array, Ys: Array, *, holdout: float = 0.2,
                observer_orders: tuple[int, ...] | None = None,
                rhos: tuple[float, ...] = RIDGE_GRID, n_markov: int | None = None,
                r_max: int = 40, r_values: tuple[int, ...] | None = None) -> dict[str, Any]:
    """Choose ``(l, ρ, r)`` by the held-out tail error of the ERA/OKID model.

    Parameters
    ----------
    Us : ndarray, shape (m, K)
        Scaled inputs.
    Ys : ndarray, shape (p, K)
        Scaled output deviations (or their principal components).
    holdout : float
        Fraction of the episode held out at its end.
    observer_orders : tuple of int, optional
        Candidates (default :data:`OBSERVER_GRID` and the largest order with two equations
        per unknown on the head, each if it fits): at high sample rates the observer must
        span many samples to see slow modes.
    rhos : tuple of float
        Candidate ridge weights (each at least :data:`RIDGE_FLOOR`).
    n_markov : int, optional
        Markov horizon (default :func:`default_n_markov` of the head).
    r_max : int
        Largest order tried (when ``r_values`` is not given: even orders 2 ... ``r_max``).
    r_values : tuple of int, optional
        Orders tried.

    Returns
    -------
    dict
        ``observer_order``, ``ridge``, ``r``, ``tail_error``, ``table`` (best ``r`` of every
        candidate), ``cut`` (samples in the head), ``n_markov``.
    """
    if not 0.0 < holdout < 0.9:
        raise ConfigError(f'holdout must be in (0, 0.9); got {holdout!r}.')
    m, K = Us.shape
    p = Ys.shape[0]
    cut = int(round(K * (1.0 - holdout)))
    l_max = (cut // 2 - m) // (m + p)
    if l_max < 1 or K - cut < 2:
        raise ConfigError(f'{K} samples are too few to select OKID settings on a held-out '
                          f'tail (m={m}, p={p}); give observer_order and a ridge weight.')
    cands = sorted({lo for lo in (observer_orders or OBSERVER_GRID + (l_max,))
                    if 1 <= lo <= l_max})
    if not cands:
        cands = [l_max]
    nm = default_n_markov(cut) if n_markov is None else int(n_markov)
    rhos = tuple(max(float(x), RIDGE_FLOOR) for x in rhos)
    table: list[dict[str, Any]] = []
    for lo in cands:
        for markov, info in ridge_markov(Us[:, :cut], Ys[:, :cut], lo, nm, rhos):
            row: dict[str, Any] = {'observer_order': lo, 'ridge': info['ridge'], 'r': None,
                                   'tail_error': float('inf'),
                                   'effective_rank': info['effective_rank']}
            try:
                rr = max(r_values) if r_values else r_max
                A, B, C, D, _ = era_truncated(markov, rr)
                cand_r = [r for r in (r_values or tuple(range(2, rr + 1, 2)))
                          if r <= A.shape[0]]
                r, rows = select_order(A, B, C, D, Us, Ys, cut, cand_r)
                row['r'] = r
                row['tail_error'] = min(x['tail_error'] for x in rows)
            except (ConfigError, np.linalg.LinAlgError):
                pass
            table.append(row)
    ok = [row for row in table if np.isfinite(row['tail_error'])]
    if not ok:
        raise ConfigError('no OKID setting gave a stable ERA realization on these data; give '
                          'observer_order, okid_ridge and r by hand.')
    best = min(ok, key=lambda row: row['tail_error'])
    return {'observer_order': int(best['observer_order']), 'ridge': float(best['ridge']),
            'r': int(best['r']), 'tail_error': float(best['tail_error']), 'table': table,
            'cut': cut, 'n_markov': nm}


def select_order(A_full: Array, B_full: Array, C_full: Array, D: Array, Us: Array, Ys: Array,
                 cut: int, r_candidates: list[int]) -> tuple[int, list[dict[str, float]]]:
    """The ``r`` whose ERA model simulates the tail best (unstable ones rejected).

    ``A_full, B_full, C_full`` are the balanced realization of the largest candidate order;
    the leading ``r`` states of a balanced ERA realization are the order-``r`` realization.
    """
    rows = []
    for r in r_candidates:
        A, B, C = A_full[:r, :r], B_full[:r], C_full[:, :r]
        rho = float(np.max(np.abs(np.linalg.eigvals(A))))
        if not rho < 1.0:
            rows.append({'r': r, 'tail_error': float('inf'), 'spectral_radius': rho})
            continue
        x = np.zeros(r)
        K = Us.shape[1]
        Yh = np.empty((C.shape[0], K))
        BU = B @ Us
        for k in range(K):
            Yh[:, k] = C @ x
            x = A @ x + BU[:, k]
        Yh += D @ Us
        rows.append({'r': r, 'tail_error': _rel(Yh[:, cut:], Ys[:, cut:]),
                     'spectral_radius': rho})
    ok = [row for row in rows if np.isfinite(row['tail_error'])]
    if not ok:
        raise ConfigError('every ERA order gave an unstable realization on these data.')
    return int(min(ok, key=lambda row: row['tail_error'])['r']), rows


#: Decimation factors tried by ``ERAOKID(decimation='auto')``.
DECIMATION_GRID = (1, 5)


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
