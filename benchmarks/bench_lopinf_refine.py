"""Benchmark: LOpInf output-error refinement on noisy measured coordinates.

Data: a damped spring chain (``n_dof`` degrees of freedom, modes 0.5–5 Hz, 3 % damping)
driven by three inputs held for 0.1–0.4 s, sampled at 120 Hz like a motion-capture camera,
two 10-s training episodes and one 10-s test episode, outputs ``y = T q`` in oblique
coordinates with 2 % white noise (relative to their RMS). POD on the noisy outputs, the
repository's Savitzky–Golay derivatives, learned mass (the defaults on measured outputs).
For each r the script prints

* the equation-error LOpInf (``refine='none'``, the baseline): fit time, test error;
* the refined LOpInf (``refine='output-error'``): fit time, iterations, the reduction of the
  training simulation error, test error, and the ratios (time and error) to the baseline;
* the unconstrained least-squares second-order fit on the same derivatives, for reference;

and, for the sensitivities, the time of all ``r (2r + m)`` Fréchet derivatives of the
held-input discretization by the quadrature of :mod:`soft_rom.learners.lopinf.refine`
against one :func:`scipy.linalg.expm_frechet` per direction (the baseline), with their
largest difference. Test errors are relative deviation errors against the *clean* test
outputs. Run::

    .venv/bin/python benchmarks/bench_lopinf_refine.py [--r 4 8 12] [--n-dof 8]

BLAS threads: one (``OPENBLAS_NUM_THREADS=1`` unless set): the matrices are small.
"""

from __future__ import annotations

import os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402

from soft_rom.basis import POD, project  # noqa: E402
from soft_rom.ddt import SavitzkyGolay  # noqa: E402
from soft_rom.learners.lopinf import LOpInf  # noqa: E402
from soft_rom.learners.lopinf.refine import _frechet_rows, _frechet_rows_direct  # noqa: E402
from soft_rom.metrics import relative_deviation_error  # noqa: E402
from soft_rom.models import SecondOrderModel  # noqa: E402
from soft_rom.reduce import ReducedData  # noqa: E402

DT = 1 / 120
K_SAMPLES = 1200
M_IN = 3


def chain(n_dof: int, seed: int):
    rng = np.random.default_rng(seed)
    w = 2 * np.pi * np.linspace(0.5, 5.0, n_dof)
    Vm, _ = np.linalg.qr(rng.standard_normal((n_dof, n_dof)))
    K = Vm @ np.diag(w ** 2) @ Vm.T
    C = Vm @ np.diag(2 * 0.03 * w) @ Vm.T
    B = rng.standard_normal((n_dof, M_IN)) * w.mean() ** 2 * 0.02
    T = np.eye(n_dof) + 0.4 * rng.standard_normal((n_dof, n_dof))
    return K, C, B, T


def simulate(K, C, B, U):
    n = K.shape[0]
    M = np.zeros((2 * n + M_IN, 2 * n + M_IN))
    M[:n, n:2 * n] = np.eye(n)
    M[n:2 * n, :n], M[n:2 * n, n:2 * n], M[n:2 * n, 2 * n:] = -K, -C, B
    F = sla.expm(M * DT)
    x = np.zeros(2 * n)
    X = np.empty((n, U.shape[1]))
    for j in range(U.shape[1]):
        X[:, j] = x[:n]
        x = F[:2 * n, :2 * n] @ x + F[:2 * n, 2 * n:] @ U[:, j]
    return X


def episode(sys_, rng):
    K, C, B, T = sys_
    holds = rng.integers(12, 48, size=200)
    levels = rng.uniform(-1, 1, (M_IN, holds.size))
    U = np.repeat(levels, holds, axis=1)[:, :K_SAMPLES]
    return U, T @ simulate(K, C, B, U)


