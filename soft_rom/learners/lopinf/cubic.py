"""Least squares for the structure-preserving cubic LOpInf model (potential coefficients).

The model (:class:`~soft_rom.models.cubic.CubicSecondOrderModel`) is

.. math::

    \\ddot q + C \\dot q + \\nabla V(q) = B u, \\qquad
    V(q) = \\tfrac12 K(q,q) + \\tfrac16 G(q,q,q) + \\tfrac1{24} H(q,q,q,q).

The unknowns are the *independent* entries of the symmetric tensors ``K`` (``r(r+1)/2``),
``G`` (``r(r+1)(r+2)/6``), ``H`` (``r(r+1)(r+2)(r+3)/24``) and ``C``, and ``B``. Every force
component is linear in them: with the features ``z = [q, q_a q_b, q_a q_b q_c, q̇, u]``
(unique monomials), ``∇V(q) + C q̇ - B u = Φ(θ) z`` where the sparse map ``θ → Φ`` puts each
potential coefficient into every force row it differentiates into (a coefficient of
``q_a q_b q_c`` enters rows ``a``, ``b`` and ``c``). So

.. math:: \\min_\\theta \\sum_t \\|\\ddot q_t + \\Phi(\\theta) z_t\\|^2
    + \\lambda (\\|G\\|_F^2 + \\|H\\|_F^2)

is an ordinary linear least-squares problem. It is compressed with a thin QR of the feature
matrix, ``Zᵀ = Q_z R_z``: ``Σ_t |q̈_t + Φ z_t|² = Σ_i |R_z φ_i + Q_zᵀ q̈_i|² + const`` with
``φ_i`` the ``i``-th row of ``Φ``, so the dense problem has ``r · dim(z)`` rows whatever the
number of samples.

Constraints: ``K ⪰ eps``, ``C ⪰ eps`` and ``H(q,q,q,q) ≥ t |q|⁴`` with
``t ≥ eps4 · λ_max(K)`` (a potential bounded below that grows at infinity, whatever ``G``).
The least-squares solution is kept when it satisfies them: the quartic is certified by the
smallest eigenvalue of the canonical Gram matrix of ``H`` on symmetric matrices, or by a
sum-of-squares Gram matrix found by a small SDP (:func:`quartic_lower_bound`). Otherwise the
conic problem is solved with cvxpy/Clarabel: the same objective, ``K, C ⪰ eps``, and
``H(q⁴) = wᵀ X w`` with ``X ⪰ t I`` over the scaled quadratic monomials ``w`` (``|w|² = |q|⁴``),
with the free unknowns (``G``, ``B``) eliminated first and the objective compressed to a
square factor (see :func:`_constrained`: the uncompressed problem is many times slower;
``docs/methods_variants.md``). The certificate of the result is the smallest
eigenvalue of the solver's Gram matrix (``H`` is rebuilt from it exactly). A quartic has
many Gram matrices, so the objective also carries a small tie-break on ``‖X‖_F²``
(:data:`_GRAM_WEIGHT`) that picks the smallest and makes the problem strictly convex.

``quartic='projected'`` is the cheaper route for large r (:mod:`~soft_rom.learners.lopinf.
quartic`): ``K`` and ``C`` of the least squares (which must be SPD), the quartic alone moved
to the nearest sum of squares in the data's metric, certified as ``H(q⁴) ≥ t |q / e|⁴`` in
the coordinates divided by their largest training values ``e``, ``t = eps4 · λ_max(e K e)``.

When the data come from a model of this class with exact derivatives and the constraints
are inactive, the least-squares solution is the truth.
"""

from __future__ import annotations

import math
import time
from typing import Any, NamedTuple
import warnings

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla
import scipy.sparse as sp

from soft_rom.errors import ConfigError, SolverError
from soft_rom.learners.lopinf.quartic import (
    ordered,
    OrderedLeastSquares,
    projected,
    scaled_quartic_bound,
)
from soft_rom.learners.lopinf.solvers import (
    DEFAULT_EPS,
    FastSPDSolver,
    LOpInfSolution,
    OperatorSolver,
)
from soft_rom.models.tensors import (
    gram_map,
    multiplicity,
    quartic_lower_bound,
    symmetric_from_entries,
    symmetric_index,
)

