"""Dynamic mode decomposition with control (DMDc), as in the paper's section 2.3.

Given snapshot pairs from one or several episodes (a pair never straddles two episodes),

.. math::

    \\Omega = \\begin{bmatrix} Q \\\\ U \\end{bmatrix}
    \\approx \\begin{bmatrix} \\tilde U_1 \\\\ \\tilde U_2 \\end{bmatrix}
    \\tilde\\Sigma \\tilde V^\\top \\;(\\text{rank } p), \\qquad
    Q' \\approx \\hat U \\hat\\Sigma \\hat V^\\top \\;(\\text{rank } r),

    \\tilde A = \\hat U^\\top Q' \\tilde V \\tilde\\Sigma^{-1} \\tilde U_1^\\top \\hat U, \\qquad
    \\tilde B = \\hat U^\\top Q' \\tilde V \\tilde\\Sigma^{-1} \\tilde U_2^\\top,

and the ROM :math:`\\tilde q_{k+1} = \\tilde A \\tilde q_k + \\tilde B u_k`,
:math:`y_k = \\tilde E \\tilde q_k + y_{ref}` with :math:`\\tilde q = \\hat U^\\top (q - q_{ref})`
(Proctor, Brunton & Kutz, *Dynamic mode decomposition with control*, SIAM J. Appl. Dyn. Syst.
15(1), 2016; Sharma et al., section 2.3).

Choices made here (each documented where it is made):

* **Centring.** States are deviations from ``q_ref``; outputs from ``y_ref``.
* **Unit invariance.** ``Ω`` stacks displacements (m or mm) with pressures (Pa or kPa), so the
  truncation of its SVD would depend on the units. Internally the Q block is divided by one
  scalar (its RMS over the training pairs; a scalar keeps the POD basis :math:`\\hat U`
  unchanged) and each input channel by its own RMS; the scaling is undone in the operators
  (``A = A_s / s_q``, ``B = B_s diag(1/s_u)``) so the ROM state stays
  :math:`\\hat U^\\top (q - q_{ref})` in physical units. Predictions are then the same in
  any units, to rounding.
* **Output operator.** The paper solves :math:`\\min \\|Y - E_{approx} Q\\|` for the full
  ``p × n`` matrix and sets :math:`\\tilde E = E_{approx} \\hat U`. By default
  (``output_fit='reduced'``) we solve the least-squares problem directly in the reduced
  coordinates,
  :math:`\\min_{\\tilde E} \\|(Y - y_{ref}) - \\tilde E \\hat U^\\top (Q - q_{ref})\\|`,
  which never forms an ``n``-column matrix. The two coincide when the snapshots lie in the span
  of :math:`\\hat U` (e.g. at full rank); otherwise the reduced fit is the best output map for the
  states the ROM actually carries. ``output_fit='paper'`` computes
  :math:`E_{approx} \\hat U = (Y - y_{ref}) Q^+ \\hat U` (as the minimum-norm solution, still
  without forming ``E_approx``) for an exact replica.
* **Rank guard.** Singular values of ``Ω`` below ``rcond · σ_1`` are dropped even when ``p``
  asks for them (antagonistic chambers make ``U`` rank-deficient; inverting a zero singular
  value would blow up ``B̃``). The number kept is recorded in ``metadata['p']``.

Plugging in other SVDs (out-of-core data, :mod:`soft_rom.scale`): the operators depend on the
data only through a few small factors. :func:`dmdc_reduced_operators` builds ``Ã, B̃`` from
them, and :func:`dmdc_from_gram` computes every factor from Gram matrices of the (scaled,
centred) snapshots, which a streaming/Dask code can accumulate block by block.
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
from soft_rom.models import DiscreteModel

__all__ = ['DMDc', 'channel_scale', 'clip_spectral_radius', 'dmdc_from_gram',
           'dmdc_reduced_operators']

Array = NDArray[np.float64]


def channel_scale(X: ArrayLike, *, per_channel: bool = True) -> Array:
    """Positive scale factors (RMS) used to make fits unit-invariant.

    Parameters
    ----------
    X : ndarray, shape (c, k)
    per_channel : bool
        One RMS per row (shape ``(c,)``) or one for the whole array (shape ``(1,)``).

    Returns
    -------
    s : ndarray, shape (c,) or (1,)
        RMS values; a channel that is identically zero gets scale 1 (it stays zero).
    """
    X = np.asarray(X, dtype=np.float64)
    if per_channel:
        s = np.sqrt(np.mean(X ** 2, axis=1)) if X.shape[1] else np.ones(X.shape[0])
    else:
        s = np.array([np.sqrt(np.mean(X ** 2))]) if X.size else np.ones(1)
    return np.where(s > 0, s, 1.0)


def dmdc_reduced_operators(G: ArrayLike, s_omega: ArrayLike, U1_Uhat: ArrayLike,
                           U2: ArrayLike) -> tuple[Array, Array]:
    """DMDc operators from the SVD factors (Proctor et al. 2016, eq. 3.9 / paper sec. 2.3).

    Parameters
    ----------
    G : ndarray, shape (r, p)
        :math:`\\hat U^\\top Q' \\tilde V` (equal to :math:`\\hat\\Sigma \\hat V^\\top \\tilde V`).
    s_omega : ndarray, shape (p,)
        Kept singular values :math:`\\tilde\\sigma` of ``Ω`` (all positive).
    U1_Uhat : ndarray, shape (p, r)
        :math:`\\tilde U_1^\\top \\hat U`.
    U2 : ndarray, shape (m, p)
        :math:`\\tilde U_2`, the input rows of Ω's left singular vectors.

    Returns
    -------
    A : ndarray, shape (r, r)
    B : ndarray, shape (r, m)
    """
    G = np.asarray(G, dtype=np.float64)
    s = np.asarray(s_omega, dtype=np.float64).reshape(-1)
    if np.any(s <= 0):
        raise DimensionError('singular values of Omega must be positive (drop the zero ones).')
    GS = G / s[None, :]
    return GS @ np.asarray(U1_Uhat, dtype=np.float64), GS @ np.asarray(U2, dtype=np.float64).T


def clip_spectral_radius(A: ArrayLike, rho: float = 1.0) -> tuple[Array, int]:
    """``A`` with every eigenvalue of modulus ``> rho`` moved radially onto ``|z| = rho``.

    Works on the real Schur form ``A = Z T Zᵀ``: each 1×1 or 2×2 diagonal block of ``T``
    whose eigenvalue modulus exceeds ``rho`` is scaled by ``rho / |λ|`` (a 2×2 block scaled by
    ``s`` has eigenvalues ``s λ``); the coupling above the diagonal is kept, so the other
    eigenvalues do not move.

    Returns
    -------
    A_clipped : ndarray, shape (r, r)
    n_clipped : int
        Number of eigenvalues moved.
    """
    import scipy.linalg as sla
    A = np.asarray(A, dtype=np.float64)
    if A.size == 0 or float(np.max(np.abs(np.linalg.eigvals(A)))) <= rho:
        return A, 0
    T, Z = sla.schur(A, output='real')
    n = T.shape[0]
    i = moved = 0
    target = rho * (1.0 - 1e-12)
    while i < n:
        size = 2 if i + 1 < n and abs(T[i + 1, i]) > 0 else 1
        blk = T[i:i + size, i:i + size]
        mod = float(np.max(np.abs(np.linalg.eigvals(blk))))
        if mod > target:
            T[i:i + size, i:i + size] = blk * (target / mod)
            moved += size
        i += size
    return Z @ T @ Z.T, moved


def _lag_model(data: Sequence[tuple[Array, Array]], r: int, s_q: float, s_u: Array, rho: float,
               rcond: float) -> tuple[Array, Array, int]:
    """The ``'stable'`` variant: one lag of states and inputs, spectral radius ``<= rho``.

    Least squares ``x̃_{k+1} = A₁ x̃_k + A₂ x̃_{k-1} + B₀ u_k + B₁ u_{k-1}`` (the exact form of a
    sampled linear second-order system with held inputs), in the model
    ``z = [x̃_k; x̃_{k-1}; u_{k-1}]``; eigenvalues outside ``|z| ≤ rho`` are then clipped
    (:func:`clip_spectral_radius`) and ``B₀, B₁`` refitted for the clipped ``A₁, A₂``.
    """
    tgt, reg_x, reg_u = [], [], []
    for Xr, U in data:
        if Xr.shape[1] < 3:
            continue
        x = Xr[:r] / s_q
        u = U / s_u[:, None]
        tgt.append(x[:, 2:])
        reg_x.append(np.vstack([x[:, 1:-1], x[:, :-2]]))
        reg_u.append(np.vstack([u[:, 1:-1], u[:, :-2]]))
    if not tgt:
        raise DimensionError("DMDc variant 'stable' needs episodes of at least 3 samples.")
    T, Rx, Ru = (np.concatenate(a, axis=1) for a in (tgt, reg_x, reg_u))
    m = Ru.shape[0] // 2
    theta = np.linalg.lstsq(np.vstack([Rx, Ru]).T, T.T, rcond=rcond)[0].T
    A12, B01 = theta[:, :2 * r], theta[:, 2 * r:]
    n = 2 * r + m
    Az = np.zeros((n, n))
    Az[r:2 * r, :r] = np.eye(r)
    Az[:r, :2 * r] = A12
    Ax = Az[:2 * r, :2 * r]
    Ax_c, clipped = clip_spectral_radius(Ax, rho)
    if clipped:
        A12 = Ax_c[:r]
        B01 = np.linalg.lstsq(Ru.T, (T - A12 @ Rx).T, rcond=rcond)[0].T
        Az[:r, :2 * r] = A12
        Az[r:2 * r, :2 * r] = Ax_c[r:]
    Az[:r, 2 * r:] = B01[:, m:]
    Bz = np.zeros((n, m))
    Bz[:r] = B01[:, :m]
    Bz[2 * r:] = np.eye(m)
    # Back to physical units: z_phys = D z_scaled with D = diag(s_q, s_q, s_u).
    dz = np.concatenate([np.full(2 * r, s_q), s_u])
    A = Az * dz[:, None] / dz[None, :]
    B = Bz * dz[:, None] / s_u[None, :]
    return A, B, clipped


def _eig_desc(G: Array) -> tuple[Array, Array]:
    w, V = np.linalg.eigh((G + G.T) / 2)
    order = np.argsort(w)[::-1]
    return np.clip(w[order], 0.0, None), V[:, order]


def dmdc_from_gram(gram: ArrayLike, U: ArrayLike, Y: ArrayLike, cur: ArrayLike,
                   nxt: ArrayLike, *, r: int, p: int | None = None,
                   rcond: float = 1e-7) -> dict[str, Array]:
    """DMDc by the method of snapshots, from the Gram matrix of the (scaled, centred) states.

    For out-of-core data: ``gram = Xᵀ X`` with ``X`` the ``(n, K)`` matrix of *all* centred
    (and scaled) snapshots of all episodes side by side can be accumulated row block by row
    block; ``cur``/``nxt`` index the columns forming the pairs ``(q_k, q_{k+1})``. Nothing of
    size ``n`` is formed; the POD basis is returned as coefficients, :math:`\\hat U = X_{nxt}
    W` with ``W = basis_coef``. Accuracy: the Gram squares the condition number, so singular
    values below about ``sqrt(eps) σ_1`` are lost (``rcond`` defaults to 1e-7 for that reason).

    Parameters
    ----------
    gram : ndarray, shape (K, K)
        ``Xᵀ X`` of the scaled, centred snapshots.
    U : ndarray, shape (m, K)
        Scaled inputs, aligned with the columns of ``X``.
    Y : ndarray, shape (q, K)
        Output deviations ``Y - y_ref`` (any scaling), aligned with ``X``.
    cur, nxt : ndarray of int, shape (K',)
        Columns of the pairs: ``q_k = X[:, cur]``, ``q_{k+1} = X[:, nxt]``.
    r, p : int
        Truncations of ``Q'`` and ``Ω`` (``p`` defaults to ``r + m``).

    Returns
    -------
    dict with ``A (r, r)``, ``B (r, m)`` (in the scaled input units), ``E (q, r)`` (reduced
    output fit), ``basis_coef (K', r)``, ``s_omega (p,)``, ``s_qp (r,)``.
    """
    Gm = np.asarray(gram, dtype=np.float64)
    U = np.asarray(U, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    cur = np.asarray(cur, dtype=np.intp)
    nxt = np.asarray(nxt, dtype=np.intp)
    m = U.shape[0]
    Uc = U[:, cur]
    w_om, V_om = _eig_desc(Gm[np.ix_(cur, cur)] + Uc.T @ Uc)
    w_qp, V_qp = _eig_desc(Gm[np.ix_(nxt, nxt)])
    s_om, s_qp = np.sqrt(w_om), np.sqrt(w_qp)
    if s_qp[0] <= 0:
        raise DimensionError('the shifted snapshots are all zero; nothing to reduce.')
    if not 1 <= r <= int(np.sum(s_qp > rcond * s_qp[0])):
        raise ConfigError(f'r={r} exceeds the numerical rank of the shifted snapshots.')
    p = r + m if p is None else int(p)
    p = min(p, int(np.sum(s_om > rcond * s_om[0])))
    Vt_om, Vh = V_om[:, :p], V_qp[:, :r]
    s_t, s_h = s_om[:p], s_qp[:r]
    G = s_h[:, None] * (Vh.T @ Vt_om)                       # Ûᵀ Q' Ṽ = Σ̂ V̂ᵀ Ṽ
    U1_Uhat = (Vt_om.T @ Gm[np.ix_(cur, nxt)] @ Vh) / np.outer(s_t, s_h)
    U2 = (Uc @ Vt_om) / s_t[None, :]
    A, B = dmdc_reduced_operators(G, s_t, U1_Uhat, U2)
    W = Vh / s_h[None, :]
    Xr = W.T @ Gm[nxt, :]                                   # Ûᵀ X, shape (r, K)
    E = np.linalg.lstsq(Xr.T, Y.T, rcond=None)[0].T
    return {'A': A, 'B': B, 'E': E, 'basis_coef': W, 's_omega': s_t, 's_qp': s_h}


def _as_episodes(episodes: Episode | Sequence[Episode]) -> list[Episode]:
    eps = [episodes] if isinstance(episodes, Episode) else list(episodes)
    if not eps:
        raise DimensionError('no episodes given: DMDc needs at least one episode with Q.')
    for ep in eps:
        if not isinstance(ep, Episode):
            raise DimensionError(f'expected Episode objects; got {type(ep).__name__}.')
        if ep.Q is None:
            raise DimensionError(
                f'episode {ep.name!r} has no state snapshots Q; DMDc needs full states '
                '(use ERA/OKID for input/output data only).')
        if ep.n_samples < 2:
            raise DimensionError(f'episode {ep.name!r} has fewer than 2 samples: no pairs.')
    return eps


class DMDc:
    """Dynamic mode decomposition with control (learner).

    Parameters
    ----------
    r : int, optional
        Truncation of the SVD of the shifted snapshots ``Q'`` (ROM dimension). ``None``:
        smallest ``r`` capturing ``energy`` of :math:`\\sum \\hat\\sigma_i^2`.
    p : int, optional
        Truncation of the SVD of ``Ω = [Q; U]``. ``None``: ``r + m``. Always capped at the
        numerical rank of ``Ω`` (singular values above ``rcond · σ_1``).
    energy : float
        Energy fraction used when ``r`` is ``None``.
    output_fit : {'reduced', 'paper'}
        How the output operator is fitted (module docstring).
    rcond : float
        Relative threshold below which singular values count as zero.
    variant : {'paper', 'stable'}
        ``'paper'`` (default): the formulation above, unchanged. ``'stable'``: one lag of
        states and inputs, ``x̃_{k+1} = A₁ x̃_k + A₂ x̃_{k-1} + B₀ u_k + B₁ u_{k-1}`` by least
        squares on the same POD coordinates (the exact form of a sampled linear second-order
        system with held inputs, which positions alone cannot represent: DMDc on positions
        of a second-order body is marginally unstable at most ``r``), then every eigenvalue
        of the companion matrix outside ``|z| ≤ max_spectral_radius`` pulled radially onto
        that circle (:func:`clip_spectral_radius`) and ``B₀, B₁`` refitted. The model state
        is ``[x̃_k; x̃_{k-1}; u_{k-1}]`` (``2 r + m`` states, ``C = [Ẽ, 0, 0]``);
        ``metadata['r']`` is the basis size ``r``.
    max_spectral_radius : float, optional
        Bound of the ``'stable'`` variant; default ``exp(-dt / (10 T))`` with ``T`` the
        longest training episode: no mode of the ROM has a decay time longer than ten times
        the time the data cover (such a mode is not identified by the data; on a nonlinear
        body the lagged regression otherwise puts modes on or outside the unit circle).

    Attributes
    ----------
    model_ : DiscreteModel
        The ROM (``method='dmdc'``, ``D = 0``), states ``Ûᵀ (q - q_ref)``.
    basis_ : ndarray, shape (n, r)
        :math:`\\hat U` of the model.
    q_ref_ : ndarray, shape (n,)
    y_ref_ : ndarray, shape (p_out,)
    singular_values_omega_, singular_values_qp_ : ndarray
        All singular values of the scaled ``Ω`` and of ``Q'``.
    input_scale_ : ndarray, shape (m,)
    state_scale_ : float
    fit_time_ : float
        Seconds spent in ``fit``.

    Examples
    --------
    >>> model = DMDc(r=12).fit(episodes).model_            # doctest: +SKIP
    >>> models = {r: DMDc(r=2).fit(episodes).model_for(r) for r in (2, 4, 8)}  # doctest: +SKIP

    :meth:`model_for` rebuilds the ROM for another ``(r, p)`` from the stored SVD factors,
    without touching the snapshots again.
    """

    def __init__(self, r: int | None = None, p: int | None = None, *, energy: float = 0.95,
                 output_fit: str = 'reduced', rcond: float = 1e-10, variant: str = 'paper',
                 max_spectral_radius: float | None = None) -> None:
        self.r = r
        self.variant = variant
        self.max_spectral_radius = max_spectral_radius
        self.p = p
        self.energy = energy
        self.output_fit = output_fit
        self.rcond = rcond

    # ---------------------------------------------------------------------------------
    def fit(self, episodes: Episode | Sequence[Episode], q_ref: ArrayLike | None = None,
            y_ref: ArrayLike | None = None, *, input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> DMDc:
        """Learn the DMDc ROM from one or several episodes.

        Parameters
        ----------
        episodes : Episode or sequence of Episode
            Each with ``Q (n, k_i)``, ``U (m, k_i)``, ``Y (p, k_i)`` and uniform time steps
            (the same ``dt`` for all). Pairs ``(q_j, q_{j+1})`` are formed inside each episode.
        q_ref : ndarray, shape (n,), optional
            Reference configuration; default the first snapshot of the first episode.
        y_ref : ndarray, shape (p,), optional
            Output reference; default the first output of the first episode.
        input_names, output_names, input_units, output_units, metadata
            Passed to the model (``metadata`` is merged with the fit diagnostics).

        Returns
        -------
        self
        """
        t0 = time.perf_counter()
        if self.output_fit not in ('reduced', 'paper'):
            raise ConfigError(f"output_fit must be 'reduced' or 'paper'; got {self.output_fit!r}.")
        if self.variant not in ('paper', 'stable'):
            raise ConfigError(f"variant must be 'paper' or 'stable'; got {self.variant!r}.")
        if self.max_spectral_radius is not None:
            rho = float(self.max_spectral_radius)
            if not (np.isfinite(rho) and rho > 0):
                raise ConfigError(f'max_spectral_radius must be > 0; got '
                                  f'{self.max_spectral_radius!r}.')
        eps = _as_episodes(episodes)
        n = int(eps[0].Q.shape[0])
        m = eps[0].U.shape[0]
        p_out = eps[0].Y.shape[0]
        dts = []
        for ep in eps:
            if ep.Q.shape[0] != n or ep.U.shape[0] != m or ep.Y.shape[0] != p_out:
                raise DimensionError(
                    f'episode {ep.name!r} has (n, m, p) = ({ep.Q.shape[0]}, {ep.U.shape[0]}, '
                    f'{ep.Y.shape[0]}); the first episode has ({n}, {m}, {p_out}).')
            if not ep.is_uniform():
                raise DimensionError(f'episode {ep.name!r} is not uniformly sampled.')
            dts.append(ep.dt)
        dt = float(dts[0])
        if any(abs(d - dt) > 1e-6 * dt for d in dts):
            raise DimensionError(f'episodes have different sample times {dts}; resample first.')
        qs = [np.asarray(ep.Q[:, :], dtype=np.float64) for ep in eps]
        q_ref = qs[0][:, 0].copy() if q_ref is None else as_signal(
            'q_ref', np.reshape(q_ref, (-1, 1)), rows=n)[:, 0]
        y_ref = eps[0].Y[:, 0].copy() if y_ref is None else as_signal(
            'y_ref', np.reshape(y_ref, (-1, 1)), rows=p_out)[:, 0]
        Qc = [q - q_ref[:, None] for q in qs]
        for ep, q in zip(eps, Qc):
            check_finite(f'Q of episode {ep.name!r}', q)
            check_finite(f'U of episode {ep.name!r}', ep.U)
            check_finite(f'Y of episode {ep.name!r}', ep.Y)
        X = np.concatenate([q[:, :-1] for q in Qc], axis=1)         # Q   (n, K')
        Xp = np.concatenate([q[:, 1:] for q in Qc], axis=1)         # Q'  (n, K')
        Uc = np.concatenate([ep.U[:, :-1] for ep in eps], axis=1)   # U   (m, K')
        Q_all = np.concatenate(Qc, axis=1)
        Y_all = np.concatenate([ep.Y for ep in eps], axis=1) - y_ref[:, None]

        s_q = float(channel_scale(X, per_channel=False)[0])
        s_u = channel_scale(Uc)
        Omega = np.concatenate([X / s_q, Uc / s_u[:, None]], axis=0)
        Ut, st, Vtt = np.linalg.svd(Omega, full_matrices=False)
        Uh, sh, Vht = np.linalg.svd(Xp, full_matrices=False)
        if sh.size == 0 or sh[0] <= 0:
            raise DimensionError('the states never move away from q_ref: nothing to learn.')
        rank_h = int(np.sum(sh > self.rcond * sh[0]))
        rank_t = int(np.sum(st > self.rcond * st[0])) if st.size and st[0] > 0 else 0
        if rank_t == 0:
            raise DimensionError('Omega = [Q; U] is zero: no data to learn from.')

        self.q_ref_ = q_ref
        self.y_ref_ = y_ref
        self.state_scale_ = s_q
        self.input_scale_ = s_u
        self.singular_values_omega_ = st
        self.singular_values_qp_ = sh
        self.n_pairs_ = int(X.shape[1])
        self.dt_ = dt
        # Factors kept for model_for(): all small (at most rank x rank, or rank x K).
        self._Uh = Uh[:, :rank_h]
        self._st, self._sh = st[:rank_t], sh[:rank_h]
        self._U1h = Ut[:n, :rank_t].T @ Uh[:, :rank_h]                  # Ũ1ᵀ Û   (pt, ph)
        self._U2 = Ut[n:, :rank_t]                                      # Ũ2      (m, pt)
        self._G = sh[:rank_h, None] * (Vht[:rank_h] @ Vtt[:rank_t].T)    # ÛᵀQ'Ṽ  (ph, pt)
        self._Xr = Uh[:, :rank_h].T @ Q_all                             # ÛᵀQ    (ph, K)
        self._Yd = Y_all
        if self.variant == 'stable':
            self._lagdata = [(Uh[:, :rank_h].T @ q, ep.U) for q, ep in zip(Qc, eps)]
            t_long = max(q.shape[1] for q in Qc) * dt
            self.rho_max_ = (float(np.exp(-dt / (10.0 * t_long)))
                             if self.max_spectral_radius is None
                             else float(self.max_spectral_radius))
        self._Q_all = Q_all if self.output_fit == 'paper' else None
        self._model_kwargs = dict(input_names=input_names, output_names=output_names,
                                  input_units=input_units, output_units=output_units)
        self._metadata = dict(metadata or {})
        self._metadata.setdefault('envelope', training_envelope(eps, y_ref))
        self._episodes = [ep.name for ep in eps]
        self.fit_time_ = time.perf_counter() - t0
        self.model_ = self.model_for(self.r, self.p)
        self.fit_time_ = time.perf_counter() - t0
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, '_G'):
            raise NotFittedError('this DMDc is not fitted yet; call fit(episodes) first.')

    def model_for(self, r: int | None = None, p: int | None = None) -> DiscreteModel:
        """Build the ROM for truncations ``(r, p)`` from the stored factors.

        Parameters
        ----------
        r, p : int, optional
            As in the constructor (``None``: by ``energy`` / ``r + m``).
        """
        self._check_fitted()
        t0 = time.perf_counter()
        sh = self.singular_values_qp_
        if r is None:
            if not 0.0 < self.energy <= 1.0:
                raise ConfigError(f'energy must be in (0, 1]; got {self.energy!r}.')
            cum = np.cumsum(sh ** 2) / np.sum(sh ** 2)
            r = int(min(np.searchsorted(cum, self.energy - 1e-12) + 1, self._sh.size))
        r = int(r)
        if not 1 <= r <= self._sh.size:
            raise ConfigError(
                f'r must be between 1 and {self._sh.size} (numerical rank of the shifted '
                f"snapshots Q'); got {r}.")
        m = self._U2.shape[0]
        p_req = r + m if p is None else int(p)
        if p_req < 1:
            raise ConfigError(f'p must be positive; got {p_req}.')
        p_used = min(p_req, self._st.size)
        A, Bs = dmdc_reduced_operators(self._G[:r, :p_used], self._st[:p_used],
                                       self._U1h[:p_used, :r], self._U2[:, :p_used])
        # Undo the scaling. The regression is Q' ≈ Q' Ω_s⁺ Ω_s with Ω_s = [Q/s_q; U/s_u], so
        # Ûᵀq' = Ûᵀ Q' Ṽ Σ̃⁻¹ (Ũ1ᵀ Û x / s_q + Ũ2ᵀ diag(1/s_u) u) with x = Ûᵀ(q - q_ref):
        # A = A_s / s_q and B = B_s diag(1/s_u). The states stay in physical units.
        A = A / self.state_scale_
        B = Bs / self.input_scale_[None, :]
        clipped = 0
        if self.variant == 'stable':
            A, B, clipped = _lag_model(self._lagdata, r, self.state_scale_, self.input_scale_,
                                       self.rho_max_, self.rcond)
        if self.output_fit == 'paper':
            # E_approx Û = Yd Q⁺ Û with Q⁺Û the minimum-norm solution of Q Z = Û.
            assert self._Q_all is not None
            Z = np.linalg.lstsq(self._Q_all, self._Uh[:, :r], rcond=None)[0]
            E = self._Yd @ Z
        else:
            E = np.linalg.lstsq(self._Xr[:r].T, self._Yd.T, rcond=None)[0].T
        Yhat = E @ self._Xr[:r]
        train_err = float(np.linalg.norm(self._Yd - Yhat) / max(np.linalg.norm(self._Yd), 1e-300))
        ev = np.linalg.eigvals(A)
        meta = dict(self._metadata)
        meta.update({
            'learner': 'DMDc',
            'r': r, 'p': p_used, 'p_requested': p_req,
            'output_fit': self.output_fit,
            'variant': self.variant,
            'max_spectral_radius': self.rho_max_ if self.variant == 'stable' else None,
            'eigenvalues_clipped': int(clipped),
            'rcond': self.rcond,
            'episodes': self._episodes,
            'n_pairs': self.n_pairs_,
            'state_scale': self.state_scale_,
            'input_scale': self.input_scale_.tolist(),
            'singular_values_omega': self.singular_values_omega_[:200].tolist(),
            'singular_values_qp': self.singular_values_qp_[:200].tolist(),
            'energy_captured': float(np.sum(sh[:r] ** 2) / np.sum(sh ** 2)),
            'output_projection_error': train_err,
            'eigenvalues_real': ev.real.tolist(),
            'eigenvalues_imag': ev.imag.tolist(),
            'stability_margin': float(1.0 - np.max(np.abs(ev))),
            'fit_time_s': float(self.fit_time_ + time.perf_counter() - t0),
        })
        Cout = E if self.variant == 'paper' else np.hstack([E, np.zeros((E.shape[0],
                                                                         A.shape[0] - r))])
        model = DiscreteModel(A, B, Cout, None, dt=self.dt_, method='dmdc', y_ref=self.y_ref_,
                              metadata=meta, **self._model_kwargs)
        self.basis_ = self._Uh[:, :r]
        return model

    def reduce(self, Q: ArrayLike) -> Array:
        """Reduced state ``Ûᵀ (q - q_ref)`` of absolute snapshots ``Q (n, k)``."""
        self._check_fitted()
        Q = as_signal('Q', Q, rows=self.q_ref_.size)
        return self.basis_.T @ (Q - self.q_ref_[:, None])
