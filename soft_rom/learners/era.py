"""ERA/OKID: linear ROMs from input/output data alone (paper section 2.4).

Two steps, each usable alone:

1. :func:`okid_markov` -- observer/Kalman filter identification (Juang, Phan, Horta & Longman,
   *Identification of observer/Kalman filter Markov parameters: theory and experiments*,
   J. Guid. Control Dyn. 16(2), 1993). With :math:`v_k = [u_k; y_k]` the observer model

   .. math:: y_k = D u_k + \\sum_{i=1}^{l} \\bar Y_i v_{k-i},
       \\qquad \\bar Y_i = C \\bar A^{i-1} [B + G D, \\; -G],

   is fitted by least squares over the samples :math:`k = l, \\dots, K-1` (no assumption on
   the initial state), and the system Markov parameters are recovered by

   .. math:: Y_0 = D, \\qquad
       Y_k = \\bar Y^{(1)}_k + \\sum_{i=1}^{\\min(k, l)} \\bar Y^{(2)}_i Y_{k-i},

   with :math:`\\bar Y^{(1)}_k = 0` for :math:`k > l`; so any number of Markov parameters
   can be computed from an observer of order ``l``.
2. :func:`era` -- the eigensystem realization algorithm (Juang & Pappa, *An eigensystem
   realization algorithm for modal parameter identification and model reduction*, J. Guid.
   Control Dyn. 8(5), 1985): block Hankel matrices :math:`H_0 = [Y_{i+j+1}]`,
   :math:`H_1 = [Y_{i+j+2}]`, SVD :math:`H_0 = P S Q^\\top`, and

   .. math:: A = S_r^{-1/2} P_r^\\top H_1 Q_r S_r^{-1/2}, \\quad
       B = S_r^{1/2} Q_r^\\top E_m, \\quad C = E_p^\\top P_r S_r^{1/2}, \\quad D = Y_0.

The model is :math:`x_{k+1} = A x_k + B u_k`, :math:`y_k = C x_k + D u_k + y_{ref}`.

The horizon problem and its knobs. With ``p = 40`` outputs the observer regression has
``m + l (m + p)`` unknowns per output row, so ``K`` samples allow an observer of order
``l < K / (m + p + 1)`` (a few dozen samples at 1 kHz), while the slow modes of a soft body
last seconds. Three knobs, with defaults chosen by trying them on a lightly damped
second-order system with 40 outputs at 1 kHz (see :class:`ERAOKID`):

* ``observer_order`` (``l``): with many outputs a low order already makes the observer
  dead-beat (``l p >= n``), and the recursion above then extends the Markov sequence as far
  as wanted;
* ``n_markov``: how many system Markov parameters feed the Hankel matrices (their time span
  ``n_markov · dt_model`` should cover the slow modes);
* ``decimation``: fit at ``dt_model = decimation · dt_data``: outputs are sampled every
  ``decimation`` samples and inputs averaged over each block (the input held over one model
  step); :func:`soft_rom.evaluation.predict` uses the same rule.

Unit invariance: inputs and outputs are divided by their per-channel RMS before OKID/ERA
and the realization is scaled back (``B = B_s diag(1/s_u)``, ``C = diag(s_y) C_s``,
``D = diag(s_y) D_s diag(1/s_u)``); the Hankel singular values are those of the scaled data.
"""

from __future__ import annotations

from collections.abc import Sequence
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal, check_finite, Episode
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.learners.dmdc import channel_scale
from soft_rom.models import DiscreteModel

__all__ = ['ERAOKID', 'decimate', 'era', 'hankel_rank', 'okid_markov']

Array = NDArray[np.float64]


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


def okid_markov(U: ArrayLike, Y: ArrayLike, *, observer_order: int, n_markov: int,
                rcond: float | None = None) -> tuple[Array, dict[str, Any]]:
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
        raise ConfigError(f'observer_order must be >= 1; got {observer_order!r}.')
    if nm < 1:
        raise ConfigError(f'n_markov must be >= 1; got {n_markov!r}.')
    n_unknowns = m + lo * (m + p)
    rows = K - lo
    if rows < n_unknowns:
        kmax = (K - m) // (m + p + 1)
        raise ConfigError(
            f'OKID with observer_order={lo} has {n_unknowns} unknowns per output but only '
            f'{rows} equations ({K} samples): use observer_order <= {max(kmax, 0)}, more data, '
            'or less decimation.')
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
    info = {'residual': float(np.linalg.norm(resid) / den) if den > 0 else 0.0,
            'rank': int(rank), 'n_unknowns': int(n_unknowns)}
    return markov, info