__all__ = ['CubicSolution', 'DEFAULT_EPS4', 'DEFAULT_REG', 'QUARTIC_ROUTES', 'fit_cubic',
           'fit_scaled', 'isotropic_quartic']

Array = NDArray[np.float64]

#: Tikhonov weight on ``||G||_F² + ||H||_F²`` per sample (scaled coordinates).
DEFAULT_REG = 1e-4
#: The quartic form must satisfy ``H(q⁴) ≥ eps4 · λ_max(K) · |q|⁴`` (scaled coordinates).
DEFAULT_EPS4 = 1e-6
_VERBOSE = False
#: Clarabel's KKT iterative refinement, tightened: the dense objective block is ill-conditioned
#: and the default refinement stalls the interior point early.
_CLARABEL_REFINE = {'iterative_refinement_reltol': 1e-14, 'iterative_refinement_abstol': 1e-14,
                    'iterative_refinement_max_iter': 30}
#: Clarabel settings tried in turn. On ill-conditioned data (a small ``reg``) the interior
#: point can stop on a numerical error with one and converge with the other, and which one
#: depends on round-off (two reductions of the same data that differ by 1e-14); the result
#: is certified either way (:func:`fit_cubic`).
_CLARABEL_SETTINGS = (_CLARABEL_REFINE, {**_CLARABEL_REFINE, 'equilibrate_enable': False})
#: Weight of the tie-break ``‖X‖_F² / s²`` in the conic objective (which is 1 at ``θ = 0``),
#: ``s`` the larger of the least-squares ``H``'s norm and the smallest feasible ``X``'s
#: (``t √n``). A quartic has many Gram matrices ``X``: without the term the problem is not
#: strictly convex in ``X``, and the interior point's answer moved by 1e-6 (predictions) when
#: the data moved by 1e-14 (two reductions of the same set, streamed and in memory). With it
#: the smallest Gram matrix is chosen and those fits agree to 1e-12 on the scale benchmark;
#: docs/methods_variants.md has the measurements. 0 turns it off.
_GRAM_WEIGHT = 1e-8
#: How an uncertified least-squares quartic is made certified: jointly with ``K, C`` by the
#: conic problem (``'conic'``), or alone, nearest in the data's metric with ``K, C`` of the
#: least squares (``'projected'``, :mod:`soft_rom.learners.lopinf.quartic`).
QUARTIC_ROUTES = ('conic', 'projected')


class CubicSolution(NamedTuple):
    """Result of :func:`fit_cubic` (scaled coordinates of the data it was given)."""

    K: Array
    C: Array
    G: Array
    H: Array
    B: Array
    info: dict[str, Any]


def _monomials(Q: Array, degree: int) -> Array:
    """Unique monomials of ``degree`` of the rows of ``Q`` (order of ``symmetric_index``)."""
    idx = symmetric_index(Q.shape[0], degree)
    out = np.ones((len(idx), Q.shape[1]))
    for row, beta in enumerate(idx):
        for a in beta:
            out[row] *= Q[a]
    return out


