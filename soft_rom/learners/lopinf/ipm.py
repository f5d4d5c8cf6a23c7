"""Primal-dual interior point for the reduced LOpInf problem (two symmetric PSD cones).

The problem solved (``θ``: the ``r(r+1)`` svec coordinates of ``C`` and ``K``; ``φ`` the
squared objective ``||[C, K] A + G||_F²``, a convex quadratic with constant Hessian ``H``):

.. math:: \\min_\\theta \\varphi(\\theta) \\quad \\text{s.t.}\\quad
    X_C = C - \\epsilon_C I \\succeq 0,\\quad X_K = K - \\epsilon_K I \\succeq 0.

Optimality: ``∇φ = S`` (``S = (S_C, S_K) ⪰ 0``, the multipliers) and ``X S = 0``.

Method: Mehrotra predictor-corrector with Nesterov-Todd scaling (Todd, Toh & Tütüncü, *On the
Nesterov-Todd direction in semidefinite programming*, SIAM J. Optim. 8(3), 1998). For each
cone the scaling point ``W`` (``W S W = X``) turns the linearized complementarity into
``ΔS = σμ X⁻¹ - S - W⁻¹ ΔX W⁻¹`` (plus the second-order corrector), so every iteration solves

.. math:: (H + W_C^{-1} \\otimes_s W_C^{-1} \\oplus W_K^{-1} \\otimes_s W_K^{-1})\\,\\Delta\\theta
    = -r_d + \\mathrm{svec}(R_c),

one Cholesky factorization of an ``r(r+1)`` square SPD matrix shared by the predictor and the
corrector. The symmetric Kronecker blocks are assembled by index gathers (no ``r⁴`` loops).
A primal-dual method needs about a dozen factorizations where the primal log-barrier path
following needed 20-35 (one per damped Newton step).

Stopping test, certified: for any ``S ⪰ 0`` the Lagrange dual function
``ψ(S) = min_θ φ(θ) - <S, X(θ)>`` (an unconstrained quadratic, one solve with the factored
``H``) is a lower bound on the optimum, so ``φ(θ) - ψ(S)`` bounds the suboptimality of the
iterate; the solver stops when that bound is below ``rtol · φ(θ)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla

from soft_rom.errors import SolverError
from soft_rom.resources import check_memory

__all__ = ['SymIndex', 'SPDFactor', 'lift', 'solve_two_cone_qp']

Array = NDArray[np.float64]


class SymIndex:
    """svec coordinates of a pair (C, K) of symmetric r×r matrices (orthonormal basis)."""

    def __init__(self, r: int) -> None:
        self.r = r
        n = r * (r + 1) // 2
        # five n x n index arrays here and the (2n)^2 Hessian of the solve, at the least
        check_memory(8.0 * 9 * n * n, f'the LOpInf operator solve at r={r} ({2 * n} unknowns)',
                     'Choose a smaller r (model files hold r <= 128 for LOpInf).')
        iu, ju = np.triu_indices(r)
        self.iu, self.ju = iu, ju
        self.n = int(iu.size)  # per matrix
        diag = iu == ju
        self.scale = np.where(diag, 1.0, np.sqrt(2.0))
        w = np.where(diag, 0.5, 1.0 / np.sqrt(2.0))
        # Each basis element E = w (e_p e_q^T + e_q e_p^T); (p, q) = (iu, ju).
        self.w = w
        self._cc = 2.0 * np.outer(w, w)
        self._pp = iu[:, None] * r + iu[None, :]
        self._qq = ju[:, None] * r + ju[None, :]
        self._pq = iu[:, None] * r + ju[None, :]
        self._qp = ju[:, None] * r + iu[None, :]
        # svec -> row-major vec map P (r², n): w at (p r + q) and (q r + p).
        self._row1, self._row2 = iu * r + ju, ju * r + iu
        self._P = np.zeros((r * r, self.n))
        cols = np.arange(self.n)
        np.add.at(self._P, (self._row1, cols), w)
        np.add.at(self._P, (self._row2, cols), w)

    def svec(self, M: Array) -> Array:
        """Orthonormal svec of a symmetric matrix."""
        return np.asarray(M[self.iu, self.ju] * self.scale)

    def smat(self, v: Array) -> Array:
        """Inverse of :meth:`svec`."""
        M = np.zeros((self.r, self.r))
        M[self.iu, self.ju] = v / self.scale
        return M + M.T - np.diag(np.diag(M))

    def split(self, theta: Array) -> tuple[Array, Array]:
        """``(C, K)`` from the stacked svec coordinates."""
        return self.smat(theta[:self.n]), self.smat(theta[self.n:])

    def join(self, C: Array, K: Array) -> Array:
        """Stacked svec coordinates of ``(C, K)``."""
        return np.concatenate([self.svec(C), self.svec(K)])

    def grad(self, GW: Array) -> Array:
        """Gradient in svec coordinates from a gradient w.r.t. the entries of W = [C, K]."""
        r = self.r
        GC, GK = GW[:, :r], GW[:, r:]
        return np.concatenate([self.svec(0.5 * (GC + GC.T)), self.svec(0.5 * (GK + GK.T))])

    def hessian_quadratic(self, Gz: Array) -> Array:
        """Hessian of ``tr(W Gz Wᵀ)`` in svec coordinates (without the factor 2).

        ``tr(W Gz Wᵀ) = Σ_{X, Y ∈ {C, K}} tr(X M_XY Y)`` and, with row-major ``vec``,
        ``tr(X M Y) = vec(X)ᵀ (I ⊗ M) vec(Y)``; so each block is ``Pᵀ (I ⊗ M) P`` with ``P``
        the svec-to-vec map (two entries per column): one batched product and two row
        gathers per block.
        """
        r, n = self.r, self.n
        H = np.empty((2 * n, 2 * n))
        P3 = self._P.reshape(r, r, n)
        for i in range(2):
            for j in range(2):
                M = Gz[i * r:(i + 1) * r, j * r:(j + 1) * r]
                Y = np.matmul(M, P3).reshape(r * r, n)          # (I ⊗ M) P
                H[i * n:(i + 1) * n, j * n:(j + 1) * n] = self.w[:, None] * (
                    Y[self._row1] + Y[self._row2])
        return H

    def _hessian_quadratic_reference(self, Gz: Array) -> Array:
        """Loop-free but slow reference of :meth:`hessian_quadratic` (tests)."""
        r, n = self.r, self.n
        p, q, w = [self.iu, self.ju], [self.ju, self.iu], [self.w, self.w]
        rows, cols, ws = [], [], []
        for off in (0, r):
            for s in range(2):
                rows.append(p[s])
                cols.append(q[s] + off)
                ws.append(w[s])
        row_s = [np.concatenate([rows[0], rows[2]]), np.concatenate([rows[1], rows[3]])]
        col_s = [np.concatenate([cols[0], cols[2]]), np.concatenate([cols[1], cols[3]])]
        w_s = [np.concatenate([ws[0], ws[2]]), np.concatenate([ws[1], ws[3]])]
        H = np.zeros((2 * n, 2 * n))
        for s in range(2):
            for t in range(2):
                H += (np.outer(w_s[s], w_s[t]) * Gz[np.ix_(col_s[s], col_s[t])]
                      * (row_s[s][:, None] == row_s[t][None, :]))
        return H

    def skron(self, Xi: Array) -> Array:
        """Svec matrix of ``ΔX ↦ Xi ΔX Xi`` (``Xi ⊗_s Xi``, Xi symmetric).

        With ``E_a = c_a (e_p e_qᵀ + e_q e_pᵀ)`` the entry is
        ``2 c_a c_b (Xi[p,k] Xi[q,l] + Xi[p,l] Xi[q,k])`` for ``b = (k, l)``.
        """
        x = Xi.ravel()
        H = x.take(self._pp) * x.take(self._qq)
        H += x.take(self._pq) * x.take(self._qp)
        H *= self._cc
        return H


class SPDFactor:
    """Cholesky factor of a symmetric positive (semi)definite matrix.

    Cholesky needs no diagonal pre-scaling (its accuracy is invariant to it); if the matrix
    is numerically singular, a Jacobi-scaled eigendecomposition gives minimum-norm solutions.
    """

    def __init__(self, H: Array) -> None:
        self.cho: Any = None
        self.eig: tuple[Array, Array, Array] | None = None
        try:
            self.cho = sla.cho_factor(H, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            d = np.sqrt(np.clip(np.diag(H), 0.0, None))
            d[d == 0] = 1.0
            lam, V = np.linalg.eigh(H * np.outer(1.0 / d, 1.0 / d))
            keep = lam > 1e-13 * max(lam[-1], 1e-300)
            self.eig = (lam[keep], V[:, keep], d)

    def solve(self, g: Array) -> Array:
        """``H⁻¹ g`` (minimum norm when ``H`` is singular)."""
        if self.cho is not None:
            return np.asarray(sla.cho_solve(self.cho, g, check_finite=False))
        assert self.eig is not None
        lam, V, d = self.eig
        return np.asarray((V @ ((V.T @ (g / d)) / lam)) / d)


def lift(M: Array, floor: float) -> Array:
    """``M`` with its eigenvalues raised to at least ``floor``."""
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    lam = np.maximum(lam, floor)
    return np.asarray((V * lam) @ V.T)


def _max_step(L: Array, D: Array) -> float:
    """Largest ``α ≤ 1e30`` with ``L Lᵀ + α D ⪰ 0`` (``L`` Cholesky factor)."""
    Li_D = sla.solve_triangular(L, D, lower=True, check_finite=False)
    T = sla.solve_triangular(L, Li_D.T, lower=True, check_finite=False)
    lam = float(np.linalg.eigvalsh(0.5 * (T + T.T))[0])
    return 1e30 if lam >= 0 else -1.0 / lam


def _nt_scaling(X: Array, S: Array) -> tuple[Array, Array, Array]:
    """Cholesky factor of X, the NT point's inverse ``W⁻¹`` and ``X⁻¹``."""
    L = np.linalg.cholesky(X)
    M = L.T @ S @ L
    lam, U = np.linalg.eigh(0.5 * (M + M.T))
    lam = np.maximum(lam, 1e-300)
    Li = sla.solve_triangular(L, np.eye(L.shape[0]), lower=True, check_finite=False)
    T = Li.T @ U                                      # L⁻ᵀ U
    Wi = (T * np.sqrt(lam)) @ T.T                     # W⁻¹ = L⁻ᵀ U Λ^½ Uᵀ L⁻¹
    Xi = Li.T @ Li
    return (np.asarray(L, dtype=np.float64), np.asarray(0.5 * (Wi + Wi.T), dtype=np.float64),
            np.asarray(0.5 * (Xi + Xi.T), dtype=np.float64))


