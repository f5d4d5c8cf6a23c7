"""Compiled element loop of the corotational force (numba, the ``fast`` extra).

One pass over the elements computes, per tetrahedron, the deformation gradient, its polar
rotation (the scaled Newton iteration of :func:`soft_rom.sim.fem.polar_rotation`, stopped per
element), the first Piola stress and the nodal forces, and adds them into the nodal force
array. The numpy path of :class:`soft_rom.sim.fem.CorotationalFEM` makes about 300 passes
over arrays of all elements for the same work; this loop keeps each element in registers.
Both give the same forces to round-off (``tests/sim/test_fem.py``).

Without numba, :data:`AVAILABLE` is false and the numpy path is used.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ['AVAILABLE', 'elastic_force']

try:
    import numba
except ImportError:  # pragma: no cover - exercised by the minimum-versions run
    AVAILABLE = False
else:
    AVAILABLE = True


def _elastic_force(x: Any, tets: Any, dinv: Any, two_mu_v: Any, lam_v: Any, tol: float,
                   max_iter: int, out: Any) -> int:
    """Add ``-dU/dq`` of every element into ``out`` (n_nodes, 3); returns the inverted count.

    ``dinv`` (n_el, 3, 3) holds ``D_m^{-1}``; ``two_mu_v = 2 mu V`` and ``lam_v = lambda V``.
    An element with ``det F <= 0`` is skipped and counted: the caller then takes the numpy
    path, whose SVD handles inverted elements.
    """
    n_el = tets.shape[0]
    bad = 0
    F = np.empty(9)
    X = np.empty(9)
    C = np.empty(9)
    for e in range(n_el):
        t0, t1, t2, t3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        for i in range(3):
            base = x[t0, i]
            d0 = x[t1, i] - base
            d1 = x[t2, i] - base
            d2 = x[t3, i] - base
            for j in range(3):
                F[3 * i + j] = d0 * dinv[e, 0, j] + d1 * dinv[e, 1, j] + d2 * dinv[e, 2, j]
        det0 = (F[0] * (F[4] * F[8] - F[5] * F[7]) + F[1] * (F[5] * F[6] - F[3] * F[8])
                + F[2] * (F[3] * F[7] - F[4] * F[6]))
        if not det0 > 0:
            bad += 1
            continue
        for i in range(9):
            X[i] = F[i]
        for it in range(max_iter):
            a, b, c, d, ee, f, g, h, k = X[0], X[1], X[2], X[3], X[4], X[5], X[6], X[7], X[8]
            C[0] = ee * k - f * h
            C[1] = f * g - d * k
            C[2] = d * h - ee * g
            C[3] = c * h - b * k
            C[4] = a * k - c * g
            C[5] = b * g - a * h
            C[6] = b * f - c * ee
            C[7] = c * d - a * f
            C[8] = a * ee - b * d
            det = a * C[0] + b * C[1] + c * C[2]
            if it < 4:
                gam = 1.0 / np.cbrt(abs(det))
                s1 = 0.5 * gam
                s2 = 0.5 / (gam * det)
            else:
                s1 = 0.5
                s2 = 0.5 / det
            change = 0.0
            for i in range(9):
                xn = s1 * X[i] + s2 * C[i]
                dx = abs(xn - X[i])
                if dx > change:
                    change = dx
                X[i] = xn
            if change * change <= tol:
                break
        tr = 0.0
        for i in range(9):
            tr += X[i] * F[i]
        tr -= 3.0
        tm = -two_mu_v[e]
        lt = -lam_v[e] * tr
        for i in range(3):
            P0 = tm * (F[3 * i] - X[3 * i]) + lt * X[3 * i]
            P1 = tm * (F[3 * i + 1] - X[3 * i + 1]) + lt * X[3 * i + 1]
            P2 = tm * (F[3 * i + 2] - X[3 * i + 2]) + lt * X[3 * i + 2]
            f1 = P0 * dinv[e, 0, 0] + P1 * dinv[e, 0, 1] + P2 * dinv[e, 0, 2]
            f2 = P0 * dinv[e, 1, 0] + P1 * dinv[e, 1, 1] + P2 * dinv[e, 1, 2]
            f3 = P0 * dinv[e, 2, 0] + P1 * dinv[e, 2, 1] + P2 * dinv[e, 2, 2]
            out[t1, i] += f1
            out[t2, i] += f2
            out[t3, i] += f3
            out[t0, i] -= f1 + f2 + f3
    return bad


if AVAILABLE:
    _compiled = numba.njit(cache=True, nogil=True, fastmath=False)(_elastic_force)


def elastic_force(x: np.ndarray, tets: np.ndarray, dinv: np.ndarray, two_mu_v: np.ndarray,
                  lam_v: np.ndarray, *, tol: float = 1e-15,
                  max_iter: int = 40) -> np.ndarray | None:
    """Nodal elastic forces (n_nodes, 3), or ``None`` when an element is inverted.

    Parameters
    ----------
    x : ndarray, shape (n_nodes, 3)
    tets : ndarray of int64, shape (n_el, 4)
    dinv : ndarray, shape (n_el, 3, 3)
        Inverse rest edge matrices ``D_m^{-1}``.
    two_mu_v, lam_v : ndarray, shape (n_el,)
        ``2 mu V`` and ``lambda V`` per element.
    tol, max_iter
        Stopping rule of the polar iteration (:func:`soft_rom.sim.fem.polar_rotation`).
    """
    out = np.zeros((x.shape[0], 3))
    bad = _compiled(np.ascontiguousarray(x, dtype=np.float64), tets, dinv, two_mu_v, lam_v,
                    float(tol), int(max_iter), out)
    return None if bad else out