class _Layout:
    """Indices of the features ``z`` and unknowns ``θ`` and the map ``θ → Φ`` per row."""

    def __init__(self, r: int, m: int) -> None:
        self.r, self.m = r, m
        self.idx = {d: symmetric_index(r, d) for d in (1, 2, 3, 4)}
        self.pos = {d: {b: j for j, b in enumerate(self.idx[d])} for d in (1, 2, 3)}
        n1, n2, n3 = (len(self.idx[d]) for d in (1, 2, 3))
        self.z_off = {'q1': 0, 'q2': n1, 'q3': n1 + n2, 'qd': n1 + n2 + n3,
                      'u': n1 + n2 + n3 + r}
        self.n_z = n1 + n2 + n3 + r + m
        nK, nG, nH = (len(self.idx[d]) for d in (2, 3, 4))
        self.t_off = {'K': 0, 'G': nK, 'H': nK + nG, 'C': nK + nG + nH,
                      'B': nK + nG + nH + nK}
        self.n_theta = nK + nG + nH + nK + r * m
        rows: list[list[int]] = [[] for _ in range(r)]
        cols: list[list[int]] = [[] for _ in range(r)]
        vals: list[list[float]] = [[] for _ in range(r)]

        def put(i: int, feat: int, theta: int, v: float) -> None:
            rows[i].append(feat)
            cols[i].append(theta)
            vals[i].append(v)

        for name, deg, zkey, scale in (('K', 2, 'q1', 1.0), ('G', 3, 'q2', 0.5),
                                       ('H', 4, 'q3', 1.0 / 6.0)):
            for j, alpha in enumerate(self.idx[deg]):
                for i in sorted(set(alpha)):
                    beta = list(alpha)
                    beta.remove(i)
                    rest = tuple(beta)
                    put(i, self.z_off[zkey] + self.pos[deg - 1][rest], self.t_off[name] + j,
                        scale * multiplicity(rest))
        for j, pair in enumerate(self.idx[2]):          # C, symmetric
            a, b = pair
            put(a, self.z_off['qd'] + b, self.t_off['C'] + j, 1.0)
            if a != b:
                put(b, self.z_off['qd'] + a, self.t_off['C'] + j, 1.0)
        for i in range(r):
            for j in range(m):
                put(i, self.z_off['u'] + j, self.t_off['B'] + i * m + j, -1.0)
        self.L = [sp.csr_matrix((vals[i], (rows[i], cols[i])), shape=(self.n_z, self.n_theta))
                  for i in range(r)]

    def features(self, Q: Array, Qd: Array, U: Array) -> Array:
        return np.vstack([Q, _monomials(Q, 2), _monomials(Q, 3), Qd, U])

    def tensor_weights(self, name: str) -> Array:
        """``mult(α)``: ``||T||_F² = Σ mult(α) θ_α²``."""
        deg = {'K': 2, 'C': 2, 'G': 3, 'H': 4}[name]
        return np.array([multiplicity(a) for a in self.idx[deg]], dtype=np.float64)

    def unpack(self, theta: Array) -> tuple[Array, Array, Array, Array, Array]:
        r, m, o = self.r, self.m, self.t_off
        K = symmetric_from_entries(theta[o['K']:o['G']], r, 2)
        G = symmetric_from_entries(theta[o['G']:o['H']], r, 3)
        H = symmetric_from_entries(theta[o['H']:o['C']], r, 4)
        C = symmetric_from_entries(theta[o['C']:o['B']], r, 2)
        B = theta[o['B']:].reshape(r, m)
        return K, C, G, H, B


def isotropic_quartic(r: int) -> Array:
    """The symmetric tensor ``S`` with ``S(q, q, q, q) = |q|⁴`` (``t·S`` is the quartic floor)."""
    eye = np.eye(r)
    return (np.einsum('ij,kl->ijkl', eye, eye) + np.einsum('ik,jl->ijkl', eye, eye)
            + np.einsum('il,jk->ijkl', eye, eye)) / 3.0


def _nl_force(Q: Array, G: Array, H: Array) -> Array:
    """``½ G(q,q,·) + ⅙ H(q,q,q,·)`` for every column of ``Q``."""
    return (0.5 * np.einsum('ijk,jt,kt->it', G, Q, Q)
            + np.einsum('ijkl,jt,kt,lt->it', H, Q, Q, Q) / 6.0)