def _split(idx: SymIndex, v: Array, nc: int) -> list[Array]:
    """The ``nc`` symmetric matrices of a stacked svec vector."""
    n = idx.n
    return [idx.smat(v[i * n:(i + 1) * n]) for i in range(nc)]


def _join(idx: SymIndex, Ms: list[Array]) -> Array:
    """The stacked svec vector of symmetric matrices."""
    return np.concatenate([idx.svec(M) for M in Ms])


class _NewtonSystem:
    """One interior-point iteration's Newton system: NT scalings and the factored matrix.

    Built from the current iterate ``(X, S)`` of each cone and the dual residual ``rd``;
    raises ``numpy.linalg.LinAlgError`` when the scaled matrix is not positive definite.
    """

    def __init__(self, H: Array, idx: SymIndex, nc: int, Xs: list[Array], Ss: list[Array],
                 rd: Array) -> None:
        n = idx.n
        self.idx, self.nc, self.Ss, self.rd = idx, nc, Ss, rd
        self.scal = [_nt_scaling(X, S) for X, S in zip(Xs, Ss)]
        Hn = H.copy()
        for i in range(nc):
            Hn[i * n:(i + 1) * n, i * n:(i + 1) * n] += idx.skron(self.scal[i][1])
        self.fac = sla.cho_factor(Hn, lower=True, check_finite=False)

    def direction(self, Rc: list[Array]) -> tuple[Array, list[Array], list[Array]]:
        """``(Δx, ΔX, ΔS)`` for the complementarity right-hand sides ``Rc``."""
        scal, nc = self.scal, self.nc
        rhs = -self.rd + _join(self.idx, Rc)
        dx = sla.cho_solve(self.fac, rhs, check_finite=False)
        dX = list(_split(self.idx, dx, nc))
        dS = [Rc[i] - scal[i][1] @ dX[i] @ scal[i][1] for i in range(nc)]
        dS = [0.5 * (M + M.T) for M in dS]
        return dx, dX, dS

    def step_len(self, dX: list[Array], dS: list[Array]) -> float:
        """Largest step along ``(ΔX, ΔS)`` that keeps every ``X`` and ``S`` in its cone."""
        a = 1e30
        for i in range(self.nc):
            a = min(a, _max_step(self.scal[i][0], dX[i]),
                    _max_step(np.asarray(np.linalg.cholesky(self.Ss[i])), dS[i]))
        return a

    def mehrotra_step(self, Xs: list[Array], mu: float
                      ) -> tuple[Array, list[Array], list[Array], float]:
        """Predictor-corrector direction ``(Δx, ΔX, ΔS)`` and its step length."""
        Ss, scal, nc, r = self.Ss, self.scal, self.nc, self.idx.r
        # Predictor (affine scaling).
        Rc_aff = [-S for S in Ss]
        dx_a, dX_a, dS_a = self.direction(Rc_aff)
        a_aff = min(1.0, self.step_len(dX_a, dS_a))
        mu_aff = sum(float(np.sum((X + a_aff * dX) * (S + a_aff * dS)))
                     for X, S, dX, dS in zip(Xs, Ss, dX_a, dS_a)) / (nc * r)
        sigma = min(max((mu_aff / mu) ** 3, 0.0), 1.0)
        # Corrector: centring plus the second-order term sym(X⁻¹ ΔX_a ΔS_a).
        Rc = []
        for i in range(nc):
            Xi = scal[i][2]
            T = Xi @ dX_a[i] @ dS_a[i]
            Rc.append(sigma * mu * Xi - Ss[i] - 0.5 * (T + T.T))
        dx, dX, dS = self.direction(Rc)
        alpha = min(1.0, 0.98 * self.step_len(dX, dS))
        if alpha < 0.5 * a_aff:
            # The second-order term can point out of the cone (it is a heuristic in the NT
            # scaling); then take the plain centred direction.
            sigma = max(sigma, 0.1)
            dx, dX, dS = self.direction([sigma * mu * scal[i][2] - Ss[i] for i in range(nc)])
            alpha = min(1.0, 0.98 * self.step_len(dX, dS))
        return dx, dX, dS, alpha