def unconstrained(Qhat, U, est, V, y_ref, test_U):
    Qs, Qd, Qdd, (Us,) = est.episodes(Qhat, DT, [U])
    X, *_ = np.linalg.lstsq(np.vstack([Qs, Qd, Us]).T, Qdd.T, rcond=None)
    r = Qs.shape[0]
    X = X.T
    model = SecondOrderModel(-X[:, :r], -X[:, r:2 * r], X[:, 2 * r:], V, dt=DT, y_ref=y_ref)
    with np.errstate(all='ignore'):
        return model.simulate(test_U)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--r', type=int, nargs='+', default=[4, 8, 12])
    ap.add_argument('--n-dof', type=int, default=8)
    ap.add_argument('--noise', type=float, default=0.02)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    sys_ = chain(args.n_dof, args.seed)
    train = [episode(sys_, rng) for _ in range(2)]
    test_U, test_Y = episode(sys_, rng)
    scale = float(np.sqrt(np.mean(np.concatenate([y for _, y in train], 1) ** 2)))
    noisy = [(u, y + args.noise * scale * rng.standard_normal(y.shape)) for u, y in train]
    y_ref = np.zeros(test_Y.shape[0])
    print(f'chain: {args.n_dof} DOF, p = {test_Y.shape[0]}, m = {M_IN}, 2 x {K_SAMPLES} '
          f'training samples at {1 / DT:.0f} Hz, noise {100 * args.noise:.0f} % of RMS')
    print(f'{"r":>3} {"eq.err s":>9} {"eq.err test":>11} {"refined s":>9} {"iters":>5} '
          f'{"train -%":>8} {"refined test":>12} {"time x":>7} {"error x":>7} '
          f'{"unconstr. test":>14}')
    for r in args.r:
        if r > test_Y.shape[0]:
            continue
        pod = POD(r=r).fit([y for _, y in noisy], y_ref)
        V = pod.basis_
        Qhat = [project(y, V, y_ref) for _, y in noisy]
        U = [u for u, _ in noisy]
        Y = [y for _, y in noisy]
        out = {}
        for refine in ('none', 'output-error'):
            t0 = time.perf_counter()
            lrn = LOpInf(r=r, ddt=SavitzkyGolay(), mass='learned', refine=refine).fit(
                ReducedData.from_arrays(Qhat, U, Y, DT, y_ref))
            sec = time.perf_counter() - t0
            err = relative_deviation_error(test_Y, lrn.model_.simulate(test_U), y_ref)
            out[refine] = (sec, err, lrn.diagnostics_['refinement'])
        base = unconstrained(Qhat, U, SavitzkyGolay(), V, y_ref, test_U)
        e_unc = relative_deviation_error(test_Y, base, y_ref)
        (s0, e0, _), (s1, e1, info) = out['none'], out['output-error']
        print(f'{r:>3} {s0:>9.2f} {e0:>11.4f} {s1:>9.2f} {info["iterations"]:>5} '
              f'{100 * info["improvement"]:>8.1f} {e1:>12.4f} {s1 / s0:>7.1f} {e1 / e0:>7.2f} '
              f'{e_unc:>14.4f}')
    print('\nFréchet derivatives of the held-input discretization (all r(2r+m) directions):')
    print(f'{"r":>3} {"quadrature ms":>13} {"expm_frechet ms":>15} {"speed-up":>8} '
          f'{"max rel diff":>12}')
    for r in args.r:
        K, C, B, _ = chain(r, args.seed + 1)
        n, N = 2 * r, 2 * r + M_IN
        M = np.zeros((N, N))
        M[:r, r:n] = np.eye(r)
        M[r:n, :r], M[r:n, r:n], M[r:n, n:] = -K, -C, B
        M *= DT
        t0 = time.perf_counter()
        _, dF = _frechet_rows(M, r, n, DT)
        t_q = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, ref = _frechet_rows_direct(M, r, n, DT)     # one scipy expm_frechet per direction
        t_f = time.perf_counter() - t0
        diff = float(np.max(np.abs(dF - ref)) / np.max(np.abs(ref)))
        print(f'{r:>3} {1e3 * t_q:>13.2f} {1e3 * t_f:>15.2f} {t_f / t_q:>8.1f} {diff:>12.1e}')


if __name__ == '__main__':
    main()