def fit_cubic(Q: Array, Qd: Array, Qdd: Array, U: Array, *, eps: float = DEFAULT_EPS,
              reg: float = DEFAULT_REG, eps4: float = DEFAULT_EPS4, quartic: str = 'conic',
              linear_solver: OperatorSolver | None = None) -> CubicSolution:
    """Fit ``K, C, G, H, B`` to ``Q̈ + C Q̇ + ∇V(Q) = B U`` (columns are samples).

    Parameters
    ----------
    Q, Qd, Qdd : ndarray, shape (r, k)
    U : ndarray, shape (m, k)
    eps : float
        ``K, C ⪰ eps``.
    reg : float
        Tikhonov weight (per sample) on ``||G||_F² + ||H||_F²``.
    eps4 : float
        Relative floor of the quartic form (see module docstring).
    quartic : {'conic', 'projected'}
        How an uncertified least-squares quartic is made certified (:data:`QUARTIC_ROUTES`).
        ``'projected'`` needs ``K, C`` of the least squares SPD, and certifies
        ``H(q⁴) ≥ eps4 · λ_max(e K e) · |q / e|⁴`` in the coordinates scaled by their largest
        values ``e`` (:mod:`~soft_rom.learners.lopinf.quartic`).
    linear_solver : OperatorSolver, optional
        SPD solver of the linear block (default :class:`FastSPDSolver`).
    """
    t0 = time.perf_counter()
    Q, Qd, Qdd, U = (np.asarray(a, dtype=np.float64) for a in (Q, Qd, Qdd, U))
    r = Q.shape[0]
    if quartic not in QUARTIC_ROUTES:
        raise ConfigError(f'unknown cubic quartic route {quartic!r}; known: '
                          + ', '.join(QUARTIC_ROUTES) + '.')
    lay = _Layout(r, U.shape[0])
    norm_qdd = max(float(np.linalg.norm(Qdd)), 1e-300)
    ls, base = _least_squares(lay, Q, Qd, Qdd, U, reg,
                              ordered(lay) if quartic == 'projected' else None)
    theta = ls.theta
    K, C, G, H, B = lay.unpack(theta)
    info: dict[str, Any] = {'solver': 'cubic-potential-least-squares', 'reg': float(reg),
                            'eps': float(eps), 'eps4': float(eps4), 'quartic': quartic,
                            'n_unknowns': lay.n_theta, 'n_features': lay.n_z}

    def spd_ok(Km: Array, Cm: Array) -> bool:
        return bool(np.linalg.eigvalsh(Km)[0] >= eps and np.linalg.eigvalsh(Cm)[0] >= eps)

    def target_of(Km: Array) -> float:
        return float(eps4) * max(float(np.linalg.eigvalsh(Km)[-1]), 1e-300)

    if quartic == 'projected':
        theta, t_low, target, how = _project(lay, ls, Q, eps, eps4, info)
        K, C, G, H, B = lay.unpack(theta)
    else:
        target = target_of(K)
        t_low, how = quartic_lower_bound(H, target=target) if spd_ok(K, C) else (-1.0, '')
    if quartic == 'conic' and spd_ok(K, C) and t_low >= target:
        info['method'] = 'least-squares (constraints inactive)'
    elif quartic == 'conic':
        lin = FastSPDSolver() if linear_solver is None else linear_solver
        K0 = lin.solve(Q, Qd, Qdd, U, eps=eps).K
        target = target_of(K0)
        h_ls = float(np.linalg.norm(theta[lay.t_off['H']:lay.t_off['C']]))
        N, g = _normal(ls)
        K, C, G, H, B, sdp_info = _constrained(N, g, lay, eps, target, h_ls)
        info.update(sdp_info)
        info['method'] = 'conic (K, C ⪰ eps, sum-of-squares quartic)'
        t_low, how = quartic_lower_bound(H, target=target, sdp=False)
        if info['certificate'] > t_low:                 # the solver's own Gram matrix
            t_low, how = info['certificate'], 'sos'
    info['quartic_certificate'] = how
    if not (np.linalg.eigvalsh(K)[0] >= 0.999 * eps and np.linalg.eigvalsh(C)[0] >= 0.999 * eps
            and t_low >= 0.99 * target):
        raise SolverError('the cubic LOpInf fit could not satisfy K, C ⪰ eps and a '
                          'positive quartic potential; try a larger --cubic-reg.')
    res = Qdd + C @ Qd + K @ Q + _nl_force(Q, G, H) - B @ U
    info['quartic_lower_bound'] = float(t_low)
    info['quartic_target'] = float(target)
    info['objective'] = float(np.linalg.norm(res))
    info['objective_relative'] = float(np.linalg.norm(res)) / norm_qdd
    info['residual_outside_features'] = math.sqrt(max(base, 0.0)) / norm_qdd
    info['time_s'] = time.perf_counter() - t0
    return CubicSolution(K, C, G, H, B, info)


