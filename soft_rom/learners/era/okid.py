"""OKID: system Markov parameters from arbitrary input/output data (paper section 2.4).

Observer/Kalman filter identification (Juang, Phan, Horta & Longman, *Identification of
observer/Kalman filter Markov parameters: theory and experiments*, J. Guid. Control Dyn.
16(2), 1993). With :math:`v_k = [u_k; y_k]` the observer model

.. math:: y_k = D u_k + \\sum_{i=1}^{l} \\bar Y_i v_{k-i},
    \\qquad \\bar Y_i = C \\bar A^{i-1} [B + G D, \\; -G],

is fitted by least squares (or ridge, :func:`ridge_markov`) over the samples
:math:`k = l, \\dots, K-1` (no assumption on the initial state), and the system Markov
parameters are recovered by

.. math:: Y_0 = D, \\qquad
    Y_k = \\bar Y^{(1)}_k + \\sum_{i=1}^{\\min(k, l)} \\bar Y^{(2)}_i Y_{k-i},

with :math:`\\bar Y^{(1)}_k = 0` for :math:`k > l`; so any number of Markov parameters
can be computed from an observer of order ``l``. The data are prepared here too: decimation
(:func:`decimate`) and the compression to the excited input and output directions
(:func:`compress_inputs`, :func:`compress_outputs`). Why the ridge solve is needed and how its
weight is chosen: ``docs/methods_variants.md`` (ERA/OKID).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal
from soft_rom.errors import ConfigError

__all__ = ['INPUT_RANK_TOL', 'MAX_MARKOV', 'RIDGE_FLOOR', 'compress_inputs', 'compress_outputs',
           'decimate', 'default_n_markov', 'markov_from_observer', 'okid_markov',
           'okid_regression', 'ridge_markov']

Array = NDArray[np.float64]

#: Smallest relative ridge weight (a relative output precision of about 3e-3).
RIDGE_FLOOR = 1e-10


#: Cap of the automatic Markov horizon.
MAX_MARKOV = 500


def decimate(U: ArrayLike, Y: ArrayLike, factor: int) -> tuple[Array, Array]:
    """Resample input/output data at ``factor`` times the sample time.

    Outputs are sampled at the start of each block (``Y[:, ::factor]``); inputs are averaged
    over the block (the value held during one model step). Only complete blocks are kept.

    Parameters
    ----------
    U : ndarray, shape (m, k)
    Y : ndarray, shape (p, k)
    factor : int

    Returns
    -------
    Ud : ndarray, shape (m, k // factor)
    Yd : ndarray, shape (p, k // factor)
    """
    U = as_signal('U', U)
    Y = as_signal('Y', Y, cols=U.shape[1])
    d = int(factor)
    if d < 1:
        raise ConfigError(f'decimation must be a positive integer; got {factor!r}.')
    if d == 1:
        return U, Y
    kd = U.shape[1] // d
    Ud = U[:, :kd * d].reshape(U.shape[0], kd, d).mean(axis=2)
    return Ud, Y[:, :kd * d:d]


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


def okid_markov(U: ArrayLike, Y: ArrayLike, *, observer_order: int, n_markov: int,
                rcond: float | None = None, ridge: float | None = None,
                intercept: bool = False) -> tuple[Array, dict[str, Any]]:
    """System Markov parameters from arbitrary input/output data by OKID.

    Parameters
    ----------
    U : ndarray, shape (m, K)
        Inputs (deviations or absolute: the model has no input offset).
    Y : ndarray, shape (p, K)
        Output deviations from ``y_ref``.
    observer_order : int
        ``l``, number of past samples in the observer model; needs
        ``K - l >= m + l (m + p)``.
    n_markov : int
        Number of Markov parameters ``Y_1 .. Y_n_markov`` to return besides ``Y_0 = D``.
    rcond : float, optional
        Cut-off for the least-squares solve (``numpy.linalg.lstsq``).
    ridge : float, optional
        Relative Tikhonov weight ``ρ`` (``λ = ρ σ_1(Φ)²``;
        :mod:`soft_rom.learners.era.select`): the well-posed solve. ``None``: plain least
        squares (exact data only).
    intercept : bool
        Ridge solve with an unpenalized constant term (insensitive to an output offset).

    Returns
    -------
    markov : ndarray, shape (n_markov + 1, p, m)
        ``markov[0] = D``, ``markov[k] = C A^{k-1} B``.
    info : dict
        ``residual`` (relative residual of the observer fit), ``rank`` and ``n_unknowns``.
    """
    U = as_signal('U', U)
    Y = as_signal('Y', Y, cols=U.shape[1])
    m, K = U.shape
    p = Y.shape[0]
    lo = int(observer_order)
    nm = int(n_markov)
    if lo < 1:
        raise ConfigError(f'--observer-order must be >= 1; got {observer_order!r}.')
    if nm < 1:
        raise ConfigError(f'--n-markov must be >= 1; got {n_markov!r}.')
    n_unknowns = m + lo * (m + p)
    rows = K - lo
    if rows < n_unknowns:
        kmax = (K - m) // (m + p + 1)
        raise ConfigError(
            f'OKID with --observer-order {lo} has {n_unknowns} unknowns per output but only '
            f'{rows} equations ({K} samples): use --observer-order <= {max(kmax, 0)}, more data, '
            'or less decimation.')
    if ridge is not None:
        markov, info = ridge_markov(U, Y, lo, nm, (float(ridge),), intercept)[0]
        info['rank'] = info['effective_rank']
        return markov, info
    V = np.concatenate([U, Y], axis=0)                       # (m + p, K)
    Phi = np.empty((n_unknowns, rows))
    Phi[:m] = U[:, lo:]
    for i in range(1, lo + 1):
        a = m + (i - 1) * (m + p)
        Phi[a:a + m + p] = V[:, lo - i:K - i]
    theta, _, rank, _ = np.linalg.lstsq(Phi.T, Y[:, lo:].T, rcond=rcond)
    theta = theta.T                                          # (p, n_unknowns)
    resid = Y[:, lo:] - theta @ Phi
    den = np.linalg.norm(Y[:, lo:])
    markov = markov_from_observer(theta, m, p, lo, nm)
    info = {'residual': float(np.linalg.norm(resid) / den) if den > 0 else 0.0,
            'rank': int(rank), 'n_unknowns': int(n_unknowns)}
    return markov, info


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
        raise ConfigError(f"--output-rank must be an integer, 'auto' or None; got {q!r}.")
    if q is None:
        return Ys, None
    q = int(q)
    if not 1 <= q <= p:
        raise ConfigError(f'--output-rank must be between 1 and p = {p}; got {q}.')
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
    whatever rounding makes them (``docs/methods_variants.md``, ERA/OKID). Identifying on the
    excited directions gives those responses exactly zero (the minimum-norm answer); the model
    is lifted back with ``B = B_e P_uᵀ``, ``D = D_e P_uᵀ``.

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
