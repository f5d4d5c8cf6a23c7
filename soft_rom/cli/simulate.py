"""``soft-rom simulate``: run the embedded eel FOM and write one ROS 2 bag per episode.

Before anything is simulated the run is sized: the memory of the FEM system and its banded
Cholesky factor per worker, and the disk the bags will take, are estimated from the mesh
resolution and refused (with the estimate) when they do not fit.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import time
from typing import TYPE_CHECKING

from soft_rom.cli._common import (
    add_output,
    add_quiet,
    available_memory,
    check_writable_folder,
    finite_float,
    int_range,
)

if TYPE_CHECKING:
    import numpy as np

__all__ = ['add_parser', 'estimate_resources', 'read_inputs', 'run']

#: Shortest time step: bags stamp in nanoseconds, so a step of a microsecond is stamped to
#: 0.1 %; shorter ones lose their uniform grid (or all of it, below a nanosecond).
MIN_DT = 1e-6
#: Largest pressure, Pa (``--amplitude``'s bound).
MAX_PRESSURE = 1e7

MAX_RESOLUTION = 64


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``simulate`` and its options."""
    parser = sub.add_parser(
        'simulate', help='simulate the embedded eel FOM and record episode bags',
        description='Simulate episodes Ep 1..Ep N of the embedded corotational-FEM eel (random '
                    'seeded chamber pressures, T = n_steps * dt) and write each as a ROS 2 bag '
                    '(ep1, ep2, ...) with the bag contract topics, plus a JSON sidecar '
                    'with the simulator parameters.')
    add_output(parser, help='output folder', default=Path('eel_bags'), old=True)
    parser.add_argument('--episodes', type=int_range(1, 10_000), default=6,
                        help='number of episodes, Ep 1..Ep N (default: %(default)s)')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='rosbag2 storage format (default: %(default)s)')
    parser.add_argument('--resolution', type=int_range(1, MAX_RESOLUTION), default=1,
                        help='mesh resolution: 1 = 5,145 DOF (default), 2 = 33,237, '
                             '3 = 103,305, 4 = 234,357 (the paper: 231,336)')
    parser.add_argument('--seed', type=int_range(0, 2**63 - 1), default=0,
                        help='seed of the pressure sequences (default: %(default)s)')
    parser.add_argument('--steps', type=int_range(1, 100_000_000), default=2000,
                        help='samples per episode (default: %(default)s)')
    parser.add_argument('--dt', type=finite_float(MIN_DT, 1.0), default=1e-3,
                        help='time step in seconds (default: %(default)s)')
    parser.add_argument('--amplitude', type=finite_float(0.0, 1e7), default=50e3,
                        help='pressure amplitude in Pa, 0 to 1e7 (default: %(default)s)')
    parser.add_argument('--independent', action='store_true',
                        help='draw each chamber in [0, amplitude] instead of antagonistic pairs')
    parser.add_argument('--bias', type=finite_float(-1e7, 1e7), default=0.0,
                        help='common pressure of antagonistic pairs, Pa (default: 0)')
    parser.add_argument('--no-state', action='store_true',
                        help='do not write the full FEM state topic')
    parser.add_argument('--jacobian', choices=('rest', 'corotated'), default='rest',
                        help='tangent of the implicit solve (default: %(default)s)')
    parser.add_argument('--jobs', type=int_range(1, 512), default=1,
                        help='worker processes (default: %(default)s)')
    parser.add_argument('--inputs', type=Path, metavar='U.npz',
                        help='drive the FOM with given pressures instead of random ones: an '
                             '.npz with t (k,) on a uniform grid in s and U (6, k) in Pa (e.g. '
                             'the closed_loop.npz of soft-rom control); writes one bag named '
                             'after the file')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace bags that soft-rom simulate wrote before (never others)')
    add_quiet(parser, old=True)
    parser.set_defaults(func=run)


