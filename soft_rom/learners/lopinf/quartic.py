"""The cubic LOpInf's least squares by QR, and its quartic moved to the nearest sum of squares.

:func:`~soft_rom.learners.lopinf.cubic.fit_cubic` certifies the quartic potential
``H(q⁴) ≥ t |q|⁴`` jointly with ``K, C ⪰ eps`` by a conic problem (``quartic='conic'``, the
default). Its dense objective beside a semidefinite cone of side ``r(r+1)/2`` is what makes it
slow at r = 16 (more than 15 minutes in Clarabel on the eel). ``quartic='projected'`` solves
a smaller problem, built from what the least squares already computed (:func:`projected`):

1. ``K`` and ``C`` are those of the least squares, which must be SPD (they are on re-projected
   data of the eel at r = 16: smallest eigenvalues 3.6 and 0.37; on trajectories they are
   often not, and the route refuses).
2. The quartic alone is moved to the nearest sum of squares **in the data's metric**: the
   residual with ``G`` and ``B`` refitted and ``K``, ``C`` held is ``|R_HH (θ_H - θ̂_H)|``, the
   ``H`` block of a QR whose columns are ordered ``G, B, H, K, C``. Its leading
   :data:`KEEP` singular directions are kept exactly, the rest weighted by the next singular
   value (the objective of the conic solver stays a few million nonzeros).
3. The Gram matrix is that of the coordinates divided by their largest training values,
   ``q̃ = q / e``; ``X ⪰ t I`` certifies ``H(q⁴) ≥ t |q̃|⁴``. In these coordinates the
   solver's accuracy is relative to the data's own scale. In the unscaled coordinates of
   the eel at r = 16 (extents 12 to 0.017), SCS's Gram matrix was off by -8.8 against
   a largest eigenvalue of 1e7, and the shift that certified it (10.9 ``|q|⁴``) took the
   test errors from 0.06 to 1.3. Scaled, it was off by -0.0024 and the shift was harmless.
4. Solved with SCS through cvxpy: a first-order method only eigen-decomposes the Gram matrix;
   Clarabel's interior point factors the cone's dense block. SCS stops "inaccurate" at a few
   thousand iterations at r = 16, so its Gram matrix is shifted by a multiple of ``I`` (the
   quartic ``|q̃|⁴``) up to ``λmin = t``: the quartic returned is certified whatever the
   solver's accuracy. Then ``G`` and ``B`` are refitted.

``docs/methods_variants.md`` ("A certified cubic LOpInf at r = 16") has the measurements.
"""

from __future__ import annotations

import math
import time
from typing import Any
import warnings

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla

from soft_rom.errors import SolverError
from soft_rom.models.tensors import gram_map, quartic_lower_bound, scaled_quartic

#: :class:`soft_rom.learners.lopinf.cubic._Layout` (not imported: that module imports this one)
_Layout = Any

__all__ = ['JITTER', 'KEEP', 'MAX_ITERS', 'RANK_TOL', 'OrderedLeastSquares', 'ordered',
           'projected', 'scaled_quartic_bound']

Array = NDArray[np.float64]

#: The least squares' scaled columns count as dependent below this relative pivot ...
RANK_TOL = 1e-10
#: ... and then all get this ridge (relative to their unit norm).
JITTER = 1e-13
#: Singular directions of the quartic's metric kept exactly in the projection.
KEEP = 1000
#: SCS iterations of the projection (its Gram matrix is shifted to the floor afterwards).
MAX_ITERS = 5000


class OrderedLeastSquares:
    """The least squares ``min |A θ - b|² + Σ ridge θ²`` by a QR with its columns in ``order``.

    Columns are scaled to unit norm (``cs``) before the Householder QR, so monomials of
    coordinates that span decades do not lose the solution (the normal equations did:
    ``docs/methods_variants.md``). Dependent columns (antagonistic inputs make ``B``'s
    pairwise dependent) get a relative ridge of :data:`JITTER`.

    Attributes: ``R``, ``c`` and ``y`` (``R y = c``, ``y`` the scaled unknowns in ``order``),
    ``cs`` (column norms, natural order), ``order`` and ``theta`` (the solution, natural
    order).
    """

    def __init__(self, A: Array, b: Array, ridge: Array,
                 order: NDArray[np.intp] | None = None) -> None:
        n = A.shape[1]
        self.order: NDArray[np.intp] = (np.arange(n) if order is None
                                        else np.asarray(order, dtype=np.intp))
        cs = np.sqrt(np.einsum('ij,ij->j', A, A) + ridge)
        cs[cs == 0.0] = 1.0
        self.cs = cs
        rows = np.flatnonzero(ridge > 0)
        pen = np.zeros((len(rows), n))
        pen[np.arange(len(rows)), rows] = np.sqrt(ridge[rows]) / cs[rows]
        Qa, R = np.linalg.qr(np.vstack([A / cs, pen])[:, self.order])
        c = Qa[:len(b)].T @ b
        del Qa
        d = np.abs(np.diag(R))
        if d.min() <= RANK_TOL * d.max():
            Qj, R = np.linalg.qr(np.vstack([R, math.sqrt(JITTER) * np.eye(n)]))
            c = Qj[:n].T @ c
        self.R, self.c = R, c
        self.y = sla.solve_triangular(R, c)
        self.theta = np.empty(n)
        self.theta[self.order] = self.y / cs[self.order]


