"""Solvers for the LOpInf operator problem with symmetric positive definite K and C.

.. math::

    \\min_{K, C, B}\\ \\| \\ddot Q + C \\dot Q + K Q - B U \\|_F
    \\quad \\text{s.t.} \\quad K = K^T \\succeq \\epsilon I, \\quad C = C^T \\succeq \\epsilon I

(Sharma et al., *Lagrangian Operator Inference*, eq. (opt); strict definiteness is enforced as
``λ_min ≥ eps`` with the one constant :data:`DEFAULT_EPS`, shared by every solver so that their
objectives are comparable). ``B`` is unconstrained and eliminated in closed form: for fixed
``W = [C, K]`` the best ``B`` is ``B = (W Z + Q̈) U⁺`` with ``Z = [Q̇; Q]``, the
**minimum-norm** solution, computed from a rank-revealing SVD of ``U`` (rank-deficient inputs,
e.g. antagonistic chambers driven with opposite pressures, are handled; no singular Gram block
is ever inverted). What remains is a problem in ``(C, K)`` alone,

.. math:: \\min_{W = [C, K]}\\ \\| W A + G \\|_F, \\qquad A \\in \\mathbb R^{2r\\times q},\\
    G \\in \\mathbb R^{r \\times q},\\ q \\le 3r,

obtained by projecting ``Z`` and ``Q̈`` on the orthogonal complement of the row space of ``U``
and taking the triangular factor of a thin QR of the ``(k, 3r)`` matrix ``[Z⊥; Q̈⊥]ᵀ``. This is
the Gram-matrix reduction ``G = D Dᵀ`` written with its square root ``R`` (``RᵀR = G``), so
the condition number is not squared; it costs one pass over the data.

Solvers (objects behind :class:`OperatorSolver`):

* :class:`FastSPDSolver` (default): the symmetric least-squares solution in closed form; if it
  is already feasible it *is* the optimum and is returned; otherwise a primal-dual interior
  point (:mod:`soft_rom.learners.lopinf.ipm`: Nesterov-Todd scaling, Mehrotra
  predictor-corrector, Newton systems assembled in symmetric-Kronecker form, ``K`` eliminated
  by a Schur complement when its constraint is inactive), started from the least-squares
  solution lifted into the cones, stopped on a certified duality gap. ``eps`` may be one
  margin or a pair ``(eps_C, eps_K)``.
* :class:`CvxpySolver`: the reference conic formulation with cvxpy (Clarabel or SCS), either
  on the reduced data (``formulation='reduced'``) or straightforwardly over the raw ``r × k``
  residual (``formulation='raw'``, the benchmark baseline).
"""

from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg as sla

from soft_rom.errors import ConfigError, DimensionError, SolverError
from soft_rom.learners.lopinf.ipm import BlockFactor, solve_two_cone_qp
from soft_rom.learners.lopinf.ipm import lift as _lift
from soft_rom.learners.lopinf.ipm import SymIndex as _SymIndex

__all__ = [
    'CvxpySolver',
    'DEFAULT_EPS',
    'FastSPDSolver',
    'LOpInfSolution',
    'OperatorSolver',
    'ReducedProblem',
    'objective',
    'reduce_data',
]

Array = NDArray[np.float64]

#: Lower bound on the eigenvalues of K (1/s²) and C (1/s) used for "positive definite" by
#: every solver. K and C do not change with the units of q or u (only B does), so this
#: constant is unit-independent.
DEFAULT_EPS = 1e-6

#: A margin: one bound for both K and C, or ``(eps_C, eps_K)``.
Margin = float | tuple[float, float]


def split_margin(eps: Margin) -> tuple[float, float]:
    """``(eps_C, eps_K)`` from one number or a pair; both must be finite and ``>= 0``."""
    pair: tuple[Any, ...] = (eps, eps) if isinstance(eps, (int, float, np.number)) else tuple(eps)
    if len(pair) != 2:
        raise ConfigError(f'eps must be a number or a pair (eps_C, eps_K); got {eps!r}.')
    try:
        out = (float(pair[0]), float(pair[1]))
    except (TypeError, ValueError):
        raise ConfigError(f'eps must be a number or a pair (eps_C, eps_K); got {eps!r}.') from None
    if not all(np.isfinite(v) and v >= 0 for v in out):
        raise ConfigError(f'eps must be >= 0 and finite; got {eps!r}.')
    return out