def estimate_resources(resolution: int, *, jobs: int, episodes: int, steps: int,
                       state: bool) -> tuple[int, float, float]:
    """``(n_dof, memory_bytes, disk_bytes)`` of a simulation, before building anything.

    Memory: per worker, :func:`soft_rom.sim.eel.memory_estimate` (the rest-system factor
    of the linear solver installed, CHOLMOD or banded, and the operators); disk: per sample
    the inputs and centerline, and with the state the nodal positions (8 bytes per DOF).
    """
    from soft_rom.sim.eel import memory_estimate

    n_dof, per_worker = memory_estimate(resolution)
    memory = min(jobs, episodes) * per_worker
    per_sample = 2048.0 + (8.0 * n_dof if state else 0.0)
    disk = episodes * steps * per_sample
    return n_dof, memory, disk


def _check_existing(out: Path, episodes: int, overwrite: bool,
                    names: list[str] | None = None) -> None:
    """Refuse to replace a bag that soft-rom simulate did not write."""
    import json

    from soft_rom.errors import OutputExistsError
    from soft_rom.outputs import is_marked, refuse_foreign

    for name in names or [f'ep{e}' for e in range(1, episodes + 1)]:
        bag = out / name
        side_path = bag.with_suffix('.json')
        if side_path.exists() or side_path.is_symlink():
            if not overwrite:
                raise OutputExistsError(f'{side_path} exists already; choose another --output '
                                        'or pass --overwrite to replace it')
            try:
                side_info = json.loads(side_path.read_text(encoding='utf-8'))
            except (OSError, ValueError):
                side_info = None
            if not (isinstance(side_info, dict)
                    and side_info.get('format') == 'soft_rom.sim_episode'):
                raise OutputExistsError(f'{side_path} was not written by soft-rom simulate; '
                                        'refusing to replace it')
        if not bag.exists() and not bag.is_symlink():
            continue
        if not overwrite:
            raise OutputExistsError(f'{bag} exists already; choose another --output or pass '
                                    '--overwrite to replace it')
        ours = bag.is_dir() and not bag.is_symlink() and is_marked(bag, ('simulated',))
        if not ours and bag.is_dir():
            try:  # bags simulated before the marker existed have the sidecar
                side = json.loads(bag.with_suffix('.json').read_text(encoding='utf-8'))
                ours = isinstance(side, dict) and side.get('format') == 'soft_rom.sim_episode'
            except (OSError, ValueError):
                ours = False
        if not ours:
            raise OutputExistsError(f'{bag} was not written by soft-rom simulate; refusing to '
                                    'replace it (--overwrite only replaces soft_rom outputs)')
        refuse_foreign(bag)


def read_inputs(path: Path, n_chambers: int = 6) -> tuple[float, np.ndarray]:
    """``(dt, U)`` from an ``.npz`` with ``t`` (k,) on a uniform grid and ``U`` (m, k)."""
    import numpy as np

    from soft_rom.errors import ConfigError
    from soft_rom.models.archive import read_user_arrays

    if not path.exists():
        raise FileNotFoundError(2, 'No such file or directory', str(path))
    z = read_user_arrays(path, '--inputs', ('t', 'U'))
    if 't' not in z or 'U' not in z:
        raise ConfigError(f'--inputs {path}: needs arrays t (k,) and U ({n_chambers}, k); '
                          f'{" and ".join(n for n in ("t", "U") if n not in z)} missing')
    t = np.asarray(z['t'], dtype=np.float64).reshape(-1)
    U = np.asarray(z['U'], dtype=np.float64)
    if U.ndim != 2 or U.shape != (n_chambers, t.size) or t.size < 1:
        raise ConfigError(f'--inputs {path}: U must be ({n_chambers}, k) with k = len(t) = '
                          f'{t.size}; got {U.shape}')
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(U))):
        raise ConfigError(f'--inputs {path}: t and U must be finite (NaN or Inf found)')
    if np.max(np.abs(U), initial=0.0) > MAX_PRESSURE:
        raise ConfigError(f'--inputs {path}: pressures up to {np.max(np.abs(U)):.3g} Pa; the '
                          f'eel takes at most {MAX_PRESSURE:g} Pa (as --amplitude)')
    if t.size == 1:
        return 1e-3, U
    steps = np.diff(t)
    dt = float(np.median(steps))
    if not dt > 0 or np.max(np.abs(steps - dt)) > 1e-6 * dt:
        raise ConfigError(f'--inputs {path}: t must be a uniform increasing grid (steps from '
                          f'{steps.min():g} to {steps.max():g} s)')
    if not MIN_DT <= dt <= 1.0:
        raise ConfigError(f'--inputs {path}: the step of t is {dt:g} s; it must be between '
                          f'{MIN_DT:g} and 1 s (as --dt; bags stamp in nanoseconds)')
    return dt, U


