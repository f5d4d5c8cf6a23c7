"""LOpInf margins in the data's terms, modal diagnostics, and Tikhonov regularization.

**Damping margin.** A second-order ROM ``q̈ + C q̇ + K q = B u`` with symmetric ``C, K`` has
modes ``λ`` with ``(λ² I + λ C + K) x = 0``; for a unit eigenvector, ``λ² + c λ + k = 0`` with
the real Rayleigh quotients ``c = x*Cx``, ``k = x*Kx``, so the damping ratio of the mode is
``ζ = c / (2 √k)`` (``ζ ≥ 1`` when overdamped). The convex constraint

.. math:: C \\succeq \\alpha I + \\beta K, \\qquad \\alpha = \\zeta_{min}\\,\\omega_*,\\quad
    \\beta = \\zeta_{min} / \\omega_*,

gives ``c ≥ α + β k`` for every mode, hence ``ζ ≥ (α/√k + β√k)/2 ≥ √(αβ) = ζ_min``: **every**
mode of the ROM has a damping ratio of at least ``ζ_min``, whether or not ``C`` and ``K``
commute (the bound is tight at the frequency ``ω_*`` and grows away from it, like Rayleigh
damping ``C = a I + b K``). ``ω_*`` is taken from the data: the geometric mean of the slowest
and fastest natural frequencies of a first fit with the absolute margin, which balances the
over-damping forced at both ends of the ROM's band. The constraint is a change of variables
(``C' = C - βK ⪰ αI``; the residual becomes ``Q̈ + C' Q̇ + K (Q + β Q̇) - B U``), so the same
solvers handle it. The stiffness margin is relative: ``K ⪰ 1e-6 · λ_max(K₀)``.

Why a damping ratio and not an absolute eigenvalue bound: ``λ_min(C) ≥ 1e-6`` 1/s leaves a
mode that decays over hours; a damping ratio has the same meaning at every time scale and
unit of time, and soft bodies are heavily damped (``ζ`` of a few percent or more), so the
default ``ζ_min = 0.01`` rejects only spurious, ringing modes.

**Tikhonov regularization.** ``λ_C ||C||² + λ_K ||K||² + λ_B ||B||²`` (in the learner's scaled
coordinates) with ``λ_X = γ · ||X-regressor||²_F / dim``: ``γ`` is dimensionless (a ridge
relative to the mean energy of ``Q̇``, ``Q`` and ``U``). It is added as extra data columns,
so every solver gets it for free. :func:`select_regularization` picks ``γ`` by the error on a
held-out tail of every training episode (fit on the heads, simulate whole episodes), and
rejects candidates whose simulation blows up (more than ``blowup`` times the largest training
state) or is not finite: the opinf ``fit_regselect`` recipe.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla

from soft_rom.errors import ConfigError

__all__ = ['DEFAULT_MIN_DAMPING_RATIO', 'DEFAULT_REG_GRID', 'augment_tikhonov',
           'damping_bound', 'least_damped_mode', 'modal_table', 'select_regularization',
           'simulate_reduced']

Array = NDArray[np.float64]

#: Default minimum damping ratio of every LOpInf mode.
DEFAULT_MIN_DAMPING_RATIO = 0.01

#: Default grid of the dimensionless Tikhonov weight γ (0: none).
DEFAULT_REG_GRID = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2)

#: Relative stiffness margin: ``K ⪰ K_REL_MARGIN · λ_max(K₀)``.
K_REL_MARGIN = 1e-6


def modal_table(K: Array, C: Array) -> list[dict[str, float]]:
    """Modes of ``q̈ + C q̇ + K q``: one per conjugate pair or real root, slowest first.

    Returns
    -------
    list of dict
        ``frequency_hz`` (undamped ``|λ|/2π``), ``damped_frequency_hz`` (``|Im λ|/2π``),
        ``damping_ratio`` (``-Re λ / |λ|``), ``eigenvalue_real``, ``eigenvalue_imag``.
    """
    r = K.shape[0]
    A = np.block([[np.zeros((r, r)), np.eye(r)], [-K, -C]])
    ev = np.linalg.eigvals(A)
    keep = ev[ev.imag >= -1e-12 * np.maximum(np.abs(ev), 1e-300)]
    out = []
    for z in keep:
        mag = float(abs(z))
        zeta = float(-z.real / mag) if mag > 0 else 1.0
        out.append({'frequency_hz': mag / (2 * np.pi),
                    'damped_frequency_hz': abs(float(z.imag)) / (2 * np.pi),
                    'damping_ratio': zeta, 'eigenvalue_real': float(z.real),
                    'eigenvalue_imag': float(z.imag)})
    out.sort(key=lambda d: d['frequency_hz'])
    return out


def least_damped_mode(K: Array, C: Array) -> dict[str, float]:
    """The mode with the smallest damping ratio (see :func:`modal_table`)."""
    return min(modal_table(K, C), key=lambda d: d['damping_ratio'])


def damping_bound(K0: Array, min_damping_ratio: float, *,
                  frequency: float | None = None) -> dict[str, float]:
    """``α, β`` of ``C ⪰ αI + βK`` and the stiffness floor, from a first fit's ``K₀``.

    Parameters
    ----------
    K0 : ndarray, shape (r, r)
        Stiffness of a fit with the absolute margin (sets the frequency band).
    min_damping_ratio : float
        ``ζ_min`` in ``[0, 1)``.
    frequency : float, optional
        ``ω_*`` (rad/s); default ``√(ω_min ω_max)`` of ``K₀``.
    """
    z = float(min_damping_ratio)
    if not 0.0 <= z < 1.0:
        raise ConfigError(f'--min-damping-ratio must be in [0, 1); got {min_damping_ratio!r}.')
    lam = np.linalg.eigvalsh(0.5 * (K0 + K0.T))
    eps_k = K_REL_MARGIN * max(float(lam[-1]), 1e-300)
    if frequency is None:
        lo = max(float(lam[0]), eps_k)
        w_star = float((lo * max(float(lam[-1]), lo)) ** 0.25)
    else:
        w_star = float(frequency)
        if not np.isfinite(w_star) or w_star <= 0:
            raise ConfigError(f'damping frequency must be > 0 rad/s; got {frequency!r}.')
    return {'alpha': z * w_star, 'beta': z / w_star, 'eps_K': eps_k,
            'frequency_rad_s': w_star, 'min_damping_ratio': z}


def augment_tikhonov(Q: Array, Qd: Array, Qdd: Array, U: Array, gamma: float
                     ) -> tuple[Array, Array, Array, Array, dict[str, float]]:
    """Append the columns that add ``λ_C||C||² + λ_K||K||² + λ_B||B||²`` to the objective.

    ``λ_C = γ ||Q̇||²/r``, ``λ_K = γ ||Q||²/r``, ``λ_B = γ ||U||²/m`` (module docstring).
    """
    g = float(gamma)
    if not (np.isfinite(g) and g >= 0):
        raise ConfigError(f'regularization weight must be >= 0; got {gamma!r}.')
    r, m = Q.shape[0], U.shape[0]
    lam = {'C': g * float(np.sum(Qd ** 2)) / r, 'K': g * float(np.sum(Q ** 2)) / r,
           'B': g * float(np.sum(U ** 2)) / max(m, 1)}
    if g == 0:
        return Q, Qd, Qdd, U, lam
    cols = 2 * r + m
    Za, Zd, Zdd, Zu = (np.zeros((r, cols)), np.zeros((r, cols)), np.zeros((r, cols)),
                       np.zeros((m, cols)))
    Zd[:, :r] = np.sqrt(lam['C']) * np.eye(r)
    Za[:, r:2 * r] = np.sqrt(lam['K']) * np.eye(r)
    Zu[:, 2 * r:] = np.sqrt(lam['B']) * np.eye(m)
    return (np.hstack([Q, Za]), np.hstack([Qd, Zd]), np.hstack([Qdd, Zdd]), np.hstack([U, Zu]),
            lam)


def simulate_reduced(K: Array, C: Array, B: Array, U: Array, q0: Array, v0: Array,
                     dt: float) -> Array:
    """Reduced trajectory ``q̂`` (r, k) for inputs held over each step (exact ZOH)."""
    r, m = B.shape
    Ac = np.block([[np.zeros((r, r)), np.eye(r)], [-K, -C]])
    M = np.zeros((2 * r + m, 2 * r + m))
    M[:2 * r, :2 * r] = Ac * dt
    M[:2 * r, 2 * r:] = np.vstack([np.zeros((r, m)), B]) * dt
    F = sla.expm(M)
    Ad, Bd = F[:2 * r, :2 * r], F[:2 * r, 2 * r:]
    k = U.shape[1]
    X = np.empty((2 * r, k))
    x = np.concatenate([q0, v0])
    BU = Bd @ U
    with np.errstate(over='ignore', invalid='ignore'):
        for j in range(k):
            X[:, j] = x
            x = Ad @ x + BU[:, j]
    return X[:r]


def select_regularization(fit: Callable[[list[Array], list[Array], list[Array], list[Array],
                                         float], tuple[Array, Array, Array]],
                          Qs: Sequence[Array], Qd: Sequence[Array], Qdd: Sequence[Array],
                          Us: Sequence[Array], dt: float, *,
                          grid: Sequence[float] = DEFAULT_REG_GRID, holdout: float = 0.2,
                          blowup: float = 10.0) -> tuple[float, list[dict[str, Any]]]:
    """Pick the Tikhonov weight ``γ`` by the held-out tail error of every training episode.

    Parameters
    ----------
    fit : callable
        ``fit(Q, Qd, Qdd, U, gamma) -> (K, C, B)`` on lists of per-episode arrays.
    Qs, Qd, Qdd, Us : sequence of ndarray
        Per-episode (scaled) reduced states, derivatives and inputs (trimmed alike).
    dt : float
    grid : sequence of float
        Candidate ``γ``.
    holdout : float
        Fraction of every episode held out at its end.
    blowup : float
        Reject a candidate whose simulated state exceeds ``blowup`` times the largest
        training state anywhere on the episode.

    Returns
    -------
    gamma : float
        The selected weight.
    table : list of dict
        ``gamma``, ``tail_error`` (relative, all tails together, ``inf`` when rejected),
        ``rejected`` (reason or ``''``).
    """
    if not 0.0 < holdout < 0.9:
        raise ConfigError(f'holdout must be in (0, 0.9); got {holdout!r}.')
    cut = [max(int(round(q.shape[1] * (1.0 - holdout))), 2) for q in Qs]
    if any(c >= q.shape[1] - 1 for c, q in zip(cut, Qs)):
        raise ConfigError('episodes too short to hold out a tail for regularization selection.')
    heads = [[x[:, :c] for x, c in zip(arrs, cut)] for arrs in (Qs, Qd, Qdd, Us)]
    qmax = max(float(np.max(np.abs(q))) for q in Qs)
    table: list[dict[str, Any]] = []
    for g in grid:
        row: dict[str, Any] = {'gamma': float(g), 'tail_error': float('inf'), 'rejected': ''}
        try:
            K, C, B = fit(heads[0], heads[1], heads[2], heads[3], float(g))
        except Exception as err:  # a failed candidate is a rejected candidate
            row['rejected'] = f'fit failed: {err}'
            table.append(row)
            continue
        num = den = 0.0
        for q, qd, u, c in zip(Qs, Qd, Us, cut):
            Xs = simulate_reduced(K, C, B, u, q[:, 0], qd[:, 0], dt)
            if not np.all(np.isfinite(Xs)) or float(np.max(np.abs(Xs))) > blowup * qmax:
                row['rejected'] = 'blows up on the training horizon'
                break
            num += float(np.sum((Xs[:, c:] - q[:, c:]) ** 2))
            den += float(np.sum(q[:, c:] ** 2))
        if not row['rejected']:
            row['tail_error'] = float(np.sqrt(num / max(den, 1e-300)))
        table.append(row)
    ok = [row for row in table if not row['rejected']]
    if not ok:
        raise ConfigError('every regularization candidate was rejected (blow-up or failed '
                          'fit); check the data or widen the grid.')
    best = min(ok, key=lambda row: row['tail_error'])
    return float(best['gamma']), table


def constrained_solve(solver: Any, Q: Array, Qd: Array, Qdd: Array, U: Array, *, eps: float,
                      min_damping_ratio: float, frequency: float | None = None,
                      gamma: float = 0.0, bound: dict[str, float] | None = None
                      ) -> tuple[Array, Array, Array, dict[str, Any]]:
    """The LOpInf operator solve with the damping margin and Tikhonov weight ``γ``.

    First the solve with the absolute margin ``eps``; if its ``(C, K)`` already satisfies
    ``C ⪰ αI + βK`` and ``K ⪰ eps_K`` it is the optimum of the margin problem too; otherwise
    the margin problem is solved by the change of variables of the module docstring.

    Returns
    -------
    K, C, B : ndarray
        Operators (``B`` in the scaled input units of the data given).
    info : dict
        The solver report plus ``margin`` (``alpha``, ``beta``, ``eps_K``,
        ``frequency_rad_s``, ``min_damping_ratio``, ``active``) and ``regularization``.
    """
    Qa, Qda, Qdda, Ua, lam = augment_tikhonov(Q, Qd, Qdd, U, gamma)
    sol = solver.solve(Qa, Qda, Qdda, Ua, eps=eps)
    K, C, B = 0.5 * (sol.K + sol.K.T), 0.5 * (sol.C + sol.C.T), sol.B
    info = dict(sol.info)
    info['regularization'] = {'gamma': float(gamma), 'lambda': lam}
    if min_damping_ratio <= 0:
        info['margin'] = {'min_damping_ratio': 0.0, 'active': False}
        return K, C, B, info
    bd = dict(bound) if bound is not None else damping_bound(K, min_damping_ratio,
                                                             frequency=frequency)
    eye = np.eye(K.shape[0])
    slack_c = float(np.linalg.eigvalsh(C - bd['alpha'] * eye - bd['beta'] * K)[0])
    slack_k = float(np.linalg.eigvalsh(K)[0]) - bd['eps_K']
    if slack_c >= 0 and slack_k >= 0:
        info['margin'] = dict(bd, active=False)
        return K, C, B, info
    sol = solver.solve(Qa + bd['beta'] * Qda, Qda, Qdda, Ua, eps=(bd['alpha'], bd['eps_K']))
    K = 0.5 * (sol.K + sol.K.T)
    C = 0.5 * (sol.C + sol.C.T) + bd['beta'] * K
    info = dict(sol.info)
    info['regularization'] = {'gamma': float(gamma), 'lambda': lam}
    info['margin'] = dict(bd, active=True)
    return K, C, sol.B, info