def ordered(lay: _Layout) -> NDArray[np.intp]:
    """The columns ``G, B | H | K, C``: free unknowns, the quartic, then the held ones."""
    o = lay.t_off
    return np.concatenate([np.arange(o['G'], o['H']), np.arange(o['B'], lay.n_theta),
                           np.arange(o['H'], o['C']), np.arange(o['K'], o['G']),
                           np.arange(o['C'], o['B'])])


def _weights(lay: _Layout, e: Array) -> Array:
    """``e_a e_b e_c e_d`` per quartic coefficient: ``H̃ = H · e⊗e⊗e⊗e``."""
    return np.array([float(np.prod(e[list(a)])) for a in lay.idx[4]])


def scaled_quartic_bound(H: Array, e: Array) -> float:
    """Smallest eigenvalue of the canonical Gram matrix of ``H̃ = H · e⊗e⊗e⊗e`` (cheap bound)."""
    return quartic_lower_bound(scaled_quartic(H, e), sdp=False)[0]


def projected(lay: _Layout, ls: OrderedLeastSquares, e: Array, t4: float, *,
              keep: int = KEEP, max_iters: int = MAX_ITERS) -> tuple[Array, dict[str, Any]]:
    """``θ``: ``K, C`` of ``ls``, ``H`` the nearest certified sum of squares, ``G, B`` refitted.

    ``ls`` must be ordered by :func:`ordered`; ``e`` are the coordinates' largest training
    values and ``t4`` the floor: ``H(q⁴) ≥ t4 |q / e|⁴`` is certified by the returned
    ``info['certificate']`` (``≥ t4``). See the module docstring.
    """
    import cvxpy as cp
    t0 = time.perf_counter()
    o = lay.t_off
    nf = (o['H'] - o['G']) + (lay.n_theta - o['B'])
    nh = o['C'] - o['H']
    R, c, cs = ls.R, ls.c, ls.cs[ls.order]
    y = ls.y.copy()                                 # the least squares, scaled, in order
    _, S, Vt = np.linalg.svd(R[nf:nf + nh, nf:nf + nh])
    keep = max(1, min(int(keep), nh))             # nh: the exact metric
    Tg, ns = gram_map(lay.r)
    w = _weights(lay, e)
    ch = cs[nf:nf + nh]
    X = cp.Variable((ns, ns), symmetric=True)
    dh = cp.multiply(ch / w, Tg @ cp.vec(X, order='C')) - y[nf:nf + nh]
    tail = (S[keep] / S[0]) ** 2 if keep < nh else 0.0
    objective = cp.sum_squares((S[:keep, None] * Vt[:keep] / S[0]) @ dh)
    if tail:
        objective = objective + tail * cp.sum_squares(dh)
    prob = cp.Problem(cp.Minimize(objective), [X - t4 * np.eye(ns) >> 0])
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', UserWarning)    # 'inaccurate': shifted and certified
        prob.solve(solver='SCS', max_iters=int(max_iters), eps_abs=1e-6, eps_rel=1e-6)
    if X.value is None:
        raise SolverError(f'the projection of the cubic LOpInf quartic failed (SCS ended '
                          f'{prob.status}); use the default quartic="conic".')
    Xv = 0.5 * (np.asarray(X.value) + np.asarray(X.value).T)
    shift = max(t4 - float(np.linalg.eigvalsh(Xv)[0]), 0.0)
    Xv += shift * np.eye(ns)
    y[nf:nf + nh] = ch * (Tg @ Xv.ravel()) / w
    y[:nf] = sla.solve_triangular(R[:nf, :nf], c[:nf] - R[:nf, nf:] @ y[nf:])
    theta = np.empty(lay.n_theta)
    theta[ls.order] = y / cs
    return theta, {'projection_status': str(prob.status), 'projection_shift': shift,
                   'projection_seconds': time.perf_counter() - t0,
                   'certificate': float(np.linalg.eigvalsh(Xv)[0])}
