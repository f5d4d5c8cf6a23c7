"""The paper's two studies at the paper's size as one resumable run (``soft-rom study``).

At resolution 4 (234,357 DOF) the six 2-s episodes with their full state are about 22 GB
of bags and as much again as a training set: too large to hold in memory, and hours of
work. This run goes through the same public pieces as :func:`soft_rom.study.run.run_study`
in stages, each recorded when done, so that an interrupted run resumes where it stopped:

1. ``simulate``: the missing episodes only, shared among ``jobs`` processes, each running its
   episodes side by side (one solve with all of them per step,
   :meth:`~soft_rom.sim.EelModel.simulate_lockstep`); steps counted into one progress bar
   with its ETA. A bag is written under a temporary name and renamed when complete, with
   its sidecar: a bag that exists is finished;
2. ``convert``: bags to the training set (written atomically);
3. ``study1``, ``study2``: the fits stream the snapshots from disk
   (:attr:`~soft_rom.study.run.StudyConfig.streaming`), so their memory stays bounded;
4. ``cold_read``: one sequential read of the training episodes' state chunk files with the
   page cache dropped (as ``benchmarks/bench_scale.py``), the yardstick of the streaming fit;
5. ``report``: ``summary.json`` and ``report.md``.

Every stage after ``simulate`` runs in a child process, so its wall time and peak RSS are
its own; they go to ``stages/<stage>.json`` (written atomically) with the stage's result.
Before anything runs, :func:`plan_run` sizes what is left (disk for bags and training set,
memory of the simulation workers and of the fits) and :func:`check_plan` refuses, with the
figures, a run that would not fit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
import json
import math
import multiprocessing
import os
from pathlib import Path
import resource
import shutil
import time
from typing import Any

from soft_rom.dataset._format import Q_CHUNK_COLS, Q_CHUNK_ROWS
from soft_rom.errors import ConfigError, ResourceError, SoftRomError, SolverError
from soft_rom.study.run import StudyConfig

__all__ = ['RunPlan', 'STAGES', 'check_plan', 'plan_run', 'run_paper_scale']

#: The stages, in order.
STAGES = ('simulate', 'convert', 'study1', 'study2', 'cold_read', 'report')
#: Memory bound of the streaming fits (bytes), as for the synthetic benchmark.
FIT_MEMORY = 4e9
#: Bytes per sample of a bag besides the state: pressures, centerline, headers.
_BAG_OVERHEAD = 2048.0
_GB = 1e9


@dataclass(frozen=True)
class RunPlan:
    """What is left of a run, and what it needs (bytes), from :func:`plan_run`."""

    n_dof: int
    n_steps: int
    episodes_todo: tuple[int, ...]
    stages_done: tuple[str, ...]
    bag_bytes: float
    set_bytes: float
    sim_memory: float
    fit_memory: float
    solver: str
    bag_dir: Path
    out: Path

    def describe(self) -> str:
        """One line per need, for the console."""
        eps = ', '.join(f'ep{e}' for e in self.episodes_todo) or 'none'
        return (f'about {self.n_dof:,} DOF, {self.n_steps} steps per episode; to simulate: {eps} '
                f'({self.bag_bytes / _GB:.1f} GB of bags); training set '
                f'{self.set_bytes / _GB:.1f} GB; memory: simulation '
                f'{self.sim_memory / _GB:.1f} GB ({self.solver}), fits '
                f'{self.fit_memory / _GB:.1f} GB; stages done: '
                f'{", ".join(self.stages_done) or "none"}')


def _stage_dir(out: Path) -> Path:
    return out / 'stages'


def _stage_record(out: Path, stage: str) -> dict[str, Any] | None:
    path = _stage_dir(out) / f'{stage}.json'
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text(encoding='utf-8'))
    except (OSError, ValueError):
        return None                      # unreadable: the stage runs again
    return record if isinstance(record, dict) else None


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.tmp-{os.getpid()}')
    tmp.write_text(json.dumps(obj, indent=2, allow_nan=False), encoding='utf-8')
    os.replace(tmp, path)


def plan_run(out: Path, cfg: StudyConfig, bag_dir: Path) -> RunPlan:
    """Size what is left of the run in ``out`` (bags in ``bag_dir``)."""
    from soft_rom.sim.eel import cholmod_available, memory_estimate
    from soft_rom.study.run import _read_sidecar, _same_recording

    solver = 'cholmod' if cholmod_available() else 'banded'
    n_dof, per_worker = memory_estimate(cfg.resolution, solver)
    n_steps = int(round(cfg.duration / cfg.dt))
    wanted = dict(seed=cfg.seed, storage=cfg.storage, n_steps=n_steps, dt=cfg.dt)
    todo = []
    for i in range(1, cfg.n_episodes + 1):
        bag, side = bag_dir / f'ep{i}', bag_dir / f'ep{i}.json'
        if bag.is_dir() and side.is_file() and _same_recording(_read_sidecar(side), wanted,
                                                               cfg.resolution):
            continue
        todo.append(i)
    done = tuple(s for s in STAGES if _stage_record(out, s) is not None)
    per_sample = 8.0 * n_dof + _BAG_OVERHEAD
    bag_bytes = len(todo) * n_steps * per_sample
    # the training set stores whole chunks of Q, its edge chunks padded
    rows = math.ceil(n_dof / Q_CHUNK_ROWS) * Q_CHUNK_ROWS
    cols = math.ceil(n_steps / Q_CHUNK_COLS) * Q_CHUNK_COLS
    set_bytes = 0.0 if 'convert' in done else cfg.n_episodes * (8.0 * rows * cols
                                                                 + 1e3 * n_steps)
    workers = min(cfg.jobs, max(len(todo), 1))
    sim_memory = workers * per_worker if todo else 0.0
    return RunPlan(n_dof=n_dof, n_steps=n_steps, episodes_todo=tuple(todo), stages_done=done,
                   bag_bytes=bag_bytes, set_bytes=set_bytes, sim_memory=sim_memory,
                   fit_memory=FIT_MEMORY, solver=solver, bag_dir=bag_dir, out=out)


def _existing(folder: Path) -> Path:
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder


def check_plan(plan: RunPlan, *, free_disk: Callable[[Path], float] | None = None,
               free_memory: float | None = None) -> None:
    """Refuse, with the figures, a run whose bags, training set or memory would not fit.

    Raises
    ------
    ResourceError
        One line: what is needed where, what is free, and what to do.
    """
    from soft_rom.resources import available_memory

    def disk(p: Path) -> float:
        return float(shutil.disk_usage(_existing(p)).free)

    avail = available_memory() if free_memory is None else free_memory
    need_mem = max(plan.sim_memory, plan.fit_memory)
    if need_mem > avail:
        raise ResourceError(
            f'the run needs about {need_mem / _GB:.1f} GB of memory (simulation '
            f'{plan.sim_memory / _GB:.1f} GB with {plan.solver}, fits '
            f'{plan.fit_memory / _GB:.1f} GB); {avail / _GB:.1f} GB available. Use fewer '
            '--jobs, or stop other work')
    free_disk = free_disk or disk
    bags, out = _existing(plan.bag_dir), _existing(plan.out)
    if os.stat(bags).st_dev == os.stat(out).st_dev:
        need = {bags: plan.bag_bytes + plan.set_bytes}
    else:
        need = {bags: plan.bag_bytes, out: plan.set_bytes}
    short = [(p, n, free_disk(p)) for p, n in need.items() if n > free_disk(p)]
    if short:
        where = '; '.join(f'{n / _GB:.1f} GB in {p}, {f / _GB:.1f} GB free' for p, n, f in short)
        raise ResourceError(
            f'the run needs {plan.bag_bytes / _GB:.1f} GB for the bags of '
            f'{len(plan.episodes_todo)} episode(s) and {plan.set_bytes / _GB:.1f} GB for the '
            f'training set: {where}. Free disk space, or put --bags on another disk')


# ----------------------------------------------------------------------------- simulate
def _context() -> Any:
    """Fresh processes (``spawn``), never a fork of this one.

    A fork of this multi-threaded process (BLAS, progress threads) can inherit a held lock
    and hang, as a forked worker did under pytest. A script that calls
    :func:`run_paper_scale` needs the usual ``if __name__ == '__main__':`` guard.
    """
    return multiprocessing.get_context('spawn')


_PROGRESS: Any = None


def _init_worker(progress: Any) -> None:
    global _PROGRESS
    _PROGRESS = progress


def _simulate_group(task: tuple[StudyConfig, int, list[int], list[Path], dict[str, Any]]
                    ) -> list[dict[str, Any]]:
    """One worker: its episodes side by side (:func:`soft_rom.sim.record.record_lockstep`)."""
    from soft_rom.outputs import mark
    from soft_rom.sim.eel import EelModel
    from soft_rom.sim.record import record_lockstep

    cfg, slot, episodes, paths, kwargs = task
    model = EelModel(resolution=cfg.resolution)

    def tick(j: int) -> None:
        if _PROGRESS is not None:
            _PROGRESS[slot] = (j + 1) * len(episodes)

    sides = record_lockstep(model, episodes, paths, on_step=tick, **kwargs)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    for path, side in zip(paths, sides):
        mark(path, 'simulated')
        side['peak_rss_gb'] = rss
    return sides


def _simulate(plan: RunPlan, cfg: StudyConfig, progress: bool,
              echo: Callable[[str], None]) -> dict[str, Any]:
    """Simulate the missing episodes; returns the stage record."""
    from tqdm import tqdm

    t0 = time.perf_counter()
    todo = list(plan.episodes_todo)
    plan.bag_dir.mkdir(parents=True, exist_ok=True)
    for e in todo:          # bags a killed run left half-written (the writer's temporary names)
        for tmp in plan.bag_dir.glob(f'.ep{e}.tmp-*'):
            if tmp.is_dir() and not tmp.is_symlink():
                shutil.rmtree(tmp, ignore_errors=True)
    kwargs = dict(seed=cfg.seed, storage=cfg.storage, n_steps=plan.n_steps, dt=cfg.dt,
                  state=cfg.record_state, overwrite=True, **cfg.sim_options)
    kwargs.pop('jacobian', None)            # lockstep: the rest tangent
    ctx = _context()
    jobs = max(1, min(cfg.jobs, len(todo)))
    groups = [todo[i::jobs] for i in range(jobs)]        # each worker's episodes, in lockstep
    shared = ctx.Array('q', jobs, lock=False)
    tasks = [(cfg, slot, g, [plan.bag_dir / f'ep{e}' for e in g], kwargs)
             for slot, g in enumerate(groups)]
    sidecars: list[dict[str, Any]] = []
    total = len(todo) * plan.n_steps
    with tqdm(total=total, desc=f'simulate {len(todo)} episode(s)', unit='step',
              disable=not progress, smoothing=0.05, mininterval=2.0) as bar, \
            ProcessPoolExecutor(max_workers=jobs, mp_context=ctx,
                                initializer=_init_worker, initargs=(shared,)) as pool:
        futures = [pool.submit(_simulate_group, task) for task in tasks]
        while True:
            finished = sum(f.done() for f in futures)
            steps = int(sum(shared[:]))
            if steps > bar.n:
                bar.update(steps - bar.n)
            if finished == len(futures):
                break
            for task, f in zip(tasks, futures):
                err = f.exception() if f.done() else None
                if err is not None:
                    for g in futures:
                        g.cancel()
                    if isinstance(err, SoftRomError):
                        raise err
                    eps = ', '.join(f'ep{e}' for e in task[2])
                    raise SolverError(f'simulating {eps} failed ({type(err).__name__}: {err}); '
                                      'the finished episodes are kept: run the same command '
                                      'again to resume') from err
            time.sleep(0.5)
        sidecars = sorted((side for f in futures for side in f.result()),
                          key=lambda side: side['episode'])
    for s in sidecars:
        echo(f'  {s["bag"]}: {s["wall_s"]:.0f} s, {s["linear_solver"]}, peak RSS '
             f'{s["peak_rss_gb"]:.2f} GB')
    wall = time.perf_counter() - t0
    return {'wall_s': wall, 'peak_rss_gb': max((s['peak_rss_gb'] for s in sidecars),
                                               default=0.0),
            'result': {'episodes': [s['episode'] for s in sidecars],
                       'episode_wall_s': {s['bag']: s['wall_s'] for s in sidecars},
                       'linear_solver': sidecars[0]['linear_solver'] if sidecars else None,
                       'jobs': cfg.jobs}}


# ----------------------------------------------------------------------------- child stages
def _stage_child(func: Callable[[Path, StudyConfig, Path, bool], dict[str, Any]], stage: str,
                 out: str, cfg: StudyConfig, bag_dir: str, progress: bool) -> None:
    """Run one stage in this (child) process and write its record."""
    import logging
    logging.basicConfig(level=logging.WARNING, format='%(message)s')
    out_p = Path(out)
    t0 = time.perf_counter()
    result = func(out_p, cfg, Path(bag_dir), progress)
    record = {'wall_s': time.perf_counter() - t0,
              'peak_rss_gb': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
              'result': result}
    from soft_rom.study.run import _jsonable
    _write_json(_stage_dir(out_p) / f'{stage}.json', _jsonable(record))


def _bags(cfg: StudyConfig, bag_dir: Path) -> list[Path]:
    return [bag_dir / f'ep{i}' for i in range(1, cfg.n_episodes + 1)]


def _convert(out: Path, cfg: StudyConfig, bag_dir: Path, progress: bool) -> dict[str, Any]:
    from soft_rom.convert import convert
    convert(_bags(cfg, bag_dir), out / 'data.zarr', overwrite=True, progress=progress)
    return {'training_set_bytes': _du(out / 'data.zarr'), 'bag_bytes': sum(
        _du(b) for b in _bags(cfg, bag_dir))}


def _study1(out: Path, cfg: StudyConfig, bag_dir: Path, progress: bool) -> dict[str, Any]:
    from soft_rom.dataset import TrainingSet
    from soft_rom.study.run import study_time_extrapolation
    return study_time_extrapolation(TrainingSet.open(out / 'data.zarr'), cfg, out)


def _study2(out: Path, cfg: StudyConfig, bag_dir: Path, progress: bool) -> dict[str, Any]:
    from soft_rom.dataset import TrainingSet
    from soft_rom.study.run import study_unseen_inputs
    ts = TrainingSet.open(out / 'data.zarr')
    if len(ts.episode_names) < 3:
        return {}
    _drop_cache(_training_chunks(out))     # the fits read from disk, as the cold read does
    return study_unseen_inputs(ts, cfg, out)


def _training_chunks(out: Path) -> list[str]:
    """The state chunk files of the study-2 training episodes (ep1, ep2)."""
    return sorted(str(p) for ep in ('ep1', 'ep2')
                  for p in (out / 'data.zarr').glob(f'**/{ep}/Q/**/*') if p.is_file())


def _drop_cache(files: list[str]) -> None:
    """Evict ``files`` from the page cache (``posix_fadvise``, no root needed)."""
    os.sync()
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def _cold_read(out: Path, cfg: StudyConfig, bag_dir: Path, progress: bool) -> dict[str, Any]:
    """Sequential read of the state chunk files of ep1 and ep2, page cache dropped first."""
    files = _training_chunks(out)
    _drop_cache(files)
    buf = memoryview(bytearray(16 * 2 ** 20))
    total = 0
    t0 = time.perf_counter()
    for f in files:
        with open(f, 'rb', buffering=0) as fh:
            while got := fh.readinto(buf):
                total += got
    return {'files': len(files), 'bytes': total, 'seconds': time.perf_counter() - t0}


def _report(out: Path, cfg: StudyConfig, bag_dir: Path, progress: bool) -> dict[str, Any]:
    """``summary.json`` and ``report.md`` from the stage records."""
    from soft_rom.dataset import TrainingSet
    from soft_rom.study.report import study_report
    from soft_rom.study.run import _conclusions, _jsonable, fom_summary

    records = {s: _stage_record(out, s) or {} for s in STAGES if s != 'report'}
    ts = TrainingSet.open(out / 'data.zarr')
    summary: dict[str, Any] = {'config': asdict(cfg), 'fom': fom_summary(ts, cfg)}
    for key in ('study1', 'study2'):
        if records[key].get('result'):
            summary[key] = records[key]['result']
    summary['conclusions'] = _conclusions(summary.get('study1'), summary.get('study2'))
    summary['timings'] = {s: r.get('wall_s') for s, r in records.items() if r}
    summary['paper_scale'] = {
        'stages': {s: {'wall_s': r.get('wall_s'), 'peak_rss_gb': r.get('peak_rss_gb')}
                   for s, r in records.items() if r},
        'disk': records['convert'].get('result', {}),
        'streaming_fit_vs_cold_read': _fit_vs_read(summary.get('study2'),
                                                   records['cold_read'].get('result')),
    }
    (out / 'summary.json').write_text(json.dumps(_jsonable(summary), indent=2,
                                                 allow_nan=False))
    (out / 'report.md').write_text(study_report(summary))
    return {'summary': str(out / 'summary.json')}


def _fit_vs_read(s2: dict[str, Any] | None, cold: dict[str, Any] | None) -> dict[str, Any]:
    """The study-2 LOpInf sweep (one streamed POD of ep1 + ep2) against one cold read.

    ``ratio``: the whole sweep over one read; ``per_pass_ratio``: the POD's time per pass
    over one read (``benchmarks/bench_scale.py``'s measure: throughput against a raw read).
    """
    if not s2 or not cold or not cold.get('seconds'):
        return {}
    fit = s2.get('fit_seconds', {}).get('lopinf')
    if fit is None:
        return {'cold_read_s': cold['seconds'], 'bytes': cold['bytes']}
    out = {'lopinf_fit_s': fit, 'cold_read_s': cold['seconds'], 'bytes': cold['bytes'],
           'ratio': fit / cold['seconds']}
    pod = s2.get('streaming_pod') or {}
    if pod.get('passes') and pod.get('seconds'):    # per pass, as bench_scale.py compares
        out.update(pod_method=pod.get('pod_method'), passes=int(pod['passes']),
                   pod_s=float(pod['seconds']),
                   per_pass_ratio=float(pod['seconds']) / int(pod['passes']) / cold['seconds'])
    return out


def _du(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


_STAGE_FUNCS: dict[str, Callable[[Path, StudyConfig, Path, bool], dict[str, Any]]] = {
    'convert': _convert, 'study1': _study1, 'study2': _study2, 'cold_read': _cold_read,
    'report': _report,
}


def _run_child(stage: str, out: Path, cfg: StudyConfig, bag_dir: Path, progress: bool) -> None:
    ctx = _context()
    proc = ctx.Process(target=_stage_child, args=(_STAGE_FUNCS[stage], stage, str(out), cfg,
                                                  str(bag_dir), progress),
                       name=f'soft-rom {stage}')
    proc.start()
    try:
        proc.join()
    except BaseException:
        proc.terminate()
        proc.join()
        raise
    if proc.exitcode != 0 or _stage_record(out, stage) is None:
        raise SolverError(f'stage {stage} failed (exit code {proc.exitcode}); the stages '
                           f'before it are kept: run the same command again to resume')


# ----------------------------------------------------------------------------- the run
def _fmt(seconds: float) -> str:
    m, s = divmod(int(round(seconds)), 60)
    h, m = divmod(m, 60)
    return f'{h} h {m:02d} min' if h else f'{m} min {s:02d} s'


def run_paper_scale(out: str | Path, cfg: StudyConfig, *, bag_dir: str | Path | None = None,
                    progress: bool = True, echo: Callable[[str], None] = print,
                    stages: Sequence[str] = STAGES) -> dict[str, Any]:
    """Run (or resume) the studies in stages; returns the summary.

    Parameters
    ----------
    out : path
        Report folder; ``stages/`` records what is done, ``data.zarr`` is the training set.
    cfg : StudyConfig
        ``streaming`` is set here; ``jobs`` simulation processes.
    bag_dir : path, optional
        Bags (default ``out/bags``).
    stages : sequence of str
        Run only up to these (tests); the default runs all.
    Raises
    ------
    ResourceError
        Before any work, when the bags, the training set or the memory would not fit.
    """
    from soft_rom.outputs import mark

    unknown = set(stages) - set(STAGES)
    if unknown:
        raise ConfigError(f'unknown stage(s) {sorted(unknown)}; stages are {STAGES}.')
    cfg = replace(cfg, streaming=True)
    out = Path(out)
    bags = Path(bag_dir) if bag_dir is not None else out / 'bags'
    plan = plan_run(out, cfg, bags)
    check_plan(plan)
    out.mkdir(parents=True, exist_ok=True)
    mark(out, 'study', manifest=False)  # a resumed run finds its own folder (it grows)
    _write_json(out / 'stages' / 'config.json', asdict(cfg))
    echo(f'paper-scale run: {plan.describe()}')
    t_run = time.perf_counter()
    for i, stage in enumerate(s for s in STAGES if s in stages):
        record = _stage_record(out, stage)
        if stage == 'simulate' and plan.episodes_todo:
            # bags to (re)record: what was made from the bags is made again after them
            for later in STAGES:
                (_stage_dir(out) / f'{later}.json').unlink(missing_ok=True)
            record = None
        if record is not None:
            echo(f'[{i + 1}/{len(STAGES)}] {stage}: done before ({_fmt(record["wall_s"])}), '
                 'skipped')
            continue
        echo(f'[{i + 1}/{len(STAGES)}] {stage} (elapsed {_fmt(time.perf_counter() - t_run)})')
        if stage == 'simulate':
            rec = _simulate(plan, cfg, progress, echo)
            _write_json(_stage_dir(out) / 'simulate.json', rec)
        else:
            _run_child(stage, out, cfg, bags, progress)
        rec = _stage_record(out, stage) or {}
        echo(f'      {stage} done in {_fmt(rec.get("wall_s", 0.0))}, peak RSS '
             f'{rec.get("peak_rss_gb", 0.0):.2f} GB')
    mark(out, 'study')                  # the stages done: what the folder holds is ours
    summary_path = out / 'summary.json'
    if 'report' in stages and summary_path.is_file():
        summary: dict[str, Any] = json.loads(summary_path.read_text(encoding='utf-8'))
        return summary
    return {}
