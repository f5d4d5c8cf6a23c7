"""Predictor benchmarks: core step, replay, message conversion, bag writing.

Run: ``.venv/bin/python benchmarks/bench_predictor.py [--r 16] [--k 2000]``

Each figure is printed beside a naive baseline measured in the same run (and the target
from issue 5 where there is one). Message conversions are timed on plain attribute
objects (no rclpy here); rclpy's checked setters add their own cost on top.
"""

# ruff: noqa: E402  (thread settings must precede the numpy import)
from __future__ import annotations

import os

# Tiny matrices: threaded BLAS only adds latency (and wrecks timings on a busy machine).
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import argparse
import array
import tempfile
import time
from types import SimpleNamespace as NS

import numpy as np

from soft_rom.data import Episode
from soft_rom.models import SecondOrderModel
from soft_rom.predictor import Predictor, PredictorConfig, replay_episode
from soft_rom.predictor.conversions import (
    array_to_data,
    data_to_array,
    outputs_to_points,
    poses_to_points,
    set_points,
)


def _model(r: int, m: int = 6, p: int = 40, seed: int = 0) -> SecondOrderModel:
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            0.01 * rng.standard_normal((p, r)), dt=1e-3,
                            y_ref=rng.standard_normal(p))


def _best(fn, n: int, repeat: int = 5) -> float:
    """Best mean seconds per call over ``repeat`` runs of ``n`` calls."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        best = min(best, (time.perf_counter() - t0) / n)
    return best


def _row(name: str, ours: float, naive: float, unit: str = 'us', target: str = '') -> None:
    scale = 1e6 if unit == 'us' else 1e3 if unit == 'ms' else 1.0
    print(f'{name:<44s} {ours * scale:10.2f} {unit:<2s} {naive * scale:10.2f} {unit:<2s} '
          f'{naive / ours:8.1f}x  {target}')


def main() -> None:
    """Print the benchmark table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('--r', type=int, default=16)
    ap.add_argument('--k', type=int, default=2000)
    args = ap.parse_args()
    model = _model(args.r)
    rng = np.random.default_rng(1)
    m, p = model.n_inputs, model.n_outputs
    print(f'model: LOpInf r={args.r} (state {model.n_states}), m={m}, p={p}, dt={model.dt}')
    print(f'{"":<44s} {"ours":>13s} {"naive":>13s} {"speedup":>9s}  target')

    # 1. core step -------------------------------------------------------------------------
    pred = Predictor(model)
    u = rng.standard_normal(m)
    pred.set_input(u, 0.0)
    x = np.zeros(model.n_states)

    def naive_step() -> None:
        nonlocal x
        x = model.step(x, u)            # looks the system up and allocates each call

    _row('core step (held input)', _best(pred.step, 20000), _best(naive_step, 20000),
         target='<= 20 us')
    t = [0.0]

    def update() -> None:               # what one input callback + publish does
        t[0] += model.dt
        pred.set_input(u, t[0])
        pred.output()

    x2 = np.zeros(model.n_states)

    def naive_update() -> None:
        nonlocal x2
        x2 = model.step(x2, u)
        model.output(x2, u)

    _row('input callback: advance + latch + output', _best(update, 10000),
         _best(naive_update, 10000))
    pj = Predictor(model, PredictorConfig(stepping='input'))
    tj = [0.0]
    jitter = rng.uniform(0.9e-3, 1.1e-3, 64)       # 64 distinct intervals, then cache hits
    cnt = [0]

    def jittered() -> None:
        tj[0] += jitter[cnt[0] % 64]
        cnt[0] += 1
        pj.set_input(u, tj[0])

    _row('input stepping, jittered stamps (cached)', _best(jittered, 5000),
         _best(naive_update, 5000))

    # 2. replay ----------------------------------------------------------------------------
    k = args.k
    U = rng.standard_normal((m, k))
    ep = Episode(t=np.arange(k) * model.dt, U=U, Y=model.simulate(U))

    def ours_replay() -> None:
        replay_episode(Predictor(model), ep, measured=True)

    def naive_replay() -> None:
        xs = np.zeros(model.n_states)
        for j in range(k):
            model.output(xs, U[:, j])
            xs = model.step(xs, U[:, j])

    ours = _best(ours_replay, 1, repeat=3)
    _row(f'replay {k} steps (with monitor)', ours, _best(naive_replay, 1, repeat=3),
         unit='ms', target='<= 200 ms')
    _row('  vs model.simulate (vectorised, no monitor)', ours,
         _best(lambda: model.simulate(U), 1, repeat=3), unit='ms')
    c0 = time.process_time()
    ours_replay()
    print(f'  replay CPU time (process_time, robust to a busy machine): '
          f'{(time.process_time() - c0) * 1e3:.1f} ms')
    res = replay_episode(Predictor(model), ep, measured=False)
    print(f'  replay vs simulate max abs difference: {np.abs(res.Y - ep.Y).max():.2e}')

    # 3. conversions -----------------------------------------------------------------------
    n = p // 2
    y = rng.standard_normal(p)
    poses = [NS(position=NS(x=0.0, y=0.0, z=0.0)) for _ in range(n)]
    positions = [q.position for q in poses]
    buf = np.empty((n, 3))

    def ours_out() -> None:
        set_points(positions, outputs_to_points(y, 'xz', out=buf))

    def naive_out() -> None:
        for i in range(n):
            poses[i].position.x = float(y[i])
            poses[i].position.y = 0.0
            poses[i].position.z = float(y[n + i])

    _row('output -> 20 poses (in place)', _best(ours_out, 20000), _best(naive_out, 20000))

    def naive_new() -> None:            # rebuilding the message each time
        [NS(position=NS(x=float(y[i]), y=0.0, z=float(y[n + i]))) for i in range(n)]

    _row('  vs new pose objects each publish', _best(ours_out, 20000),
         _best(naive_new, 20000))
    _row('PoseArray.poses (20) -> outputs', _best(lambda: poses_to_points(poses), 20000),
         _best(lambda: np.array([[q.position.x, q.position.y, q.position.z]
                                 for q in poses]), 20000))
    data_in = array.array('d', rng.standard_normal(m))
    _row('Float64MultiArray.data (6) -> u', _best(lambda: data_to_array(data_in), 50000),
         _best(lambda: np.array([float(v) for v in data_in]), 50000))
    _row('y (40) -> Float64MultiArray.data', _best(lambda: array_to_data(y), 50000),
         _best(lambda: array.array('d', [float(v) for v in y]), 50000))

    # 4. bag writing (rosbags serialization dominates) -------------------------------------
    from soft_rom.bags.replay_io import replay_to_bag

    kb = min(k, 1000)
    epb = Episode(t=ep.t[:kb], U=ep.U[:, :kb], Y=ep.Y[:, :kb])
    with tempfile.TemporaryDirectory() as tmp:
        for every in (1, 20):
            t0 = time.perf_counter()
            replay_to_bag(Predictor(model), epb, f'{tmp}/b{every}', publish_every=every)
            dt = time.perf_counter() - t0
            print(f'replay -> MCAP bag, {kb} steps, publish every {every:>2d}: '
                  f'{dt * 1e3:8.1f} ms ({dt / kb * 1e6:.0f} us/step)')


