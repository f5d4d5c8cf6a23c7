"""The paper's two studies end to end on the embedded eel FOM, and the one-command demo.

Pipeline (every step goes through the same public pieces a user calls):

1. :mod:`soft_rom.sim` simulates Ep 1 … Ep N and records each as a ROS 2 bag
   (:class:`soft_rom.bags.EpisodeBagWriter`, the bag contract of docs/bag_contract.md);
2. :mod:`soft_rom.convert` turns the bags into a zarr training set;
3. the pipeline of ``soft-rom fit`` (:mod:`soft_rom.pipeline`) fits LOpInf / DMDc /
   ERA-OKID ROMs over ranges of ``r`` (:mod:`soft_rom.study.studies`);
4. :mod:`soft_rom.evaluation` predicts and scores them (both metrics);
5. figures and a Markdown report with the paper's numbers beside ours; with ``replay``, a test
   bag through the predictor core (:mod:`soft_rom.study.replay`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
import json
import logging
import os
from pathlib import Path
import platform
import time
from typing import Any

import numpy as np

from soft_rom.errors import BagError, ConfigError, SolverError
from soft_rom.study.config import blas_threads, StudyConfig

# _conclusions, _in_memory, _record_held_out: re-exported for the paper-scale run and tests.
from soft_rom.study.fits import _in_memory as _in_memory
from soft_rom.study.fits import _record_held_out as _record_held_out
from soft_rom.study.fits import sweep
from soft_rom.study.presets import CUBIC_EEL_OPTIONS, ERA_EEL_OPTIONS
from soft_rom.study.replay import replay_check
from soft_rom.study.report import study_report
from soft_rom.study.studies import _conclusions as _conclusions
from soft_rom.study.studies import _jsonable, study_time_extrapolation, study_unseen_inputs

__all__ = ['CUBIC_EEL_OPTIONS', 'ERA_EEL_OPTIONS', 'StudyConfig', 'run_study', 'simulate_bags',
           'study_time_extrapolation', 'study_unseen_inputs', 'sweep']


# ----------------------------------------------------------------------------- simulation
def simulate_bags(bag_dir: Path, cfg: StudyConfig, *, progress: bool = True) -> list[Path]:
    """Simulate Ep 1 … Ep N and write one bag per episode (``bag_dir/ep<i>``).

    Bags already present are reused (their JSON sidecar must show the same settings).
    """
    from soft_rom.sim.record import record_episodes
    bag_dir.mkdir(parents=True, exist_ok=True)
    n_steps = int(round(cfg.duration / cfg.dt))
    wanted = dict(seed=cfg.seed, storage=cfg.storage, n_steps=n_steps, dt=cfg.dt,
                  state=cfg.record_state, **cfg.sim_options)
    todo = []
    for i in range(1, cfg.n_episodes + 1):
        sidecar = bag_dir / f'ep{i}.json'
        if (bag_dir / f'ep{i}').exists() and sidecar.exists():
            meta = _read_sidecar(sidecar)
            if _same_recording(meta, wanted, cfg.resolution):
                continue
            raise ConfigError(
                f'{bag_dir / f"ep{i}"} exists but was recorded with other settings; '
                'remove it or use another --bags folder.')
        if (bag_dir / f'ep{i}').exists() or (bag_dir / f'ep{i}').is_symlink():
            raise ConfigError(
                f'{bag_dir / f"ep{i}"} exists but was not recorded by soft-rom simulate (no '
                f"ep{i}.json beside it): --bags reuses only the embedded eel's episodes and "
                'never replaces other bags; use another --bags folder (your own recordings '
                'go through convert, fit and evaluate).')
        todo.append(i)
    if todo:
        record_episodes(bag_dir, todo, resolution=cfg.resolution, jobs=cfg.jobs,
                        progress=progress, **wanted)
    return [bag_dir / f'ep{i}' for i in range(1, cfg.n_episodes + 1)]


def _read_sidecar(path: Path) -> dict[str, Any]:
    """The JSON sidecar ``ep<i>.json`` that ``soft-rom simulate`` writes next to a bag.

    Raises
    ------
    BagError
        The file is not UTF-8 JSON or does not hold an object; the message names it.
    """
    fix = (f'it should be the sidecar soft-rom simulate writes next to bag {path.stem}. Use '
           'another --bags folder, or remove the bag and its sidecar to record them again.')
    try:
        meta = json.loads(path.read_text(encoding='utf-8'))
    except UnicodeDecodeError as err:
        raise BagError(f'bag sidecar {path} is not UTF-8 text (byte {err.start}); {fix}'
                       ) from err
    except json.JSONDecodeError as err:
        raise BagError(f'bag sidecar {path} is not valid JSON ({err}); {fix}') from err
    if not isinstance(meta, dict):
        kind = {list: 'an array', str: 'a string', bool: 'a boolean', type(None): 'null',
                int: 'a number', float: 'a number'}.get(type(meta), type(meta).__name__)
        raise BagError(f'bag sidecar {path} must hold a JSON object; got {kind}; {fix}')
    return meta


def _same_recording(meta: dict[str, Any], wanted: dict[str, Any], resolution: int) -> bool:
    flat = dict(meta)
    for key in ('settings', 'simulation', 'recording', 'config', 'model'):
        if isinstance(meta.get(key), dict):
            flat.update(meta[key])
    checks = dict(wanted, resolution=resolution)
    return all(flat.get(k, v) == v for k, v in checks.items()
               if k in ('seed', 'storage', 'n_steps', 'dt', 'resolution'))


def run_study(out_dir: str | Path, cfg: StudyConfig | None = None, *, progress: bool = True,
              studies: Sequence[int] = (1, 2), replay: bool = False,
              bag_dir: str | Path | None = None) -> dict[str, Any]:
    """Run the studies end to end; returns the summary (also written as ``summary.json``).

    Parameters
    ----------
    out_dir : path
        Report folder: ``report.md``, PNG figures, ``summary.json``, ``models/``; bags under
        ``bags/`` and the training set ``data.zarr`` unless given.
    cfg : StudyConfig
    studies : sequence of int
        Which studies (1: time extrapolation, 2: unseen inputs).
    replay : bool
        Also replay a test bag through the predictor core (the demo does).
    bag_dir : path, optional
        Reuse bags from here (simulated there if missing).
    """
    cfg = cfg or StudyConfig()
    with blas_threads(cfg.blas_threads):
        return _run_study(Path(out_dir), cfg, progress=progress, studies=studies,
                          replay=replay, bag_dir=bag_dir)


def _run_study(out: Path, cfg: StudyConfig, *, progress: bool, studies: Sequence[int],
               replay: bool, bag_dir: str | Path | None) -> dict[str, Any]:
    from tqdm import tqdm

    from soft_rom.convert import convert
    from soft_rom.dataset import TrainingSet

    out.mkdir(parents=True, exist_ok=True)
    load_start = _load()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    bags = simulate_bags(Path(bag_dir) if bag_dir else out / 'bags', cfg, progress=progress)
    timings['simulate'] = time.perf_counter() - t0
    t0 = time.perf_counter()
    data_path = out / 'data.zarr'
    ts = TrainingSet.open(data_path) if data_path.exists() else None
    if ts is None or sorted(ts.episode_names) != sorted(b.name for b in bags):
        # none yet, or left by a run on other bags: convert (again)
        ts, _reports = convert(bags, data_path, overwrite=True, progress=progress)
    timings['convert'] = time.perf_counter() - t0
    n_fits = ((len(cfg.r_lopinf) + len(cfg.r_dmdc) + len(cfg.r_era) + len(cfg.r_cubic))
              * (1 in studies)
              + (len(cfg.r_lopinf) + len(cfg.r_dmdc) + 2 * len(cfg.r_era) + len(cfg.r_cubic))
              * (2 in studies))
    bar = tqdm(total=n_fits, desc='fit + evaluate', unit='ROM', disable=not progress)

    def tick(label: str) -> None:
        bar.set_postfix_str(label)
        bar.update()

    summary: dict[str, Any] = {'config': asdict(cfg), 'fom': fom_summary(ts, cfg)}
    with _Failures() as failures:     # a failed fit is a result: said in the report
        if 1 in studies:
            t0 = time.perf_counter()
            summary['study1'] = study_time_extrapolation(ts, cfg, out, tick)
            timings['study 1'] = time.perf_counter() - t0
        if 2 in studies and len(ts.episode_names) >= 3:
            t0 = time.perf_counter()
            summary['study2'] = study_unseen_inputs(ts, cfg, out, tick)
            timings['study 2'] = time.perf_counter() - t0
    bar.close()
    if failures.messages:
        summary['failures'] = failures.messages
    if not (summary.get('study1', {}).get('best') or summary.get('study2', {}).get('chosen')):
        raise SolverError('no method fitted a model: '
                          + ('; '.join(failures.messages) or 'no study ran'))
    if replay and 'study2' in summary:
        t0 = time.perf_counter()
        summary['replay'] = replay_check(out, bags, summary['study2'])
        timings['replay'] = time.perf_counter() - t0
    summary['conclusions'] = _conclusions(summary.get('study1'), summary.get('study2'))
    summary['timings'] = timings
    summary['machine'] = _machine(load_start)
    strict = _jsonable(summary)
    (out / 'summary.json').write_text(json.dumps(strict, indent=2, allow_nan=False))
    (out / 'report.md').write_text(study_report(strict))   # the report of summary.json
    return summary


class _Failures(logging.Handler):
    """The warnings of the studies' fits while it is entered (``messages``)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())

    def __enter__(self) -> '_Failures':
        logging.getLogger('soft_rom.study').addHandler(self)
        return self

    def __exit__(self, *exc: object) -> None:
        logging.getLogger('soft_rom.study').removeHandler(self)


