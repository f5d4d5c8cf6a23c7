"""Benchmark: LOpInf operator solve, FastSPDSolver vs the straightforward cvxpy formulation.

Data: POD coefficients of a simulated damped mass-spring chain (n = 400 degrees of freedom)
driven by three antagonistic input pairs (m = 6, ``u_{2i+1} = -u_{2i}`` so U has rank 3),
with small measurement noise on the snapshots, K = 4,000 snapshots at 1 kHz; derivatives by
8th-order central differences. For r = 10, 16, 28 the script times

* the baseline: ``cvxpy`` with Clarabel on ``min ||Q̈ + C Q̇ + K Q - B U||_F`` over the raw
  ``r × k`` residual, ``K, C ⪰ eps I`` (as one would write it in CVX);
* :class:`soft_rom.learners.lopinf.solvers.FastSPDSolver` on the same data (Gram/QR
  reduction, closed-form symmetric least squares, then a primal-dual interior point with
  Nesterov-Todd scaling on the symmetric-Kronecker Newton system, with K eliminated exactly by
  a Schur complement when its constraint is inactive; :mod:`soft_rom.learners.lopinf.ipm`),

and prints wall-clock times (cvxpy once, the fast solver best of ``--repeat``), CPU times
(``time.process_time``, less sensitive to other load on a shared machine), their ratios, and
the relative gap of the Frobenius objectives (positive: the fast solver is worse). The
reduced cvxpy formulation is timed too, for information. ``lam_min_*`` is the smallest
eigenvalue of K and C: at its default tolerances Clarabel may return a slightly infeasible
point (``lam_min < eps``), whose objective is then a little *below* the constrained optimum;
a positive gap of order 1e-9 is that, not a fast-solver shortfall. Run::

    .venv/bin/python benchmarks/bench_lopinf.py [--repeat 5] [--r 10 16 28]

BLAS threads: both solvers run with ``OPENBLAS_NUM_THREADS=1`` (and ``OMP``/``MKL``) unless
those variables are already set: the matrices are small, and on a shared machine BLAS
threads make small dense factorizations tens of times slower (both solvers are affected).
"""

from __future__ import annotations

import argparse
import os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402

from soft_rom.ddt import FiniteDifference  # noqa: E402

try:                                    # this tree
    from soft_rom.learners.lopinf.solvers import CvxpySolver, FastSPDSolver, objective
except ImportError:                     # a revision before the learners were packages (ab.py)
    from soft_rom.learners.lopinf_solvers import (  # type: ignore[no-redef]
        CvxpySolver,
        FastSPDSolver,
        objective,
    )


