"""Symmetric tensors of the cubic LOpInf potential, and a certified bound of its quartic.

A symmetric tensor of degree ``d`` on ``r`` coordinates is stored by its independent entries
(sorted index tuples, :func:`symmetric_index`). :func:`quartic_lower_bound` certifies
``H(q, q, q, q) >= t |q|^4`` (used by the cubic model's trust check and by the cubic fit).
"""

from __future__ import annotations

from itertools import combinations_with_replacement, permutations
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.sparse as sp

from soft_rom.errors import DimensionError

__all__ = ['gram_map', 'is_symmetric', 'multiplicity', 'quartic_certified_positive',
           'quartic_lower_bound', 'scaled_quartic', 'symmetric_entries', 'symmetric_from_entries',
           'symmetric_index', 'symmetrize']

Array = NDArray[np.float64]


def symmetric_index(r: int, degree: int) -> list[tuple[int, ...]]:
    """The independent entries of a symmetric tensor: sorted index tuples ``i1 ≤ … ≤ id``.

    There are ``C(r + d - 1, d)`` of them (``r(r+1)(r+2)/6`` for ``d = 3``).
    """
    return list(combinations_with_replacement(range(r), degree))


def symmetrize(T: ArrayLike) -> Array:
    """Average of a tensor over all permutations of its axes (its fully symmetric part)."""
    T = np.asarray(T, dtype=np.float64)
    perms = list(permutations(range(T.ndim)))
    out = np.zeros_like(T)
    for p in perms:
        out += np.transpose(T, p)
    return out / len(perms)


def symmetric_from_entries(values: ArrayLike, r: int, degree: int) -> Array:
    """The full symmetric tensor ``(r,)*degree`` from its independent entries.

    Parameters
    ----------
    values : ndarray, shape (n_independent,)
        In the order of :func:`symmetric_index`.
    """
    values = np.asarray(values, dtype=np.float64)
    idx = symmetric_index(r, degree)
    if values.shape != (len(idx),):
        raise DimensionError(f'need {len(idx)} independent entries; got {values.shape}.')
    T = np.zeros((r,) * degree)
    for v, alpha in zip(values, idx):
        for p in set(permutations(alpha)):
            T[p] = v
    return T


def symmetric_entries(T: ArrayLike) -> Array:
    """The independent entries of a symmetric tensor (order of :func:`symmetric_index`)."""
    T = np.asarray(T, dtype=np.float64)
    return np.array([T[a] for a in symmetric_index(T.shape[0], T.ndim)])


def is_symmetric(T: Array, rtol: float = 1e-10) -> bool:
    scale = max(float(np.max(np.abs(T))) if T.size else 0.0, 1e-300)
    return all(float(np.max(np.abs(T - np.transpose(T, p)))) <= rtol * scale
               for p in permutations(range(T.ndim)))


def multiplicity(beta: tuple[int, ...]) -> int:
    """Number of distinct permutations of a multiset of indices."""
    out = math.factorial(len(beta))
    for v in set(beta):
        out //= math.factorial(beta.count(v))
    return out


def gram_map(r: int) -> tuple[sp.csr_matrix, int]:
    """Map ``vec(X)`` (Gram matrix on scaled quadratic monomials) to the entries of ``H``."""
    pairs = symmetric_index(r, 2)
    quads = symmetric_index(r, 4)
    qpos = {b: j for j, b in enumerate(quads)}
    ns = len(pairs)
    c = np.array([1.0 if a == b else math.sqrt(2.0) for a, b in pairs])
    rows, cols, vals = [], [], []
    for p in range(ns):
        for q in range(ns):
            beta = tuple(sorted(pairs[p] + pairs[q]))
            rows.append(qpos[beta])
            cols.append(p * ns + q)
            vals.append(c[p] * c[q] / multiplicity(beta))
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(quads), ns * ns)), ns


def quartic_certified_positive(H: Array) -> bool:
    """Whether ``H(q⁴) > 0`` for all ``q ≠ 0`` is certified (:func:`quartic_lower_bound`).

    Positivity does not depend on the coordinates' scale; a certificate's accuracy does (the
    sum-of-squares solver works to a tolerance relative to the largest coefficients). So
    ``H`` is certified in the coordinates ``q_i / s_i`` that make its diagonal ``H(e_i⁴)``
    one: a scale the form carries with it. A diagonal entry ``≤ 0`` is not positive.
    """
    d = np.einsum('iiii->i', np.asarray(H, dtype=np.float64))
    if not np.all(d > 0):
        return False
    return quartic_lower_bound(scaled_quartic(H, d ** -0.25), target=0.0)[0] > 0


def scaled_quartic(H: Array, s: Array) -> Array:
    """``H · s⊗s⊗s⊗s``: the quartic form in the coordinates ``q / s``."""
    return np.einsum('ijkl,i,j,k,l->ijkl', H, s, s, s, s)


def quartic_lower_bound(H: Array, *, target: float | None = None, sdp: bool = True
                        ) -> tuple[float, str]:
    """A certified ``t`` with ``H(q,q,q,q) ≥ t |q|⁴`` for all ``q``, and how it was found.

    First the smallest eigenvalue of the canonical Gram matrix (``H`` as a quadratic form on
    symmetric matrices ``q qᵀ``); if that is below ``target`` and ``sdp``, the best
    sum-of-squares Gram matrix (``max t`` s.t. ``X - t I ⪰ 0``, ``wᵀ X w ≡ H(q⁴)``, ``w``
    the scaled quadratic monomials), solved with cvxpy.
    """
    H = np.asarray(H, dtype=np.float64)
    r = H.shape[0]
    pairs = list(combinations_with_replacement(range(r), 2))
    U = np.zeros((r * r, len(pairs)))
    for j, (a, b) in enumerate(pairs):
        if a == b:
            U[a * r + a, j] = 1.0
        else:
            U[a * r + b, j] = U[b * r + a, j] = 1.0 / math.sqrt(2.0)
    M = U.T @ H.reshape(r * r, r * r) @ U
    t_gram = float(np.linalg.eigvalsh(0.5 * (M + M.T))[0])
    if target is None or t_gram >= target or not sdp:
        return t_gram, 'gram'
    try:
        import cvxpy as cp
    except ImportError:                                 # pragma: no cover - declared dep
        return t_gram, 'gram'
    G, ns = gram_map(r)
    mult = np.array([multiplicity(b) for b in symmetric_index(r, 4)], dtype=np.float64)
    Aeq = sp.diags(mult) @ G                        # rows in the coefficients' own scale
    h = mult * np.array([H[b] for b in symmetric_index(r, 4)])
    scale = max(float(np.max(np.abs(h))), 1e-300)
    X = cp.Variable((ns, ns), symmetric=True)
    t = cp.Variable()
    prob = cp.Problem(cp.Maximize(t), [Aeq @ cp.vec(X, order='C') == h / scale,
                                       X - t * np.eye(ns) >> 0])
    try:
        prob.solve(solver='CLARABEL')
    except Exception:                                   # a failed SDP certifies nothing
        return t_gram, 'gram'
    if prob.status not in ('optimal', 'optimal_inaccurate') or t.value is None:
        return t_gram, 'gram'
    # Certify: eigenvalues of the returned Gram matrix after removing the residual.
    Xv = np.asarray(X.value) * scale
    resid = float(np.max(np.abs(Aeq @ Xv.ravel() - h)))
    t_sdp = float(np.linalg.eigvalsh(0.5 * (Xv + Xv.T))[0]) - resid * ns
    return (t_sdp, 'sos') if t_sdp > t_gram else (t_gram, 'gram')
