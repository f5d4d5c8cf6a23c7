"""DMDc's ``'stable'`` variant: one lag of states and inputs, spectral radius bounded.

A sampled linear second-order system with inputs held over each step is exactly
``x̃_{k+1} = A₁ x̃_k + A₂ x̃_{k-1} + B₀ u_k + B₁ u_{k-1}``: positions alone (the paper's DMDc)
cannot represent it, and DMDc on the positions of a second-order body is marginally unstable at
most ``r``. :func:`lag_model` fits that form by least squares, with a Tikhonov weight chosen on
held-out tails of the training episodes (:func:`select_lag_ridge`), and pulls any eigenvalue
outside ``|z| ≤ ρ`` onto that circle (:func:`clip_spectral_radius`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import DimensionError
from soft_rom.models import run_states

__all__ = ['LAG_RIDGE_GRID', 'clip_spectral_radius', 'lag_model', 'select_lag_ridge']

Array = NDArray[np.float64]

#: Candidate relative ridge weights of the lag regression (``'auto'``).
LAG_RIDGE_GRID = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5)


def clip_spectral_radius(A: ArrayLike, rho: float = 1.0) -> tuple[Array, int]:
    """``A`` with every eigenvalue of modulus ``> rho`` moved radially onto ``|z| = rho``.

    Works on the real Schur form ``A = Z T Zᵀ``: each 1×1 or 2×2 diagonal block of ``T``
    whose eigenvalue modulus exceeds ``rho`` is scaled by ``rho / |λ|`` (a 2×2 block scaled by
    ``s`` has eigenvalues ``s λ``); the coupling above the diagonal is kept, so the other
    eigenvalues do not move.

    Returns
    -------
    A_clipped : ndarray, shape (r, r)
    n_clipped : int
        Number of eigenvalues moved.
    """
    import scipy.linalg as sla
    A = np.asarray(A, dtype=np.float64)
    if A.size == 0 or float(np.max(np.abs(np.linalg.eigvals(A)))) <= rho:
        return A, 0
    T, Z = sla.schur(A, output='real')
    n = T.shape[0]
    i = moved = 0
    target = rho * (1.0 - 1e-12)
    while i < n:
        size = 2 if i + 1 < n and abs(T[i + 1, i]) > 0 else 1
        blk = T[i:i + size, i:i + size]
        mod = float(np.max(np.abs(np.linalg.eigvals(blk))))
        if mod > target:
            T[i:i + size, i:i + size] = blk * (target / mod)
            moved += size
        i += size
    return Z @ T @ Z.T, moved


def lag_model(data: Sequence[tuple[Array, ...]], r: int, s_q: float, s_u: Array, rho: float,
              rcond: float, ridge: float = 0.0) -> tuple[Array, Array, int]:
    """The ``'stable'`` variant: one lag of states and inputs, spectral radius ``<= rho``.

    Least squares ``x̃_{k+1} = A₁ x̃_k + A₂ x̃_{k-1} + B₀ u_k + B₁ u_{k-1}`` (the exact form of a
    sampled linear second-order system with held inputs), in the model
    ``z = [x̃_k; x̃_{k-1}; u_{k-1}]``; eigenvalues outside ``|z| ≤ rho`` are then clipped
    (:func:`clip_spectral_radius`) and ``B₀, B₁`` refitted for the clipped ``A₁, A₂``.

    ``data``: per episode ``(X̃ (l, k), U (m, k), ...)``, the coordinates in the basis of the
    shifted snapshots. ``ridge``: relative Tikhonov weight (``λ = ridge · tr(RRᵀ) / dim``
    with ``R`` the regressors): consecutive samples of a smooth motion make ``x̃_k`` and
    ``x̃_{k-1}`` nearly collinear, and without it the least squares put spurious unstable
    modes in the regression (``0``: plain least squares).
    """
    tgt, reg_x, reg_u = [], [], []
    for Xr, U, *_ in data:
        if Xr.shape[1] < 3:
            continue
        x = Xr[:r] / s_q
        u = U / s_u[:, None]
        tgt.append(x[:, 2:])
        reg_x.append(np.vstack([x[:, 1:-1], x[:, :-2]]))
        reg_u.append(np.vstack([u[:, 1:-1], u[:, :-2]]))
    if not tgt:
        raise DimensionError("DMDc variant 'stable' needs episodes of at least 3 samples.")
    T, Rx, Ru = (np.concatenate(a, axis=1) for a in (tgt, reg_x, reg_u))
    m = Ru.shape[0] // 2
    R = np.vstack([Rx, Ru])
    if ridge > 0:
        Gr = R @ R.T
        Gr[np.diag_indices_from(Gr)] += float(ridge) * float(np.trace(Gr)) / Gr.shape[0]
        theta = np.linalg.solve(Gr, R @ T.T).T
    else:
        theta = np.linalg.lstsq(R.T, T.T, rcond=rcond)[0].T
    A12, B01 = theta[:, :2 * r], theta[:, 2 * r:]
    n = 2 * r + m
    Az = np.zeros((n, n))
    Az[r:2 * r, :r] = np.eye(r)
    Az[:r, :2 * r] = A12
    Ax = Az[:2 * r, :2 * r]
    Ax_c, clipped = clip_spectral_radius(Ax, rho)
    if clipped:
        A12 = Ax_c[:r]
        B01 = np.linalg.lstsq(Ru.T, (T - A12 @ Rx).T, rcond=rcond)[0].T
        Az[:r, :2 * r] = A12
        Az[r:2 * r, :2 * r] = Ax_c[r:]
    Az[:r, 2 * r:] = B01[:, m:]
    Bz = np.zeros((n, m))
    Bz[:r] = B01[:, :m]
    Bz[2 * r:] = np.eye(m)
    # Back to physical units: z_phys = D z_scaled with D = diag(s_q, s_q, s_u).
    dz = np.concatenate([np.full(2 * r, s_q), s_u])
    A = Az * dz[:, None] / dz[None, :]
    B = Bz * dz[:, None] / s_u[None, :]
    return A, B, clipped


def select_lag_ridge(data: Sequence[tuple[Array, Array, Array]], r: int, s_q: float,
                     s_u: Array, rho: float, rcond: float, E: Array, *,
                     grid: Sequence[float] = LAG_RIDGE_GRID, holdout: float = 0.2
                     ) -> tuple[float, list[dict[str, Any]]]:
    """The ridge of :func:`lag_model` with the smallest error on held-out tails.

    Each candidate is fitted on the first ``1 - holdout`` of every training episode; the
    whole episodes are simulated from rest and the relative output error on deviations of
    the tails pooled (``data``: per episode ``(X̃, U, Y - y_ref)``; ``E``: the output map of
    the coordinates). Returns the ridge and the table of every candidate.
    """
    heads = [(x[:, :int(round(x.shape[1] * (1 - holdout)))],
              u[:, :int(round(u.shape[1] * (1 - holdout)))]) for x, u, _ in data]
    table = []
    for ridge in grid:
        try:
            A, B, _ = lag_model(heads, r, s_q, s_u, rho, rcond, float(ridge))
        except (np.linalg.LinAlgError, DimensionError):
            table.append({'ridge': float(ridge), 'tail_error': float('inf')})
            continue
        err = dev = 0.0
        for _x, u, yd in data:
            c = int(round(u.shape[1] * (1 - holdout)))
            with np.errstate(all='ignore'):
                X = run_states(A, B, np.zeros(A.shape[0]), u[:, :-1])
                Yh = E @ X[:r]
            err += float(np.sum((yd[:, c:] - Yh[:, c:]) ** 2))
            dev += float(np.sum(yd[:, c:] ** 2))
        e = float(np.sqrt(err / dev)) if dev > 0 else float('inf')
        table.append({'ridge': float(ridge), 'tail_error': e if np.isfinite(e) else float('inf')})
    best = min(table, key=lambda row: row['tail_error'])
    return best['ridge'], table
