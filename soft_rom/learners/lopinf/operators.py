"""The operator fit of LOpInf on scaled reduced data: linear or cubic forces, mass, refinement.

:func:`scaled_derivatives` makes the scaled coordinates and their time derivatives (per
episode, edges trimmed); :func:`solve_operators` fits ``K, C, B`` (and the cubic potential's
``G, H``) to them: the mass matrix learned first when asked
(:mod:`soft_rom.learners.lopinf.mass`), then the SPD-constrained fit with its damping margin
and Tikhonov weight (:mod:`soft_rom.learners.lopinf.margins`), then the refinement by the
simulation error (:mod:`soft_rom.learners.lopinf.refine`), or the cubic fit
(:mod:`soft_rom.learners.lopinf.cubic`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.ddt import DerivativeEstimator, FiniteDifference
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.learners.lopinf import margins
from soft_rom.learners.lopinf.solvers import OperatorSolver

__all__ = ['Operators', 'ScaledData', 'half_width', 'scaled_derivatives', 'solve_operators']

Array = NDArray[np.float64]


def _rms(X: Array, axis: int | None = None) -> Array:
    s = np.atleast_1d(np.sqrt(np.mean(X ** 2, axis=axis))) if X.size else np.ones(1)
    return np.where(s > 0, s, 1.0)


def half_width(estimator: DerivativeEstimator) -> int:
    """Samples an estimator trims at each end of an episode."""
    return int(getattr(estimator, 'half_width', getattr(estimator, 'order', 8) // 2))


def _episodes(estimator: DerivativeEstimator, Qs: Sequence[Array], dt: float,
              others: Sequence[Sequence[Array]]) -> tuple[Array, Array, Array, list[Array]]:
    if isinstance(estimator, FiniteDifference):
        return estimator.episodes(Qs, dt, others)
    parts = [estimator.derivatives(q, dt) for q in Qs]
    stacked = [np.concatenate([pp[j] for pp in parts], axis=1) for j in range(3)]
    trimmed = [np.concatenate([estimator.trim(x) for x in sig], axis=1) for sig in others]
    return stacked[0], stacked[1], stacked[2], trimmed


@dataclass
class ScaledData:
    """Scaled coordinates and derivatives (trimmed), and the scales (unit invariance).

    ``Qs, Qd, Qdd (r, K')`` and ``Us (m, K')``: the samples the derivative estimator keeps;
    ``all_q (r, K)``: every coordinate sample (unscaled); ``s_q`` the scalar state scale;
    ``s_u (m,)`` the input scales; ``lengths``: samples kept per episode.
    """

    Qs: Array
    Qd: Array
    Qdd: Array
    Us: Array
    all_q: Array
    s_q: float
    s_u: Array
    lengths: list[int]


def scaled_derivatives(Qhat: Sequence[Array], U: Sequence[Array], dt: float,
                       estimator: DerivativeEstimator, scale: bool,
                       names: Sequence[str]) -> ScaledData:
    """Divide by the RMS scales and differentiate every episode (edges trimmed)."""
    m = U[0].shape[0]
    all_q = np.concatenate(Qhat, axis=1)
    all_u = np.concatenate(U, axis=1)
    if not np.any(all_q):
        raise DimensionError('the reduced states are identically zero: the body never '
                             'moved away from q_ref, so there is nothing to learn.')
    s_q = float(_rms(all_q)[0]) if scale else 1.0
    s_u = _rms(all_u, axis=1) if scale else np.ones(m)
    need = 2 * half_width(estimator)
    too_short = [i for i, q in enumerate(Qhat) if q.shape[1] <= need]
    if too_short:
        label = ', '.join(f'{names[i]!r}' if i < len(names) else str(i) for i in too_short)
        counts = ', '.join(str(Qhat[i].shape[1]) for i in too_short)
        raise DimensionError(
            f'episode(s) {label} ({counts} samples) too short for the derivative '
            f'estimator --ddt {estimator}, which needs more than {need} samples per episode; '
            'drop them or use a shorter estimator (soft-rom fit --ddt fd2, or '
            'savgol:WINDOW with a smaller window).')
    Qs, Qd, Qdd, (Us,) = _episodes(estimator, [q / s_q for q in Qhat], dt,
                                   [[u / s_u[:, None] for u in U]])
    return ScaledData(Qs, Qd, Qdd, Us, all_q, s_q, s_u,
                      [q.shape[1] - 2 * half_width(estimator) for q in Qhat])


@dataclass
class Operators:
    """The fitted operators in scaled units (``B`` scaled), and how they were found."""

    K: Array
    C: Array
    Bs: Array
    info: dict[str, Any]
    reg: dict[str, Any]
    residual: float
    refined: dict[str, Any] | None
    mass_factor: Array | None
    mass_info: dict[str, Any] | None
    nonlinear: dict[str, Array] | None


@dataclass(frozen=True)
class FitSettings:
    """The learner's settings the operator fit uses (see :class:`~.learner.LOpInf`)."""

    eps: float
    forces: str
    mass: str
    refine: str
    cubic_options: dict[str, Any] | None
    min_damping_ratio: float
    damping_frequency: float | None
    regularization: float | str | None
    reg_grid: Sequence[float]