def solve_two_cone_qp(H: Array, c: Array, fval: Any, idx: SymIndex, x0: Array, *,
                      h_factor: Any, rtol: float, max_iter: int = 100, n_cones: int = 2
                      ) -> tuple[Array, dict[str, Any]]:
    """Minimize ``φ(x) = ½ xᵀ H x + cᵀ x + φ₀`` over ``x = (svec X_C, svec X_K)`` in two PSD cones.

    Each iteration checks the certified gap, then takes one Mehrotra predictor-corrector
    step (:class:`_NewtonSystem`) to a fraction of the distance to the cones' boundary.

    Parameters
    ----------
    H : ndarray, shape (2n, 2n)
        Hessian of ``φ`` (SPD or PSD), ``n = r(r+1)/2``.
    c : ndarray, shape (2n,)
        ``∇φ(0)``.
    fval : callable
        ``fval(x) -> φ(x)`` evaluated accurately from the data (for the stopping test).
    idx : SymIndex
    x0 : ndarray, shape (2n,)
        Strictly feasible start (both matrices positive definite).
    h_factor : SPDFactor
        Factor of ``H`` (for the dual bound).
    rtol : float
        Stop when ``φ(x) - ψ(S) ≤ rtol · φ(x)``.
    max_iter : int
    n_cones : int
        2: ``x = (svec X_C, svec X_K)``; 1: ``x = svec X`` (one cone).

    Returns
    -------
    x : ndarray, shape (2n,)
    info : dict
        ``iterations``, ``gap_bound`` (absolute, on ``φ``), ``dual_bound``.
    """
    r = idx.r
    nc = int(n_cones)
    x = x0.copy()
    d0 = x - h_factor.solve(-c)                      # x0 minus the unconstrained minimizer
    mu0 = max(float(d0 @ (H @ d0)) / (nc * r), 1e-300)
    Xs = list(_split(idx, x, nc))
    Ss: list[Array] = [np.asarray(mu0 * np.linalg.inv(X), dtype=np.float64) for X in Xs]
    s = _join(idx, Ss)
    best: tuple[float, Array, float] | None = None
    it = 0
    while it < max_iter:
        it += 1
        rd = H @ x + c - s
        f = float(fval(x))
        # Certified lower bound from the dual point S (any S ⪰ 0 works).
        xh = h_factor.solve(s - c)
        psi = float(fval(xh)) - float(s @ xh)
        gap = f - psi
        if best is None or gap < best[0]:
            best = (gap, x.copy(), psi)
        if gap <= rtol * max(abs(f), 1e-300):
            break
        mu = float(x @ s) / (nc * r)
        try:
            system = _NewtonSystem(H, idx, nc, Xs, Ss, rd)
        except np.linalg.LinAlgError:
            break
        dx, dX, dS, alpha = system.mehrotra_step(Xs, mu)
        x = x + alpha * dx
        Xs = [Xs[i] + alpha * dX[i] for i in range(nc)]
        Ss = [Ss[i] + alpha * dS[i] for i in range(nc)]
        Xs = [np.asarray(0.5 * (M + M.T), dtype=np.float64) for M in Xs]
        Ss = [np.asarray(0.5 * (M + M.T), dtype=np.float64) for M in Ss]
        x = _join(idx, Xs)
        s = _join(idx, Ss)
        if not all(np.all(np.isfinite(M)) for M in Xs + Ss):
            raise SolverError('LOpInf interior point: non-finite iterate; check the data for '
                              'NaN/huge values.')
    assert best is not None
    gap, x_best, psi = best
    if gap > rtol * max(abs(float(fval(x_best))), 1e-300) * 1e3:
        raise SolverError(f'LOpInf interior point stopped after {it} iterations with a gap '
                          f'bound {gap:.3g} (relative '
                          f'{gap / max(abs(float(fval(x_best))), 1e-300):.3g}); '
                          'check the data for NaN/huge values.')
    return x_best, {'iterations': it, 'gap_bound': max(gap, 0.0), 'dual_bound': psi}