def _compressed(lay: _Layout, Q: Array, Qd: Array, Qdd: Array, U: Array
                ) -> tuple[Array, Array, float]:
    """``(A, b, base)``: ``|A θ - b|² + base`` is the equation's squared residual.

    The rows are compressed by a QR of the features (``r · n_z`` rows whatever the number of
    samples); ``base`` is the part of ``|Q̈|²`` outside the features' range.
    """
    r = Q.shape[0]
    Z = lay.features(Q, Qd, U)
    Qz, Rz = np.linalg.qr(Z.T)
    A = np.vstack([(lay.L[i].T @ Rz.T).T for i in range(r)])
    b = -np.concatenate([Qz.T @ Qdd[i] for i in range(r)])
    return A, b, float(np.linalg.norm(Qdd) ** 2 - np.linalg.norm(b) ** 2)


def _least_squares(lay: _Layout, Q: Array, Qd: Array, Qdd: Array, U: Array, reg: float,
                   order: NDArray[np.intp] | None = None) -> tuple[OrderedLeastSquares, float]:
    """The regularized least squares, compressed by a QR of the features.

    Returns the solved least squares (:class:`~soft_rom.learners.lopinf.quartic.
    OrderedLeastSquares`, its columns in ``order``) and the squared residual outside the
    features' range.

    ``θ`` comes from a Householder QR of the compressed rows (and the ridge's rows) with
    their columns scaled to unit norm, not from the normal equations: the monomials of
    coordinates that span three decades (r = 16 on the eel) span nine, and the normal
    equations (condition number squared, a jitter scaled by the largest columns) lost the
    solution there: relative residual 4e-2 at ``reg`` 1e-10, against 8e-4 with this QR at
    ``reg`` 0, on re-projected eel data (``benchmarks/bench_eel_nonlinearity.py
    --reproject``). The ridge rows are dense here; a second QR of ``[R; diag]`` would be
    cheaper at r = 16 (not done). ``N`` and ``g``, which the conic problem needs, are formed
    from the triangular factor (:func:`_normal`).
    """
    k = Q.shape[1]
    A, b, base = _compressed(lay, Q, Qd, Qdd, U)
    o = lay.t_off
    w_all = np.zeros(lay.n_theta)
    w_all[np.arange(o['G'], o['C'])] = np.concatenate([lay.tensor_weights('G'),
                                                       lay.tensor_weights('H')])
    ls = OrderedLeastSquares(A, b, float(reg) * k * w_all, order)
    if not np.all(np.isfinite(ls.theta)):
        raise SolverError('the cubic LOpInf least squares has no finite solution; '
                          'try a larger --cubic-reg.')
    return ls, base


def _normal(ls: OrderedLeastSquares) -> tuple[Array, Array]:
    """The normal matrix ``N`` (with a relative jitter of 1e-13) and ``g``, natural order."""
    n = len(ls.theta)
    Rd = ls.R * ls.cs[ls.order][None, :]                    # N = Rdᵀ Rd, in order
    N, g = np.empty((n, n)), np.empty(n)
    N[np.ix_(ls.order, ls.order)] = Rd.T @ Rd
    g[ls.order] = Rd.T @ ls.c
    N += 1e-13 * float(np.trace(N)) / n * np.eye(n)
    return N, g