def _hankel(markov: Array, start: int, rows: int, cols: int) -> Array:
    _, p, m = markov.shape
    H = np.empty((rows * p, cols * m))
    for i in range(rows):
        for j in range(cols):
            H[i * p:(i + 1) * p, j * m:(j + 1) * m] = markov[start + i + j]
    return H


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
        tol: float = 1e-3) -> tuple[Array, Array, Array, Array, Array]:
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
    elif n_block_rows is None:
        n_block_rows = N - int(n_block_cols)
    elif n_block_cols is None:
        n_block_cols = N - int(n_block_rows)
    a, b = int(n_block_rows), int(n_block_cols)
    if a < 1 or b < 1 or a + b > N:
        raise ConfigError(f'Hankel blocks ({a} rows, {b} columns) need 1 <= rows, cols and '
                          f'rows + cols <= {N} (the number of Markov parameters).')
    H0 = _hankel(markov, 1, a, b)
    H1 = _hankel(markov, 2, a, b)
    P, s, Qt = np.linalg.svd(H0, full_matrices=False)
    r = hankel_rank(s, tol=tol) if r is None else int(r)
    if not 1 <= r <= s.size or s[r - 1] <= 0:
        raise ConfigError(f'r must be between 1 and the numerical rank of the Hankel matrix '
                          f'({int(np.sum(s > 0))} of {s.size} singular values > 0); got {r}.')
    sq = np.sqrt(s[:r])
    A = (P[:, :r].T @ H1 @ Qt[:r].T) / np.outer(sq, sq)
    B = sq[:, None] * Qt[:r, :m]
    C = P[:p, :r] * sq[None, :]
    return A, B, C, markov[0].copy(), s


