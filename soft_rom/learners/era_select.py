"""Well-posed OKID and data-driven ERA/OKID settings.

**Why regularize OKID.** The observer regression ``Y = Θ Φ`` (:func:`soft_rom.learners.era.
okid_markov`) has ``m + l (m + p)`` unknowns per output and a data matrix whose rows are
lagged copies of smooth, densely sampled signals: its singular values fall over many decades,
and on nearly noise-free data the least-squares residual stays small while the coefficients
along the weak directions are whatever rounding makes them (on the eel: Markov parameters
changing by 59 % between 1 and 2 BLAS threads and by 900 % under a 1e-9 perturbation of the
outputs, with the same 1.6e-6 residual). Those directions are not determined by the data.

**Inputs the data never take.** Actuators driven in fixed combinations (the eel's
antagonistic pressure pairs, ``u_2 = -u_1``) excite fewer than ``m`` input directions, so
``Φ`` has exactly zero singular values and the responses to the missing directions are
undetermined whatever the ridge. :func:`compress_inputs` identifies on the excited directions
(rank-revealing, :data:`INPUT_RANK_TOL`) and lifts the model back, so those responses are
zero. On the eel this alone removed the thread dependence of the study's plain least-squares
setting (49 % to exactly 0) and, at ``ρ = 1e-9``, cut the Markov change under a 1e-9
perturbation from 3.6e-4 to 2e-6.

**The formulation.** Ridge (Tikhonov) least squares on the scaled data,

.. math:: \\Theta = \\arg\\min \\|Y - \\Theta\\Phi\\|_F^2 + \\lambda \\|\\Theta\\|_F^2, \\qquad
    \\lambda = \\rho\\, \\sigma_1(\\Phi)^2,

solved from one factorization of ``Φ`` (``Θ = Y V diag(s/(s²+λ)) Uᵀ``, from the
eigendecomposition of ``ΦΦᵀ``). Its conditioning is ``(σ_1² + λ)/λ ≤ 1/ρ + 1``; the
directions it damps are those with ``σ_i < √ρ σ_1``, i.e. where an output error of relative
size ``√ρ`` would already dominate the coefficient. ``ρ`` is chosen from :data:`RIDGE_GRID`
(1e-10 ... 1e-4) by the criterion below, never below :data:`RIDGE_FLOOR`: with the input
null space removed, even ``ρ = 1e-10`` gives results that agree to about 1e-9 between BLAS
thread counts on the eel. The regression is tried without and with an unpenalized intercept
(centered data): with it the coefficients do not depend on a constant output offset (the
first sample of noisy data used as ``y_ref`` carries the noise into every deviation);
without it the mean levels inform the static gains (exact data starting at rest). Output
channels are scaled by their RMS but never by less than ``OUTPUT_SCALE_FLOOR`` of the
largest: a nearly static channel (next to a clamp) would otherwise be blown up to unit size
with its perturbations.

**The criterion: blocked cross-validation.** The training episode is cut into
``n = 1 / holdout`` (default 5) contiguous blocks (:func:`cv_folds`). For every block, every
candidate ``(d, l, ρ, intercept)`` is fitted on the observer equations outside it (and
outside the ``l`` samples after it, whose regressors are the block's outputs); its ERA model
(a randomized truncated SVD of the Hankel matrix) is, for every order of :data:`R_GRID`,
stabilized (eigenvalues outside the unit circle reflected inside, :func:`stabilize`),
simulated from rest over the whole episode, its ``C, D`` refitted by least squares on the
samples outside the block (:func:`fit_output_map`), and its output error on the block
summed; the score is the pooled relative error over the blocks. Every sample is predicted
once by a model that did not see it, and each model is fitted on 80 % of the episode. A
single held-out tail (``criterion='tail'``, the former rule) scores 20 % of the samples, and
on the eel it ranked candidates no better than chance (0.0049 test error for its choice,
against 0.0018 now). The refit makes each realization the output-error fit for its ERA
poles, which is what corrects the bias the ridge puts on the Markov parameters.

**Stable choice.** Errors within ``TIE_TOL`` (3 %) of the best are tied and the tie is
broken by a fixed preference (:func:`choose`: largest ``ρ``, intercept, smallest ``r``,
smallest ``l``, smallest ``d``), so a perturbation of the data that moves the errors by far
less than 3 % cannot change the settings (before: nearly equal errors of neighbouring ``r``
flipped the choice under a 1e-9 perturbation). The chosen ``(d, l, ρ, intercept, r)`` is
refitted on the whole episode with the exact ERA, stabilized and its ``C, D`` refitted. The
Markov horizon is ``n_markov = min(K // 3, MAX_MARKOV)``.

**Sensitivity to output perturbations.** A relative perturbation ``ε`` of absolute
coordinates is ``ε ‖Y‖ / ‖Y - y_ref‖`` of the motion the model identifies (1.2e-7 for
``ε = 1e-9`` on the eel, whose motion is 0.84 % of its coordinates). The Markov parameters
estimated from the data cannot move by less than about that: on the eel they move 1.1-2x it
at ``ρ = 1e-4 … 1e-3`` (models no better than predicting no motion) and 15-20x at the
selected ``ρ = 1e-9``, while the predicted outputs move by far less (the test error is the
same to five digits).

About 700 lines: the search (folds, candidates, orders) and its numerical kernels, which
belong together.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError

__all__ = ['blas_threads', 'choose', 'compress_inputs', 'compress_outputs', 'cv_folds',
           'default_n_markov', 'fir_response', 'first_order_responses', 'fit_output_map',
           'fold_errors', 'INPUT_RANK_TOL', 'INTERCEPTS', 'MAX_MARKOV', 'modal_inputs',
           'OBSERVER_GRID', 'okid_regression', 'OUTPUT_SCALE_FLOOR', 'POWER_ITERATIONS',
           'R_GRID', 'R_MAX', 'real_modal_states', 'RIDGE_FLOOR', 'RIDGE_GRID',
           'ridge_markov', 'score_orders', 'select_okid', 'simulate_states', 'stabilize',
           'stabilize_refit', 'TIE_TOL']

Array = NDArray[np.float64]

#: Smallest relative ridge weight (a relative output precision of about 3e-3).
RIDGE_FLOOR = 1e-10
#: Candidate relative ridge weights ``ρ``.
RIDGE_GRID = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-4)
#: Output channels are scaled by their RMS, but never by less than this fraction of the
#: largest channel RMS (nearly static channels would otherwise amplify their perturbations).
OUTPUT_SCALE_FLOOR = 0.1
#: Orders tried by the selection (up to ``r_max``).
R_GRID = (2, 4, 6, 8, 10, 12, 16, 20, 24, 28, 32, 40, 48, 56)
#: OKID regressions tried without / with an intercept (:func:`ridge_markov`).
INTERCEPTS = (False, True)
#: Candidate observer orders (those that fit the data are tried).
OBSERVER_GRID = (8, 16, 32, 64)
#: Cap of the automatic Markov horizon.
MAX_MARKOV = 500
#: Power iterations of the randomized truncated SVD in the search (:func:`era_truncated`).
POWER_ITERATIONS = 2
#: Largest order tried by the selection.
R_MAX = 40
#: Relative band of held-out errors treated as tied (:func:`choose`).
TIE_TOL = 0.03


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
    """System Markov parameters ``(nm + 1, p, m)`` from the observer coefficients.

    ``Y_k = Ȳ⁽¹⁾_k + [Ȳ⁽²⁾_1 … Ȳ⁽²⁾_j] [Y_{k-1}; …; Y_{k-j}]``, ``j = min(k, l)``: one
    matrix product per ``k``.
    """
    blocks = theta[:, m:].reshape(p, lo, m + p)
    Y1 = blocks[:, :, :m].transpose(1, 0, 2)                   # (lo, p, m)
    Y2 = np.ascontiguousarray(blocks[:, :, m:]).reshape(p, lo * p)   # [Ȳ2_1 … Ȳ2_lo]
    markov = np.zeros((nm + 1, p, m))
    markov[0] = theta[:, :m]
    for k in range(1, nm + 1):
        j = min(k, lo)
        past = markov[k - j:k][::-1].reshape(j * p, m)
        acc = Y2[:, :j * p] @ past
        if k <= lo:
            acc += Y1[k - 1]
        markov[k] = acc
    return markov


def ridge_markov(U: Array, Y: Array, lo: int, nm: int, rhos: tuple[float, ...],
                 intercept: bool = False, rows: NDArray[np.bool_] | None = None
                 ) -> list[tuple[Array, dict[str, Any]]]:
    """Ridge OKID for several ``ρ`` from one factorization; ``[(markov, info), ...]``.

    ``rows``: boolean mask of shape (K,) of the samples ``k`` whose observer equations are
    used (default all ``k >= l``; a cross-validation fold leaves a block out).

    ``intercept``: with an unpenalized constant term (centered regression), so that the
    coefficients do not depend on a constant offset of the outputs (an error in ``y_ref``,
    the first sample of noisy data); without it the mean levels of the data inform the static
    gains (exact data starting at rest).
    """
    m, p = U.shape[0], Y.shape[0]
    Phi, T = okid_regression(U, Y, lo)
    if rows is not None:
        keep = np.asarray(rows, dtype=bool)[lo:]
        Phi, T = Phi[:, keep], T[:, keep]
    if intercept:
        Phi = Phi - Phi.mean(axis=1, keepdims=True)
        T = T - T.mean(axis=1, keepdims=True)
    # Ridge from the eigendecomposition of the Gram matrix ΦΦᵀ = W diag(s²) Wᵀ (the SVD's
    # left factors): its rounding, ε σ_1², is far below every λ = ρ σ_1² used (ρ ≥ 1e-10).
    e, W = np.linalg.eigh(Phi @ Phi.T)
    e, W = np.maximum(e[::-1], 0.0), W[:, ::-1]
    TW = (T @ Phi.T) @ W                              # (p, n_unknowns) = T V diag(s)
    den = float(np.linalg.norm(T))
    out = []
    for rho in rhos:
        if not (np.isfinite(rho) and rho > 0):
            raise ConfigError(f'OKID ridge weight must be > 0; got {rho!r}.')
        lam = float(rho) * float(e[0])
        theta = (TW / (e + lam)[None, :]) @ W.T
        resid = float(np.linalg.norm(T - theta @ Phi))
        markov = markov_from_observer(theta, m, p, lo, nm)
        out.append((markov, {'residual': resid / den if den > 0 else 0.0,
                             'ridge': float(rho), 'intercept': bool(intercept),
                             'n_unknowns': int(Phi.shape[0]),
                             'effective_rank': int(np.sum(e > lam)),
                             'condition': float((e[0] + lam) / (e[-1] + lam))}))
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
    from soft_rom.learners.era import _hankel, check_hankel_memory
    N = markov.shape[0] - 1
    p, m = markov.shape[1:]
    a = min(max(int(round(N * m / (m + p))), 1), N - 1)
    b = N - a
    check_hankel_memory(a * p, b * m, copies=2.5)     # H_0, H_1 and the sketches
    H0 = _hankel(markov, 1, a, b)
    H1 = _hankel(markov, 2, a, b)
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


def choose(rows: list[dict[str, Any]], tie_tol: float = TIE_TOL) -> dict[str, Any]:
    """The selected candidate: the preferred one among those tied with the best.

    Candidates whose held-out error is within ``tie_tol`` (relative) of the best are tied;
    among them the preference is fixed: the largest ridge weight, then the regression with an
    intercept, then the smallest order ``r``, then the smallest observer order, then the
    smallest decimation. A perturbation of
    the data that moves the errors by much less than ``tie_tol`` cannot change the choice
    unless an error sits within that perturbation of the band's edge.
    """
    ok = [row for row in rows if np.isfinite(row['tail_error'])]
    if not ok:
        raise ConfigError('no OKID setting gave a stable ERA realization on these data; give '
                          'observer_order, okid_ridge and r by hand.')
    best = min(row['tail_error'] for row in ok)
    tied = [row for row in ok if row['tail_error'] <= best * (1.0 + tie_tol)]
    return min(tied, key=lambda row: (-row['ridge'], not row.get('intercept', False), row['r'],
                                      row['observer_order'], row.get('decimation', 1)))


def cv_folds(K: int, lo: int, holdout: float, criterion: str = 'blocked'
             ) -> list[tuple[NDArray[np.bool_], NDArray[np.bool_]]]:
    """Validation folds ``[(rows, test), ...]``: boolean masks of shape (K,).

    ``rows``: the samples whose observer equations are fitted; ``test``: the samples scored
    (the output map ``C, D`` is refitted on the others). ``'tail'``: one fold, the last
    ``holdout`` of the episode. ``'blocked'``: ``n = round(1 / holdout)`` contiguous blocks,
    each left out once; the ``l`` equations after a block are dropped as well, since their
    regressors are the block's outputs (hv-block cross-validation).
    """
    if criterion not in ('blocked', 'tail'):
        raise ConfigError(f"criterion must be 'blocked' or 'tail'; got {criterion!r}.")
    idx = np.arange(K)
    if criterion == 'tail':
        cut = int(round(K * (1.0 - holdout)))
        return [(idx < cut, idx >= cut)]
    n = max(int(round(1.0 / holdout)), 2)
    edges = np.round(np.linspace(0, K, n + 1)).astype(int)
    return [(~((idx >= a) & (idx < b + lo)), (idx >= a) & (idx < b))
            for a, b in zip(edges[:-1], edges[1:])]


def select_okid(Us: Array, Ys: Array, *, holdout: float = 0.2,
                observer_orders: tuple[int, ...] | None = None,
                rhos: tuple[float, ...] = RIDGE_GRID, n_markov: int | None = None,
                r_max: int = R_MAX, r_values: tuple[int, ...] | None = None,
                refit: bool = True, tie_tol: float = TIE_TOL,
                intercepts: tuple[bool, ...] | None = None,
                criterion: str = 'blocked') -> dict[str, Any]:
    """Choose ``(l, ρ, r)`` by the held-out error of the ERA/OKID model.

    Parameters
    ----------
    Us : ndarray, shape (m, K)
        Scaled inputs.
    Ys : ndarray, shape (p, K)
        Scaled output deviations (or their principal components).
    holdout : float
        Fraction of the episode held out in each fold (:func:`cv_folds`).
    observer_orders : tuple of int, optional
        Candidates (default :data:`OBSERVER_GRID` and the largest order with two equations
        per unknown in a fold, each if it fits): at high sample rates the observer must
        span many samples to see slow modes. Given ones that do not fit are skipped; if
        none fits, :class:`~soft_rom.errors.ConfigError`.
    rhos : tuple of float
        Candidate ridge weights (each at least :data:`RIDGE_FLOOR`).
    n_markov : int, optional
        Markov horizon (default :func:`default_n_markov` of the samples of a fold).
    r_max : int
        Largest order tried (when ``r_values`` is not given: the orders of :data:`R_GRID`
        up to ``r_max``).
    r_values : tuple of int, optional
        Orders tried.
    refit : bool
        Score the stabilized realization with ``C, D`` refitted on the fold's other samples
        (:func:`stabilize`, :func:`fit_output_map`); ``False``: the ERA realization as it
        is, unstable ones rejected.
    tie_tol : float
        Relative band of tied errors (:func:`choose`).
    intercepts : tuple of bool
        OKID regressions tried without / with an intercept (:func:`ridge_markov`).
    criterion : {'blocked', 'tail'}
        Blocked cross-validation (default) or the last ``holdout`` only (:func:`cv_folds`).

    Returns
    -------
    dict
        ``observer_order``, ``ridge``, ``intercept``, ``r``, ``tail_error`` (held-out
        relative error of the chosen candidate, pooled over the folds), ``rows`` (every
        candidate tried), ``table`` (best ``r`` of every ``(l, ρ, intercept)``), ``cut``
        (samples before the last fold), ``n_markov``, ``folds``.
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
    if not cands:       # only orders given by hand can all be out of reach
        raise ConfigError(
            f'observer_order {", ".join(str(lo) for lo in observer_orders or ())} is too large '
            f'for {K} samples: the selection fits each fold on {cut} samples with two '
            f'equations per unknown (m={m}, p={p} identified channels), so observer_order '
            f'<= {l_max}. Give a smaller observer order, a longer episode, or less '
            'decimation.')
    nm = default_n_markov(cut) if n_markov is None else int(n_markov)
    rhos = tuple(max(float(x), RIDGE_FLOOR) for x in rhos)
    intercepts = INTERCEPTS if intercepts is None else intercepts
    rr = max(r_values) if r_values else r_max
    grid_r = [r for r in (r_values or R_GRID) if r <= rr]
    rows: list[dict[str, Any]] = []
    table: list[dict[str, Any]] = []
    # The scored samples do not depend on l: one reference for every candidate.
    ref = float(sum(np.sum(Ys[:, test] ** 2) for _, test in cv_folds(K, 1, holdout,
                                                                      criterion)))
    # Exact pruning: the pooled squared error only grows from fold to fold, so an order (and a
    # ridge weight, once all its orders are out) whose partial error already exceeds the band
    # of the best complete candidate (``best (1 + tie_tol)``) can be neither chosen nor tied;
    # its remaining folds are skipped and its rows carry that lower bound
    # (``complete: False``). Each order is scored independently, so the choice is the same.
    bound = float('inf')
    pairs = [(lo, icpt) for lo in cands for icpt in intercepts]
    folds = {lo: cv_folds(K, lo, holdout, criterion) for lo in cands}
    n_folds = len(folds[cands[0]])
    err = {c: np.zeros((len(rhos), len(grid_r))) for c in pairs}
    radius = {c: np.zeros((len(rhos), len(grid_r))) for c in pairs}
    alive = {c: np.ones((len(rhos), len(grid_r)), dtype=bool) for c in pairs}

    def run_fold(c: tuple[int, bool], fold: tuple[NDArray[np.bool_], NDArray[np.bool_]]
                 ) -> None:
        lo, icpt = c
        live = np.flatnonzero(alive[c].any(axis=1))
        fits = ridge_markov(Us, Ys, lo, nm, tuple(rhos[i] for i in live), icpt,
                            rows=fold[0])
        for i, (markov, _info) in zip(live, fits):
            try:
                A, B, C, D, _ = era_truncated(markov, rr)
                cand_r = [r for j, r in enumerate(grid_r)
                          if alive[c][i, j] and r <= A.shape[0]]
                found = {row['r']: row for row in fold_errors(
                    A, B, C, D, Us, Ys, fold[1], cand_r, refit=refit)}
            except (ConfigError, np.linalg.LinAlgError):
                found = {}
            for j, r in enumerate(grid_r):
                if not alive[c][i, j]:
                    continue
                row = found.get(r)
                err[c][i, j] += row['sq_error'] if row is not None else float('inf')
                radius[c][i, j] = max(radius[c][i, j], row['spectral_radius']
                                      if row is not None else float('inf'))
            alive[c][i] &= err[c][i] <= bound

    # The last block of every candidate first, then the candidates in the order of that
    # error, each through its other blocks: good candidates complete early and set the bound.
    for c in pairs:
        run_fold(c, folds[c[0]][-1])
    for c in sorted(pairs, key=lambda c: float(np.min(err[c]))):
        alive[c] &= err[c] <= bound
        for fold in folds[c[0]][-2::-1]:
            if not alive[c].any():
                break
            run_fold(c, fold)
        if alive[c].any():
            bound = min(bound, float(np.min(err[c][alive[c]])) * (1.0 + tie_tol) ** 2)
    for c in pairs:
        lo, icpt = c
        for i, rho in enumerate(rhos):
            base = {'observer_order': lo, 'ridge': rho, 'intercept': icpt}
            found = []
            for j, r in enumerate(grid_r):
                e = float(np.sqrt(err[c][i, j] / ref)) if ref > 0 else float('inf')
                found.append({**base, 'r': r, 'complete': bool(alive[c][i, j]),
                              'tail_error': e if np.isfinite(e) else float('inf'),
                              'spectral_radius': float(radius[c][i, j])})
            rows.extend(found)
            fin = [row for row in found if np.isfinite(row['tail_error'])]
            table.append(min(fin, key=lambda row: row['tail_error']) if fin else
                         {**base, 'r': None, 'tail_error': float('inf')})
    best = choose(rows, tie_tol)
    return {'observer_order': int(best['observer_order']), 'ridge': float(best['ridge']),
            'intercept': bool(best['intercept']), 'r': int(best['r']),
            'tail_error': float(best['tail_error']), 'rows': rows,
            'table': table, 'cut': cut, 'n_markov': nm, 'folds': n_folds,
            'criterion': criterion}


