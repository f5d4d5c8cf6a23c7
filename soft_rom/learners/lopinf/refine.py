"""Output-error refinement of LOpInf operators: fit what the ROM is used for, a simulation.

Why: LOpInf's operator problem is an *equation-error* criterion: it compares the measured
coordinates' second derivative with ``-C q' - K q + B u`` sample by sample. On measured
coordinates (motion capture with noise) the derivatives are estimated from noisy data, so
the regressors carry errors too (an errors-in-variables problem): the least-squares
operators are biased, more so the more the estimator smooths (it delays and flattens the
signals it differentiates). An unconstrained fit can absorb part of that bias with
non-symmetric operators; the SPD-constrained one cannot. The classical remedy of system
identification is the *output-error* (prediction-error) criterion: the operators that make
the simulated coordinates closest to the measured ones,

.. math::

    \\min_{K, C, B, x_0} \\sum_i \\| L^{-T} z_i(K, C, B, x_{0,i}) - \\hat Q_i \\|_F^2,
    \\qquad \\ddot z + C \\dot z + K z = B u, \\ z(0), \\dot z(0) = x_{0,i},

with inputs held over each sample as in :meth:`~soft_rom.models.SecondOrderModel.simulate`
and ``z = Lᵀ q`` the coordinates of the learned mass (``L = I`` for the identity mass).
Measurement noise on ``Q̂`` enters only as output noise here, so the criterion is
unbiased for it. The constraints are kept by the parametrization

.. math::

    K = \\varepsilon_K I + L_K L_K^T, \\qquad C = \\alpha I + \\beta K + L_C L_C^T

(``L_K``, ``L_C`` lower triangular): the refined ROM keeps SPD stiffness and damping and
the minimum damping ratio of :mod:`soft_rom.learners.lopinf.margins`, so it is
asymptotically stable for every iterate. The problem is not convex; it is started from the
equation-error LOpInf solution (a good and stable start) and solved by Levenberg–Marquardt
with exact gradients: the sensitivities of the held-input discretization (Fréchet
derivatives of the matrix exponential) are propagated along the trajectory by the same
recursion as the states, in blocks of time, so that memory does not grow with the episode
length. An iterate is accepted only if it lowers the simulation error; the result is never
worse on the training episodes than the start (``info['improvement']``).
"""

from __future__ import annotations

from collections.abc import Sequence
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla

from soft_rom.models import run_states

__all__ = ['REFINE_CHOICES', 'refine_output_error']

Array = NDArray[np.float64]

#: Values of the ``refine`` hyperparameter of :class:`~soft_rom.learners.lopinf.LOpInf`.
REFINE_CHOICES = ('none', 'output-error')

#: Most parameters x samples x coordinates held at once (time blocks are cut to this).
_BLOCK_BUDGET = 4_000_000

#: Most work of one Levenberg–Marquardt iteration, samples x r x parameters² (about a
#: second here); a larger problem is not refined (``status`` ``'skipped_too_large'``).
MAX_WORK = 3e10