def _project(lay: _Layout, ls: OrderedLeastSquares, Q: Array, eps: float, eps4: float,
             info: dict[str, Any]) -> tuple[Array, float, float, str]:
    """``quartic='projected'``: ``(θ, certified floor, target, how)``, ``info`` updated."""
    K, C, _G, H, _B = lay.unpack(ls.theta)
    lows = (float(np.linalg.eigvalsh(K)[0]), float(np.linalg.eigvalsh(C)[0]))
    if min(lows) < eps:
        raise SolverError('quartic="projected" keeps K and C of the least squares, and they '
                          f'are not SPD here (smallest eigenvalues {lows[0]:.3g}, '
                          f'{lows[1]:.3g}); use the default quartic="conic".')
    e = np.abs(Q).max(axis=1)
    e[e == 0.0] = 1.0
    target = float(eps4) * max(float(np.linalg.eigvalsh(K * np.outer(e, e))[-1]), 1e-300)
    t_low = scaled_quartic_bound(H, e)
    info['quartic_scale'] = e.tolist()
    if t_low >= target:
        info['method'] = 'least-squares (constraints inactive)'
        return ls.theta, t_low, target, 'gram (coordinates / their largest values)'
    theta, p_info = projected(lay, ls, e, target)
    info.update(p_info)
    info['method'] = 'least-squares K, C; quartic projected onto sums of squares'
    return theta, p_info['certificate'], target, 'sos (coordinates / their largest values)'


def _sym_map(r: int) -> Array:
    """``vec(S) = M θ`` for a symmetric ``S`` from its independent entries (row-major)."""
    idx = symmetric_index(r, 2)
    M = np.zeros((r * r, len(idx)))
    for j, (a, b) in enumerate(idx):
        M[a * r + b, j] = M[b * r + a, j] = 1.0
    return M