def fold_errors(A_full: Array, B_full: Array, C_full: Array, D: Array, Us: Array,
                Ys: Array, test: NDArray[np.bool_], r_candidates: list[int], *,
                refit: bool = True) -> list[dict[str, Any]]:
    """Squared output error on the samples ``test`` of every order ``r`` (from rest).

    ``A_full, B_full, C_full`` are the balanced realization of the largest candidate order;
    the leading ``r`` states of a balanced ERA realization are the order-``r`` realization,
    simulated from rest over the whole episode. With ``refit`` it is stabilized and ``C, D``
    are refitted on the other samples; otherwise unstable realizations score ``inf``.
    Rows: ``r``, ``sq_error``, ``spectral_radius``.
    """
    rows = []
    fit = ~test
    if refit:
        modal = [modal_inputs(A_full[:r, :r], B_full[:r], Us) for r in r_candidates]
        live = [x for x in modal if x[0] is not None]
        if live:
            Z = first_order_responses(np.concatenate([x[0] for x in live]),
                                      np.concatenate([x[1] for x in live]))
        at = 0
        for r, (ev, _G, rho) in zip(r_candidates, modal):
            if ev is None:
                rows.append({'r': r, 'sq_error': float('inf'), 'spectral_radius': rho})
                continue
            X = real_modal_states(ev, Z[at:at + r])
            at += r
            C, Dr = fit_output_map(X[:, fit], Us[:, fit], Ys[:, fit])
            e = float(np.sum((C @ X[:, test] + Dr @ Us[:, test] - Ys[:, test]) ** 2))
            rows.append({'r': r, 'sq_error': e if np.isfinite(e) else float('inf'),
                         'spectral_radius': rho})
        return rows
    for r in r_candidates:
        A, B, C = A_full[:r, :r], B_full[:r], C_full[:, :r]
        rho = float(np.max(np.abs(np.linalg.eigvals(A))))
        if not rho < 1.0:
            rows.append({'r': r, 'sq_error': float('inf'), 'spectral_radius': rho})
            continue
        X = simulate_states(A, B, Us)
        e = float(np.sum((C @ X[:, test] + D @ Us[:, test] - Ys[:, test]) ** 2))
        rows.append({'r': r, 'sq_error': e if np.isfinite(e) else float('inf'),
                     'spectral_radius': rho})
    return rows


