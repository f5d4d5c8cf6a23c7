"""LOpInf with a learned symmetric positive definite mass matrix.

.. math::

    \\min_{M, C, K, B}\\ \\| M \\ddot Q + C \\dot Q + K Q - B U \\|_F \\quad
    \\text{s.t.}\\ M = M^T \\succeq I,\\ C = C^T \\succeq \\epsilon I,\\ K = K^T \\succeq \\epsilon I.

Why: in coordinates ``y = T q`` of a mechanical system ``M_0 q'' + C_0 q' + K_0 q = B_0 u``
(e.g. the measured outputs of a real robot, POD-reduced) the identity-mass form
``y'' + C y' + K y = B u`` has the stiffness ``T M_0^{-1} K_0 T^{-1}``, which is not
symmetric, so the identity-mass LOpInf pays a bias for its symmetry constraints. The form
``M y'' + C y' + K y = B u`` with ``M = T^{-T} M_0 T^{-1}``, ``C = T^{-T} C_0 T^{-1}``,
``K = T^{-T} K_0 T^{-1}`` is exact in every coordinates. The problem is convex; the objective
is homogeneous in ``(M, C, K, B)``, so ``M ⪰ I`` only fixes the scale (the bound is active at
the optimum unless the residual is zero, when every point of the ray ``α (M, C, K, B)`` is
optimal and gives the same model).

The fitted model is returned in the identity-mass class: with ``M = L L^T`` and ``z = L^T q``,

.. math::

    \\ddot z + L^{-1} C L^{-T} \\dot z + L^{-1} K L^{-T} z = L^{-1} B u, \\qquad
    y = E L^{-T} z + y_{ref},

whose stiffness and damping are symmetric positive definite (eigenvalues at least
``eps / λ_max(M)``), so the model file, predictor, replay and node are unchanged.

Solution: ``B`` is eliminated in closed form and the samples are compressed to the
square-root Gram form ``||[C, K, M] D||_F`` (``D`` of shape (3r, ≤ 3r), from the thin QR of
:func:`~soft_rom.learners.lopinf_solvers.reduce_data`), so the conic problem has
``3 r (r + 1) / 2`` unknowns whatever the number of samples. Two feasible candidates are
compared and the lower objective is kept:

* the homogeneous least-squares solution (smallest right singular vector of the linear map
  ``(C, K, M) -> [C, K, M] D`` on symmetric matrices), scaled so that ``λ_min(M) = 1``,
  when its three blocks are positive definite; it is exact for exact data;
* the conic problem solved by cvxpy with Clarabel (an upper bound ``tr M ≤ 1e6 r``, far
  from active, keeps the feasible set bounded for exact data).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg as sla

from soft_rom.errors import ConfigError, SolverError
from soft_rom.learners.lopinf_solvers import DEFAULT_EPS, LOpInfSolution, reduce_data

__all__ = ['MASS_CHOICES', 'solve_learned_mass', 'to_identity_mass']

Array = NDArray[np.float64]

#: Values of the ``mass`` hyperparameter of :class:`~soft_rom.learners.lopinf.LOpInf`.
MASS_CHOICES = ('identity', 'learned')

_MASS_FLOOR = 1e-6


def _sym_basis(r: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(r) for j in range(i, r)]


def _smat(v: Array, idx: list[tuple[int, int]], r: int) -> Array:
    S = np.zeros((r, r))
    for val, (i, j) in zip(v, idx):
        S[i, j] = S[j, i] = val
    return S


def _phi(D: Array, r: int, W: Array) -> tuple[Array, list[tuple[int, int]]]:
    """Matrix of the linear map ``θ = (svec C, svec K, svec M) -> vec(W [C, K, M] D)``."""
    idx = _sym_basis(r)
    cols = []
    for block in range(3):
        rows = D[block * r:(block + 1) * r]            # (r, q)
        for i, j in idx:
            Y = np.zeros((r, D.shape[1]))
            Y[i] += rows[j]
            if i != j:
                Y[j] += rows[i]
            cols.append((W @ Y).ravel())
    return np.stack(cols, axis=1), idx


def _trace_ls(D: Array, r: int, W: Array) -> tuple[Array, Array, Array]:
    """``min ||W [C, K, M] D||_F`` over symmetric blocks with ``tr M = r`` (closed form).

    Null-space method: ``θ = θ_p + N φ`` with ``aᵀ θ_p = r`` and ``aᵀ N = 0``.
    """
    Phi, idx = _phi(D, r, W)
    ns = len(idx)
    a = np.zeros(3 * ns)
    a[2 * ns:] = [1.0 if i == j else 0.0 for i, j in idx]
    theta_p = a * (r / float(a @ a))
    Qa, _ = np.linalg.qr(np.column_stack([a, np.eye(3 * ns)[:, :3 * ns - 1]]))
    N = Qa[:, 1:]
    phi, *_ = np.linalg.lstsq(Phi @ N, -(Phi @ theta_p), rcond=None)
    theta = theta_p + N @ phi
    C, K, M = (_smat(theta[b * ns:(b + 1) * ns], idx, r) for b in range(3))
    return M, C, K


def _conic(D: Array, r: int, eps: float, solver: str, W: Array
           ) -> tuple[Array, Array, Array, str]:
    import cvxpy as cp
    Mv = cp.Variable((r, r), symmetric=True)
    Cv = cp.Variable((r, r), symmetric=True)
    Kv = cp.Variable((r, r), symmetric=True)
    eye = np.eye(r)
    cons = [Mv >> _MASS_FLOOR * eye, Cv >> eps * eye, Kv >> eps * eye, cp.trace(Mv) == r]
    prob = cp.Problem(cp.Minimize(cp.norm(W @ cp.hstack([Cv, Kv, Mv]) @ D, 'fro')), cons)
    try:
        prob.solve(solver=solver)
    except cp.error.SolverError as exc:
        raise SolverError(f'the learned-mass LOpInf problem failed in {solver}: {exc}') from exc
    if Mv.value is None or prob.status not in ('optimal', 'optimal_inaccurate'):
        raise SolverError(f'the learned-mass LOpInf problem ended with status {prob.status!r} '
                          f'in {solver}.')
    sym = [0.5 * (X.value + X.value.T) for X in (Mv, Cv, Kv)]
    return sym[0], sym[1], sym[2], str(prob.status)


def solve_learned_mass(Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
                       eps: float = DEFAULT_EPS, solver: str = 'CLARABEL',
                       max_iter: int = 20, tol: float = 1e-9
                       ) -> tuple[LOpInfSolution, Array]:
    """Fit ``M, C, K, B`` (module docstring) and return the identity-mass form.

    Parameters
    ----------
    Q, Qd, Qdd : ndarray, shape (r, k)
        Coordinates and their first and second time derivatives.
    U : ndarray, shape (m, k)
        Inputs.
    eps : float
        ``C, K ⪰ eps I`` (the margins of the identity-mass LOpInf); ``M ⪰ I``.
    solver : str
        cvxpy solver name for the conic candidate (default Clarabel).

    Returns
    -------
    solution : LOpInfSolution
        ``K', C'`` (r, r) symmetric positive definite, ``B'`` (r, m) of the model in
        ``z = Lᵀ q``; ``info`` holds the objective, the chosen candidate and the
        eigenvalues of ``M`` (JSON-serialisable).
    Lt : ndarray, shape (r, r)
        ``Lᵀ`` (upper triangular, ``M = L Lᵀ``): the model's coordinates are ``Lᵀ q``.
    """
    if not eps >= 0:
        raise ConfigError(f'eps must be >= 0; got {eps!r}.')
    prob = reduce_data(Q, Qd, Qdd, U)
    r = prob.r
    D = np.vstack([prob.A, prob.G])                     # ||[C, K, M] D||_F
    scale = float(np.linalg.norm(D))
    if not scale > 0:
        raise SolverError('the learned-mass LOpInf problem has no data (all zero).')
    Dn = D / scale

    def obj(M: Array, C: Array, K: Array, W: Array) -> float:
        return float(np.linalg.norm(W @ np.hstack([C, K, M]) @ Dn))

    W = np.eye(r)
    status, method, history = 'not needed', '', []
    M = np.eye(r)
    for it in range(max_iter):
        M_old = M
        M, C, K = _trace_ls(Dn, r, W)
        lam = [float(np.linalg.eigvalsh(X)[0]) for X in (M, C, K)]
        if lam[0] >= _MASS_FLOOR and lam[1] >= eps and lam[2] >= eps:
            method = 'trace-least-squares'
        else:
            M, C, K, status = _conic(Dn, r, eps, solver, W)
            method = f'cvxpy-{solver.lower()}'
        history.append(obj(M, C, K, np.linalg.inv(M)) * scale)
        if it and np.linalg.norm(M - M_old) <= tol * np.linalg.norm(M):
            break
        W = np.linalg.inv(M)                            # acceleration-error weights
        W = 0.5 * (W + W.T)
    val = obj(M, C, K, np.eye(r))
    B = (M @ prob.Dv + np.hstack([C, K]) @ prob.Zv) @ prob.pinv_left
    Kp, Cp, Bp, Lt = to_identity_mass(M, C, K, B)
    info: dict[str, Any] = {
        'solver': 'learned-mass', 'method': method, 'conic_status': status,
        'objective': val * scale, 'eps': float(eps),
        'acceleration_residuals': history, 'iterations': len(history),
        'eigenvalues_M': [float(x) for x in np.linalg.eigvalsh(M)],
        'rank_u': int(prob.rank_u),
    }
    return LOpInfSolution(Kp, Cp, Bp, info), Lt


def to_identity_mass(M: ArrayLike, C: ArrayLike, K: ArrayLike, B: ArrayLike
                     ) -> tuple[Array, Array, Array, Array]:
    """``(L⁻¹ K L⁻ᵀ, L⁻¹ C L⁻ᵀ, L⁻¹ B, Lᵀ)`` for ``M = L Lᵀ`` (``M`` SPD, shape (r, r)).

    The model ``M q'' + C q' + K q = B u`` in the coordinates ``z = Lᵀ q``.
    """
    M, C, K, B = (np.asarray(x, dtype=np.float64) for x in (M, C, K, B))
    try:
        L = np.linalg.cholesky(0.5 * (M + M.T))
    except np.linalg.LinAlgError as exc:
        raise SolverError('the learned mass matrix is not positive definite.') from exc

    def congr(X: Array) -> Array:
        Y = sla.solve_triangular(L, X, lower=True)
        Y = sla.solve_triangular(L, Y.T, lower=True)
        return 0.5 * (Y + Y.T)

    Bp = sla.solve_triangular(L, B, lower=True)
    return congr(K), congr(C), Bp, np.ascontiguousarray(L.T)