def _constrained(N: Array, g: Array, lay: _Layout, eps: float, t4: float, h_ls: float
                 ) -> tuple[Array, Array, Array, Array, Array, dict[str, Any]]:
    """``min θᵀNθ - 2gᵀθ`` s.t. ``K, C ⪰ eps``, ``H = Gram(X)``, ``X ⪰ t4 I``.

    Plus the tie-break :data:`_GRAM_WEIGHT` ``· ‖X‖_F² / s²``, ``s = max(h_ls, t4 √ns)`` with
    ``h_ls`` the norm of the least-squares ``H`` entries.

    ``N = AᵀA + diag(ridge)`` and ``g = Aᵀb`` are the normal equations of the least squares.

    The problem handed to the conic solver is compressed first: the unconstrained unknowns
    (``G``, ``B``) are eliminated in closed form (Schur complement of the normal matrix), the
    objective over the rest is ``|Lᵀθ_S - c|²`` with the Cholesky factor of that complement
    (a dense square of side ``dim θ_S``, whatever the number of samples), and ``H`` is a
    variable of its own tied to the Gram matrix by a sparse equality, so the dense objective
    block and the dense cone block are not multiplied together. ``info['certificate']`` is
    the lower bound of the quartic certified by the returned Gram matrix.
    """
    import cvxpy as cp
    r, o = lay.r, lay.t_off
    t0 = time.perf_counter()
    n = lay.n_theta
    idx = np.arange(n)
    S = np.concatenate([idx[o['K']:o['G']], idx[o['H']:o['C']], idx[o['C']:o['B']]])
    F = np.concatenate([idx[o['G']:o['H']], idx[o['B']:]])
    NFS = N[np.ix_(F, S)]
    W = sla.cho_solve(sla.cho_factor(N[np.ix_(F, F)]), np.column_stack([NFS, g[F]]))
    Ns = N[np.ix_(S, S)] - NFS.T @ W[:, :-1]
    Lc = np.linalg.cholesky(0.5 * (Ns + Ns.T))
    c = sla.solve_triangular(Lc, g[S] - NFS.T @ W[:, -1], lower=True)
    scale = max(float(np.linalg.norm(c)), 1e-300)
    Tg, ns = gram_map(r)
    nK, nH = o['G'] - o['K'], o['C'] - o['H']
    th = cp.Variable(len(S))
    X = cp.Variable((ns, ns), symmetric=True)
    Ms = _sym_map(r)
    Kx = cp.reshape(Ms @ th[:nK], (r, r), order='C')
    Cx = cp.reshape(Ms @ th[nK + nH:], (r, r), order='C')
    cons = [th[nK:nK + nH] == Tg @ cp.vec(X, order='C'),
            0.5 * (Kx + Kx.T) - eps * np.eye(r) >> 0, 0.5 * (Cx + Cx.T) - eps * np.eye(r) >> 0,
            X - t4 * np.eye(ns) >> 0]
    objective = cp.sum_squares(Lc.T @ th - c) / scale ** 2
    if _GRAM_WEIGHT:
        s_x = max(h_ls, t4 * math.sqrt(ns), 1e-300)
        objective = objective + _GRAM_WEIGHT * cp.sum_squares(X) / s_x ** 2
    prob = cp.Problem(cp.Minimize(objective), cons)
    settings = _solve_conic(prob, th)
    Xv = np.asarray(X.value)
    Xv = 0.5 * (Xv + Xv.T)
    th_s = np.asarray(th.value, dtype=np.float64).copy()
    th_s[nK:nK + nH] = Tg @ Xv.ravel()                  # H exactly the Gram matrix's quartic
    full = np.zeros(n)
    full[S] = th_s
    full[F] = W[:, -1] - W[:, :-1] @ th_s
    K, C, G, H, B = lay.unpack(full)
    info = {'conic_status': str(prob.status), 'conic_seconds': time.perf_counter() - t0,
            'conic_settings': settings,
            'conic_unknowns': int(len(S) + ns * (ns + 1) // 2),
            'certificate': float(np.linalg.eigvalsh(Xv)[0])}
    return K, C, G, H, B, info


def _solve_conic(prob: Any, th: Any) -> int:
    """Solve ``prob`` with each of :data:`_CLARABEL_SETTINGS` until one ends optimal.

    Returns the index of the settings that worked; raises :class:`SolverError` (one line,
    with the last reason) when none did.
    """
    why = ''
    for i, opts in enumerate(_CLARABEL_SETTINGS):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter('ignore', UserWarning)  # 'may be inaccurate': certified
                prob.solve(solver='CLARABEL', verbose=_VERBOSE, **opts)
        except Exception as err:  # noqa: BLE001 - cvxpy's SolverError, or a failure inside
            text = ' '.join(str(err).split())                 # one line
            why = 'it stopped on a numerical error' if 'failed' in text else text
            continue
        if prob.status in ('optimal', 'optimal_inaccurate') and th.value is not None:
            return i
        why = f'it ended {prob.status}'
    raise SolverError(f'the conic cubic LOpInf problem failed ({why}, with each of '
                      f'{len(_CLARABEL_SETTINGS)} solver settings); try a larger --cubic-reg.')


def fit_scaled(Q: Array, Qd: Array, Qdd: Array, U: Array, state_scale: float,
               solver: OperatorSolver, eps: float, options: dict[str, Any] | None
               ) -> tuple[LOpInfSolution, dict[str, Array]]:
    """What :class:`~soft_rom.learners.lopinf.LOpInf` calls for ``forces='cubic'``.

    ``Q`` are the reduced coordinates divided by ``state_scale``; the returned ``K, C, B``
    are in those scaled units (as the linear solvers return them) and ``G, H`` already in
    the original units (``G = G̃ / s``, ``H = H̃ / s²``).
    """
    opts = dict(options or {})
    unknown = set(opts) - {'reg', 'eps4', 'quartic'}
    if unknown:
        raise ConfigError(f'unknown cubic option(s) {sorted(unknown)}; known: reg, eps4, '
                          'quartic.')
    sol = fit_cubic(Q, Qd, Qdd, U, eps=eps, linear_solver=solver, **opts)
    s = float(state_scale)
    return (LOpInfSolution(sol.K, sol.C, sol.B, sol.info),
            {'G': sol.G / s, 'H': sol.H / s ** 2})