class ERAOKID:
    """ERA/OKID learner: a discrete ROM from the inputs and outputs of one episode.

    Parameters
    ----------
    r : int, optional
        Order of the ROM; ``None``: the number of Hankel singular values above
        ``hsv_tol · σ_1`` (:func:`hankel_rank`).
    n_markov : int
        System Markov parameters used in the Hankel matrices (their span is
        ``n_markov · decimation · dt``).
    observer_order : int, optional
        OKID observer order ``l``; ``None``: the largest order with at least two equations per
        unknown (``K / 2 >= m + l (m + p)``, ``K`` samples after decimation), capped at
        ``max_observer_order``.
    decimation : int
        Fit at ``decimation`` times the data sample time (module docstring).
    n_block_rows, n_block_cols : int, optional
        Hankel block sizes (default: half of ``n_markov`` each).
    hsv_tol : float
        Threshold of the default order rule.
    max_observer_order : int
        Cap for the automatic observer order.
    output_rank : int, optional
        Identify on the leading ``output_rank`` principal components of the scaled outputs
        (``Y_s ≈ P Z``, ``P`` orthonormal ``(p, q)``) and lift ``C = P C_Z``, ``D = P D_Z``.
        With strongly correlated outputs (the 20 centerline points of a soft body) this cuts
        the OKID unknowns from ``m + l (m + p)`` to ``m + l (m + q)``, so a much longer
        observer fits in the same data. ``None``: all ``p`` outputs.
    okid_rcond : float, optional
        Relative singular-value cut-off of the OKID least-squares solve (regularisation).

    How the defaults were chosen (``decimation=5``, ``n_markov=100``, automatic observer
    order): a lightly damped second-order system (12 modes, 1.5 to 60 Hz, damping 2 to 5 %),
    6 antagonistic pressure inputs (random steps with 20 ms ramps), 40 outputs at 1 kHz with
    0.1 % noise; fit on 1.5 s, errors on deviations (train ``t < 1.5 s`` / test ``1.5-2 s`` /
    an unseen input sequence), r from 24 to 40:

    ============  ========  ========  =====================================================
    decimation    n_markov  observer  result
    ============  ========  ========  =====================================================
    1             50-200    2-10      unstable or > 20 % train error: the Hankel span
                                      (0.05-0.2 s) is far shorter than the slow modes
    1             400       5-10      3 % / 6-15 % / --, 0.4 s span, but slow (8000-row SVD)
    2             100-200   2-10      unreliable (errors 6 % to > 100 %, often unstable)
    2             400       5-10      0.3-1 % / 1-4 %, slow
    **5**         **100**   **3**     **0.7-1.4 % / 3-3.7 % / 1.9-2.6 %**, stable, 0.5 s
    5             200       2-5       0.3-1 % / 2-6 % / 1.3-3.7 %, stable
    5             100-200   6         unstable: 282 unknowns for 294 equations fit noise
    5             any       1         ~96 %: a one-step observer is not dead-beat with noise
    10            any       1-3       fails: 150 samples leave no room for an observer
    ============  ========  ========  =====================================================

    The rule kept: at least two equations per OKID unknown (automatic observer order), a
    Hankel span ``n_markov · decimation · dt`` of about 0.5 s, and decimation so that the
    1.5-2 s episode still has a few hundred samples.

    Noise-free simulations of the embedded (geometrically nonlinear) eel, 5,145 DOF, are
    harder: with all 40 outputs every setting above gave unstable realizations (the OKID
    recursion amplifies the near-exact, over-parameterised observer). What worked there was
    ``output_rank=4, decimation=1, observer_order=36, n_markov=500``: 11-14 % training error
    on deviations for r = 24-32 on either episode (LOpInf: 13 %), stability margin within
    1e-4 of zero; ``decimation=2, observer_order=18, n_markov=250`` works on one episode but
    not on the other. Treat ERA/OKID on such data as fragile and check the stability margin.

    Attributes
    ----------
    model_ : DiscreteModel
        ``method='era'``, ``dt = decimation · dt_data``.
    hankel_singular_values_ : ndarray
    markov_ : ndarray, shape (n_markov + 1, p, m)
        Markov parameters of the scaled data.
    observer_order_ : int
    okid_residual_ : float
        Relative residual of the observer fit.
    output_basis_ : ndarray, shape (p, q) or None
        Output principal directions used when ``output_rank`` is set.
    y_ref_ : ndarray, shape (p,)
    input_scale_, output_scale_ : ndarray
    """

    def __init__(self, r: int | None = None, *, n_markov: int = 100,
                 observer_order: int | None = None, decimation: int = 5,
                 n_block_rows: int | None = None, n_block_cols: int | None = None,
                 hsv_tol: float = 1e-3, max_observer_order: int = 10,
                 output_rank: int | None = None, okid_rcond: float | None = None) -> None:
        self.r = r
        self.n_markov = n_markov
        self.observer_order = observer_order
        self.decimation = decimation
        self.n_block_rows = n_block_rows
        self.n_block_cols = n_block_cols
        self.hsv_tol = hsv_tol
        self.max_observer_order = max_observer_order
        self.output_rank = output_rank
        self.okid_rcond = okid_rcond

    def fit(self, episode: Episode | Sequence[Episode], y_ref: ArrayLike | None = None, *,
            input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> ERAOKID:
        """Identify the ROM from one episode.

        Parameters
        ----------
        episode : Episode
            Uniformly sampled ``U (m, k)``, ``Y (p, k)``; ``Q`` is ignored. A list with one
            episode is accepted; several are refused (OKID needs one continuous record).
        y_ref : ndarray, shape (p,), optional
            Output reference; default the first output sample.

        Returns
        -------
        self
        """
        t0 = time.perf_counter()
        if not isinstance(episode, Episode):
            eps = list(episode)
            if len(eps) != 1:
                raise DimensionError(
                    f'ERA/OKID fits one episode at a time (one continuous record); got '
                    f'{len(eps)} episodes. Fit one model per episode, e.g. '
                    '--era-episode ep2 on the command line.')
            episode = eps[0]
        ep = episode
        if not ep.is_uniform():
            raise DimensionError(f'episode {ep.name!r} is not uniformly sampled.')
        check_finite(f'U of episode {ep.name!r}', ep.U)
        check_finite(f'Y of episode {ep.name!r}', ep.Y)
        m, p = ep.U.shape[0], ep.Y.shape[0]
        y_ref = ep.Y[:, 0].copy() if y_ref is None else as_signal(
            'y_ref', np.reshape(y_ref, (-1, 1)), rows=p)[:, 0]
        d = int(self.decimation)
        Ud, Yd = decimate(ep.U, ep.Y - y_ref[:, None], d)
        s_u = channel_scale(Ud)
        s_y = channel_scale(Yd)
        Us, Ys = Ud / s_u[:, None], Yd / s_y[:, None]
        P = None
        if self.output_rank is not None:
            q = int(self.output_rank)
            if not 1 <= q <= p:
                raise ConfigError(f'output_rank must be between 1 and p = {p}; got {q}.')
            P = np.linalg.svd(Ys, full_matrices=False)[0][:, :q]     # (p, q), orthonormal
            Ys = P.T @ Ys
        p_id = Ys.shape[0]
        K = Us.shape[1]
        if self.observer_order is None:
            # Keep at least 2 equations per unknown: near-square regressions fit the noise
            # and give unstable Markov sequences (see the sweep in the class docstring).
            lo = min(int(self.max_observer_order), (K // 2 - m) // (m + p_id))
            if lo < 1:
                raise DimensionError(
                    f'episode {ep.name!r} has {K} samples after decimation {d}: too few for '
                    f'OKID with m={m}, p={p_id} (needs at least {2 * (2 * m + p_id)}). Use less '
                    'decimation or a longer episode.')
        else:
            lo = int(self.observer_order)
        markov, info = okid_markov(Us, Ys, observer_order=lo, n_markov=int(self.n_markov),
                                   rcond=self.okid_rcond)
        A, Bs, Cs, Ds, hsv = era(markov, self.r, n_block_rows=self.n_block_rows,
                                 n_block_cols=self.n_block_cols, tol=self.hsv_tol)
        if P is not None:
            Cs, Ds = P @ Cs, P @ Ds
        self.output_basis_ = P
        B = Bs / s_u[None, :]
        C = s_y[:, None] * Cs
        D = s_y[:, None] * Ds / s_u[None, :]
        ev = np.linalg.eigvals(A)
        r = A.shape[0]
        dt = d * ep.dt
        self.markov_ = markov
        self.hankel_singular_values_ = hsv
        self.observer_order_ = lo
        self.okid_residual_ = info['residual']
        self.y_ref_ = y_ref
        self.input_scale_ = s_u
        self.output_scale_ = s_y
        self.fit_time_ = time.perf_counter() - t0
        meta = dict(metadata or {})
        meta.setdefault('envelope', training_envelope([ep], y_ref))
        meta.update({
            'learner': 'ERAOKID', 'r': r, 'episode': ep.name,
            'decimation': d, 'dt_data': ep.dt, 'n_markov': int(self.n_markov),
            'observer_order': lo, 'okid_residual': info['residual'],
            'okid_rank': info['rank'], 'okid_unknowns': info['n_unknowns'],
            'n_block_rows': self.n_block_rows, 'n_block_cols': self.n_block_cols,
            'hsv_tol': self.hsv_tol, 'output_rank': self.output_rank,
            'okid_rcond': self.okid_rcond,
            'hankel_singular_values': hsv[:200].tolist(),
            'input_scale': s_u.tolist(), 'output_scale': s_y.tolist(),
            'eigenvalues_real': ev.real.tolist(), 'eigenvalues_imag': ev.imag.tolist(),
            'stability_margin': float(1.0 - np.max(np.abs(ev))),
            'fit_time_s': self.fit_time_,
        })
        self.model_ = DiscreteModel(A, B, C, D, dt=dt, method='era', y_ref=y_ref,
                                    input_names=input_names, output_names=output_names,
                                    input_units=input_units, output_units=output_units,
                                    metadata=meta)
        return self

    def model_for(self, r: int) -> DiscreteModel:
        """The ROM of order ``r`` from the stored Markov parameters (no new OKID solve)."""
        if not hasattr(self, 'markov_'):
            raise NotFittedError('this ERAOKID is not fitted yet; call fit(episode) first.')
        A, Bs, Cs, Ds, _ = era(self.markov_, int(r), n_block_rows=self.n_block_rows,
                               n_block_cols=self.n_block_cols, tol=self.hsv_tol)
        if self.output_basis_ is not None:
            Cs, Ds = self.output_basis_ @ Cs, self.output_basis_ @ Ds
        s_u, s_y = self.input_scale_, self.output_scale_
        old = self.model_
        ev = np.linalg.eigvals(A)
        meta = dict(old.metadata)
        meta.update({'r': int(r), 'eigenvalues_real': ev.real.tolist(),
                     'eigenvalues_imag': ev.imag.tolist(),
                     'stability_margin': float(1.0 - np.max(np.abs(ev)))})
        return DiscreteModel(A, Bs / s_u[None, :], s_y[:, None] * Cs,
                             s_y[:, None] * Ds / s_u[None, :], dt=old.dt, method='era',
                             y_ref=self.y_ref_, input_names=old.input_names,
                             output_names=old.output_names, input_units=old.input_units,
                             output_units=old.output_units, metadata=meta)
