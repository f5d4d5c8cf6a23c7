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

Reduced data: the learner fits on the coordinates of the centred snapshots in any
orthonormal basis ``W`` (:class:`~soft_rom.reduce.data.ReducedData`): with ``X = W Z`` the SVDs
of ``Ω = diag(W, I) [Z; U]`` and of ``Q' = W Z'`` are those of ``[Z; U]`` and ``Z'`` with left
factors multiplied by ``W``, and every operator is unchanged by that orthonormal factor. In
memory the coordinates are the centred snapshots themselves (``W = I``); streamed, the POD
coordinates (:mod:`soft_rom.reduce.streaming`). The operators come from the small factors
(:func:`dmdc_reduced_operators`).
"""

from __future__ import annotations

from collections.abc import Sequence
import time
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.basis import snapshot_range
from soft_rom.data import as_signal, Episode
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.learners.dmdc_stable import clip_spectral_radius, lag_model, select_lag_ridge
from soft_rom.models import DiscreteModel
from soft_rom.reduce import InMemoryPOD, ReducedData, training_data

__all__ = ['DMDc', 'channel_scale', 'clip_spectral_radius', 'dmdc_reduced_operators']

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
        of a second-order body is marginally unstable at most ``r``), regularized by
        ``lag_ridge``, then every eigenvalue of the companion matrix outside
        ``|z| ≤ max_spectral_radius`` pulled radially onto that circle
        (:func:`~soft_rom.learners.dmdc_stable.clip_spectral_radius`) and ``B₀, B₁``
        refitted. The model state is ``[x̃_k; x̃_{k-1}; u_{k-1}]`` (``2 r + m`` states,
        ``C = [Ẽ, 0, 0]``); ``metadata['r']`` is the basis size ``r``.
    max_spectral_radius : float, optional
        Bound of the ``'stable'`` variant; default ``exp(-dt / (10 T))`` with ``T`` the
        longest training episode: no mode of the ROM has a decay time longer than ten times
        the time the data cover (such a mode is not identified by the data; on a nonlinear
        body the lagged regression otherwise puts modes on or outside the unit circle).
    lag_ridge : float or 'auto'
        Relative Tikhonov weight of the ``'stable'`` variant's lag regression; ``'auto'``
        (default): chosen for each ``r`` on held-out tails of the training episodes
        (:func:`~soft_rom.learners.dmdc_stable.select_lag_ridge`; ``metadata['lag_ridge']``
        and ``metadata['lag_ridge_table']``).

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
                 max_spectral_radius: float | None = None,
                 lag_ridge: float | str = 'auto') -> None:
        self.r = r
        self.lag_ridge = lag_ridge
        self.variant = variant
        self.max_spectral_radius = max_spectral_radius
        self.p = p
        self.energy = energy
        self.output_fit = output_fit
        self.rcond = rcond

    #: What the learner needs from a reducer: coordinates in any orthonormal basis of the
    #: snapshots (in memory, the centred snapshots themselves: exactly the paper's SVDs).
    reduction: ClassVar[str] = 'identity'
    #: The method name of its models and of ``soft-rom fit --method``.
    method: ClassVar[str] = 'dmdc'

    def coordinates_needed(self, r_max: int | None, n_inputs: int) -> int | None:
        """Coordinates a (streaming) reducer must keep for models up to ``r_max``."""
        if r_max is None:
            return None
        return max(int(r_max), int(self.p) if self.p is not None else int(r_max) + n_inputs)

    # ---------------------------------------------------------------------------------
    def fit(self, data: ReducedData | Episode | Sequence[Episode],
            q_ref: ArrayLike | None = None, y_ref: ArrayLike | None = None, *,
            input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> DMDc:
        """Learn the DMDc ROM from reduced data, or from one or several episodes.

        Parameters
        ----------
        data : ReducedData, Episode or sequence of Episode
            Coordinates of the centred snapshots in an orthonormal basis
            (:class:`~soft_rom.reduce.data.ReducedData`, ``basis`` ``'identity'`` or
            ``'pod'``), or episodes with ``Q (n, k_i)``, ``U (m, k_i)``, ``Y (p, k_i)`` and
            uniform time steps (the same ``dt`` for all), used as they are (the identity
            basis). Pairs ``(q_j, q_{j+1})`` are formed inside each episode.
        q_ref : ndarray, shape (n,), optional
            Episodes only: reference configuration; default the first snapshot.
        y_ref : ndarray, shape (p,), optional
            Episodes only: output reference; default the first output of the first episode.
        input_names, output_names, input_units, output_units, metadata
            Passed to the model (``metadata`` is merged with the fit diagnostics).

        Returns
        -------
        self
        """
        t0 = time.perf_counter()
        self._check_options()
        if not isinstance(data, ReducedData):
            td = training_data(data, q_ref, y_ref, names=dict(
                input_names=input_names, output_names=output_names, input_units=input_units,
                output_units=output_units))
            for ep in td.episodes:
                if ep.n_samples < 2:
                    raise DimensionError(f'episode {ep.name!r} has fewer than 2 samples: no '
                                         'pairs.')
            data = InMemoryPOD().reduce(td, basis='identity', what='DMDc')
        if data.basis not in ('identity', 'pod') or data.coordinates is None:
            raise ConfigError(f'DMDc fits on snapshot coordinates; these reduced data have '
                              f'basis {data.basis!r}.')
        self._factorize(data)
        self._model_kwargs = data.model_names()
        self._metadata = {**data.metadata, **dict(metadata or {})}
        self._metadata.setdefault('envelope', training_envelope(zip(data.U, data.Y),
                                                                data.y_ref, data.dt))
        self._episodes = list(data.names)
        self.fit_time_ = time.perf_counter() - t0
        self.model_ = self.model_for(self.r, self.p)
        self.fit_time_ = time.perf_counter() - t0
        return self

    def _check_options(self) -> None:
        if self.output_fit not in ('reduced', 'paper'):
            raise ConfigError(f"output_fit must be 'reduced' or 'paper'; got {self.output_fit!r}.")
        if self.variant not in ('paper', 'stable'):
            raise ConfigError(f"--dmdc-variant must be 'paper' or 'stable'; got {self.variant!r}.")
        if self.max_spectral_radius is not None:
            rho = float(self.max_spectral_radius)
            if not (np.isfinite(rho) and rho > 0):
                raise ConfigError(f'max_spectral_radius must be > 0; got '
                                  f'{self.max_spectral_radius!r}.')

    def _factorize(self, data: ReducedData) -> None:
        """The two SVDs (paper sec. 2.3) on the coordinates; every small factor is kept."""
        dt = data.dt
        Qc = list(data.coordinates or ())
        n_rows, pairs_sq = int(data.n_states or Qc[0].shape[0]), data.pairs_sq_norm
        Q_full = np.concatenate(Qc, axis=1) if self.output_fit == 'paper' else None
        # The centred snapshots themselves: their range first, to far below rcond, so that
        # the SVDs below are taken on a few hundred coordinates instead of n rows (the
        # operators are unchanged by the orthonormal factor, see the module docstring)
        W = snapshot_range(Qc, 1e-3 * self.rcond) if data.basis == 'identity' else None
        if W is not None:
            n_rows, pairs_sq = Qc[0].shape[0], sum(float(np.vdot(q[:, :-1], q[:, :-1]))
                                                   for q in Qc)
            Qc = [W.T @ q for q in Qc]
        l = Qc[0].shape[0]
        X = np.concatenate([q[:, :-1] for q in Qc], axis=1)         # Q   (l, K')
        Xp = np.concatenate([q[:, 1:] for q in Qc], axis=1)         # Q'  (l, K')
        Uc = np.concatenate([u[:, :-1] for u in data.U], axis=1)    # U   (m, K')
        Q_all = np.concatenate(Qc, axis=1)
        Y_all = np.concatenate(data.Y, axis=1) - data.y_ref[:, None]
        if pairs_sq is None:                            # the states themselves: their RMS
            s_q = float(channel_scale(X, per_channel=False)[0])
        else:                                           # the RMS over the n full-order rows
            s_q = float(np.sqrt(pairs_sq / (n_rows * X.shape[1])))
            s_q = s_q if s_q > 0 else 1.0
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
        self.q_ref_ = data.q_ref
        self.y_ref_ = data.y_ref
        self.state_scale_ = s_q
        self.input_scale_ = s_u
        self.singular_values_omega_ = st
        self.singular_values_qp_ = sh
        self.n_pairs_ = int(X.shape[1])
        self.dt_ = dt
        # Factors kept for model_for(): all small (at most rank x rank, or rank x K).
        self._Uh = Uh[:, :rank_h] if W is None else W @ Uh[:, :rank_h]
        self._lift = data.lift
        self._st, self._sh = st[:rank_t], sh[:rank_h]
        self._U1h = Ut[:l, :rank_t].T @ Uh[:, :rank_h]                  # Ũ1ᵀ Û   (pt, ph)
        self._U2 = Ut[l:, :rank_t]                                      # Ũ2      (m, pt)
        self._G = sh[:rank_h, None] * (Vht[:rank_h] @ Vtt[:rank_t].T)    # ÛᵀQ'Ṽ  (ph, pt)
        self._Xr = Uh[:, :rank_h].T @ Q_all                             # ÛᵀQ    (ph, K)
        self._Yd = Y_all
        if self.variant == 'stable':
            self._lagdata = [(Uh[:, :rank_h].T @ q, u, y - data.y_ref[:, None])
                             for q, u, y in zip(Qc, data.U, data.Y)]
            t_long = max(q.shape[1] for q in Qc) * dt
            self.rho_max_ = (float(np.exp(-dt / (10.0 * t_long)))
                             if self.max_spectral_radius is None
                             else float(self.max_spectral_radius))
        self._Q_all = Q_full

    def _check_fitted(self) -> None:
        if not hasattr(self, '_G'):
            raise NotFittedError('this DMDc is not fitted yet; call fit(episodes) first.')

    def model_for(self, r: int | None = None, p: int | None = None, *,
                  variant: str | None = None) -> DiscreteModel:
        """Build the ROM for truncations ``(r, p)`` from the stored factors.

        Parameters
        ----------
        r, p : int, optional
            As in the constructor (``None``: by ``energy`` / the learner's ``p``, else
            ``r + m``).
        variant : {'paper', 'stable'}, optional
            Default the learner's; ``'paper'`` from a ``'stable'`` fit gives the paper's model
            of the same SVDs (to compare the two).
        """
        self._check_fitted()
        variant = self.variant if variant is None else variant
        if variant not in ('paper', 'stable') or (variant == 'stable'
                                                  and not hasattr(self, '_lagdata')):
            raise ConfigError(f"a DMDc variant must be 'paper', or 'stable' for a learner fitted "
                              f'as the stable variant; got {variant!r}.')
        t0 = time.perf_counter()
        r, p_req, p_used = self._orders(r, self.p if p is None else p)
        A, Bs = dmdc_reduced_operators(self._G[:r, :p_used], self._st[:p_used],
                                       self._U1h[:p_used, :r], self._U2[:, :p_used])
        # Undo the scaling. The regression is Q' ≈ Q' Ω_s⁺ Ω_s with Ω_s = [Q/s_q; U/s_u], so
        # Ûᵀq' = Ûᵀ Q' Ṽ Σ̃⁻¹ (Ũ1ᵀ Û x / s_q + Ũ2ᵀ diag(1/s_u) u) with x = Ûᵀ(q - q_ref):
        # A = A_s / s_q and B = B_s diag(1/s_u). The states stay in physical units.
        A = A / self.state_scale_
        B = Bs / self.input_scale_[None, :]
        if self.output_fit == 'paper':
            # E_approx Û = Yd Q⁺ Û with Q⁺Û the minimum-norm solution of Q Z = Û.
            assert self._Q_all is not None
            Z = np.linalg.lstsq(self._Q_all, self._Uh[:, :r], rcond=None)[0]
            E = self._Yd @ Z
        else:
            E = np.linalg.lstsq(self._Xr[:r].T, self._Yd.T, rcond=None)[0].T
        clipped = 0
        lag: dict[str, Any] = {}
        if variant == 'stable':
            A, B, clipped, lag = self._stable(r, E)
        Yhat = E @ self._Xr[:r]
        scale = max(float(np.linalg.norm(self._Yd)), 1e-300)
        train_err = float(np.linalg.norm(self._Yd - Yhat)) / scale
        meta = self._model_metadata(A, r, p_req, p_used, variant, clipped, train_err, t0)
        meta.update(lag)
        Cout = E if variant == 'paper' else np.hstack([E, np.zeros((E.shape[0],
                                                                         A.shape[0] - r))])
        model = DiscreteModel(A, B, Cout, None, dt=self.dt_, method='dmdc', y_ref=self.y_ref_,
                              metadata=meta, **self._model_kwargs)
        self.basis_ = self._lift(self._Uh[:, :r])
        return model

    def _stable(self, r: int, E: Array) -> tuple[Array, Array, int, dict[str, Any]]:
        """The stable variant's ``A, B`` of order ``r``, its ridge chosen (or given)."""
        args = (r, self.state_scale_, self.input_scale_, self.rho_max_, self.rcond)
        table = None
        if isinstance(self.lag_ridge, str):
            if self.lag_ridge != 'auto':
                raise ConfigError(f"the lag ridge must be a number >= 0 or 'auto'; got "
                                  f'{self.lag_ridge!r}.')
            ridge, table = select_lag_ridge(self._lagdata, *args, E)
        else:
            ridge = float(self.lag_ridge)
        A, B, clipped = lag_model(self._lagdata, *args, ridge)
        return A, B, clipped, {'lag_ridge': ridge, 'lag_ridge_table': table}

    def _orders(self, r: int | None, p: int | None) -> tuple[int, int, int]:
        """``(r, p asked, p used)``: ``r`` by energy when not given, ``p`` capped at the rank."""
        sh = self.singular_values_qp_
        if r is None:
            if not 0.0 < self.energy <= 1.0:
                raise ConfigError(f'--energy must be in (0, 1]; got {self.energy!r}.')
            cum = np.cumsum(sh ** 2) / np.sum(sh ** 2)
            r = int(min(np.searchsorted(cum, self.energy - 1e-12) + 1, self._sh.size))
        r = int(r)
        if not 1 <= r <= self._sh.size:
            raise ConfigError(
                f'--r must be between 1 and {self._sh.size} for DMDc here (the numerical rank '
                f"of the shifted snapshots Q'); got {r}.")
        m = self._U2.shape[0]
        p_req = r + m if p is None else int(p)
        if p_req < 1:
            raise ConfigError(f'--p must be positive; got {p_req}.')
        return r, p_req, min(p_req, self._st.size)

    def _model_metadata(self, A: Array, r: int, p_req: int, p_used: int, variant: str,
                        clipped: int, train_err: float, t0: float) -> dict[str, Any]:
        """The fit diagnostics stored in the model of order ``r``."""
        sh = self.singular_values_qp_
        ev = np.linalg.eigvals(A)
        meta = dict(self._metadata)
        meta.update({
            'learner': 'DMDc',
            'r': r, 'p': p_used, 'p_requested': p_req,
            'output_fit': self.output_fit,
            'variant': variant,
            'max_spectral_radius': self.rho_max_ if variant == 'stable' else None,
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
        return meta

    def reduce(self, Q: ArrayLike) -> Array:
        """Reduced state ``Ûᵀ (q - q_ref)`` of absolute snapshots ``Q (n, k)``."""
        self._check_fitted()
        if self.basis_ is None or self.q_ref_ is None:
            raise NotFittedError('this DMDc was fitted on coordinates whose modes were not '
                                 'kept (streamed): it cannot reduce full states.')
        Q = as_signal('Q', Q, rows=self.q_ref_.size)
        return self.basis_.T @ (Q - self.q_ref_[:, None])
