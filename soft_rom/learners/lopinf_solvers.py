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
  is already ``≥ eps`` it *is* the optimum and is returned; otherwise a primal log-barrier
  interior-point method (damped Newton on the reduced problem; Newton steps are affine
  invariant, i.e. perfectly preconditioned, which is what ill-conditioned POD data need),
  started from the least-squares solution with its eigenvalues lifted into the cone, stopped
  when the duality-gap bound ``2r / t`` falls below ``rtol`` times the objective.
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
              eps: float = DEFAULT_EPS) -> LOpInfSolution:
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
    R = np.linalg.qr(np.vstack([Zp, Dp]).T, mode='r')
    return ReducedProblem(A=np.ascontiguousarray(R[:, :2 * r].T),
                          G=np.ascontiguousarray(R[:, 2 * r:].T), Zv=Zv, Dv=Dv,
                          pinv_left=pinv_left, rank_u=rho,
                          norm_qdd=float(np.linalg.norm(Qdd)))


# -- symmetric parameterisation ---------------------------------------------------------------


class _SymIndex:
    """svec coordinates of a pair (C, K) of symmetric r×r matrices (orthonormal basis)."""

    def __init__(self, r: int) -> None:
        self.r = r
        iu, ju = np.triu_indices(r)
        self.iu, self.ju = iu, ju
        self.n = iu.size  # per matrix
        diag = iu == ju
        self.scale = np.where(diag, 1.0, np.sqrt(2.0))
        w = np.where(diag, 0.5, 1.0 / np.sqrt(2.0))
        # Each basis element E = w (e_p e_q^T + e_q e_p^T); (p, q) = (iu, ju).
        self.p = [iu, ju]
        self.q = [ju, iu]
        self.w = [w, w]
        self._cc = 2.0 * np.outer(w, w)
        self._pp = iu[:, None] * r + iu[None, :]
        self._qq = ju[:, None] * r + ju[None, :]
        self._pq = iu[:, None] * r + ju[None, :]
        self._qp = ju[:, None] * r + iu[None, :]

    def svec(self, M: Array) -> Array:
        return M[self.iu, self.ju] * self.scale

    def smat(self, v: Array) -> Array:
        M = np.zeros((self.r, self.r))
        M[self.iu, self.ju] = v / self.scale
        return M + M.T - np.diag(np.diag(M))

    def split(self, theta: Array) -> tuple[Array, Array]:
        return self.smat(theta[:self.n]), self.smat(theta[self.n:])

    def join(self, C: Array, K: Array) -> Array:
        return np.concatenate([self.svec(C), self.svec(K)])

    def grad(self, GW: Array) -> Array:
        """Gradient in svec coordinates from a gradient w.r.t. the entries of W = [C, K]."""
        r = self.r
        GC, GK = GW[:, :r], GW[:, r:]
        return np.concatenate([self.svec(0.5 * (GC + GC.T)), self.svec(0.5 * (GK + GK.T))])

    def hessian_quadratic(self, Gz: Array) -> Array:
        """Hessian of ``tr(W Gz Wᵀ)`` in svec coordinates (without the factor 2)."""
        r, n = self.r, self.n
        rows, cols, ws = [], [], []
        for off in (0, r):
            for s in range(2):
                rows.append(self.p[s])
                cols.append(self.q[s] + off)
                ws.append(self.w[s])
        # Stack C-part and K-part: each element has two entries (s = 0, 1).
        row_s = [np.concatenate([rows[0], rows[2]]), np.concatenate([rows[1], rows[3]])]
        col_s = [np.concatenate([cols[0], cols[2]]), np.concatenate([cols[1], cols[3]])]
        w_s = [np.concatenate([ws[0], ws[2]]), np.concatenate([ws[1], ws[3]])]
        H = np.zeros((2 * n, 2 * n))
        for s in range(2):
            for t in range(2):
                H += (np.outer(w_s[s], w_s[t]) * Gz[np.ix_(col_s[s], col_s[t])]
                      * (row_s[s][:, None] == row_s[t][None, :]))
        return H

    def hessian_logdet(self, Xi: Array) -> Array:
        """``tr(Xi E_a Xi E_b)``: Hessian of ``-logdet X`` in svec coordinates.

        With ``E_a = c_a (e_p e_qᵀ + e_q e_pᵀ)`` this is
        ``2 c_a c_b (Xi[p,k] Xi[q,l] + Xi[p,l] Xi[q,k])`` for ``b = (k, l)``.
        """
        x = Xi.ravel()
        H = x.take(self._pp) * x.take(self._qq)
        H += x.take(self._pq) * x.take(self._qp)
        H *= self._cc
        return H