def kalman_figures() -> None:
    """Acceptance figure: Kalman-corrected vs open-loop error of a mismatched model."""
    from soft_rom.predictor import kalman_vs_open_loop

    true = _model(6, m=3, p=8, seed=3)
    wrong = SecondOrderModel(true.K * 1.3, true.C * 0.7, true.B * 1.15, true.E, dt=true.dt,
                             y_ref=true.y_ref)
    rng = np.random.default_rng(4)
    k = 1500
    U = np.repeat(rng.standard_normal((3, k // 20 + 1)), 20, axis=1)[:, :k]
    Y = true.simulate(U)
    sigma = 0.02 * np.std(Y - true.y_ref[:, None])
    noisy = Episode(t=np.arange(k) * true.dt, U=U, Y=Y + sigma * rng.standard_normal(Y.shape))
    cfg = PredictorConfig(process_noise=1e-6, measurement_noise=sigma ** 2)
    res = kalman_vs_open_loop(wrong, noisy, config=cfg, Y_true=Y)
    print('Kalman vs open loop (synthetic: K x1.3, C x0.7, B x1.15; noise 2 % of deviations)')
    print(f'  deviation error  open loop {res["open_loop"]:.4f}  Kalman {res["kalman"]:.4f}  '
          f'ratio {res["ratio"]:.4f} (target <= 0.5)')
    print(f'  absolute error   open loop {res["open_loop_abs"]:.3e}  Kalman '
          f'{res["kalman_abs"]:.3e}')


if __name__ == '__main__':
    main()
    kalman_figures()