#: Singular values of U below ``rank_rtol * σ_max(U)`` are treated as zero.
DEFAULT_RANK_RTOL = 1e-10


class LOpInfSolution(NamedTuple):
    """Result of an operator solve; unpacks as ``K, C, B, info``."""

    K: Array
    C: Array
    B: Array
    info: dict[str, Any]


@runtime_checkable
class OperatorSolver(Protocol):
    """What :class:`~soft_rom.learners.lopinf.LOpInf` needs from an operator solver."""

    def solve(self, Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
              eps: Margin = DEFAULT_EPS) -> LOpInfSolution:
        """Return ``(K, C, B, info)`` for data ``Q, Qd, Qdd`` (r, k) and ``U`` (m, k)."""
        ...


def objective(K: ArrayLike, C: ArrayLike, B: ArrayLike, Q: ArrayLike, Qd: ArrayLike,
              Qdd: ArrayLike, U: ArrayLike) -> float:
    """``||Q̈ + C Q̇ + K Q - B U||_F`` evaluated on the raw data."""
    R = (np.asarray(Qdd) + np.asarray(C) @ np.asarray(Qd) + np.asarray(K) @ np.asarray(Q)
         - np.asarray(B) @ np.asarray(U))
    return float(np.linalg.norm(R))


# -- data reduction --------------------------------------------------------------------------


@dataclass(frozen=True)
class ReducedProblem:
    """The operator problem after eliminating B and compressing the samples.

    ``||Q̈ + C Q̇ + K Q - B_opt(C, K) U||_F = ||W A + G||_F`` with ``W = [C, K]``.

    Attributes
    ----------
    A : ndarray, shape (2r, q)
    G : ndarray, shape (r, q)
    Zv : ndarray, shape (2r, rho)
        ``[Q̇; Q] V_U`` (``V_U``: right singular vectors of U, rank ``rho``).
    Dv : ndarray, shape (r, rho)
        ``Q̈ V_U``.
    pinv_left : ndarray, shape (rho, m)
        ``S_U⁻¹ U_Uᵀ`` so that ``B = (W Zv + Dv) @ pinv_left``.
    rank_u : int
        Numerical rank ``rho`` of U.
    norm_qdd : float
        ``||Q̈||_F`` (scale of the problem).
    """

    A: Array
    G: Array
    Zv: Array
    Dv: Array
    pinv_left: Array
    rank_u: int
    norm_qdd: float

    @property
    def r(self) -> int:
        """Reduced dimension."""
        return int(self.G.shape[0])

    def residual_norm(self, C: Array, K: Array) -> float:
        """``||W A + G||_F`` (the objective with the optimal B)."""
        return float(np.linalg.norm(np.hstack([C, K]) @ self.A + self.G))

    def best_B(self, C: Array, K: Array) -> Array:
        """Minimum-norm optimal ``B`` for given ``C, K``; shape (r, m)."""
        return (np.hstack([C, K]) @ self.Zv + self.Dv) @ self.pinv_left


def _check_data(Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike
                ) -> tuple[Array, Array, Array, Array]:
    arrs = [np.asarray(x, dtype=np.float64) for x in (Q, Qd, Qdd, U)]
    Q, Qd, Qdd, U = [a[np.newaxis, :] if a.ndim == 1 else a for a in arrs]
    r, k = Q.shape
    for name, a in (('Qd', Qd), ('Qdd', Qdd)):
        if a.shape != (r, k):
            raise DimensionError(f'{name} must have the shape of Q {(r, k)}; got {a.shape}.')
    if U.ndim != 2 or U.shape[1] != k:
        raise DimensionError(f'U must have shape (m, {k}); got {U.shape}.')
    for name, a in (('Q', Q), ('Qd', Qd), ('Qdd', Qdd), ('U', U)):
        if not np.all(np.isfinite(a)):
            raise DimensionError(f'{name} contains NaN or Inf; clean the data before fitting.')
    return Q, Qd, Qdd, U


