"""Acceptance figures of the embedded eel FOM (issue 3); prints tables, no asserts.

Usage::

    .venv/bin/python benchmarks/bench_sim.py --resolution 2,3,4  # fast extra vs today, A/B
    .venv/bin/python benchmarks/bench_sim.py --resolution 4 --steps 200 --lockstep 3
    .venv/bin/python benchmarks/bench_sim.py cantilever          # mesh-convergence table
    .venv/bin/python benchmarks/bench_sim.py episodes            # s/episode, default mesh
    .venv/bin/python benchmarks/bench_sim.py nonlinearity        # FOM vs its linearization
    .venv/bin/python benchmarks/bench_sim.py scale --resolution 4 --steps 3
    .venv/bin/python benchmarks/bench_sim.py plot --png benchmarks/eel_ep1_centerline.png
    .venv/bin/python benchmarks/bench_sim.py invariance          # rigid rotation -> 0 force

Timings are wall-clock on whatever machine runs this; ratios are against baselines measured
in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import scipy.sparse.linalg as spla

from soft_rom.sim import CorotationalFEM, EelModel, simulate_episode, tetrahedralize
from soft_rom.sim.mesh import box_grid


def cantilever(args: argparse.Namespace) -> None:
    """Tip-loaded cantilever of the same tetrahedra vs Euler-Bernoulli (and Timoshenko)."""
    L, h = args.length, args.height
    E, nu = 1.0e6, args.poisson
    P = 1e-3 * E * h ** 2 * (h / L) ** 2   # small: tip deflection ~ 4e-3 h ... linear regime
    I = h ** 4 / 12
    d_eb = P * L ** 3 / (3 * E * I)
    G = E / (2 * (1 + nu))
    kappa = 10 * (1 + nu) / (12 + 11 * nu)   # Cowper, square section
    d_timo = d_eb + P * L / (kappa * G * h * h)
    print(f'cantilever L={L} m, square h={h} m (L/h={L / h:g}), E={E:g} Pa, nu={nu}, '
          f'tip load P={P:.3e} N; Euler-Bernoulli tip deflection {d_eb:.6e} m, '
          f'Timoshenko {d_timo:.6e} m')
    print(f'{"n/h":>4} {"DOF":>8} {"tets":>8} {"tip defl (m)":>14} {"vs EB":>8} {"vs Timo":>8} '
          f'{"s":>6}')
    for n in args.n:
        t0 = time.perf_counter()
        nx = int(round(n * L / h))
        xs, ys, zs = box_grid(L, h, h, nx, n, n)
        mesh = tetrahedralize(xs, ys, zs, np.zeros((nx, n, n), dtype=np.int64))
        fem = CorotationalFEM(mesh.nodes, mesh.tets, young=E, poisson=nu, density=1000.0)
        K = fem.stiffness()
        free = np.repeat(mesh.nodes[:, 0] > 1e-12, 3)
        tip = np.nonzero(np.abs(mesh.nodes[:, 0] - L) < 1e-12)[0]
        # consistent load of a uniform traction on the tip face: trapezoid weights
        w = np.ones(len(tip))
        gj, gk = mesh.grid_index[tip, 1], mesh.grid_index[tip, 2]
        w *= np.where((gj == 0) | (gj == n), 0.5, 1.0) * np.where((gk == 0) | (gk == n), 0.5, 1.0)
        f = np.zeros(mesh.n_dof)
        f[3 * tip + 2] = P * w / w.sum()
        Kf = K[free][:, free].tocsc()
        lu = spla.splu(Kf, permc_spec='MMD_AT_PLUS_A')
        u = np.zeros(mesh.n_dof)
        u[free] = lu.solve(f[free])
        d = float(np.mean(u[3 * tip + 2]))
        print(f'{n:4d} {mesh.n_dof:8d} {len(mesh.tets):8d} {d:14.6e} {d / d_eb - 1:+8.2%} '
              f'{d / d_timo - 1:+8.2%} {time.perf_counter() - t0:6.1f}')


def episodes(args: argparse.Namespace) -> None:
    """Seconds per episode (2,000 steps) on the default mesh; accuracy of the two tangents."""
    model = EelModel(resolution=args.resolution)
    print(f'eel resolution {args.resolution}: {model.n_dof:,} DOF, {model.n_nodes:,} nodes, '
          f'{len(model.fem.tets):,} tets')
    runs = {}
    for jac, n_ep in (('rest', args.episodes), ('corotated', args.corotated_episodes)):
        walls = []
        for ep in range(1, n_ep + 1):
            r = simulate_episode(model, ep, n_steps=args.steps, jacobian=jac)
            runs[jac, ep] = r
            walls.append(r.info['wall_s'])
            extra = (f", {r.info['cg_iterations'] / args.steps:.1f} CG it/step"
                     if jac == 'corotated' else '')
            print(f'  {jac:9s} Ep {ep}: {r.info["wall_s"]:.2f} s for {args.steps} steps '
                  f'({1e3 * r.info["wall_s"] / args.steps:.2f} ms/step){extra}; tail z in '
                  f'[{1e3 * r.centerline[-1, 2].min():.1f}, {1e3 * r.centerline[-1, 2].max():.1f}]'
                  f' mm, head point 2 |z| <= {1e3 * np.abs(r.centerline[1, 2]).max():.2f} mm')
        if walls:
            print(f'  {jac}: mean {np.mean(walls):.2f} s per episode')
    if args.corotated_episodes:
        # both tangents against a 4x finer time step (corotated tangent), Ep 1
        from soft_rom.sim.inputs import random_pressures
        U = random_pressures(args.steps, 1e-3, seed=0, episode=1)
        ref = model.simulate(np.repeat(U, 4, axis=1), 4 * args.steps, 0.25e-3,
                             jacobian='corotated')
        Yr = ref.outputs()[:, ::4]
        dev = Yr - Yr[:, :1]
        for jac in ('rest', 'corotated'):
            e = np.linalg.norm(runs[jac, 1].outputs() - Yr) / np.linalg.norm(dev)
            print(f'  Ep 1 {jac:9s} tangent, dt = 1 ms, vs dt = 0.25 ms: relative deviation '
                  f'error {e:.4f}')


def nonlinearity(args: argparse.Namespace) -> None:
    """FOM vs the linearized FOM (same integrator) as the pressure amplitude grows."""
    model = EelModel(resolution=args.resolution)
    print(f'{"amplitude (kPa)":>16} {"tail |z| max (mm)":>18} {"rel. dev. error nl vs lin":>26}')
    for amp in args.amplitudes:
        rn = simulate_episode(model, 1, amplitude=amp, n_steps=args.steps)
        rl = simulate_episode(model, 1, amplitude=amp, n_steps=args.steps, linear=True)
        Yn, Yl = rn.outputs(), rl.outputs()
        e = np.linalg.norm(Yn - Yl) / np.linalg.norm(Yn - Yn[:, :1])
        print(f'{amp / 1e3:16.3g} {1e3 * np.abs(rn.centerline[-1, 2]).max():18.3f} {e:26.2e}')


def scale(args: argparse.Namespace) -> None:
    """Build time, factorization and seconds per step at a large resolution."""
    t0 = time.perf_counter()
    model = EelModel(resolution=args.resolution)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    model.stiffness()
    t_k = time.perf_counter() - t0
    print(f'resolution {args.resolution}: {model.n_dof:,} DOF, {len(model.fem.tets):,} tets; '
          f'mesh+operators {t_build:.1f} s, stiffness assembly {t_k:.1f} s')
    U = np.full((6, args.steps), 20e3)
    U[1::2] *= -1
    r = model.simulate(U, args.steps, jacobian=args.jacobian)
    per_step = (r.info['wall_s'] - r.info['factor_s']) / args.steps
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f'  factorization ({r.info["solver"]}) {r.info["factor_s"]:.1f} s; '
          f'{per_step:.3f} s per step ({args.jacobian} tangent, {args.steps} steps); '
          f'peak RSS {rss:.1f} GB')


def invariance(args: argparse.Namespace) -> None:
    """Rigid rotations of the whole eel mesh produce zero elastic force (to round-off)."""
    from scipy.spatial.transform import Rotation
    model = EelModel(resolution=args.resolution)
    X = model.mesh.nodes
    rng = np.random.default_rng(0)
    ref = np.abs(model.fem.elastic_force(X + 1e-3 * rng.standard_normal(X.shape))).max()
    for k in range(3):
        R = Rotation.from_rotvec(rng.normal(size=3) * (k + 1)).as_matrix()
        f = model.fem.elastic_force(X @ R.T + rng.normal(size=3))
        print(f'  rotation {np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())):6.1f}'
              f' deg: max |f| = {np.abs(f).max():.2e} N  (force of a 1 mm random '
              f'perturbation: {ref:.2e} N)')


def plot(args: argparse.Namespace) -> None:
    """PNG of centerline shapes at t = 0.5, 1, 2 s of one episode."""
    from soft_rom.sim.plots import plot_centerline_shapes
    model = EelModel(resolution=args.resolution)
    r = simulate_episode(model, args.episode, n_steps=2000)
    path = plot_centerline_shapes(r.t, r.centerline, [0.5, 1.0, 2.0], args.png,
                                  title=f'Eel FOM, Ep {args.episode} ({model.n_dof:,} DOF)')
    for tq in (0.5, 1.0, 2.0):
        j = int(np.argmin(np.abs(r.t - tq)))
        print(f'  t={r.t[j]:.3f} s: tail (x, z) = ({r.centerline[-1, 0, j]:.4f}, '
              f'{r.centerline[-1, 2, j]:.4f}) m, point 2 z = {r.centerline[1, 2, j]:.5f} m')
    print(f'wrote {path}')


#: The two configurations of ``solvers``: today's (numpy forces, banded Cholesky) and the
#: ``fast`` extra's (compiled element loop, CHOLMOD).
CONFIGS = {'banded+numpy': ('banded', False), 'cholmod+numba': ('cholmod', True)}


def _one_config(args: argparse.Namespace) -> None:
    """Child process of ``solvers``: one resolution, one configuration; JSON on stdout."""
    from soft_rom.sim.inputs import random_pressures
    solver, compiled = CONFIGS[args.config]
    c0, t0 = time.process_time(), time.perf_counter()
    model = EelModel(resolution=args.resolution)
    model.fem.compiled = compiled
    model._rest_factor(1e-3, solver)
    setup, setup_cpu = time.perf_counter() - t0, time.process_time() - c0
    if compiled:                 # the JIT compile (cached on disk after the first run)
        model.fem.elastic_force(model.mesh.nodes)
    U = random_pressures(args.steps, 1e-3, seed=0, episode=1, amplitude=50e3)
    keep = set(range(0, args.steps, max(args.steps // 4, 1))) | {args.steps - 1}
    saved: dict[str, np.ndarray] = {}

    def cb(j: int, t: float, u: np.ndarray, cl: np.ndarray, x: np.ndarray) -> None:
        if j in keep:
            saved[f'x{j}'] = x.copy()

    c0 = time.process_time()
    r = model.simulate(U, args.steps, linear_solver=solver, callback=cb)
    step_cpu = (time.process_time() - c0) / args.steps
    step = (r.info['wall_s'] - r.info['factor_s']) / args.steps
    cg = None
    if args.corotated_steps:
        rc = model.simulate(U, args.corotated_steps, jacobian='corotated',
                            linear_solver=solver)
        cg = rc.info['cg_iterations'] / args.corotated_steps
    lock = lock_cpu = None
    if args.lockstep > 1:            # episodes side by side: one multi-RHS solve per step
        n = min(args.steps, args.lockstep_steps)
        Us = [random_pressures(n, 1e-3, seed=0, episode=e, amplitude=50e3)
              for e in range(1, args.lockstep + 1)]
        c0 = time.process_time()
        rl = model.simulate_lockstep(Us, n, linear_solver=solver)
        lock_cpu = (time.process_time() - c0) / (n * args.lockstep)
        lock = (rl[0].info['wall_s'] - rl[0].info['factor_s']) / (n * args.lockstep)
    np.savez(args.save, centerline=r.centerline, rest=model.mesh.nodes, **saved)
    print(json.dumps({'n_dof': model.n_dof, 'solver': r.info['solver'], 'setup_s': setup,
                      'setup_cpu_s': setup_cpu, 'step_s': step, 'step_cpu_s': step_cpu,
                      'cg_per_step': cg, 'lockstep_s': lock, 'lockstep_cpu_s': lock_cpu,
                      'peak_rss_gb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}))


def solvers(args: argparse.Namespace) -> None:
    """Setup, s/step, CG iterations, peak RSS: the fast extra against today's path, A/B.

    Each (resolution, configuration) runs in its own process (its own peak RSS), the two
    configurations back to back on the same pressures; trajectories are compared at five
    checkpoints (relative to the motion) and over every centerline sample.
    """
    print(f'load average before: {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} CPUs; '
          f'{args.steps} steps of Ep 1 at 50 kPa, rest tangent; CG: '
          f'{args.corotated_steps} steps with the corotated tangent; lockstep: '
          f'{args.lockstep} episodes side by side for {min(args.steps, args.lockstep_steps)} '
          'steps, seconds per episode-step')
    head = (f'{"res":>3} {"DOF":>8} {"configuration":>14} {"setup s":>8} {"s/step":>7} '
            f'{"cpu/step":>8} {"CG it":>6} {"RSS GB":>7} {"lockstep":>8} {"cpu":>6}')
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for res in args.resolution:
            out: dict[str, dict] = {}
            for name in CONFIGS:
                save = Path(tmp) / f'r{res}_{name}.npz'
                cmd = [sys.executable, __file__, '_one', '--config', name, '--resolution',
                       str(res), '--steps', str(args.steps), '--corotated-steps',
                       str(args.corotated_steps), '--lockstep', str(args.lockstep),
                       '--lockstep-steps', str(args.lockstep_steps), '--save', str(save)]
                done = subprocess.run(cmd, capture_output=True, text=True, check=False)
                if done.returncode:
                    print(done.stderr[-2000:])
                    raise SystemExit(f'resolution {res} {name} failed')
                out[name] = json.loads(done.stdout.strip().splitlines()[-1])
                out[name]['save'] = save
            a, b = (np.load(out[n]['save']) for n in CONFIGS)
            states = [k for k in a.files if k.startswith('x')]
            rest = a['rest']
            diff = max(np.linalg.norm(a[k] - b[k]) / max(np.linalg.norm(a[k] - rest), 1e-300)
                       for k in states if np.linalg.norm(a[k] - rest) > 0)
            dcl = np.abs(a['centerline'] - b['centerline']).max()
            rows.append((res, out, diff, dcl))
            print(head if len(rows) == 1 else '', end='\n' if len(rows) == 1 else '')
            for name, o in out.items():
                cg = '-' if o['cg_per_step'] is None else f'{o["cg_per_step"]:.1f}'
                lock = ('       -      -' if o['lockstep_s'] is None else
                        f'{o["lockstep_s"]:8.3f} {o["lockstep_cpu_s"]:6.3f}')
                print(f'{res:3d} {o["n_dof"]:8,d} {name:>14} {o["setup_s"]:8.1f} '
                      f'{o["step_s"]:7.3f} {o["step_cpu_s"]:8.3f} {cg:>6} '
                      f'{o["peak_rss_gb"]:7.2f} {lock}')
            old, new = out['banded+numpy'], out['cholmod+numba']
            print(f'    ratio today/new: step {old["step_s"] / new["step_s"]:.2f}x '
                  f'(cpu {old["step_cpu_s"] / new["step_cpu_s"]:.2f}x), setup '
                  f'{old["setup_s"] / new["setup_s"]:.2f}x, RSS '
                  f'{old["peak_rss_gb"] / new["peak_rss_gb"]:.2f}x'
                  + ('' if new['lockstep_s'] is None else
                     f', today one by one / new in lockstep '
                     f'{old["step_s"] / new["lockstep_s"]:.2f}x (cpu '
                     f'{old["step_cpu_s"] / new["lockstep_cpu_s"]:.2f}x)')
                  + '; trajectories: state '
                  f'difference / motion <= {diff:.1e}, centerline max |diff| {dcl:.1e} m')
    print(f'load average after: {os.getloadavg()[0]:.2f} (1 min)')


def _resolutions(text: str) -> list[int]:
    return [int(v) for v in text.split(',') if v.strip()]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0].startswith('-') and argv[0] not in ('-h', '--help'):
        argv = ['solvers', *argv]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest='what', required=True)
    p = sub.add_parser('solvers', help='default: the fast extra vs today, A/B')
    p.add_argument('--resolution', type=_resolutions, default=[2, 3, 4])
    p.add_argument('--steps', type=int, default=200)
    p.add_argument('--corotated-steps', type=int, default=5)
    p.add_argument('--lockstep', type=int, default=3)
    p.add_argument('--lockstep-steps', type=int, default=20)
    p.set_defaults(func=solvers)
    p = sub.add_parser('_one')
    p.add_argument('--config', choices=list(CONFIGS), required=True)
    p.add_argument('--resolution', type=int, required=True)
    p.add_argument('--steps', type=int, required=True)
    p.add_argument('--corotated-steps', type=int, default=0)
    p.add_argument('--lockstep', type=int, default=0)
    p.add_argument('--lockstep-steps', type=int, default=20)
    p.add_argument('--save', type=Path, required=True)
    p.set_defaults(func=_one_config)
    p = sub.add_parser('cantilever')
    p.add_argument('--n', type=int, nargs='+', default=[2, 4, 6, 8, 10])
    p.add_argument('--length', type=float, default=1.0)
    p.add_argument('--height', type=float, default=0.1)
    p.add_argument('--poisson', type=float, default=0.42)
    p.set_defaults(func=cantilever)
    p = sub.add_parser('episodes')
    p.add_argument('--resolution', type=int, default=1)
    p.add_argument('--episodes', type=int, default=6)
    p.add_argument('--steps', type=int, default=2000)
    p.add_argument('--corotated-episodes', type=int, default=1)
    p.set_defaults(func=episodes)
    p = sub.add_parser('nonlinearity')
    p.add_argument('--resolution', type=int, default=1)
    p.add_argument('--steps', type=int, default=2000)
    p.add_argument('--amplitudes', type=float, nargs='+',
                   default=[100, 1e3, 10e3, 25e3, 50e3, 100e3])
    p.set_defaults(func=nonlinearity)
    p = sub.add_parser('scale')
    p.add_argument('--resolution', type=int, default=4)
    p.add_argument('--steps', type=int, default=3)
    p.add_argument('--jacobian', default='rest')
    p.set_defaults(func=scale)
    p = sub.add_parser('invariance')
    p.add_argument('--resolution', type=int, default=1)
    p.set_defaults(func=invariance)
    p = sub.add_parser('plot')
    p.add_argument('--resolution', type=int, default=1)
    p.add_argument('--episode', type=int, default=1)
    p.add_argument('--png', type=Path, default=Path('benchmarks/eel_ep1_centerline.png'))
    p.set_defaults(func=plot)
    args = parser.parse_args(argv)
    args.func(args)
    return 0


if __name__ == '__main__':
    sys.exit(main())
