"""Benchmark: the conic fit of the cubic LOpInf model, compressed vs uncompressed.

Data: the damped chain of ``bench_lopinf.py`` (POD coefficients, ``m = 6`` antagonistic
inputs, measurement noise, 4,000 snapshots at 1 kHz, 8th-order differences), or with
``--data FILE.npz`` reduced eel data (arrays ``Q1``, ``U1``, ``Q2``, ``U2``, ``dt``: training
episodes 1 and 2). Coordinates are scaled as :class:`~soft_rom.learners.lopinf.LOpInf` scales
them. The noisy least-squares quartic is not positive, so the fit takes the conic path
(``K, C ⪰ eps``, sum-of-squares quartic). For each ``r`` the script times

* the baseline: the same conic problem written directly, all ``n_θ`` unknowns with the
  objective ``|Lᵀθ - c|²`` over the Cholesky factor of the full normal matrix and ``H`` an
  expression of the Gram matrix (what the first version of the fit did; minutes at
  ``r = 10``, so only up to ``--baseline-max-r``, default 6);
* :func:`soft_rom.learners.lopinf.cubic.fit_cubic` end to end (least squares, linear
  start, compressed conic problem, certificate), and its conic part alone,

and prints the seconds, the ratio of the two conic solves and the relative difference of the
objectives ``θᵀNθ - 2gᵀθ + |b|²`` (positive: the compressed fit is worse). Run::

    .venv/bin/python benchmarks/bench_cubic.py [--r 4 6 10] [--baseline-max-r 10]
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
from pathlib import Path
import time
from typing import Any
import warnings

import numpy as np
import scipy.linalg as sla

from soft_rom.ddt import FiniteDifference
from soft_rom.learners.lopinf import cubic as lc
from soft_rom.models.tensors import gram_map, symmetric_entries


def _chain_module() -> object:
    spec = importlib.util.spec_from_file_location(
        'bench_lopinf', Path(__file__).with_name('bench_lopinf.py'))
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod


def _data(r: int, path: str | None) -> tuple[np.ndarray, ...]:
    """Scaled ``Q, Qd, Qdd, U`` (columns are samples)."""
    if path is None:
        mod: Any = _chain_module()
        Q, Qd, Qdd, U = mod.make_data(r)
    else:
        d = np.load(path)
        dt = float(d['dt'])
        fd = FiniteDifference(order=8)
        Qs, Us = [d['Q1'][:r], d['Q2'][:r]], [d['U1'], d['U2']]
        sq = math.sqrt(float(np.mean(np.concatenate(Qs, 1) ** 2)))
        su = np.sqrt(np.mean(np.concatenate(Us, 1) ** 2, axis=1))
        su[su == 0] = 1.0
        Q, Qd, Qdd, (U,) = fd.episodes([q / sq for q in Qs], dt, [[u / su[:, None] for u in Us]])
        return Q, Qd, Qdd, U
    sq = math.sqrt(float(np.mean(Q ** 2)))
    su = np.sqrt(np.mean(U ** 2, axis=1))
    su[su == 0] = 1.0
    return Q / sq, Qd / sq, Qdd / sq, U / su[:, None]


def _baseline(A: np.ndarray, b: np.ndarray, lay: lc._Layout, ridge: np.ndarray, eps: float,
              t4: float) -> np.ndarray:
    """The uncompressed conic problem; returns ``θ``."""
    import cvxpy as cp
    r, o = lay.r, lay.t_off
    N = A.T @ A + np.diag(ridge)
    N += 1e-13 * float(np.trace(N)) / N.shape[0] * np.eye(N.shape[0])
    Lc = np.linalg.cholesky(N)
    c = sla.solve_triangular(Lc, A.T @ b, lower=True)
    scale = max(float(np.linalg.norm(c)), 1e-300)
    Tg, ns = gram_map(r)
    th_K, th_G = cp.Variable(o['G'] - o['K']), cp.Variable(o['H'] - o['G'])
    th_C, th_B = cp.Variable(o['B'] - o['C']), cp.Variable(lay.n_theta - o['B'])
    X = cp.Variable((ns, ns), symmetric=True)
    theta = cp.hstack([th_K, th_G, Tg @ cp.vec(X, order='C'), th_C, th_B])
    Ms = lc._sym_map(r)
    Kx = cp.reshape(Ms @ th_K, (r, r), order='C')
    Cx = cp.reshape(Ms @ th_C, (r, r), order='C')
    cons = [0.5 * (Kx + Kx.T) - eps * np.eye(r) >> 0, 0.5 * (Cx + Cx.T) - eps * np.eye(r) >> 0,
            X - t4 * np.eye(ns) >> 0]
    prob = cp.Problem(cp.Minimize(cp.sum_squares(Lc.T @ theta - c) / scale ** 2), cons)
    prob.solve(solver='CLARABEL')
    return np.concatenate([th_K.value, th_G.value, Tg @ np.asarray(X.value).ravel(),
                           th_C.value, th_B.value])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--r', type=int, nargs='+', default=[4, 6, 10])
    ap.add_argument('--baseline-max-r', type=int, default=6)
    ap.add_argument('--data', default=None, help='reduced eel data (.npz), default the chain')
    ap.add_argument('--reg', type=float, default=1e-3)
    ap.add_argument('--eps4', type=float, default=1e-2)
    args = ap.parse_args()
    warnings.simplefilter('ignore', UserWarning)
    import cvxpy  # noqa: F401  (import time is not fit time)
    print(f'data: {args.data or "damped chain (bench_lopinf.make_data)"}; '
          f'OPENBLAS_NUM_THREADS={os.environ.get("OPENBLAS_NUM_THREADS", "unset")}')
    for r in args.r:
        Q, Qd, Qdd, U = _data(r, args.data)
        t0 = time.perf_counter()
        sol = lc.fit_cubic(Q, Qd, Qdd, U, reg=args.reg, eps4=args.eps4)
        t_new = time.perf_counter() - t0
        lay = lc._Layout(r, U.shape[0])
        Z = lay.features(Q, Qd, U)
        Qz, Rz = np.linalg.qr(Z.T)
        A = np.vstack([(lay.L[i].T @ Rz.T).T for i in range(r)])
        b = -np.concatenate([Qz.T @ Qdd[i] for i in range(r)])
        o = lay.t_off
        ridge = np.zeros(lay.n_theta)
        ridge[o['G']:o['C']] = args.reg * Q.shape[1] * np.concatenate(
            [lay.tensor_weights('G'), lay.tensor_weights('H')])

        def obj(th: np.ndarray, A: np.ndarray = A, b: np.ndarray = b,
                ridge: np.ndarray = ridge) -> float:
            return float(np.sum((A @ th - b) ** 2) + np.sum(ridge * th ** 2))

        th_new = np.concatenate([symmetric_entries(sol.K), symmetric_entries(sol.G),
                                 symmetric_entries(sol.H), symmetric_entries(sol.C),
                                 sol.B.ravel()])
        f_new = obj(th_new)
        line = (f'r={r:2d}: {sol.info["method"]}; fit {t_new:6.1f} s '
                f'(conic {sol.info.get("conic_seconds", 0.0):.1f} s, '
                f'{sol.info.get("conic_unknowns", 0)} conic unknowns)')
        if 'conic_seconds' in sol.info and r <= args.baseline_max_r:
            t0 = time.perf_counter()
            th_old = _baseline(A, b, lay, ridge, 1e-6, float(sol.info['quartic_target']))
            t_old = time.perf_counter() - t0
            f_old = obj(th_old)
            t_conic = float(sol.info['conic_seconds'])
            line += (f'; baseline conic {t_old:6.1f} s, conic ratio {t_old / t_conic:5.1f}x, '
                     f'objective gap {(f_new - f_old) / abs(f_old):+.2e}')
        print(line, flush=True)


if __name__ == '__main__':
    main()
