"""Record simulated episodes as ROS 2 bags (one bag per episode, plus a JSON sidecar).

Each sample ``j`` of an episode is written at ``t_j = j dt`` exactly as a SOFA + ROS 2
recording at 1 kHz would look (the bag contract of ``docs/bag_contract.md``, through
:class:`soft_rom.bags.EpisodeBagWriter`): one ``FluidPressure`` per chamber, the centerline
``PoseArray`` and, unless disabled, the full state ``Float64MultiArray`` with layout
``[nodes, 3]``. States are streamed from the simulator's callback, never held in memory.

The sidecar ``<name>.json`` beside the bag ``<name>/`` keeps the provenance: simulator
parameters, seed, pressure settings, mesh size, wall time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
import json
import multiprocessing
from pathlib import Path
from typing import Any

import numpy as np

from soft_rom import __version__
from soft_rom.errors import ConfigError
from soft_rom.sim.eel import EelConfig, EelModel
from soft_rom.sim.inputs import DEFAULT_AMPLITUDE, random_pressures

__all__ = ['SIDECAR_FORMAT', 'record_episode', 'record_episodes', 'record_lockstep']

SIDECAR_FORMAT = 'soft_rom.sim_episode'


def record_episode(model: EelModel, episode: int, path: str | Path, *, seed: int = 0,
                   storage: str = 'mcap', n_steps: int = 2000, dt: float = 1e-3,
                   amplitude: float = DEFAULT_AMPLITUDE, antagonistic: bool = True,
                   bias: float = 0.0, state: bool = True, overwrite: bool = False,
                   progress: bool = False,
                   jacobian: str = 'rest', pressures: np.ndarray | None = None,
                   source: str | None = None,
                   on_step: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Simulate episode ``Ep <episode>`` and write it as a bag at ``path``.

    Parameters
    ----------
    model : EelModel
    episode : int
        Episode number (1-based); with ``seed`` it fixes the pressure sequence.
    path : str or Path
        Bag directory to create; the sidecar is ``path`` with suffix ``.json``.
    storage : {'mcap', 'sqlite3'}
    n_steps, dt : int, float
        Samples and time step (2,000 x 1 ms = 2 s).
    amplitude, antagonistic, bias
        Pressure sequence settings (:func:`soft_rom.sim.random_pressures`).
    state : bool
        Write the full nodal positions on the state topic.
    progress : bool
        Show a tqdm bar over the steps.
    pressures : ndarray, shape (6, n_steps), optional
        Given pressures (``soft-rom simulate --inputs``) instead of the random sequence;
        ``source`` names where they came from (for the sidecar).
    on_step : callable, optional
        ``on_step(j)`` after sample ``j`` is written (progress counters of other processes).

    Returns
    -------
    dict
        The sidecar content (also written to disk).
    """
    from soft_rom.bags import EpisodeBagWriter

    path = Path(path)
    if pressures is None:
        U = random_pressures(n_steps, dt, seed=seed, episode=episode, amplitude=amplitude,
                             antagonistic=antagonistic, bias=bias, n_chambers=model.n_chambers)
        generator = {'generator': 'soft_rom.sim.random_pressures', 'amplitude_pa': amplitude,
                     'antagonistic': bool(antagonistic), 'bias_pa': bias}
    else:
        U = np.asarray(pressures, dtype=np.float64)
        generator = {'generator': 'given', 'source': source}
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_steps, desc=Path(path).name, unit='step', leave=False)
    with EpisodeBagWriter(path, storage=storage, n_chambers=model.n_chambers,
                          n_nodes=model.n_nodes if state else None, frame_id='world',
                          overwrite=overwrite) as writer:
        def write(j: int, t: float, u: np.ndarray, centerline: np.ndarray,
                  positions: np.ndarray) -> None:
            writer.write(t, u, centerline, positions if state else None)
            if bar is not None:
                bar.update(1)
            if on_step is not None:
                on_step(j)

        try:
            result = model.simulate(U, n_steps, dt, callback=write, jacobian=jacobian)
        finally:
            if bar is not None:
                bar.close()
    return _write_sidecar(model, episode, path, result, seed=seed, storage=storage,
                          n_steps=n_steps, dt=dt, amplitude=amplitude,
                          antagonistic=antagonistic, bias=bias, state=state,
                          generator=generator)