def score_orders(A_full: Array, B_full: Array, C_full: Array, D: Array, Us: Array,
                 Ys: Array, cut: int, r_candidates: list[int], *, refit: bool = True
                 ) -> list[dict[str, Any]]:
    """Relative output error on the tail ``k >= cut`` of every order ``r``.

    The single-fold case of :func:`fold_errors` (the ``'tail'`` criterion).
    """
    test = np.arange(Us.shape[1]) >= cut
    den = float(np.linalg.norm(Ys[:, test]))
    return [{'r': row['r'], 'spectral_radius': row['spectral_radius'],
             'tail_error': float(np.sqrt(row['sq_error'])) / max(den, 1e-300)}
            for row in fold_errors(A_full, B_full, C_full, D, Us, Ys, test, r_candidates,
                                   refit=refit)]


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
    return ev, G, rho


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


def blas_threads(n: int | None) -> Any:
    """Limit BLAS threads to ``n`` while fitting (threadpoolctl, when installed)."""
    if n is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: without it the process's BLAS settings apply
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(n), user_api='blas')


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


def compress_outputs(Ys: Array, rank: int | str | None) -> tuple[Array, Array | None]:
    """Leading principal components ``P`` (p, q) of the scaled outputs: ``(Pᵀ Y_s, P)``.

    ``rank``: ``q``; ``'auto'``: the components holding 99 % of the energy, at least
    ``min(p, 4)``; ``None`` (or ``q = p``): the outputs as they are (``P = None``).
    """
    p = Ys.shape[0]
    q = rank
    if q == 'auto':
        sv = np.linalg.svd(Ys, compute_uv=False)
        cum = np.cumsum(sv ** 2) / max(float(np.sum(sv ** 2)), 1e-300)
        q = min(p, max(4, int(np.searchsorted(cum, 0.99) + 1)))
    elif isinstance(q, str):
        raise ConfigError(f"output_rank must be an integer, 'auto' or None; got {q!r}.")
    if q is None:
        return Ys, None
    q = int(q)
    if not 1 <= q <= p:
        raise ConfigError(f'output_rank must be between 1 and p = {p}; got {q}.')
    if q == p:
        return Ys, None
    P = np.linalg.svd(Ys, full_matrices=False)[0][:, :q]         # (p, q), orthonormal
    return P.T @ Ys, P