def reduce_data(Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
                rank_rtol: float = DEFAULT_RANK_RTOL) -> ReducedProblem:
    """Eliminate ``B`` and compress ``k`` samples to ``q ≤ 3r`` columns.

    Parameters
    ----------
    Q, Qd, Qdd : ndarray, shape (r, k)
        Reduced states and their first and second time derivatives.
    U : ndarray, shape (m, k)
        Inputs.
    rank_rtol : float
        Relative threshold on the singular values of ``U`` for its numerical rank.
    """
    Q, Qd, Qdd, U = _check_data(Q, Qd, Qdd, U)
    r = Q.shape[0]
    Z = np.vstack([Qd, Q])
    m = U.shape[0]
    if m:
        Uu, s, Vt = np.linalg.svd(U, full_matrices=False)
        rho = int(np.sum(s > rank_rtol * s[0])) if s.size and s[0] > 0 else 0
    else:
        rho = 0
    if rho:
        Vr = Vt[:rho].T
        Zv = Z @ Vr
        Dv = Qdd @ Vr
        Zp = Z - Zv @ Vr.T
        Dp = Qdd - Dv @ Vr.T
        pinv_left = Uu[:, :rho].T / s[:rho, None]
    else:
        Zv, Dv = np.zeros((2 * r, 0)), np.zeros((r, 0))
        Zp, Dp = Z, Qdd
        pinv_left = np.zeros((0, m))
    R: Array = np.asarray(np.linalg.qr(np.vstack([Zp, Dp]).T, mode='r'))
    return ReducedProblem(A=np.ascontiguousarray(R[:, :2 * r].T),
                          G=np.ascontiguousarray(R[:, 2 * r:].T), Zv=Zv, Dv=Dv,
                          pinv_left=pinv_left, rank_u=rho,
                          norm_qdd=float(np.linalg.norm(Qdd)))


# -- solvers ----------------------------------------------------------------------------------


