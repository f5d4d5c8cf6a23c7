"""Predictor benchmarks: core step, event-time input paths, runtime loop, replay, bags.

Run: ``.venv/bin/python benchmarks/bench_predictor.py [--r 16] [--k 2000] [--epoch-minutes 10]``

Each figure is printed beside a naive baseline measured in the same run (a bare
``x <- A x + B u`` through the model's own ``step``/``output``, or an interpreted loop)
and the ratio. All input stamps are int nanoseconds at an epoch (1.7e9 s), as a live robot
sends them. Message conversions are timed on plain attribute objects (no rclpy here);
rclpy's checked setters add their own cost on top. ``--epoch-minutes`` runs that many
minutes at 1 kHz through the core and prints the largest difference from
``model.simulate`` (the time-base acceptance figure).
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
from soft_rom.predictor.loop import LoopSettings, RuntimeLoop


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


#: Every timed figure (seconds) by name, for ``--json-out`` (benchmarks/ab.py reads it).
FIGURES: dict[str, float] = {}


def _row(name: str, ours: float, naive: float, unit: str = 'us', target: str = '') -> None:
    FIGURES[name.strip()] = ours
    scale = 1e6 if unit == 'us' else 1e3 if unit == 'ms' else 1.0
    print(f'{name:<44s} {ours * scale:10.2f} {unit:<2s} {naive * scale:10.2f} {unit:<2s} '
          f'{naive / ours:8.1f}x  {target}')


def main() -> None:
    """Print the benchmark table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('--r', type=int, default=16)
    ap.add_argument('--k', type=int, default=2000)
    ap.add_argument('--epoch-minutes', type=float, default=10.0)
    ap.add_argument('--json-out', default=None, metavar='FILE',
                    help='also write the timings (s) as JSON (benchmarks/ab.py reads them)')
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
    T0 = 1_700_000_000 * 10 ** 9
    h_ns = int(round(model.dt * 1e9))
    t = [T0]

    def update() -> None:               # one array message: event step + latch + output
        t[0] += h_ns
        pred.set_input_ns(u, t[0])
        pred.output()

    x2 = np.zeros(model.n_states)

    def naive_update() -> None:
        nonlocal x2
        x2 = model.step(x2, u)
        model.output(x2, u)

    _row('array input (event, epoch ns): step+output', _best(update, 10000),
         _best(naive_update, 10000), target='<= 20 us')
    pf = Predictor(model, PredictorConfig(stepping='fixed'))
    tf = [T0]

    def fixed_update() -> None:         # the clocked path: advance + latch + output
        tf[0] += h_ns
        pf.advance_to_ns(tf[0])
        pf.set_input_ns(u, tf[0])
        pf.output()

    _row('array input (fixed stepping): same', _best(fixed_update, 10000),
         _best(naive_update, 10000))
    pc = Predictor(model)
    tc = [T0]
    order = [list(rng.permutation(m)) for _ in range(64)]
    cnt = [0]

    def chambers() -> None:             # six per-chamber messages, any order, one step
        tc[0] += h_ns
        for i in order[cnt[0] % 64]:
            pc.set_channel_ns(i, float(u[i]), tc[0])
        cnt[0] += 1

    def naive_chambers() -> None:
        nonlocal x2
        for i in range(m):
            u[i] = float(u[i])
        x2 = model.step(x2, u)
        model.output(x2, u)

    _row(f'{m} chamber messages (event, shuffled) per step', _best(chambers, 5000),
         _best(naive_chambers, 5000), target='<= 6 x 20 us')
    loop = RuntimeLoop(Predictor(model), LoopSettings())
    tl = [T0]

    def loop_array() -> None:           # what the node's array callback does
        tl[0] += h_ns
        pub = loop.on_array(u, tl[0], tl[0])
        for _t, _y in pub.outputs:
            pass

    _row('runtime loop: array message -> Publish', _best(loop_array, 10000),
         _best(naive_update, 10000))
    loop_u = RuntimeLoop(Predictor(model), LoopSettings())
    tu = [T0]
    recv = np.round(rng.uniform(0.05e6, 0.9e6, 64)).astype(int).tolist()

    def loop_unstamped() -> None:       # no stamp: the sender's sequence (SequenceClock)
        tu[0] += h_ns
        pub = loop_u.on_array(u, 0, tu[0] + recv[cnt[0] % 64])
        cnt[0] += 1
        for _t, _y in pub.outputs:
            pass

    _row('runtime loop: un-stamped array (1 kHz, jittered reception) -> Publish',
         _best(loop_unstamped, 10000), _best(naive_update, 10000))
    loop_c = RuntimeLoop(Predictor(model), LoopSettings())
    tlc = [T0]

    def loop_chambers() -> None:
        tlc[0] += h_ns
        for i in order[cnt[0] % 64]:
            loop_c.on_channel(i, float(u[i]), tlc[0], tlc[0])
        cnt[0] += 1

    _row(f'runtime loop: {m} chamber messages per step', _best(loop_chambers, 5000),
         _best(naive_chambers, 5000))
    pj = Predictor(model, PredictorConfig(stepping='input'))
    tj = [T0]
    jitter = np.round(rng.uniform(0.9e6, 1.1e6, 64)).astype(int).tolist()

    def jittered() -> None:
        tj[0] += jitter[cnt[0] % 64]
        cnt[0] += 1
        pj.set_input_ns(u, tj[0])

    _row('input stepping, jittered stamps (cached)', _best(jittered, 5000),
         _best(naive_update, 5000))

    # 2. replay ----------------------------------------------------------------------------
    k = args.k
    U = rng.standard_normal((m, k))
    ep = Episode(t=np.arange(k) * model.dt, U=U, Y=model.simulate(U))

    def ours_replay() -> None:
        replay_episode(Predictor(model), ep, measured=True, t0_ns=T0)

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
    res = replay_episode(Predictor(model), ep, measured=False, t0_ns=T0)
    print(f'  replay vs simulate max abs difference: {np.abs(res.Y - ep.Y).max():.2e}')
    loop_r = RuntimeLoop(Predictor(model), LoopSettings())
    ours_loop = _best(lambda: replay_episode(loop_r.predictor, ep, measured=True, t0_ns=T0,
                                             loop=loop_r, publish=lambda pub, t: None)
                      if not loop_r.reset() else None, 1, repeat=3)
    _row(f'replay {k} steps through the runtime loop', ours_loop,
         _best(naive_replay, 1, repeat=3), unit='ms')

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
            replay_to_bag(Predictor(model), epb, f'{tmp}/b{every}', publish_every=every,
                          t0_ns=T0)
            dt = time.perf_counter() - t0
            FIGURES[f'replay to bag, publish every {every}'] = dt
            print(f'replay -> MCAP bag, {kb} steps, publish every {every:>2d}: '
                  f'{dt * 1e3:8.1f} ms ({dt / kb * 1e6:.0f} us/step)')
        t0 = time.perf_counter()
        replay_to_bag(Predictor(model), epb, f'{tmp}/bdef', t0_ns=T0)
        dt = time.perf_counter() - t0
        print(f'replay -> MCAP bag, {kb} steps, output every step + centerline 30 Hz: '
              f'{dt * 1e3:8.1f} ms ({dt / kb * 1e6:.0f} us/step)')
    if args.epoch_minutes > 0:
        epoch_figure(args.epoch_minutes)
    kalman_figures()
    cubic_figures()
    if args.json_out:
        import json
        with open(args.json_out, 'w', encoding='utf-8') as fh:
            json.dump(FIGURES, fh)