def make_data(r: int, *, k: int = 4000, n: int = 400, m: int = 6, dt: float = 1e-3,
              noise: float = 1e-4, seed: int = 0
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reduced data ``Q, Qd, Qdd`` (r, k') and ``U`` (m, k') of a damped chain."""
    rng = np.random.default_rng(seed)
    # Chain fixed at one end; stiffness varying along the body (soft tip).
    kk = 4e4 * np.linspace(1.0, 0.2, n) * (1 + 0.1 * rng.random(n))
    Kf = np.diag(kk + np.r_[kk[1:], 0.0]) - np.diag(kk[1:], 1) - np.diag(kk[1:], -1)
    Cf = 0.5 * np.eye(n) + 2e-3 * Kf
    Bf = np.zeros((n, m))
    for i in range(m // 2):
        a, b = (i + 1) * n // (m // 2 + 1), (i + 1) * n // (m // 2 + 1) + n // 20
        Bf[a - 5:a + 5, 2 * i] = 50.0
        Bf[b - 5:b + 5, 2 * i + 1] = -40.0
    t = np.arange(k + 8) * dt
    U = np.zeros((m, t.size))
    for i in range(m // 2):
        f = rng.uniform(0.3, 3.0, 4)
        ph = rng.uniform(0, 2 * np.pi, 4)
        U[2 * i] = 1e4 * np.sum(np.sin(2 * np.pi * f[:, None] * t + ph[:, None]), axis=0)
        U[2 * i + 1] = -U[2 * i]
    Ac = np.block([[np.zeros((n, n)), np.eye(n)], [-Kf, -Cf]])
    Bc = np.vstack([np.zeros((n, m)), Bf])
    M = np.zeros((2 * n + m, 2 * n + m))
    M[:2 * n, :2 * n] = Ac * dt
    M[:2 * n, 2 * n:] = Bc * dt
    E = sla.expm(M)
    Ad, Bd = E[:2 * n, :2 * n], E[:2 * n, 2 * n:]
    X = np.zeros((2 * n, t.size))
    for j in range(t.size - 1):
        X[:, j + 1] = Ad @ X[:, j] + Bd @ U[:, j]
    Qf = X[:n] + noise * np.std(X[:n]) * rng.standard_normal((n, t.size))
    V = np.linalg.svd(Qf, full_matrices=False)[0][:, :r]
    Qhat = V.T @ Qf
    fd = FiniteDifference(8)
    Q, Qd, Qdd = fd.derivatives(Qhat, dt)
    return Q, Qd, Qdd, fd.trim(U)


def _lam_min(sol) -> float:
    """Smallest eigenvalue of K and C (the constraint is ``>= eps = 1e-6``)."""
    return float(min(np.linalg.eigvalsh(sol.K)[0], np.linalg.eigvalsh(sol.C)[0]))


def main() -> None:
    """Run the benchmark and print a table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--r', type=int, nargs='+', default=[10, 16, 28])
    ap.add_argument('--repeat', type=int, default=5, help='fast-solver repetitions (best of)')
    ap.add_argument('--no-cvxpy', action='store_true',
                    help='time the fast solver only (the cvxpy baselines take minutes)')
    ap.add_argument('--json-out', default=None, metavar='FILE',
                    help='also write the timings (s) as JSON (benchmarks/ab.py reads them)')
    args = ap.parse_args()
    figures: dict[str, float] = {}
    print(f'BLAS threads: OPENBLAS_NUM_THREADS={os.environ["OPENBLAS_NUM_THREADS"]}')
    print(f'{"r":>3} {"k":>5} {"fast method":>20} {"newton":>6} {"t_cvxpy_raw[s]":>14} '
          f'{"t_cvxpy_red[s]":>14} {"t_fast[s]":>10} {"ratio_raw":>9} {"ratio_red":>9} '
          f'{"gap_vs_raw":>10} {"gap_vs_red":>10} {"cond(Z)":>9} {"cpu_raw[s]":>10} '
          f'{"cpu_fast[s]":>11} {"cpu_ratio":>9} {"lam_min_cvx":>11} {"lam_min_fast":>12}')
    verdicts = []
    for r in args.r:
        Q, Qd, Qdd, U = make_data(r)
        cond = np.linalg.cond(np.vstack([Qd, Q]))
        best = c_best = np.inf
        if args.no_cvxpy:
            for _ in range(args.repeat):
                c0, t0 = time.process_time(), time.perf_counter()
                sol = FastSPDSolver().solve(Q, Qd, Qdd, U)
                best = min(best, time.perf_counter() - t0)
                c_best = min(c_best, time.process_time() - c0)
            figures[f'fast solver r={r} wall'] = best
            figures[f'fast solver r={r} cpu'] = c_best
            print(f'{r:>3} {Q.shape[1]:>5} fast solver {best:.4f} s (cpu {c_best:.4f} s), '
                  f'objective {objective(*sol[:3], Q, Qd, Qdd, U):.6e}', flush=True)
            continue
        c0, t0 = time.process_time(), time.perf_counter()
        ref = CvxpySolver('CLARABEL', formulation='raw').solve(Q, Qd, Qdd, U)
        t_ref, c_ref = time.perf_counter() - t0, time.process_time() - c0
        t0 = time.perf_counter()
        red = CvxpySolver('CLARABEL', formulation='reduced').solve(Q, Qd, Qdd, U)
        t_red = time.perf_counter() - t0
        for _ in range(args.repeat):
            c0, t0 = time.process_time(), time.perf_counter()
            sol = FastSPDSolver().solve(Q, Qd, Qdd, U)
            best = min(best, time.perf_counter() - t0)
            c_best = min(c_best, time.process_time() - c0)
        figures[f'fast solver r={r} wall'] = best
        figures[f'fast solver r={r} cpu'] = c_best
        figures[f'cvxpy raw r={r} wall'] = t_ref
        o_ref = objective(*ref[:3], Q, Qd, Qdd, U)
        o_fast = objective(*sol[:3], Q, Qd, Qdd, U)
        o_red = objective(*red[:3], Q, Qd, Qdd, U)
        gap, gap_red = (o_fast - o_ref) / o_ref, (o_fast - o_red) / o_red
        method = sol.info['method'].replace('symmetric-least-squares', 'closed-form')
        print(f'{r:>3} {Q.shape[1]:>5} {method:>20} {sol.info["newton_steps"]:>6} '
              f'{t_ref:>14.3f} {t_red:>14.3f} {best:>10.4f} {t_ref / best:>9.1f} '
              f'{t_red / best:>9.1f} {gap:>10.2e} {gap_red:>10.2e} {cond:>9.2e} '
              f'{c_ref:>10.3f} {c_best:>11.4f} {c_ref / c_best:>9.1f} {_lam_min(ref):>11.2e} '
              f'{_lam_min(sol):>12.2e}', flush=True)
        target = {16: 1000.0, 28: 500.0}.get(r)
        if target is not None:
            verdicts.append(f'r = {r}: {t_ref / best:.0f}x faster than cvxpy (raw; target '
                            f'>= {target:.0f}x: {"met" if t_ref / best >= target else "NOT met"})'
                            f', objective gap {gap:.1e} (target <= 1e-8: '
                            f'{"met" if gap <= 1e-8 else "NOT met"})')
    for line in verdicts:
        print(line)
    if args.json_out:
        import json
        with open(args.json_out, 'w', encoding='utf-8') as fh:
            json.dump(figures, fh)


if __name__ == '__main__':
    main()
