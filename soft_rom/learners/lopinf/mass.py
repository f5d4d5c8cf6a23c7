"""LOpInf with a learned symmetric positive definite mass matrix.

Why: in coordinates ``y = T q`` of a mechanical system ``M_0 q'' + C_0 q' + K_0 q = B_0 u``
(e.g. the measured outputs of a real robot, POD-reduced) the identity-mass form
``y'' + C y' + K y = B u`` has the stiffness ``T M_0^{-1} K_0 T^{-1}`` and the damping
``T M_0^{-1} C_0 T^{-1}``, which are not symmetric, so the identity-mass LOpInf pays a bias
for its symmetry constraints. With ``M = T^{-T} M_0 T^{-1} = L L^T`` the coordinates
``z = L^T y`` have symmetric positive definite stiffness and damping again:

.. math::

    \\ddot z + L^{-1} C L^{-T} \\dot z + L^{-1} K L^{-T} z = L^{-1} B u, \\qquad
    y = E L^{-T} z + y_{ref}.

Fit, three convex steps:

1. the unconstrained second-order least-squares fit ``q'' = A_1 q + A_2 q' + B u``
   (``A_1 = -M^{-1} K``, ``A_2 = -M^{-1} C`` for a mechanical system);
2. the symmetrizer: ``M = M^T`` with ``tr M = r`` minimizing
   ``||M A_1 - A_1^T M||_F^2 / ||A_1||_F^2 + ||M A_2 - A_2^T M||_F^2 / ||A_2||_F^2``
   (linear least squares with one linear constraint, closed form); if that ``M`` is not
   positive definite, the same objective with ``M ⪰ 10^{-3} I`` by cvxpy and Clarabel;
3. the identity-mass LOpInf (``K, C ⪰ eps I``,
   :class:`~soft_rom.learners.lopinf.solvers.FastSPDSolver`) in ``z = L^T q``.

A minimization of ``||M Q'' + C Q' + K Q - B U||_F`` over ``M ⪰ I, C, K`` in one convex
problem is *not* used: the objective is homogeneous, so it shrinks ``M`` in every direction
and its optimum on measured data is ``M = I`` (the identity-mass fit again); with
``tr M = r`` instead it shifts mass towards directions of noisy accelerations and predicts
worse. Exactness: for exact data of a mechanical system with non-proportional damping,
steps 1 and 2 recover ``A_1, A_2`` and ``M`` up to a scalar, and step 3 is then exact.
With proportional damping ``M`` is not unique, but every symmetrizer of both ``A_1`` and
``A_2`` gives coordinates with symmetric stiffness and damping.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ConfigError, SolverError
from soft_rom.learners.lopinf.solvers import DEFAULT_EPS, FastSPDSolver, LOpInfSolution

__all__ = ['MASS_CHOICES', 'SHRINKAGE', 'mass_candidates', 'solve_learned_mass']

Array = NDArray[np.float64]

#: Values of the ``mass`` hyperparameter of :class:`~soft_rom.learners.lopinf.LOpInf`.
MASS_CHOICES = ('identity', 'learned')

#: Candidates with a smallest eigenvalue below this (the trace is ``r``) are dropped.
MASS_FLOOR = 1e-8

#: Shrinkage levels ``c`` of the symmetrizer towards ``I`` (``0``: none, exact data).
SHRINKAGE = (0.0, 0.01, 0.1, 1.0, 10.0)


def _sym_basis(r: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(r) for j in range(i, r)]


def _smat(v: Array, idx: list[tuple[int, int]], r: int) -> Array:
    S = np.zeros((r, r))
    for val, (i, j) in zip(v, idx):
        S[i, j] = S[j, i] = val
    return S


def _commutator_map(As: list[Array], r: int) -> tuple[Array, list[tuple[int, int]]]:
    """Matrix of ``svec M -> [vec(M A - Aᵀ M) / ||A||_F for A in As]``."""
    idx = _sym_basis(r)
    cols = []
    for i, j in idx:
        E = np.zeros((r, r))
        E[i, j] = E[j, i] = 1.0
        cols.append(np.concatenate([((E @ A - A.T @ E) / max(float(np.linalg.norm(A)),
                                                             1e-300)).ravel() for A in As]))
    return np.stack(cols, axis=1), idx


def mass_candidates(A1: ArrayLike, A2: ArrayLike, rho: float,
                    shrinkage: tuple[float, ...] = SHRINKAGE) -> list[tuple[float, Array]]:
    """Symmetrizers ``M`` (``tr M = r``) of ``A1, A2``, shrunk towards ``I`` by the noise.

    For each ``c`` in ``shrinkage``, ``M`` minimizes
    ``||M A1 - A1ᵀ M||² / ||A1||² + ||M A2 - A2ᵀ M||² / ||A2||² + μ ||M - I||²`` with
    ``μ = c ρ² σ²`` (``σ``: the largest singular value of the commutator map, ``ρ``: the
    relative residual of the unconstrained fit, i.e. how far ``A1, A2`` can be trusted), then
    ``tr M = r``; ``c = 0`` is the trace-normalized least-squares symmetrizer (exact for exact
    data). The identity is always the last candidate (``c = inf``).

    Parameters
    ----------
    A1, A2 : ndarray, shape (r, r)
        Stiffness and damping parts ``-M⁻¹K``, ``-M⁻¹C`` of an unconstrained fit.
    rho : float
        Relative residual of that fit.
    shrinkage : tuple of float
        The levels ``c``.

    Returns
    -------
    list of (c, M)
        The positive definite candidates (smallest eigenvalue ``≥ MASS_FLOOR``).
    """
    A1, A2 = (np.asarray(a, dtype=np.float64) for a in (A1, A2))
    r = A1.shape[0]
    Phi, idx = _commutator_map([A1, A2], r)
    w = np.array([1.0 if i == j else np.sqrt(2.0) for i, j in idx])
    a = np.array([1.0 if i == j else 0.0 for i, j in idx])
    sigma = float(np.linalg.norm(Phi, 2)) if Phi.size else 0.0
    theta_p = a * (r / float(a @ a))                # tr M = r; null-space method
    Qa, _ = np.linalg.qr(np.column_stack([a, np.eye(a.size)[:, :a.size - 1]]))
    N = Qa[:, 1:]
    out: list[tuple[float, Array]] = []
    for c in shrinkage:
        mu = float(c) * rho ** 2 * sigma ** 2
        theta = theta_p
        if N.shape[1]:
            lhs, rhs = Phi @ N, -(Phi @ theta_p)
            if mu > 0:
                lhs = np.vstack([lhs, np.sqrt(mu) * (w[:, None] * N)])
                rhs = np.concatenate([rhs, np.sqrt(mu) * w * (a - theta_p)])
            phi, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
            theta = theta_p + N @ phi
        M = _smat(theta, idx, r)
        tr = float(np.trace(M))
        if not tr > 0:
            continue
        M = M * (r / tr)
        if float(np.linalg.eigvalsh(M)[0]) >= MASS_FLOOR:
            out.append((float(c), M))
    out.append((float('inf'), np.eye(r)))
    return out


def _simulation_error(K: Array, C: Array, B: Array, Lt: Array, dt: float,
                      episodes: Sequence[tuple[Array, Array]]) -> float:
    """``||Q - Q_sim||_F / ||Q||_F`` over the episodes (initial state fitted by least squares).

    The simulation is linear in the initial state, so its best value per episode is the
    least-squares fit of the free responses of the ``2r`` unit initial states to what the
    forced response (from rest) leaves; recordings that do not start at rest are scored
    fairly.
    """
    from soft_rom.models import SecondOrderModel
    model = SecondOrderModel(K, C, B, np.linalg.inv(Lt), dt=dt, y_ref=np.zeros(K.shape[0]))
    n = 2 * K.shape[0]
    num = den = 0.0
    with np.errstate(all='ignore'):
        for q, u in episodes:
            forced = model.simulate(u)
            zero = np.zeros_like(u)
            free = np.stack([np.asarray(model.simulate(zero, np.eye(n)[i])).ravel()
                             for i in range(n)], axis=1)
            rest = (q - forced).ravel()
            if not (np.all(np.isfinite(free)) and np.all(np.isfinite(rest))):
                return float('inf')
            x0, *_ = np.linalg.lstsq(free, rest, rcond=None)
            num += float(np.linalg.norm(rest - free @ x0)) ** 2
            den += float(np.linalg.norm(q)) ** 2
    return float(np.sqrt(num / den)) if den > 0 else float('inf')


def solve_learned_mass(Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
                       eps: float = DEFAULT_EPS, dt: float | None = None,
                       episodes: Sequence[tuple[ArrayLike, ArrayLike]] | None = None,
                       shrinkage: tuple[float, ...] = SHRINKAGE
                       ) -> tuple[LOpInfSolution, Array]:
    """Learn the mass matrix and the identity-mass model in ``z = Lᵀ q`` (module docstring).

    Parameters
    ----------
    Q, Qd, Qdd : ndarray, shape (r, k)
        Coordinates and their first and second time derivatives.
    U : ndarray, shape (m, k)
        Inputs.
    eps : float
        ``K', C' ⪰ eps I`` in the ``z`` coordinates (the identity-mass LOpInf margins).
    dt : float, optional
        Sample time (s) of ``episodes``.
    episodes : sequence of (Q_i (r, k_i), U_i (m, k_i)), optional
        The training episodes (same scaling as ``Q`` and ``U``, untrimmed): the candidate
        with the smallest simulation error on them is chosen. Without them (or ``dt``), the
        candidate ``c = 0.1`` (or the next positive definite one).
    shrinkage : tuple of float
        Shrinkage levels of :func:`mass_candidates`.

    Returns
    -------
    solution : LOpInfSolution
        ``K', C'`` (r, r) symmetric with eigenvalues ``≥ eps``, ``B'`` (r, m) of the model in
        ``z = Lᵀ q``; ``info`` (JSON-serialisable) has the solver report of step 3 and
        ``mass`` (chosen shrinkage, candidates' training errors, eigenvalues of ``M``).
    Lt : ndarray, shape (r, r)
        ``Lᵀ`` (upper triangular, ``M = L Lᵀ``): the model's coordinates are ``Lᵀ q``.
    """
    if not eps >= 0:
        raise ConfigError(f'eps must be >= 0; got {eps!r}.')
    Q, Qd, Qdd, U = (np.asarray(x, dtype=np.float64) for x in (Q, Qd, Qdd, U))
    r = Q.shape[0]
    Z = np.vstack([Q, Qd, U])
    X, *_ = np.linalg.lstsq(Z.T, Qdd.T, rcond=None)
    X = X.T
    rho = float(np.linalg.norm(Qdd - X @ Z)) / max(float(np.linalg.norm(Qdd)), 1e-300)
    cands = mass_candidates(X[:, :r], X[:, r:2 * r], rho, shrinkage)
    eps_list = None if episodes is None or dt is None else [
        (np.asarray(q, dtype=np.float64), np.asarray(u, dtype=np.float64)) for q, u in episodes]
    if eps_list is None:
        pick = [cm for cm in cands if cm[0] >= 0.1] or cands
        cands = pick[:1]
    best: tuple[float, float, LOpInfSolution, Array, Array] | None = None
    scores: dict[str, float] = {}
    for c, M in cands:
        Lt = np.linalg.cholesky(M).T
        sol = FastSPDSolver().solve(Lt @ Q, Lt @ Qd, Lt @ Qdd, U, eps=eps)
        score = 0.0 if eps_list is None else _simulation_error(
            sol.K, sol.C, sol.B, Lt, float(dt), eps_list)   # type: ignore[arg-type]
        scores[repr(c)] = score
        if best is None or score < best[0]:
            best = (score, c, sol, Lt, M)
    if best is None:  # pragma: no cover - the identity is always a candidate
        raise SolverError('no positive definite mass matrix candidate.')
    score, c, sol, Lt, M = best
    info = dict(sol.info)
    info['mass'] = {'shrinkage': repr(c), 'unconstrained_relative_residual': rho,
                    'training_simulation_errors': scores,
                    'eigenvalues_M': [float(x) for x in np.linalg.eigvalsh(M)]}
    return LOpInfSolution(sol.K, sol.C, sol.B, info), np.ascontiguousarray(Lt)
