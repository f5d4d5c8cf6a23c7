"""QP solvers for the eel MPC, measured on the QPs a closed loop actually poses.

The MPC of :mod:`soft_rom.control` (r = 16 LOpInf-sized ROM: 32 states, 6 inputs, 40
outputs, horizon 0.2 s at 10 ms = 20 steps, input and rate bounds) runs closed loop on the
embedded FOM over a feasible reference and the travelling wave (the inputs saturate, so
constraints are active); every QP it poses is recorded. The same sequence is then solved,
in order and warm-started, by each candidate:

* DAQP, condensed (dense active set; workspace reused, active set warm start) -- soft_rom's;
* OSQP, condensed and sparse (states kept as variables), warm-started;
* proxsuite (ProxQP dense), warm-started, if installed;
* Clarabel, condensed (interior point: no warm start);
* cvxpy on the same condensed QP (a Parameter problem, solved by its default solver);
* DAQP on the same recorded states posed with the Riccati terminal cost (another Hessian of
  the same size).

Printed: per solver the solve-time p50 / p99 / max (ms), the largest deviation of its
solutions from DAQP's (objective-scaled), the ratio of its p99 to DAQP's, and the machine
load. A whole control step (estimate, solve) is timed by the closed loop itself.

Run: ``python benchmarks/bench_mpc.py`` (``--model FILE`` for a fitted LOpInf file, default
the eel's modal ROM with r = 16; ``--repeat N`` to repeat the replay; ``--skip
osqp-sparse,clarabel`` to leave the slowest candidates out).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import time

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))


def load() -> str:
    return ' '.join(f'{v:.2f}' for v in os.getloadavg())


def record(model, duration: float):
    from soft_rom.control import (
        Controller,
        FOMPlant,
        MPC,
        parse_reference,
        Reference,
        run_closed_loop,
        simulate_inputs,
    )
    import soft_rom.control.loop as loop_mod
    from soft_rom.sim import random_pressures

    calls = []
    original = loop_mod.Controller

    class RecordingController(Controller):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            solve = self.mpc.solve

            def recorded(x, d, R, u_last):
                calls.append((np.array(x), np.array(d), np.array(R), np.array(u_last)))
                return solve(x, d, R, u_last)
            self.mpc.solve = recorded

    loop_mod.Controller = RecordingController
    stats = []
    try:
        k = int(round((duration + 0.2) / 1e-3))
        U = random_pressures(k, 1e-3, seed=100, episode=1)
        Y = simulate_inputs(model, U)
        refs = [Reference(t=np.arange(k) * 1e-3, Y=Y, label='feasible (seed 100, Ep 1)'),
                parse_reference('wave:f=2', model, duration=duration + 0.2)]
        for ref in refs:
            res = run_closed_loop(model, ref, plant=FOMPlant(model), duration=duration)
            s = res.summary()
            stats.append((ref.label, s))
    finally:
        loop_mod.Controller = original
    mpc = MPC(model)
    problems = [mpc.qp_data(*c) for c in calls]
    return mpc, problems, calls, stats


def pct(a):
    a = np.asarray(a) * 1e3
    return np.percentile(a, 50), np.percentile(a, 99), a.max()


def run_daqp(mpc, problems):
    from soft_rom.control.qp import DaqpSolver
    s = DaqpSolver(mpc.H, mpc.A_rate)
    return _run(s.solve, problems)


def run_osqp_dense(mpc, problems):
    from soft_rom.control.qp import OsqpSolver
    s = OsqpSolver(mpc.H, mpc.A_rate)
    return _run(s.solve, problems)


CPU: list[float] = []      # thread CPU time of the last run's solves (immune to preemption)


def _run(fn, problems):
    xs, ts = [], []
    CPU.clear()
    for f, lb, ub, lbA, ubA in problems:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        r = fn(f, lb, ub, lbA, ubA)
        ts.append(time.perf_counter() - t0)
        CPU.append(time.thread_time() - c0)
        xs.append(None if r.x is None else r.x)
    return xs, ts


class _R:
    def __init__(self, x):
        self.x = x


def run_clarabel(mpc, problems):
    import clarabel
    n = mpc.H.shape[0]
    P = sp.csc_matrix(np.triu(mpc.H))
    A = sp.csc_matrix(np.vstack([np.eye(n), -np.eye(n), mpc.A_rate, -mpc.A_rate]))
    settings = clarabel.DefaultSettings()
    settings.verbose = False

    def solve(f, lb, ub, lbA, ubA):
        b = np.concatenate([ub, -lb, ubA, -lbA])
        solver = clarabel.DefaultSolver(P, f, A, b, [clarabel.NonnegativeConeT(b.size)],
                                        settings)
        sol = solver.solve()
        return _R(np.array(sol.x))
    return _run(solve, problems)


def run_proxsuite(mpc, problems):
    import proxsuite
    n = mpc.H.shape[0]
    qp = proxsuite.proxqp.dense.QP(n, 0, mpc.A_rate.shape[0], True)
    state = {'init': False}

    def solve(f, lb, ub, lbA, ubA):
        if not state['init']:
            qp.settings.eps_abs = 1e-6
            qp.settings.initial_guess = (
                proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT)
            qp.init(mpc.H, f, None, None, mpc.A_rate, lbA, ubA, lb, ub)
            state['init'] = True
        else:
            qp.update(g=f, l=lbA, u=ubA, l_box=lb, u_box=ub)
        qp.solve()
        return _R(np.array(qp.results.x))
    return _run(solve, problems)


def run_osqp_sparse(mpc, problems, calls):
    """States kept as variables: ``x_{j+1} = A x_j + B (c + S v_j)``, outputs in the cost."""
    import osqp
    A, B, C, D, _ = mpc.system
    n, m, p, N = mpc.n, mpc.m, mpc.p, mpc.N
    S = np.diag(mpc.half)
    wy = mpc.config.output_weight / (p * mpc.y_scale ** 2)
    nx, nv = N * n, N * m
    Cbig = sp.kron(sp.eye(N), C, format='csr')
    sel = np.zeros((N * m, N * m))                       # y_j sees u_min(j, N-1)
    for j in range(1, N + 1):
        i = min(j, N - 1)
        sel[(j - 1) * m:j * m, i * m:(i + 1) * m] = np.eye(m)
    Dbig = sp.kron(sp.eye(N), D @ S, format='csr') @ sp.csr_matrix(sel)
    Y = sp.hstack([Cbig, Dbig]).tocsc()
    P = wy * (Y.T @ Y) + sp.block_diag([sp.csc_matrix((nx, nx)), sp.csc_matrix(mpc.H_inputs)])
    P = sp.triu(P.tocsc(), format='csc')
    Aeq = sp.hstack([sp.eye(nx) - sp.kron(sp.eye(N, k=-1), A), -sp.kron(sp.eye(N), B @ S)])
    Abox = sp.hstack([sp.csc_matrix((nv, nx)), sp.eye(nv)])
    Arate = sp.hstack([sp.csc_matrix((nv, nx)), sp.csc_matrix(mpc.A_rate)])
    Acon = sp.vstack([Aeq, Abox, Arate]).tocsc()
    solver = osqp.OSQP()
    state = {'init': False}
    Bc = np.tile(B @ mpc.centre, N)

    def solve(prob, call):
        _f, lb, ub, lbA, ubA = prob
        x0, d, R, u_last = call
        e = np.tile(d + mpc.model.y_ref + D @ mpc.centre, N) - R.T.reshape(-1)
        q = np.concatenate([wy * (Cbig.T @ e), wy * (Dbig.T @ e) - mpc._Fv @ mpc.scale(u_last)])
        beq = Bc.copy()
        beq[:n] += A @ x0
        lo = np.concatenate([beq, lb, lbA])
        hi = np.concatenate([beq, ub, ubA])
        if not state['init']:
            solver.setup(P=P, q=q, A=Acon, l=lo, u=hi, eps_abs=1e-6, eps_rel=1e-6,
                         verbose=False, polish=False, warm_starting=True, max_iter=4000)
            state['init'] = True
        else:
            solver.update(q=q, l=lo, u=hi)
        r = solver.solve()
        return _R(None if r.x is None else np.array(r.x[nx:]))

    xs, ts = [], []
    CPU.clear()
    for prob, call in zip(problems, calls):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        r = solve(prob, call)
        ts.append(time.perf_counter() - t0)
        CPU.append(time.thread_time() - c0)
        xs.append(r.x)
    return xs, ts


def run_cvxpy(mpc, problems):
    import cvxpy as cp
    n = mpc.H.shape[0]
    L = np.linalg.cholesky(mpc.H)
    z = cp.Variable(n)
    f = cp.Parameter(n)
    lbA, ubA = cp.Parameter(mpc.A_rate.shape[0]), cp.Parameter(mpc.A_rate.shape[0])
    prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(L.T @ z) + f @ z),
                      [z >= -1, z <= 1, mpc.A_rate @ z >= lbA, mpc.A_rate @ z <= ubA])

    def solve(fv, lb, ub, la, ua):
        f.value, lbA.value, ubA.value = fv, la, ua
        prob.solve(warm_start=True)
        return _R(None if z.value is None else np.array(z.value))
    return _run(solve, problems)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--model', default=None, help='LOpInf model file (default: modal r=16)')
    parser.add_argument('--duration', type=float, default=1.0)
    parser.add_argument('--repeat', type=int, default=3)
    optional = ('osqp', 'osqp-sparse', 'proxsuite', 'clarabel')
    parser.add_argument('--skip', default='',
                        help=f'comma-separated solvers to leave out, of {", ".join(optional)} '
                             '(DAQP and cvxpy always run: they give the printed ratio); '
                             'osqp-sparse alone takes minutes')
    args = parser.parse_args()
    skip = {s for s in args.skip.split(',') if s}
    if skip - set(optional):
        parser.error(f'--skip: unknown solver(s) {", ".join(sorted(skip - set(optional)))}; '
                     f'choose from {", ".join(optional)}')
    from soft_rom.models import load_model
    if args.model:
        model = load_model(args.model)
    else:
        from _eel_rom import modal_rom
        model = modal_rom(16)
    print(f'load average before: {load()}  ({os.cpu_count()} CPUs)')
    mpc, problems, calls, stats = record(model, args.duration)
    print(f'model: {model.method} r={model.r} (states {mpc.n}), m={mpc.m}, p={mpc.p}, '
          f'N={mpc.N} at {mpc.h * 1e3:g} ms: QP with {mpc.H.shape[0]} variables, '
          f'{mpc.H.shape[0]} bounds, {mpc.A_rate.shape[0]} rate constraints; '
          f'{len(problems)} QPs recorded')
    for label, s in stats:
        print(f'  closed loop on the FOM, {label}: tracking deviation error '
              f'{s["tracking_deviation_error"]:.3f}, inputs at a bound '
              f'{100 * s["saturated_fraction"]:.0f} %, control step p50/p99/max '
              f'{s["control_step"]["p50_ms"]:.3f}/{s["control_step"]["p99_ms"]:.3f}/'
              f'{s["control_step"]["max_ms"]:.3f} ms wall = p99 '
              f'{100 * s["control_step_p99_fraction_of_period"]:.1f} % of the 10 ms period; '
              f'CPU p50/p99 {s["control_step_cpu"]["p50_ms"]:.3f}/'
              f'{s["control_step_cpu"]["p99_ms"]:.3f} ms = p99 '
              f'{10 * s["control_step_cpu"]["p99_ms"]:.1f} % of the period')
    runners = [('daqp (condensed, warm)', run_daqp)]
    if 'osqp' not in skip:
        runners.append(('osqp (condensed, warm)', run_osqp_dense))
    if 'proxsuite' not in skip:
        try:
            import proxsuite  # noqa: F401
            runners.append(('proxsuite dense (warm)', run_proxsuite))
        except ImportError:
            print('  (proxsuite not installed: pip install proxsuite to include it)')
    if 'osqp-sparse' not in skip:
        runners.append(('osqp (sparse, warm)',
                        lambda mpc, problems: run_osqp_sparse(mpc, problems, calls)))
    if 'clarabel' not in skip:
        runners.append(('clarabel (condensed, cold)', run_clarabel))
    if skip:
        print(f'  (left out: {", ".join(sorted(skip))})')
    runners.append(('cvxpy (same QP, default solver)', run_cvxpy))
    results = {}
    ref_x = None
    for name, fn in runners:
        best = None
        for _ in range(args.repeat):
            xs, ts = fn(mpc, problems)
            if best is None or np.percentile(ts, 99) < np.percentile(best[1], 99):
                best = (xs, ts, list(CPU))
        xs, ts, cpu = best
        if ref_x is None:
            ref_x = xs
        # objective gap to DAQP's solution, relative to the objective's scale, and the
        # worst bound or rate violation (the QP is ill-conditioned in directions the outputs
        # hardly see, so different solvers' x differ more than their objectives)
        gaps, viol = [], 0.0
        for a, b, (f, lb, ub, lbA, ubA) in zip(xs, ref_x, problems):
            if a is None or b is None:
                continue
            ja, jb = 0.5 * a @ mpc.H @ a + f @ a, 0.5 * b @ mpc.H @ b + f @ b
            gaps.append((ja - jb) / max(abs(jb), 1e-12))
            Az = mpc.A_rate @ a
            viol = max(viol, float(np.max(np.maximum(lb - a, 0))), float(np.max(
                np.maximum(a - ub, 0))), float(np.max(np.maximum(lbA - Az, 0))),
                float(np.max(np.maximum(Az - ubA, 0))))
        dev = (max(gaps, default=float('nan')), viol)
        fails = sum(x is None for x in xs)
        results[name] = (pct(ts), dev, fails, pct(cpu))
    base = results['daqp (condensed, warm)'][0][1]
    base50 = results['daqp (condensed, warm)'][0][0]
    print('wall time per solve (ms; includes preemption by other processes) and thread CPU time '
          '(ms; what the solve itself costs):')
    print(f'{"solver":34s} {"p50":>7s} {"p99":>7s} {"max":>7s} {"cpu p50":>8s} {"cpu p99":>8s} '
          f'{"p50/daqp":>8s} {"p99/daqp":>8s} {"obj.gap":>8s} {"viol.":>8s} fails')
    for name, ((p50, p99, mx), (gap, viol), fails, (c50, c99, _cm)) in results.items():
        print(f'{name:34s} {p50:7.3f} {p99:7.3f} {mx:7.3f} {c50:8.3f} {c99:8.3f} '
              f'{p50 / base50:8.1f} {p99 / base:8.1f} {gap:8.1e} {viol:8.1e} {fails}')
    # the same recorded states, references and last inputs posed with the Riccati terminal
    # cost (MPCConfig(terminal='riccati'): another Hessian, same size), DAQP warm-started
    from dataclasses import replace

    from soft_rom.control import MPC
    mpc_t = MPC(mpc.model, replace(mpc.config, terminal='riccati'))
    problems_t = [mpc_t.qp_data(*c) for c in calls]
    best_t = None
    for _ in range(args.repeat):
        _xs, ts_t = run_daqp(mpc_t, problems_t)
        if best_t is None or np.percentile(ts_t, 99) < np.percentile(best_t[0], 99):
            best_t = (ts_t, list(CPU))
    (t50, t99, tmax), (tc50, tc99, _tcm) = pct(best_t[0]), pct(best_t[1])
    print(f'{"daqp, riccati terminal cost":34s} {t50:7.3f} {t99:7.3f} {tmax:7.3f} {tc50:8.3f} '
          f'{tc99:8.3f}   (terminal: {mpc_t.terminal})')
    cv = results['cvxpy (same QP, default solver)']
    dq = results['daqp (condensed, warm)']
    print(f'DAQP solve p50 {base50:.3f} ms, p99 {base:.3f} ms wall, p99 {dq[3][1]:.3f} ms CPU '
          f'(target p99 <= 2 ms); cvxpy / DAQP: p50 {cv[0][0] / base50:.0f}x, p99 '
          f'{cv[0][1] / base:.1f}x wall, p99 {cv[3][1] / dq[3][1]:.1f}x CPU; load average '
          f'after: {load()}')
    return 0


if __name__ == '__main__':
    from _entry import run
    run(main)