class FastSPDSolver:
    """Closed-form symmetric least squares, then a primal-dual interior point if needed.

    On :class:`ReducedProblem` data the squared objective ``φ(θ) = ||W(θ) A + G||_F²`` is a
    quadratic in the ``r(r+1)`` free entries ``θ`` of ``C`` and ``K``. The unconstrained
    symmetric least-squares solution is computed first (one factorization); if it satisfies
    the margins it *is* the optimum. Otherwise :func:`~soft_rom.learners.lopinf.ipm.
    solve_two_cone_qp` (Mehrotra predictor-corrector, Nesterov-Todd scaling) solves the
    problem; when ``K``'s constraint is inactive at the least-squares point, ``K`` is
    eliminated exactly (a Schur complement) and only the cone of ``C`` remains (half the
    unknowns); the result is kept only if its ``K`` is feasible (then the full KKT conditions
    hold), otherwise both cones are solved together. Iterations stop on a certified gap.

    Parameters
    ----------
    rtol : float
        Stop when the certified gap ``φ(θ) - ψ(S)`` (``ψ`` the Lagrange dual function) is
        below ``rtol · φ(θ)``; the Frobenius objective is then within ``rtol / 2`` of the
        optimum.
    max_newton : int
        Interior-point iterations allowed; :class:`~soft_rom.errors.SolverError` beyond.
    rank_rtol : float
        Relative singular-value threshold for the numerical rank of ``U``.
    """

    def __init__(self, *, rtol: float = 1e-9, max_newton: int = 100,
                 rank_rtol: float = DEFAULT_RANK_RTOL) -> None:
        self.rtol = rtol
        self.max_newton = max_newton
        self.rank_rtol = rank_rtol

    def __repr__(self) -> str:
        return f'FastSPDSolver(rtol={self.rtol}, max_newton={self.max_newton})'

    def solve(self, Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
              eps: Margin = DEFAULT_EPS) -> LOpInfSolution:
        """Solve the LOpInf operator problem.

        Parameters
        ----------
        Q, Qd, Qdd : ndarray, shape (r, k)
        U : ndarray, shape (m, k)
        eps : float
            Lower bound on the eigenvalues of ``K`` and ``C``.

        Returns
        -------
        LOpInfSolution
            ``K, C`` (r, r) symmetric with eigenvalues ``≥ eps``, ``B`` (r, m) minimum-norm,
            and ``info`` (JSON-serialisable: method, objective, steps, gap bound, ...).
        """
        t0 = time.perf_counter()
        prob = reduce_data(Q, Qd, Qdd, U, rank_rtol=self.rank_rtol)
        C, K, info = self.solve_reduced(prob, eps=eps)
        B = prob.best_B(C, K)
        info['time_s'] = time.perf_counter() - t0
        return LOpInfSolution(K, C, B, info)

    def solve_reduced(self, prob: ReducedProblem, *, eps: Margin = DEFAULT_EPS
                      ) -> tuple[Array, Array, dict[str, Any]]:
        """Solve on already reduced data; returns ``C, K, info``."""
        eps_c, eps_k = split_margin(eps)
        r = prob.r
        idx = _SymIndex(r)
        A, G = prob.A, prob.G
        Hf = 2.0 * idx.hessian_quadratic(A @ A.T)

        def fval(theta: Array) -> float:
            C_, K_ = idx.split(theta)
            return float(np.sum((np.hstack([C_, K_]) @ A + G) ** 2))

        def fgrad(theta: Array) -> Array:
            C_, K_ = idx.split(theta)
            return idx.grad(2.0 * (np.hstack([C_, K_]) @ A + G) @ A.T)

        # Symmetric least squares (closed form) + two refinement steps on the exact gradient.
        theta = np.zeros(2 * idx.n)
        hf_factor = BlockFactor(Hf, idx.n)
        for _ in range(3):
            theta = theta - hf_factor.solve(fgrad(theta))
        f_ls = fval(theta)
        C, K = idx.split(theta)
        lam_c, lam_k = np.linalg.eigvalsh(C)[0], np.linalg.eigvalsh(K)[0]
        info: dict[str, Any] = {'solver': 'FastSPDSolver', 'eps_C': eps_c, 'eps_K': eps_k,
                                'rank_u': prob.rank_u, 'objective_lower_bound': np.sqrt(f_ls)}
        if lam_c >= eps_c and lam_k >= eps_k:
            info.update(method='symmetric-least-squares', newton_steps=0, centrings=0,
                        objective=np.sqrt(f_ls), gap_bound=0.0, active_constraints=False)
            return C, K, _jsonable(info)

        # Strictly feasible start: least-squares solution lifted into the cone.
        def start(M: Array, e: float) -> Array:
            lam = np.linalg.eigvalsh(M)
            return idx.svec(_lift(M, e + max(1e-2 * float(np.max(np.abs(lam))), 1e-12, e))
                            - e * eye)

        eye = np.eye(r)
        theta_eps = idx.join(eps_c * eye, eps_k * eye)
        c_full = fgrad(theta_eps)
        # K's constraint is inactive at the least-squares point: eliminate K exactly
        # (unconstrained symmetric least squares in K for each C, a Schur complement), solve the
        # one-cone problem in C (half the unknowns, an eighth of the factorization cost), and
        # keep the result if its K is feasible: then the KKT conditions of the full problem
        # hold with a zero multiplier for K.
        res = (self._eliminate_k(hf_factor, c_full, fval, theta_eps, idx, start(C, eps_c), eps_k)
               if lam_k >= eps_k and hf_factor.full is None else None)
        if res is None:
            x0 = np.concatenate([start(C, eps_c), start(K, eps_k)])
            x, ipm = solve_two_cone_qp(Hf, c_full, lambda x_: fval(x_ + theta_eps), idx, x0,
                                       h_factor=hf_factor, rtol=self.rtol,
                                       max_iter=self.max_newton)
            ipm['eliminated_K'] = False
        else:
            x, ipm = res
        C, K = idx.split(x + theta_eps)
        f = fval(x + theta_eps)
        info.update(method='primal-dual-interior-point', newton_steps=ipm['iterations'],
                    eliminated_K=ipm['eliminated_K'],
                    objective=np.sqrt(f), gap_bound=ipm['gap_bound'] / max(f, 1e-300),
                    active_constraints=True,
                    objective_lower_bound=float(np.sqrt(max(ipm['dual_bound'], 0.0))),
                    lambda_min_C=float(np.linalg.eigvalsh(C)[0]),
                    lambda_min_K=float(np.linalg.eigvalsh(K)[0]))
        return C, K, _jsonable(info)


    def _eliminate_k(self, bf: BlockFactor, c: Array, fval: Any, theta_eps: Array,
                     idx: _SymIndex, xc0: Array, eps_k: float
                     ) -> tuple[Array, dict[str, Any]] | None:
        """The one-cone problem in C with K eliminated; ``None`` if K ends up infeasible."""
        n = idx.n
        tk = np.asarray(sla.cho_solve(bf.fk, c[n:], check_finite=False))
        T = np.column_stack([bf.T, tk])
        Hs = bf.S
        cs = c[:n] - bf.Hck @ tk

        def full(xc: Array) -> Array:
            return np.concatenate([xc, -(T[:, :n] @ xc + T[:, n])])

        def fred(xc: Array) -> float:
            return float(fval(full(xc) + theta_eps))

        try:
            xc, ipm = solve_two_cone_qp(Hs, cs, fred, idx, xc0, h_factor=bf.fs,
                                        rtol=self.rtol, max_iter=self.max_newton, n_cones=1)
        except SolverError:
            return None
        x = full(xc)
        K = idx.smat(x[n:]) + eps_k * np.eye(idx.r)
        if float(np.linalg.eigvalsh(K)[0]) < eps_k:
            return None
        ipm['eliminated_K'] = True
        return x, ipm