def _load() -> float | None:
    """The 1-minute load average (``None`` where the system has none)."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return None


def _machine(load_start: float | None) -> dict[str, Any]:
    """What the timings were measured on: CPUs, their model, the load, BLAS threads."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = ' '.join(line.split(':', 1)[1].split())
                break
    except OSError:
        pass
    load_end = _load()
    n = os.cpu_count()
    loads = ('' if load_start is None or load_end is None else
             f', load average {load_start:.1f} at the start and {load_end:.1f} at the end')
    return {'cpus': n, 'cpu': cpu, 'load_start': load_start, 'load_end': load_end,
            'description': f'{n} CPUs ({cpu}){loads}'}


def fom_summary(ts: Any, cfg: StudyConfig) -> dict[str, Any]:
    """The report's "Full-order model and data" table, from the training set (Ep 1)."""
    ep1 = ts['ep1']
    return {
        'episodes': len(ts.episode_names), 'samples per episode': ep1.n_samples,
        'dt [s]': ep1.dt, 'state DOF n': None if ts.q_ref is None else int(ts.q_ref.size),
        'inputs m': ep1.U.shape[0], 'outputs p': ep1.Y.shape[0],
        'max |output deviation| Ep 1 [mm]': float(
            np.max(np.abs(ep1.Y - ts.y_ref[:, None])) * 1e3),
        'storage': cfg.storage,
    }