class _Factor:
    """Cholesky factor of a symmetric positive (semi)definite matrix.

    Cholesky needs no diagonal pre-scaling (its accuracy is invariant to it); if the matrix
    is numerically singular, a Jacobi-scaled eigendecomposition gives minimum-norm solutions.
    """

    def __init__(self, H: Array) -> None:
        try:
            self.cho = sla.cho_factor(H, lower=True, check_finite=False)
            self.eig = None
        except np.linalg.LinAlgError:
            d = np.sqrt(np.clip(np.diag(H), 0.0, None))
            d[d == 0] = 1.0
            lam, V = np.linalg.eigh(H * np.outer(1.0 / d, 1.0 / d))
            keep = lam > 1e-13 * max(lam[-1], 1e-300)
            self.cho = None
            self.eig = (lam[keep], V[:, keep], d)

    def solve(self, g: Array) -> Array:
        if self.cho is not None:
            return sla.cho_solve(self.cho, g, check_finite=False)
        lam, V, d = self.eig
        return (V @ ((V.T @ (g / d)) / lam)) / d


def _lift(M: Array, floor: float) -> Array:
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    lam = np.maximum(lam, floor)
    return (V * lam) @ V.T


# -- solvers ----------------------------------------------------------------------------------


class FastSPDSolver:
    """Closed-form symmetric least squares, then a log-barrier interior point if needed.

    The constrained problem on :class:`ReducedProblem` data is

    .. math:: \\min_{\\theta}\\ \\phi_t(\\theta) = t\\,\\|W(\\theta) A + G\\|_F^2
        - \\log\\det(C - \\epsilon I) - \\log\\det(K - \\epsilon I)

    for increasing ``t``; ``θ`` are the ``r(r+1)`` free entries of ``C`` and ``K``. Each
    centring is a damped Newton method with backtracking that keeps iterates strictly
    feasible. After a centring, ``f(θ) - f* ≤ 2r / t`` (squared objective), which is the
    stopping test.

    Parameters
    ----------
    rtol : float
        Stop when the gap bound ``2r/t`` is below ``rtol`` times the squared objective
        (so the Frobenius objective is within about ``rtol/2`` of the optimum).
    mu : float
        Factor by which ``t`` grows between centrings.
    centring_tol : float
        Newton-decrement tolerance of the intermediate centrings (the last one is solved
        to ``1e-10``).
    max_newton : int
        Total Newton steps allowed; :class:`~soft_rom.errors.SolverError` beyond.
    rank_rtol : float
        Relative singular-value threshold for the numerical rank of ``U``.
    """

    def __init__(self, *, rtol: float = 1e-10, mu: float = 30.0, max_newton: int = 500,
                 centring_tol: float = 0.1, rank_rtol: float = DEFAULT_RANK_RTOL) -> None:
        self.rtol = rtol
        self.mu = mu
        self.centring_tol = centring_tol
        self.max_newton = max_newton
        self.rank_rtol = rank_rtol

    def __repr__(self) -> str:
        return f'FastSPDSolver(rtol={self.rtol}, mu={self.mu})'

    def solve(self, Q: ArrayLike, Qd: ArrayLike, Qdd: ArrayLike, U: ArrayLike, *,
              eps: float = DEFAULT_EPS) -> LOpInfSolution:
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

    def solve_reduced(self, prob: ReducedProblem, *, eps: float = DEFAULT_EPS
                      ) -> tuple[Array, Array, dict[str, Any]]:
        """Solve on already reduced data; returns ``C, K, info``."""
        if not eps >= 0:
            raise ConfigError(f'eps must be >= 0; got {eps!r}.')
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
        hf_factor = _Factor(Hf)
        for _ in range(3):
            theta = theta - hf_factor.solve(fgrad(theta))
        f_ls = fval(theta)
        C, K = idx.split(theta)
        lam_c, lam_k = np.linalg.eigvalsh(C)[0], np.linalg.eigvalsh(K)[0]
        info: dict[str, Any] = {'solver': 'FastSPDSolver', 'eps': float(eps),
                                'rank_u': prob.rank_u, 'objective_lower_bound': np.sqrt(f_ls)}
        if lam_c >= eps and lam_k >= eps:
            info.update(method='symmetric-least-squares', newton_steps=0, centrings=0,
                        objective=np.sqrt(f_ls), gap_bound=0.0, active_constraints=False)
            return C, K, _jsonable(info)

        # Strictly feasible start: least-squares solution lifted into the cone.
        def start(M: Array) -> Array:
            lam = np.linalg.eigvalsh(M)
            return _lift(M, eps + max(1e-2 * float(np.max(np.abs(lam))), 1e-12, eps))

        theta = idx.join(start(C), start(K))
        nu = 2.0 * r
        n = idx.n
        floor = max(1e-30, 1e-24 * prob.norm_qdd ** 2)
        eye = np.eye(r)

        def logdet_barrier(theta_: Array) -> float | None:
            C_, K_ = idx.split(theta_)
            val = 0.0
            for M in (C_, K_):
                try:
                    L = np.linalg.cholesky(M - eps * eye)
                except np.linalg.LinAlgError:
                    return None
                val -= 2.0 * float(np.sum(np.log(np.diag(L))))
            return val

        def barrier_derivs(theta_: Array) -> tuple[Array, Array, Array]:
            C_, K_ = idx.split(theta_)
            grads, hess = [], []
            for M in (C_, K_):
                Xi = np.linalg.inv(M - eps * eye)
                Xi = 0.5 * (Xi + Xi.T)
                grads.append(-idx.svec(Xi))
                hess.append(idx.hessian_logdet(Xi))
            return np.concatenate(grads), hess[0], hess[1]

        def residual_change(theta_: Array, step_: Array) -> tuple[float, float]:
            # f(θ + sΔ) - f(θ) = s lin + s² quad, without cancellation.
            Cs, Ks = idx.split(theta_)
            Cd, Kd = idx.split(step_)
            P = np.hstack([Cd, Kd]) @ A
            Res = np.hstack([Cs, Ks]) @ A + G
            return 2.0 * float(np.sum(Res * P)), float(np.sum(P * P))

        f = fval(theta)
        bval = logdet_barrier(theta)
        if bval is None:  # pragma: no cover - the lifted start is strictly feasible
            raise SolverError('LOpInf barrier solver: infeasible start.')
        t = nu / max(f - f_ls, floor)
        steps = centrings = predictions = 0
        final = False
        factor: _Factor | None = None
        while True:
            centrings += 1
            # Intermediate centrings are loose; the last one (whose gap bound is reported) is
            # tight.
            final = final or nu / t <= self.rtol * max(f, floor)
            dec_tol = 1e-10 if final else self.centring_tol
            while True:
                bgrad, Hc, Hk = barrier_derivs(theta)
                g = t * fgrad(theta) + bgrad
                H = t * Hf
                H[:n, :n] += Hc
                H[n:, n:] += Hk
                factor = _Factor(H)
                step = -factor.solve(g)
                dec = -float(g @ step)
                if dec <= dec_tol:
                    break
                lin, quad = residual_change(theta, step)
                s = 1.0
                accepted = False
                while s >= 1e-12:
                    cand = theta + s * step
                    bc = logdet_barrier(cand)
                    if bc is not None:
                        df = s * lin + s * s * quad
                        if t * df + (bc - bval) <= -0.25 * s * dec:
                            accepted = True
                            break
                    s *= 0.5
                steps += 1
                if not accepted:
                    break  # no further progress possible at this precision
                theta, f, bval = cand, f + df, bc
                if steps >= self.max_newton:
                    raise SolverError(f'LOpInf barrier solver did not converge in '
                                      f'{self.max_newton} Newton steps; raise max_newton or '
                                      'rtol, or check the data for NaN/huge values.')
                if final and dec <= 1e-6 and s == 1.0:
                    break  # quadratic convergence regime: one more step would be ~1e-12
            if final:
                break
            cap = nu / (self.rtol * max(f, floor))
            if t * self.mu >= cap:
                t_new, final = max(cap, t), True   # the next centring is the last one
            else:
                t_new = t * self.mu
            if centrings > 200:
                raise SolverError('LOpInf barrier solver: too many centrings; check the data '
                                  'for NaN/huge values.')
            # Predictor: follow the tangent of the central path, dθ/dt = -H⁻¹ ∇f, from the
            # (nearly) centred point, reusing the last factorization; keep it only if it stays
            # feasible and lowers the barrier objective at the new t.
            if factor is not None:
                step = -(t_new - t) * factor.solve(fgrad(theta))
                lin, quad = residual_change(theta, step)
                s = 1.0
                while s >= 1e-3:
                    bc = logdet_barrier(theta + s * step)
                    if bc is not None:
                        df = s * lin + s * s * quad
                        if t_new * df + (bc - bval) < 0:
                            theta, f, bval = theta + s * step, f + df, bc
                            predictions += 1
                            break
                    s *= 0.5
            t = t_new
        C, K = idx.split(theta)
        f = fval(theta)
        info.update(method='log-barrier-newton', newton_steps=steps, centrings=centrings,
                    predictor_steps=predictions,
                    objective=np.sqrt(f), gap_bound=nu / t, active_constraints=True,
                    lambda_min_C=float(np.linalg.eigvalsh(C)[0]),
                    lambda_min_K=float(np.linalg.eigvalsh(K)[0]))
        return C, K, _jsonable(info)


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
              eps: float = DEFAULT_EPS) -> LOpInfSolution:
        """Solve the LOpInf operator problem with cvxpy; see :meth:`FastSPDSolver.solve`."""
        import cvxpy as cp

        t0 = time.perf_counter()
        Q, Qd, Qdd, U = _check_data(Q, Qd, Qdd, U)
        r = Q.shape[0]
        prob = reduce_data(Q, Qd, Qdd, U, rank_rtol=self.rank_rtol)
        Cv = cp.Variable((r, r), symmetric=True)
        Kv = cp.Variable((r, r), symmetric=True)
        cons = [Cv >> eps * np.eye(r), Kv >> eps * np.eye(r)]
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
        if problem.status not in ('optimal', 'optimal_inaccurate') or Cv.value is None:
            raise SolverError(f'cvxpy solver {self.solver} returned status {problem.status!r}.')
        C = 0.5 * (Cv.value + Cv.value.T)
        K = 0.5 * (Kv.value + Kv.value.T)
        B = prob.best_B(C, K)
        info = {'solver': 'CvxpySolver', 'backend': self.solver,
                'formulation': self.formulation, 'status': problem.status, 'eps': float(eps),
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
