"""``soft-rom simulate``: run the embedded eel FOM and write one ROS 2 bag per episode."""

from __future__ import annotations

import argparse
from pathlib import Path
import time

__all__ = ['add_parser', 'run']


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``simulate`` and its options."""
    parser = sub.add_parser(
        'simulate', help='simulate the embedded eel FOM and record episode bags',
        description='Simulate episodes Ep 1..Ep N of the embedded corotational-FEM eel (random '
                    'seeded chamber pressures, T = n_steps * dt) and write each as a ROS 2 bag '
                    '(ep1, ep2, ...) with the SPEC bag contract topics, plus a JSON sidecar '
                    'with the simulator parameters.')
    parser.add_argument('--out', type=Path, default=Path('eel_bags'),
                        help='output folder (default: %(default)s)')
    parser.add_argument('--episodes', type=int, default=6,
                        help='number of episodes, Ep 1..Ep N (default: %(default)s)')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='rosbag2 storage format (default: %(default)s)')
    parser.add_argument('--resolution', type=int, default=1,
                        help='mesh resolution: 1 = 5,145 DOF (default), 2 = 33,237, '
                             '3 = 103,305, 4 = 234,357 (the paper: 231,336)')
    parser.add_argument('--seed', type=int, default=0,
                        help='seed of the pressure sequences (default: %(default)s)')
    parser.add_argument('--steps', type=int, default=2000,
                        help='samples per episode (default: %(default)s)')
    parser.add_argument('--dt', type=float, default=1e-3,
                        help='time step in seconds (default: %(default)s)')
    parser.add_argument('--amplitude', type=float, default=50e3,
                        help='pressure amplitude in Pa (default: %(default)s)')
    parser.add_argument('--independent', action='store_true',
                        help='draw each chamber in [0, amplitude] instead of antagonistic pairs')
    parser.add_argument('--bias', type=float, default=0.0,
                        help='common pressure of antagonistic pairs, Pa (default: 0)')
    parser.add_argument('--no-state', action='store_true',
                        help='do not write the full FEM state topic')
    parser.add_argument('--jacobian', choices=('rest', 'corotated'), default='rest',
                        help='tangent of the implicit solve (default: %(default)s)')
    parser.add_argument('--jobs', type=int, default=1,
                        help='worker processes (default: %(default)s)')
    parser.add_argument('--overwrite', action='store_true', help='replace existing bags')
    parser.add_argument('--no-progress', action='store_true', help='hide progress bars')
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate, record, print a summary; returns the exit code."""
    from soft_rom.errors import ConfigError
    from soft_rom.sim.record import record_episodes

    if args.episodes < 1 or args.steps < 1 or not args.dt > 0:
        raise ConfigError('need --episodes >= 1, --steps >= 1 and --dt > 0.')
    t0 = time.perf_counter()
    sidecars = record_episodes(
        args.out, args.episodes, resolution=args.resolution, jobs=args.jobs,
        progress=not args.no_progress, seed=args.seed, storage=args.storage,
        n_steps=args.steps, dt=args.dt, amplitude=args.amplitude,
        antagonistic=not args.independent, bias=args.bias, state=not args.no_state,
        overwrite=args.overwrite, jacobian=args.jacobian)
    wall = time.perf_counter() - t0
    first = sidecars[0]
    print(f'eel FOM: {first["n_dof"]:,} DOF ({first["n_nodes"]:,} nodes, '
          f'{first["n_tets"]:,} tetrahedra), {args.steps} steps of {args.dt:g} s per episode, '
          f'state {"not " if args.no_state else ""}written, {args.storage}')
    for s in sidecars:
        lo, hi = s['tail_z_range_m']
        print(f'  {args.out / s["bag"]}  ({s["bag"]}.json)  {s["wall_s"]:.1f} s simulated+written'
              f', tail z in [{1e3 * lo:.1f}, {1e3 * hi:.1f}] mm')
    print(f'{len(sidecars)} bag(s) in {wall:.1f} s')
    return 0