def epoch_figure(minutes: float) -> None:
    """Minutes at 1 kHz from an epoch stamp through the core vs ``model.simulate``."""
    model = _model(4, m=6, p=40, seed=5)
    k = int(round(minutes * 60_000))
    rng = np.random.default_rng(6)
    U = np.repeat(rng.standard_normal((6, k // 50 + 1)), 50, axis=1)[:, :k]
    t0 = time.perf_counter()
    Y = model.simulate(U)
    t_sim = time.perf_counter() - t0
    pred = Predictor(model)
    Ut = np.ascontiguousarray(U.T)
    y = np.empty(40)
    worst = 0.0
    T0 = 1_700_000_000 * 10 ** 9
    t0 = time.perf_counter()
    for j in range(k):
        pred.set_input_ns(Ut[j], T0 + j * 1_000_000)
        pred.output(y)
        d = np.abs(y - Y[:, j]).max()
        if d > worst:
            worst = float(d)
    t_run = time.perf_counter() - t0
    rel = worst / np.abs(Y).max()
    print(f'{minutes:g} min at 1 kHz from t0 = 1.7e9 s through the core: {k} inputs, '
          f'{pred.counters["steps"]} steps (one per input: {pred.counters["steps"] == k - 1}), '
          f'max |y - simulate| = {worst:.2e} ({rel:.1e} relative; target 1e-12); '
          f'{t_run / k * 1e6:.1f} us/input incl. the comparison (simulate: '
          f'{t_sim / k * 1e6:.1f} us/step)')


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


def cubic_figures(r: int = 10) -> None:
    """Nonlinear (cubic LOpInf) predictor step beside the linear step of its linear part."""
    try:                                # this tree
        from soft_rom.models.cubic import CubicSecondOrderModel
        from soft_rom.models.tensors import symmetrize
    except ImportError:                 # a revision before models was a package (ab.py)
        from soft_rom.models_cubic import CubicSecondOrderModel, symmetrize

    lin = _model(r)
    rng = np.random.default_rng(7)
    G = 50.0 * symmetrize(rng.standard_normal((r, r, r)))
    A = rng.standard_normal((2 * r, r))
    H = 20.0 * np.einsum('ai,aj,ak,al->ijkl', A, A, A, A)     # sum of 4th powers: positive
    cub = CubicSecondOrderModel(lin.K, lin.C, G, H, lin.B, lin.E, dt=lin.dt, y_ref=lin.y_ref)
    U = np.repeat(rng.standard_normal((lin.n_inputs, 100)), 20, axis=1)
    preds = {}
    for name, model in (('linear', lin), ('cubic', cub)):
        p = Predictor(model)
        p.set_input(U[:, 0], 0.0)
        for _ in range(200):                     # leave the rest state (real Newton work)
            p.step()
        preds[name] = p
    t_lin = _best(preds['linear'].step, 5000)
    t_cub = _best(preds['cubic'].step, 5000)
    FIGURES[f'cubic r={r} predictor step'] = t_cub
    print(f'cubic LOpInf r={r}: predictor step {t_cub * 1e6:.1f} us (target <= 50 us), linear '
          f'step {t_lin * 1e6:.1f} us, ratio {t_cub / t_lin:.1f}x')
    t0 = time.perf_counter()
    cub.simulate(U)
    print(f'cubic LOpInf r={r}: simulate {(time.perf_counter() - t0) / U.shape[1] * 1e6:.1f} '
          f'us/step ({U.shape[1]} steps)')


if __name__ == '__main__':
    main()