class CvxpySolver:
    """Reference solver: the conic program written with cvxpy.

    Parameters
    ----------
    solver : str
        cvxpy solver name, ``'CLARABEL'`` (default) or ``'SCS'``.
    formulation : str
        ``'reduced'``: ``min ||[C, K] A + G||_F`` on :class:`ReducedProblem` data (B
        eliminated, ``q ≤ 3r`` columns). ``'raw'``: the straightforward
        ``min ||Q̈ + C Q̇ + K Q - B U||_F`` over the ``r × k`` residual with ``B`` as a
        variable, as one would write it in CVX (the benchmark baseline).
    rank_rtol : float
        As in :class:`FastSPDSolver`.
    **solver_options
        Passed to ``cvxpy.Problem.solve``.

    Notes
    -----
    Whatever the formulation, the returned ``B`` is the minimum-norm optimal ``B`` for the
    returned ``(C, K)`` (unique B does not exist when U is rank-deficient).
    """

    def __init__(self, solver: str = 'CLARABEL', *, formulation: str = 'reduced',
                 rank_rtol: float = DEFAULT_RANK_RTOL, **solver_options: Any) -> None:
        if formulation not in ('reduced', 'raw'):
            raise ConfigError(f"formulation must be 'reduced' or 'raw'; got {formulation!r}.")
        self.solver = solver
        self.formulation = formulation
        self.rank_rtol = rank_rtol
        self.solver_options = solver_options

    def __repr__(self) -> str:
        return f'CvxpySolver({self.solver!r}, formulation={self.formulation!r})'

    def solve(self, Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
              eps: Margin = DEFAULT_EPS) -> LOpInfSolution:
        """Solve the LOpInf operator problem with cvxpy; see :meth:`FastSPDSolver.solve`."""
        import cvxpy as cp

        t0 = time.perf_counter()
        Q, Qd, Qdd, U = _check_data(Q, Qd, Qdd, U)
        r = Q.shape[0]
        prob = reduce_data(Q, Qd, Qdd, U, rank_rtol=self.rank_rtol)
        Cv = cp.Variable((r, r), symmetric=True)
        Kv = cp.Variable((r, r), symmetric=True)
        eps_c, eps_k = split_margin(eps)
        cons = [Cv >> eps_c * np.eye(r), Kv >> eps_k * np.eye(r)]
        if self.formulation == 'reduced':
            expr = cp.hstack([Cv, Kv]) @ prob.A + prob.G
        else:
            Bv = cp.Variable((r, U.shape[0]))
            expr = Qdd + Cv @ Qd + Kv @ Q - Bv @ U
        problem = cp.Problem(cp.Minimize(cp.norm(expr, 'fro')), cons)
        try:
            problem.solve(solver=self.solver, **self.solver_options)
        except cp.error.SolverError as err:
            raise SolverError(f'cvxpy solver {self.solver} failed: {err}') from err
        cval, kval = Cv.value, Kv.value
        if (problem.status not in ('optimal', 'optimal_inaccurate') or cval is None
                or kval is None):
            raise SolverError(f'cvxpy solver {self.solver} returned status {problem.status!r}.')
        C = 0.5 * (cval + cval.T)
        K = 0.5 * (kval + kval.T)
        B = prob.best_B(C, K)
        info = {'solver': 'CvxpySolver', 'backend': self.solver,
                'formulation': self.formulation, 'status': problem.status, 'eps_C': eps_c,
                'eps_K': eps_k,
                'rank_u': prob.rank_u, 'objective': prob.residual_norm(C, K),
                'cvxpy_objective': float(problem.value),
                'time_s': time.perf_counter() - t0}
        return LOpInfSolution(K, C, B, _jsonable(info))


def _jsonable(info: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, val in info.items():
        if isinstance(val, (bool, np.bool_)):
            out[key] = bool(val)
        elif isinstance(val, (int, np.integer)):
            out[key] = int(val)
        elif isinstance(val, (float, np.floating)):
            out[key] = float(val)
        else:
            out[key] = val
    return out