class BlockFactor:
    """Solves with ``H = [[H_cc, H_ck], [H_kc, H_kk]]`` by eliminating the K block.

    Factors ``H_kk`` and the Schur complement ``S = H_cc - H_ck H_kk⁻¹ H_kc`` (each half the
    size of ``H``: a quarter of the Cholesky cost together); ``S`` and ``T = H_kk⁻¹ H_kc`` are
    what the one-cone problem in C needs. Falls back to :class:`SPDFactor` of the whole ``H``
    when ``H_kk`` is not numerically positive definite.
    """

    def __init__(self, H: Array, n: int) -> None:
        self.n = n
        self.full: SPDFactor | None = None
        try:
            self.fk = sla.cho_factor(H[n:, n:], lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            self.full = SPDFactor(H)
            return
        self.Hck = H[:n, n:]
        self.T = np.asarray(sla.cho_solve(self.fk, self.Hck.T, check_finite=False))
        S = H[:n, :n] - self.Hck @ self.T
        self.S = 0.5 * (S + S.T)
        self.fs = SPDFactor(self.S)

    def solve(self, g: Array) -> Array:
        """``H⁻¹ g``."""
        if self.full is not None:
            return self.full.solve(g)
        n = self.n
        yk = sla.cho_solve(self.fk, g[n:], check_finite=False)
        xc = self.fs.solve(g[:n] - self.Hck @ yk)
        return np.concatenate([xc, yk - self.T @ xc])