class _Problem:
    """The parametrization, the simulation and the normal equations (module docstring)."""

    def __init__(self, episodes: Sequence[tuple[Array, Array]], dt: float, Lt: Array,
                 margin: dict[str, float], free_mass: bool = False) -> None:
        self.Q = [np.asarray(q, dtype=np.float64) for q, _ in episodes]
        self.U = [np.asarray(u, dtype=np.float64) for _, u in episodes]
        self.dt = float(dt)
        self.r = int(Lt.shape[0])
        self.m = int(self.U[0].shape[0])
        self.Lt = np.asarray(Lt, dtype=np.float64)
        self.Lt_inv: Array = np.asarray(np.linalg.inv(self.Lt), dtype=np.float64)
        self.alpha = float(margin['alpha'])
        self.beta = float(margin['beta'])
        self.eps_k = float(margin['eps_K'])
        r = self.r
        self.il = np.tril_indices(r)
        self.nl = len(self.il[0])
        self.n_op = 2 * self.nl + r * self.m
        # the mass factor's upper triangle (z = Lt q), when it is refined too
        self.iu = np.triu_indices(r)
        self.n_mass = len(self.iu[0]) if free_mass else 0
        self.n_shared = self.n_op + self.n_mass
        self._iu_diag = np.flatnonzero(self.iu[0] == self.iu[1])
        self.P = self.n_shared + 2 * r * len(self.Q)

    # -- parameters ------------------------------------------------------------------
    def pack(self, K: Array, C: Array, B: Array, x0s: Sequence[Array]) -> Array:
        r = self.r
        eye = np.eye(r)
        Lk = _factor(K - self.eps_k * eye)
        Lc = _factor(C - self.alpha * eye - self.beta * K)
        mass = [self.Lt[self.iu]] if self.n_mass else []
        return np.concatenate([Lk[self.il], Lc[self.il], B.ravel(), *mass, *x0s])

    def mass_factor(self, p: Array) -> tuple[Array, Array]:
        """``Lt`` and its inverse at ``p``."""
        if not self.n_mass:
            return self.Lt, self.Lt_inv
        Lt = np.zeros((self.r, self.r))
        Lt[self.iu] = p[self.n_op:self.n_shared]
        return Lt, np.asarray(np.linalg.inv(Lt), dtype=np.float64)

    def unpack(self, p: Array) -> tuple[Array, Array, Array, Array, Array, list[Array]]:
        r, nl, m = self.r, self.nl, self.m
        Lk = np.zeros((r, r))
        Lk[self.il] = p[:nl]
        Lc = np.zeros((r, r))
        Lc[self.il] = p[nl:2 * nl]
        B = p[2 * nl:2 * nl + r * m].reshape(r, m)
        eye = np.eye(r)
        K = self.eps_k * eye + Lk @ Lk.T
        C = self.alpha * eye + self.beta * K + Lc @ Lc.T
        o = self.n_shared
        x0s = [p[o + 2 * r * i:o + 2 * r * (i + 1)] for i in range(len(self.Q))]
        return K, C, B, Lk, Lc, x0s

    def _augmented(self, K: Array, C: Array, B: Array) -> Array:
        r, m = self.r, self.m
        M = np.zeros((2 * r + m, 2 * r + m))
        M[:r, r:2 * r] = np.eye(r)
        M[r:2 * r, :r] = -K
        M[r:2 * r, r:2 * r] = -C
        M[r:2 * r, 2 * r:] = B
        return M * self.dt

    def set_caps(self, K0: Array, C0: Array) -> None:
        """Bounds on the spectra of ``K`` and ``C`` (identifiability, module docstring)."""
        w_nyq = np.pi / self.dt
        self.k_cap = max(w_nyq ** 2, 10.0 * float(np.linalg.eigvalsh(K0)[-1]))
        self.c_cap = max(2.0 * w_nyq, 10.0 * float(np.linalg.eigvalsh(C0)[-1]))

    # -- cost ------------------------------------------------------------------------
    def cost(self, p: Array) -> float:
        K, C, B, _, _, x0s = self.unpack(p)
        if (float(np.linalg.eigvalsh(K)[-1]) > getattr(self, 'k_cap', np.inf)
                or float(np.linalg.eigvalsh(C)[-1]) > getattr(self, 'c_cap', np.inf)):
            return float('inf')
        if self.n_mass:
            diag = np.abs(p[self.n_op:self.n_shared][self._iu_diag])
            if not np.min(diag) > 1e-8 * np.max(diag):     # a singular mass factor
                return float('inf')
        Lt, Lt_inv = self.mass_factor(p)
        with np.errstate(all='ignore'):
            F = sla.expm(self._augmented(K, C, B))
        n = 2 * self.r
        Ad, Bd = F[:n, :n], F[:n, n:]
        total = 0.0
        for q, u, x0 in zip(self.Q, self.U, x0s):
            X = run_states(Ad, Bd, x0, u)[:, :-1]
            total += float(np.sum((Lt_inv @ X[:self.r] - q) ** 2))
        return total if np.isfinite(total) else float('inf')

    def tail_error(self, p: Array, heads: Sequence[int]) -> float:
        """Relative simulation error on the samples after ``heads[i]`` of every episode."""
        K, C, B, _, _, x0s = self.unpack(p)
        _, Lt_inv = self.mass_factor(p)
        n = 2 * self.r
        with np.errstate(all='ignore'):
            F = sla.expm(self._augmented(K, C, B))
            num = den = 0.0
            for q, u, x0, h in zip(self.Q, self.U, x0s, heads):
                X = run_states(F[:n, :n], F[:n, n:], x0, u)[:, :-1]
                num += float(np.sum((Lt_inv @ X[:self.r, h:] - q[:, h:]) ** 2))
                den += float(np.sum(q[:, h:] ** 2))
        val = float(np.sqrt(num / max(den, 1e-300)))
        return val if np.isfinite(val) else float('inf')

    # -- normal equations ------------------------------------------------------------
    def normal(self, p: Array) -> tuple[Array, Array, float]:
        """``JᵀJ``, ``Jᵀres`` and the cost at ``p``."""
        r, n = self.r, 2 * self.r
        K, C, B, Lk, Lc, x0s = self.unpack(p)
        _, Lt_inv = self.mass_factor(p)
        F, dF = _frechet_rows(self._augmented(K, C, B), r, n, self.dt)
        Ad, Bd = F[:n, :n], F[:n, n:]
        # d(Ad, Bd) / d(operator parameters): (n, n + m, n_op)
        dFG = np.tensordot(dF, self._chain(K, Lk, Lc), axes=([0], [0]))
        n_op, n_sh = self.n_op, self.n_shared
        ia, ib = self.iu
        JtJ = np.zeros((self.P, self.P))
        Jtr = np.zeros(self.P)
        total = 0.0
        block = max(8, _BLOCK_BUDGET // max(1, n * (n_op + n)))
        for i, (q, u, x0) in enumerate(zip(self.Q, self.U, x0s)):
            k = q.shape[1]
            X = run_states(Ad, Bd, x0, u)[:, :-1]                        # (n, k)
            Qsim = Lt_inv @ X[:r]
            res = Qsim - q                                  # (r, k)
            total += float(np.sum(res ** 2))
            XU = np.vstack([X, u])
            # S: sensitivities of the state to [operator parameters, x0 of this episode]
            S = np.zeros((n, n_op + n))
            S[:, n_op:] = np.eye(n)
            cols = np.r_[np.arange(n_sh), n_sh + 2 * r * i + np.arange(n)]
            JtJ_i = np.zeros((cols.size, cols.size))
            Jtr_i = np.zeros(cols.size)
            for j0 in range(0, k, block):
                j1 = min(k, j0 + block)
                D = np.tensordot(XU[:, j0:j1].T, dFG, axes=([1], [1]))   # (kb, n, n_op)
                Sb = np.empty((j1 - j0, n, n_op + n))
                for j in range(j1 - j0):
                    Sb[j] = S
                    S = Ad @ S
                    S[:, :n_op] += D[j]
                Jq = np.matmul(Lt_inv, Sb[:, :r, :])                  # (kb, r, n_op + n)
                if self.n_mass:
                    # q = Lt⁻¹ z: d q / d Lt[a, b] = -Lt⁻¹[:, a] q[b]
                    Jm = -Lt_inv[None, :, ia] * Qsim[ib, j0:j1].T[:, None, :]
                    Jq = np.concatenate([Jq[:, :, :n_op], Jm, Jq[:, :, n_op:]], axis=2)
                Jb = Jq.reshape(-1, cols.size)
                JtJ_i += Jb.T @ Jb
                Jtr_i += Jb.T @ res[:, j0:j1].T.ravel()
            JtJ[np.ix_(cols, cols)] += JtJ_i
            Jtr[cols] += Jtr_i
        return JtJ, Jtr, total

    def _chain(self, K: Array, Lk: Array, Lc: Array) -> Array:
        """``d(elementary entries of M/dt) / d(operator parameters)``, (r(2r+m), n_op)."""
        r, m, nl = self.r, self.m, self.nl
        w = 2 * r + m
        G = np.zeros((r * w, self.n_op))
        ii, jj = self.il
        for t, (c, d) in enumerate(zip(ii, jj)):
            # dK / dLk[c, d] = e_c (Lk[:, d])ᵀ + Lk[:, d] e_cᵀ ; C moves by beta dK
            dK = np.zeros((r, r))
            dK[c, :] += Lk[:, d]
            dK[:, c] += Lk[:, d]
            dC_from_K = self.beta * dK
            dC = np.zeros((r, r))
            dC[c, :] += Lc[:, d]
            dC[:, c] += Lc[:, d]
            for a in range(r):
                G[a * w:a * w + r, t] = -dK[a]
                G[a * w + r:a * w + 2 * r, t] = -dC_from_K[a]
                G[a * w + r:a * w + 2 * r, nl + t] = -dC[a]
        for a in range(r):
            for b in range(m):
                G[a * w + 2 * r + b, 2 * nl + a * m + b] = 1.0
        return G


def _frechet_rows(M: Array, r: int, n: int, dt: float) -> tuple[Array, Array]:
    """``expm(M)`` and its Fréchet derivatives along ``dt·e_{r+a} e_bᵀ`` (rows ``:n``).

    The derivative along ``E`` is ``∫₀¹ e^{sM} E e^{(1-s)M} ds``; for ``E = e_p e_qᵀ`` the
    integrand is the outer product of column ``p`` of ``e^{sM}`` and row ``q`` of
    ``e^{(1-s)M}``, so every direction comes from the same few exponentials. The integral
    is taken by composite 8-point Gauss–Legendre quadrature on ``P = ⌈‖A‖₁⌉`` panels, ``A =
    M[:n, :n]``, each ``e^{tM}`` as ``e^{(j/P)M} e^{(s/P)M}`` (``P + 9`` exponentials; the held
    inputs' columns of ``M`` have zero rows below, so they enter ``e^{sM}`` linearly; on a
    panel the Taylor series in ``s`` converges like ``(‖A‖₁/P)ᵏ/k!``: exact to rounding). No
    eigendecomposition is involved, so defective or nearly defective ``M`` (a slow mode
    beside the held inputs' zero eigenvalues) is no harder than any other. Above
    ``‖A‖₁ = 64`` the directions are taken one by one by :func:`scipy.linalg.expm_frechet`.

    Returns
    -------
    F : ndarray, shape (N, N)
    dF : ndarray, shape (r * N, n, N)
        Entry ``a N + b``: rows ``:n`` of the derivative along ``dt·e_{r+a} e_bᵀ``.
    """
    N = M.shape[0]
    norm = float(np.linalg.norm(M[:n, :n], 1))
    if not np.isfinite(norm) or norm > 64:
        return _frechet_rows_direct(M, r, n, dt)
    panels = max(1, int(np.ceil(norm)))
    x, w = np.polynomial.legendre.leggauss(8)
    weights = np.tile(0.5 * w / panels, panels)
    with np.errstate(all='ignore'):      # nodes (j + s) / P, s = (x + 1) / 2; 1 - s(x) = s(-x)
        F = sla.expm(M)
        whole = [sla.expm((j / panels) * M) for j in range(panels)]
        part = [sla.expm((0.5 * (xi + 1.0) / panels) * M) for xi in x]
        left = np.stack([a[:n] @ b[:, r:2 * r] for a in whole for b in part])    # (k, n, r)
        right = np.stack([a @ b for a in whole[::-1] for b in part[::-1]])       # (k, N, N)
    dF = np.einsum('k,ksa,kbt->abst', weights * dt, left, right, optimize=True)
    return F, dF.reshape(r * N, n, N)


def _frechet_rows_direct(M: Array, r: int, n: int, dt: float) -> tuple[Array, Array]:
    """:func:`_frechet_rows` one direction at a time (scipy's scaling and squaring)."""
    N = M.shape[0]
    dF = np.empty((r * N, n, N))
    E = np.zeros_like(M)
    with np.errstate(all='ignore'):
        F = sla.expm(M)
        for a in range(r):
            for b in range(N):
                E[r + a, b] = dt
                dF[a * N + b] = sla.expm_frechet(M, E, compute_expm=False)[:n]
                E[r + a, b] = 0.0
    return F, dF


def _levenberg_marquardt(prob: _Problem, p: Array, max_iter: int, tol: float
                         ) -> tuple[Array, int, str]:
    """Levenberg–Marquardt from ``p``: a step is taken only if it lowers the cost."""
    cost = prob.cost(p)
    lam = 1e-3
    iterations = 0
    status = 'max_iter'
    for iterations in range(1, max_iter + 1):  # noqa: B007 (reported after the loop)
        JtJ, Jtr, cost = prob.normal(p)
        # Marquardt scaling with a relative floor: a factor at a constraint's boundary (an
        # active damping margin) has a vanishing column, which must still be damped
        d = np.diag(JtJ).copy()
        d = np.maximum(d, 1e-6 * max(float(np.max(d)), 1e-300))
        accepted = False
        for _ in range(20):
            try:
                step = np.linalg.solve(JtJ + lam * np.diag(d), -Jtr)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            new = p + step
            c_new = prob.cost(new)
            if c_new < cost:
                accepted = True
                break
            lam *= 4.0
        if not accepted:
            status = 'no_descent'
            break
        rel = (cost - c_new) / max(cost, 1e-300)
        p, cost = new, c_new
        lam = max(lam / 3.0, 1e-12)
        if rel < tol:
            status = 'converged'
            break
    return p, iterations, status


def _best_x0(prob: _Problem, p: Array) -> Array:
    """``p`` with each episode's initial state the least-squares best for its operators."""
    K, C, B, _, _, _ = prob.unpack(p)
    _, Lt_inv = prob.mass_factor(p)
    n, r = 2 * prob.r, prob.r
    with np.errstate(all='ignore'):
        F = sla.expm(prob._augmented(K, C, B))
    Ad, Bd = F[:n, :n], F[:n, n:]
    out = p.copy()
    for i, (q, u) in enumerate(zip(prob.Q, prob.U)):
        k = q.shape[1]
        forced = Lt_inv @ run_states(Ad, Bd, np.zeros(n), u)[:r, :-1]
        Phi = np.empty((r, k, n))                 # free responses to unit initial states
        S = np.eye(n)
        for j in range(k):
            Phi[:, j, :] = Lt_inv @ S[:r]
            S = Ad @ S
        x0, *_ = np.linalg.lstsq(Phi.reshape(-1, n), (q - forced).ravel(), rcond=None)
        o = prob.n_shared + 2 * r * i
        out[o:o + n] = x0
    return out


def _factor(S: Array) -> Array:
    """Lower-triangular ``L`` with ``L Lᵀ = S`` for a symmetric PSD ``S`` (jittered if needed)."""
    S = 0.5 * (S + S.T)
    scale = max(float(np.max(np.abs(np.diag(S)))), 1e-300)
    for jitter in (0.0, 1e-12, 1e-10, 1e-8):
        try:
            return np.asarray(np.linalg.cholesky(S + jitter * scale * np.eye(S.shape[0])),
                              dtype=np.float64)
        except np.linalg.LinAlgError:
            continue
    lam, W = np.linalg.eigh(S)
    half = W * np.sqrt(np.clip(lam, 0.0, None))
    return np.asarray(np.linalg.cholesky(half @ half.T + 1e-8 * scale * np.eye(S.shape[0])),
                      dtype=np.float64)


def initial_states(episodes: Sequence[tuple[Array, Array]], Lt: Array, dt: float) -> list[Array]:
    """``[z(0); ż(0)]`` per episode from its first samples (a line through the first five)."""
    out = []
    for q, _ in episodes:
        z = Lt @ np.asarray(q[:, :5], dtype=np.float64)
        t = np.arange(z.shape[1]) * dt
        if z.shape[1] >= 2:
            slope, icpt = np.polyfit(t, z.T, 1)
        else:
            slope, icpt = np.zeros(z.shape[0]), z[:, 0]
        out.append(np.concatenate([icpt, slope]))
    return out


def refine_output_error(K: Array, C: Array, B: Array, episodes: Sequence[tuple[Array, Array]],
                        dt: float, *, Lt: Array | None = None, free_mass: bool = False,
                        margin: dict[str, Any] | None = None, eps: float = 1e-6,
                        max_iter: int = 30, tol: float = 1e-6, holdout: float = 0.2
                        ) -> tuple[Array, Array, Array, dict[str, Any]]:
    """Refine SPD second-order operators by their simulation error (module docstring).

    Parameters
    ----------
    K, C : ndarray, shape (r, r)
        Start: SPD stiffness and damping in the ``z`` coordinates (``C ⪰ αI + βK``).
    B : ndarray, shape (r, m)
        Start: input operator (for the inputs given in ``episodes``).
    episodes : sequence of (Q, U)
        Per episode the measured reduced coordinates ``Q (r, k_i)`` and the inputs
        ``U (m, k_i)`` (both in the scaled units of the fit).
    dt : float
        Sample time (s); inputs are held over each sample.
    Lt : ndarray, shape (r, r), optional
        ``z = Lt q`` (the learned mass factor, upper triangular); default the identity.
    free_mass : bool
        Refine ``Lt`` too (its upper triangle; the mass ``M = Lt^T Lt`` stays SPD while its
        diagonal keeps its sign); the refined factor is ``info['mass_factor']``.
    margin : dict, optional
        ``alpha``, ``beta``, ``eps_K`` of the constraints; default ``eps`` for both
        floors and ``beta = 0``.
    eps : float
        Floor used when ``margin`` has no entries.
    max_iter : int
        Levenberg–Marquardt iterations (each: one sensitivity pass).
    tol : float
        Stop when an iteration lowers the cost by less than this relative amount.
    holdout : float
        Validation: the refinement is first fitted on the first ``1 - holdout`` of every
        episode; if it then predicts the held-out tails worse than the start (with its best
        initial states), the start is returned (``status`` ``'rejected_on_holdout'``);
        otherwise the whole episodes are fitted from there. ``0``: no validation.

    Returns
    -------
    K, C, B : ndarray
        The refined operators (same constraints as the start).
    info : dict
        ``criterion``, ``status`` (``converged``, ``max_iter``, ``no_descent``,
        ``rejected_on_holdout``, ``skipped_too_large``), ``iterations``, ``cost_start``,
        ``cost``, ``improvement`` (relative reduction of the training simulation error),
        ``validation`` (the tail errors of the start and the refinement), ``seconds``,
        ``parameters``, ``mass_refined``, ``mass_factor``.
    """
    t0 = time.perf_counter()
    r = int(K.shape[0])
    Lt_a = np.eye(r) if Lt is None else np.asarray(Lt, dtype=np.float64)
    bd = dict(margin or {})
    floors = {'alpha': float(bd.get('alpha', eps)), 'beta': float(bd.get('beta', 0.0)),
              'eps_K': float(bd.get('eps_K', eps))}
    if not floors.get('alpha') or floors['alpha'] <= 0:
        floors['alpha'] = float(eps)
    prob = _Problem(episodes, dt, Lt_a, floors, free_mass=free_mass)
    work = float(sum(np.asarray(q).shape[1] for q, _ in episodes)) * r * prob.P ** 2
    if work > MAX_WORK:
        info = {'criterion': 'output-error', 'iterations': 0, 'status': 'skipped_too_large',
                'parameters': prob.P, 'improvement': 0.0, 'seconds': time.perf_counter() - t0,
                'mass_refined': False, 'mass_factor': Lt_a}
        return K, C, B, info
    prob.set_caps(K, C)
    p0 = prob.pack(K, C, B, initial_states(episodes, Lt_a, dt))
    cost0 = prob.cost(p0)
    p, iterations, status, check = _search(prob, p0, episodes, dt, Lt_a, floors, (K, C),
                                           free_mass=free_mass, max_iter=max_iter, tol=tol,
                                           holdout=holdout)
    cost = prob.cost(p) if p is not p0 else cost0
    Kr, Cr, Br, _, _, _ = prob.unpack(p)
    Lt_r, _ = prob.mass_factor(p)
    Kr, Cr = 0.5 * (Kr + Kr.T), 0.5 * (Cr + Cr.T)
    info = {'criterion': 'output-error', 'iterations': iterations, 'status': status,
            'cost_start': cost0, 'cost': cost,
            'improvement': 1.0 - float(np.sqrt(cost / cost0)) if cost0 > 0 else 0.0,
            'parameters': prob.P, 'seconds': time.perf_counter() - t0, 'validation': check,
            'mass_refined': bool(free_mass), 'mass_factor': Lt_r}
    return Kr, Cr, Br, info


def _search(prob: _Problem, p0: Array, episodes: Sequence[tuple[Array, Array]], dt: float,
            Lt: Array, floors: dict[str, float], start: tuple[Array, Array], *,
            free_mass: bool, max_iter: int, tol: float, holdout: float
            ) -> tuple[Array, int, str, dict[str, Any]]:
    """The Levenberg-Marquardt search, validated on the episodes' tails first (``holdout``).

    Returns the parameters, the iterations, the status and the validation's figures.
    """
    check: dict[str, Any] = {'holdout': float(holdout)}
    lengths = [int(np.asarray(q).shape[1]) for q, _ in episodes]
    heads = [int(round(k * (1.0 - holdout))) for k in lengths]
    if not (holdout > 0 and all(h >= 32 and k - h >= 8 for h, k in zip(heads, lengths))):
        check['holdout'] = 0.0
        p, iterations, status = _levenberg_marquardt(prob, p0, max_iter, tol)
        return p, iterations, status, check
    # fit on the heads, keep it only if it predicts the held-out tails better than the start
    head = _Problem([(np.asarray(q)[:, :h], np.asarray(u)[:, :h])
                     for (q, u), h in zip(episodes, heads)], dt, Lt, floors,
                    free_mass=free_mass)
    head.set_caps(*start)
    p_head, it_head, _ = _levenberg_marquardt(head, p0, max_iter, tol)
    tail_start = prob.tail_error(_best_x0(head, p0), heads)
    tail_refined = prob.tail_error(p_head, heads)
    check.update(tail_error_start=tail_start, tail_error_refined=tail_refined,
                 iterations_head=it_head)
    if not tail_refined <= tail_start:
        return p0, 0, 'rejected_on_holdout', check
    p, iterations, status = _levenberg_marquardt(prob, p_head, max_iter, tol)
    return p, iterations, status, check
