"""Acceptance figures of the embedded eel FOM (issue 3); prints tables, no asserts.

Usage::

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
from pathlib import Path
import resource
import sys
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest='what', required=True)
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