def check_settings(cfg: FitSettings) -> None:
    """Refuse settings that do not go together (before any work)."""
    if cfg.forces not in ('linear', 'cubic'):
        raise ConfigError(f"--forces must be 'linear' or 'cubic'; got {cfg.forces!r}.")
    if cfg.mass not in ('identity', 'learned') or (cfg.mass == 'learned'
                                                   and cfg.forces != 'linear'):
        raise ConfigError(f"--mass must be 'identity' or 'learned' (with --forces linear only); "
                          f'got {cfg.mass!r} with --forces {cfg.forces}.')
    if cfg.refine not in ('none', 'output-error') or (cfg.refine != 'none'
                                                      and cfg.forces != 'linear'):
        raise ConfigError(f"--refine must be 'none' or 'output-error' (with --forces linear "
                          f'only); got {cfg.refine!r} with --forces {cfg.forces}.')


def solve_operators(sd: ScaledData, Qhat: Sequence[Array], U: Sequence[Array], dt: float,
                    solver: OperatorSolver, cfg: FitSettings) -> Operators:
    """``K, C, B`` (scaled) for ``cfg``; ``sd`` is updated when a learned mass moves it.

    With a learned mass, the coordinates become ``z = Lᵀ q`` (``M = L Lᵀ``): ``sd.Qs``,
    ``sd.Qd``, ``sd.Qdd`` and ``sd.all_q`` are replaced by their images, so that the output
    operator is fitted in the model's coordinates.
    """
    check_settings(cfg)
    scaled_eps = [(np.asarray(q) / sd.s_q, np.asarray(u) / sd.s_u[:, None])
                  for q, u in zip(Qhat, U)]
    mass_factor = mass_info = None
    if cfg.mass == 'learned':
        from soft_rom.learners.lopinf.mass import solve_learned_mass
        msol, Lt = solve_learned_mass(sd.Qs, sd.Qd, sd.Qdd, sd.Us, eps=cfg.eps, dt=dt,
                                      episodes=scaled_eps)
        sd.Qs, sd.Qd, sd.Qdd, sd.all_q = Lt @ sd.Qs, Lt @ sd.Qd, Lt @ sd.Qdd, Lt @ sd.all_q
        mass_factor, mass_info = Lt, msol.info['mass']
    refined: dict[str, Any] | None = None
    nonlinear = None
    if cfg.forces == 'cubic':
        from soft_rom.learners.lopinf.cubic import fit_scaled
        sol, nonlinear = fit_scaled(sd.Qs, sd.Qd, sd.Qdd, sd.Us, sd.s_q, solver, cfg.eps,
                                    cfg.cubic_options)
        K, C, Bs = 0.5 * (sol.K + sol.K.T), 0.5 * (sol.C + sol.C.T), sol.B
        info: dict[str, Any] = dict(sol.info)
        reg: dict[str, Any] = {'mode': 'none', 'gamma': 0.0}
        residual = float(sol.info['objective'])
    else:
        K, C, Bs, info, reg = _constrained(solver, sd, dt, cfg)
        if cfg.refine == 'output-error':
            from soft_rom.learners.lopinf.refine import refine_output_error
            K, C, Bs, refined = refine_output_error(
                K, C, Bs, scaled_eps, dt, Lt=mass_factor, free_mass=mass_factor is not None,
                margin=info.get('margin'), eps=cfg.eps)
            Lt_new = refined.pop('mass_factor')
            if mass_factor is not None:   # the coordinates z = Lt q moved with it
                T = Lt_new @ np.linalg.inv(mass_factor)
                sd.Qs, sd.Qd, sd.Qdd, sd.all_q = T @ sd.Qs, T @ sd.Qd, T @ sd.Qdd, T @ sd.all_q
                mass_factor = Lt_new
        residual = float(np.linalg.norm(sd.Qdd + C @ sd.Qd + K @ sd.Qs - Bs @ sd.Us))
    return Operators(K, C, Bs, info, reg, residual, refined, mass_factor, mass_info, nonlinear)


def _constrained(solver: OperatorSolver, sd: ScaledData, dt: float, cfg: FitSettings
                 ) -> tuple[Array, Array, Array, dict[str, Any], dict[str, Any]]:
    """Operators with the damping margin and the (selected) Tikhonov weight."""
    kw: dict[str, Any] = dict(eps=cfg.eps, min_damping_ratio=float(cfg.min_damping_ratio),
                              frequency=cfg.damping_frequency)
    reg: dict[str, Any] = {'mode': 'none', 'gamma': 0.0}
    gamma = 0.0
    if isinstance(cfg.regularization, str):
        if cfg.regularization != 'auto':
            raise ConfigError(f"regularization must be a number >= 0, 'auto' or None; got "
                              f'{cfg.regularization!r}.')
        cuts = np.cumsum(sd.lengths)[:-1]
        parts = [np.split(x, cuts, axis=1) for x in (sd.Qs, sd.Qd, sd.Qdd, sd.Us)]

        def fit(q: list[Array], qd: list[Array], qdd: list[Array], u: list[Array],
                g: float) -> tuple[Array, Array, Array]:
            K_, C_, B_, _ = margins.constrained_solve(
                solver, np.hstack(q), np.hstack(qd), np.hstack(qdd), np.hstack(u),
                gamma=g, **kw)
            return K_, C_, B_

        gamma, table = margins.select_regularization(fit, parts[0], parts[1], parts[2],
                                                     parts[3], dt, grid=cfg.reg_grid)
        reg = {'mode': 'auto', 'gamma': gamma, 'candidates': table}
    elif cfg.regularization is not None:
        gamma = float(cfg.regularization)
        reg = {'mode': 'fixed', 'gamma': gamma}
    K, C, B, info = margins.constrained_solve(solver, sd.Qs, sd.Qd, sd.Qdd, sd.Us, gamma=gamma,
                                              **kw)
    reg['lambda'] = info.get('regularization', {}).get('lambda')
    return K, C, B, info, reg