def _write_sidecar(model: EelModel, episode: int, path: Path, result: Any, *, seed: int,
                   storage: str, n_steps: int, dt: float, amplitude: float,
                   antagonistic: bool, bias: float, state: bool,
                   generator: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write ``path.json``, the provenance of the bag at ``path``; returns its content.

    ``generator`` describes given pressures (``soft-rom simulate --inputs``); by default the
    random sequence of :func:`~soft_rom.sim.inputs.random_pressures`.
    """
    if generator is None:
        generator = {'generator': 'soft_rom.sim.random_pressures', 'amplitude_pa': amplitude,
                     'antagonistic': bool(antagonistic), 'bias_pa': bias}
    sidecar = {
        'format': SIDECAR_FORMAT, 'version': 1, 'soft_rom_version': __version__,
        'episode': int(episode), 'name': path.name, 'seed': int(seed), 'bag': path.name,
        'storage': storage, 'n_steps': int(n_steps), 'dt': float(dt),
        'pressures': generator,
        'state_written': bool(state), 'resolution': int(model.config.resolution),
        'simulator': model.config.to_dict(),
        'n_dof': model.n_dof, 'n_nodes': model.n_nodes, 'n_tets': int(len(model.fem.tets)),
        'boundary_condition': 'head face x = 0 clamped',
        'centerline_points': int(model.centerline_map.shape[0]),
        'wall_s': result.info['wall_s'], 'jacobian': result.info['jacobian'],
        'linear_solver': result.info['solver'],
        'tail_z_range_m': [float(result.centerline[-1, 2].min()),
                           float(result.centerline[-1, 2].max())],
    }
    if 'lockstep' in result.info:
        sidecar['lockstep'] = result.info['lockstep']
    path.with_suffix('.json').write_text(json.dumps(sidecar, indent=2), encoding='utf-8')
    return sidecar


def _one_blas_thread() -> None:
    """Worker start: one BLAS thread per process (``jobs`` processes share the cores)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:     # optional: the library's default then applies
        return
    threadpool_limits(limits=1, user_api='blas')


def record_lockstep(model: EelModel, episodes: Sequence[int], paths: Sequence[str | Path], *,
                    seed: int = 0, storage: str = 'mcap', n_steps: int = 2000,
                    dt: float = 1e-3, amplitude: float = DEFAULT_AMPLITUDE,
                    antagonistic: bool = True, bias: float = 0.0, state: bool = True,
                    overwrite: bool = False,
                    on_step: Callable[[int], None] | None = None) -> list[dict[str, Any]]:
    """Simulate several episodes side by side (:meth:`EelModel.simulate_lockstep`).

    Each episode is written to its own bag as :func:`record_episode` writes it (a bag is
    complete, with its sidecar, or absent); the rest system is solved for all of them at
    once. ``on_step(j)`` is called once sample ``j`` of every episode is written.
    """
    from contextlib import ExitStack

    from soft_rom.bags import EpisodeBagWriter

    bag_paths = [Path(p) for p in paths]
    Us = [random_pressures(n_steps, dt, seed=seed, episode=e, amplitude=amplitude,
                           antagonistic=antagonistic, bias=bias, n_chambers=model.n_chambers)
          for e in episodes]
    last = len(bag_paths) - 1
    with ExitStack() as stack:
        writers = [stack.enter_context(EpisodeBagWriter(
            p, storage=storage, n_chambers=model.n_chambers,
            n_nodes=model.n_nodes if state else None, frame_id='world', overwrite=overwrite))
            for p in bag_paths]

        def callback(i: int) -> Callable[..., None]:
            def write(j: int, t: float, u: np.ndarray, centerline: np.ndarray,
                      positions: np.ndarray) -> None:
                writers[i].write(t, u, centerline, positions if state else None)
                if i == last and on_step is not None:
                    on_step(j)
            return write

        results = model.simulate_lockstep(Us, n_steps, dt,
                                          callbacks=[callback(i) for i in range(len(bag_paths))])
    return [_write_sidecar(model, e, p, r, seed=seed, storage=storage, n_steps=n_steps, dt=dt,
                           amplitude=amplitude, antagonistic=antagonistic, bias=bias,
                           state=state)
            for e, p, r in zip(episodes, bag_paths, results)]


def _worker(args: tuple) -> dict[str, Any]:
    config, episode, path, kwargs = args
    return record_episode(EelModel(config), episode, path, **kwargs)


def record_episodes(out_dir: str | Path, episodes: int | Sequence[int] = 6, *,
                    config: EelConfig | None = None, resolution: int | None = None,
                    jobs: int = 1, progress: bool = True, **kwargs: Any) -> list[dict[str, Any]]:
    """Simulate and record several episodes as ``out_dir/ep<i>`` bags.

    Parameters
    ----------
    out_dir : str or Path
        Folder (created) for the bags ``ep1`` ... and sidecars ``ep1.json`` ...
    episodes : int or sequence of int
        ``6`` means Ep 1-Ep 6; or explicit episode numbers.
    config : EelConfig, optional
    resolution : int, optional
        Overrides ``config.resolution``.
    jobs : int
        Worker processes (each builds its own model, and uses one BLAS thread).
    progress : bool
        tqdm bars (per step with one job, per episode otherwise).
    **kwargs
        Passed to :func:`record_episode` (``seed``, ``storage``, ``n_steps``, ``dt``,
        ``amplitude``, ``antagonistic``, ``bias``, ``state``, ``overwrite``, ``jacobian``).

    Returns
    -------
    list of dict
        One sidecar per episode, in episode order.
    """
    cfg = config or EelConfig()
    if resolution is not None:
        cfg = replace(cfg, resolution=int(resolution))
    eps = list(range(1, int(episodes) + 1)) if isinstance(episodes, int) else \
        [int(e) for e in episodes]
    if not eps or min(eps) < 1:
        raise ConfigError(f'episodes must be >= 1; got {episodes!r}.')
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = max(1, min(int(jobs), len(eps)))
    if jobs == 1:
        model = EelModel(cfg)
        return [record_episode(model, e, out / f'ep{e}', progress=progress, **kwargs)
                for e in eps]
    tasks = [(cfg, e, out / f'ep{e}', dict(kwargs, progress=False)) for e in eps]
    results: list[dict[str, Any]] = []
    # Spawned, not forked: a fork of a multi-threaded caller (a test runner, an IDE, a ROS
    # node) can hand the workers a lock held by another thread, and they wait for ever.
    ctx = multiprocessing.get_context('spawn')
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx,
                             initializer=_one_blas_thread) as pool:
        try:
            it = pool.map(_worker, tasks)
            if progress:
                from tqdm import tqdm
                it = tqdm(it, total=len(tasks), desc='episodes', unit='ep')
            results.extend(it)
        except BaseException:        # Ctrl-C, a failed episode: start no other episode
            pool.shutdown(wait=True, cancel_futures=True)
            raise
    return results