#: Input directions whose singular value is below this fraction of the largest are not
#: excited by the data (:func:`compress_inputs`).
INPUT_RANK_TOL = 1e-8


def compress_inputs(Us: Array, rank: int | str | None) -> tuple[Array, Array | None]:
    """The input directions the data excite: ``(P_uᵀ U_s, P_u)``, ``P_u`` (m, m_e) orthonormal.

    Inputs driven in fixed combinations (antagonistic actuator pairs: ``u_2 = -u_1``) span
    fewer than ``m`` directions; the responses to the directions they never take are not
    determined by the data, and a least-squares or weakly regularized OKID fills them with
    whatever rounding makes them (on the eel, 3 of 6 pressure directions: their share of the
    Markov parameters changed by 3e-4 under a 1e-9 output perturbation at ``ρ = 1e-9``).
    Identifying on the excited directions gives those responses exactly zero (the
    minimum-norm answer); the model is lifted back with ``B = B_e P_uᵀ``, ``D = D_e P_uᵀ``.

    ``rank``: ``m_e``; ``'auto'``: the singular values above :data:`INPUT_RANK_TOL` times the
    largest; ``None`` (or ``m_e = m``): the inputs as they are (``P_u = None``).
    """
    m = Us.shape[0]
    if rank is None:
        return Us, None
    Pu, sv, _ = np.linalg.svd(Us, full_matrices=False)
    if rank == 'auto':
        q = max(int(np.sum(sv > INPUT_RANK_TOL * sv[0])), 1) if sv[0] > 0 else m
    elif isinstance(rank, str):
        raise ConfigError(f"input_rank must be an integer, 'auto' or None; got {rank!r}.")
    else:
        q = int(rank)
        if not 1 <= q <= m:
            raise ConfigError(f'input_rank must be between 1 and m = {m}; got {q}.')
    if q == m:
        return Us, None
    P = np.ascontiguousarray(Pu[:, :q])
    return P.T @ Us, P


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