def _run_inputs(args: argparse.Namespace, out: Path) -> int:
    from soft_rom.outputs import mark
    from soft_rom.sim.eel import EelConfig, EelModel
    from soft_rom.sim.record import record_episode

    dt, U = read_inputs(args.inputs)
    name = args.inputs.stem
    _check_existing(out, 1, args.overwrite, [name])
    _check_resources(args, out, 1, U.shape[1])
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    model = EelModel(EelConfig(resolution=args.resolution))
    side = record_episode(model, 0, out / name, storage=args.storage, n_steps=U.shape[1], dt=dt,
                          state=not args.no_state, overwrite=args.overwrite,
                          progress=not args.quiet, jacobian=args.jacobian, pressures=U,
                          source=str(args.inputs))
    mark(out / name, 'simulated')
    lo, hi = side['tail_z_range_m']
    print(f'eel FOM: {side["n_dof"]:,} DOF, {U.shape[1]} steps of {dt:g} s from {args.inputs}')
    print(f'  {out / name}  ({name}.json)  {time.perf_counter() - t0:.1f} s simulated+written, '
          f'tail z in [{1e3 * lo:.1f}, {1e3 * hi:.1f}] mm')
    return 0


def _check_resources(args: argparse.Namespace, out: Path, episodes: int, steps: int) -> None:
    """Refuse, before any work, a run the memory or the disk cannot hold."""
    from soft_rom.errors import ResourceError
    from soft_rom.outputs import check_free_space

    jobs = getattr(args, 'jobs', 1)
    n_dof, memory, disk = estimate_resources(args.resolution, jobs=jobs, episodes=episodes,
                                             steps=steps, state=not args.no_state)
    free = available_memory()
    if memory > free:
        raise ResourceError(
            f'--resolution {args.resolution} ({n_dof:,} DOF) with {min(jobs, episodes)}'
            f' job(s) needs about {memory / 1e9:.3g} GB of memory; {free / 1e9:.3g} GB '
            'available. Use a lower --resolution or fewer --jobs')
    check_free_space(out, disk, f'{episodes} episode(s) of {steps} steps at '
                                f'--resolution {args.resolution}')


def run(args: argparse.Namespace) -> int:
    """Simulate, record, print a summary; returns the exit code."""
    from soft_rom.outputs import mark
    from soft_rom.sim.record import record_episodes

    out = Path(args.output)
    check_writable_folder(out, 'bags')
    if args.inputs is not None:
        return _run_inputs(args, out)
    _check_existing(out, args.episodes, args.overwrite)
    _check_resources(args, out, args.episodes, args.steps)
    t0 = time.perf_counter()
    sidecars = record_episodes(
        out, args.episodes, resolution=args.resolution, jobs=args.jobs,
        progress=not args.quiet, seed=args.seed, storage=args.storage,
        n_steps=args.steps, dt=args.dt, amplitude=args.amplitude,
        antagonistic=not args.independent, bias=args.bias, state=not args.no_state,
        overwrite=args.overwrite, jacobian=args.jacobian)
    for s in sidecars:
        mark(out / s['bag'], 'simulated')
    wall = time.perf_counter() - t0
    first = sidecars[0]
    print(f'eel FOM: {first["n_dof"]:,} DOF ({first["n_nodes"]:,} nodes, '
          f'{first["n_tets"]:,} tetrahedra), {args.steps} steps of {args.dt:g} s per episode, '
          f'state {"not " if args.no_state else ""}written, {args.storage}')
    for s in sidecars:
        lo, hi = s['tail_z_range_m']
        print(f'  {out / s["bag"]}  ({s["bag"]}.json)  {s["wall_s"]:.1f} s simulated+written'
              f', tail z in [{1e3 * lo:.1f}, {1e3 * hi:.1f}] mm')
    print(f'{len(sidecars)} bag(s) in {wall:.1f} s')
    return 0
