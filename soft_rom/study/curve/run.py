"""The learning-curve study end to end: simulate, convert, fit, score, write the report.

Per amplitude the FOM records three sets of bags under ``bags/<amplitude>/``: ``train``
(``max(sizes)`` episodes, seed ``seed``), ``test`` (``n_test`` episodes, seed ``seed + 1``) and,
for ERA/OKID, ``long`` (one episode of ``max(sizes) * duration`` seconds, seed ``seed + 2``);
each set is converted to its own training set (``data/<amplitude>_<set>.zarr``) with
:func:`soft_rom.convert.convert`, as a user's recordings would be. Bags and training sets
already there are reused when their recorded settings match.
"""

from __future__ import annotations

from dataclasses import asdict
import json
from pathlib import Path
import resource
import sys
import time
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.metrics import relative_deviation_error
from soft_rom.study.curve.core import CurveConfig, CurveData, learning_curve

__all__ = ['amplitude_tag', 'linearization_distance', 'load_curve_data', 'run_learning_curve']


def amplitude_tag(amplitude: float) -> str:
    """Folder name of one amplitude: ``'50kPa'``, ``'5kPa'``, ``'2.5kPa'``."""
    return f'{amplitude / 1e3:g}kPa'


def _peak_memory_mb() -> dict[str, float]:
    """Peak resident memory of this process and of its finished children (MB, Linux)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return {'study process': own, 'largest child process (simulation)': kids}


def _episodes(path: Path, states: bool = True
              ) -> tuple[list[Episode], np.ndarray | None, np.ndarray]:
    """The episodes of a training set in episode order, states in memory (or dropped)."""
    from soft_rom.dataset import TrainingSet
    from soft_rom.study.run import _in_memory
    ts = TrainingSet.open(path)
    names = sorted(ts.episode_names, key=lambda s: int(s[2:]) if s[2:].isdigit() else 0)
    eps = [_in_memory(ts[name]) if states else
           Episode(t=ts[name].t, U=ts[name].U, Y=ts[name].Y, name=name) for name in names]
    q_ref = np.asarray(ts.q_ref, dtype=np.float64) if ts.q_ref is not None else None
    return eps, q_ref, np.asarray(ts.y_ref, dtype=np.float64)


def _simulate(bag_dir: Path, cfg: CurveConfig, amplitude: float, n_episodes: int, seed: int,
              n_steps: int, progress: bool) -> list[Path]:
    """Bags ``ep1`` … ``ep<n_episodes>`` in ``bag_dir``, simulated unless already there.

    A bag is reused only when its sidecar shows the same seed, length, step, resolution
    and amplitude; one recorded otherwise, or not by soft_rom, is refused.
    """
    from soft_rom.errors import ConfigError
    from soft_rom.sim.record import record_episodes
    from soft_rom.study.run import _read_sidecar
    bag_dir.mkdir(parents=True, exist_ok=True)
    wanted = {'seed': seed, 'n_steps': n_steps, 'dt': cfg.dt, 'resolution': cfg.resolution,
              'storage': cfg.storage}
    todo = []
    for i in range(1, n_episodes + 1):
        bag, sidecar = bag_dir / f'ep{i}', bag_dir / f'ep{i}.json'
        if not bag.exists() and not bag.is_symlink():
            todo.append(i)
            continue
        meta = _read_sidecar(sidecar) if sidecar.exists() else None
        same = meta is not None and all(meta.get(k) == v for k, v in wanted.items()) and \
            meta.get('pressures', {}).get('amplitude_pa') == float(amplitude)
        if not same:
            raise ConfigError(f'{bag} exists but was not recorded with these settings (seed '
                              f'{seed}, {n_steps} steps, {amplitude:g} Pa); remove it or use '
                              'another -o folder.')
    if todo:
        record_episodes(bag_dir, todo, resolution=cfg.resolution, jobs=cfg.jobs,
                        progress=progress, seed=seed, storage=cfg.storage, n_steps=n_steps,
                        dt=cfg.dt, amplitude=float(amplitude), state=True)
    return [bag_dir / f'ep{i}' for i in range(1, n_episodes + 1)]


def _recorded_set(root: Path, bag_root: Path, tag: str, which: str, cfg: CurveConfig,
                  amplitude: float, n_episodes: int, seed: int, duration: float,
                  progress: bool) -> Path:
    """Bags of one set (simulated unless there) converted to ``data/<tag>_<which>.zarr``."""
    from soft_rom.convert import convert
    from soft_rom.dataset import TrainingSet
    n_steps = int(round(duration / cfg.dt))
    bags = _simulate(bag_root / tag / which, cfg, amplitude, n_episodes, seed, n_steps,
                     progress)
    zarr = root / 'data' / f'{tag}_{which}.zarr'
    ts = TrainingSet.open(zarr) if zarr.exists() else None
    if ts is None or sorted(ts.episode_names) != sorted(b.name for b in bags):
        zarr.parent.mkdir(parents=True, exist_ok=True)
        convert(bags, zarr, overwrite=True, progress=progress)
    return zarr


def linearization_distance(episodes: list[Episode], y_ref: np.ndarray, resolution: int
                           ) -> list[float]:
    """``|Y_lin - Y| / |Y - y_ref|`` of each episode: the FOM against its linearization.

    ``Y`` are the recorded outputs, ``Y_lin`` the outputs of the FOM linearized at rest
    (:meth:`soft_rom.sim.eel.EelModel.simulate` with ``linear=True``) for the same pressures.
    """
    from soft_rom.sim.eel import EelModel
    model = EelModel(resolution=resolution)
    out = []
    for ep in episodes:
        res = model.simulate(ep.U, ep.n_samples, ep.dt, linear=True)
        out.append(float(relative_deviation_error(ep.Y, res.outputs(), y_ref)))
    return out


def load_curve_data(root: Path, cfg: CurveConfig, amplitude: float, *,
                    bag_root: Path | None = None, progress: bool = True) -> CurveData:
    """Simulate (or reuse) and convert the sets of one amplitude; the episodes in memory.

    Bags go under ``bag_root`` (default ``root/bags``), training sets under ``root/data``.
    """
    tag = amplitude_tag(amplitude)
    n_max = max(cfg.sizes)
    bags = Path(bag_root) if bag_root is not None else root / 'bags'
    train_z = _recorded_set(root, bags, tag, 'train', cfg, amplitude, n_max, cfg.seed,
                            cfg.duration, progress)
    test_z = _recorded_set(root, bags, tag, 'test', cfg, amplitude, cfg.n_test, cfg.seed + 1,
                           cfg.duration, progress)
    train, q_ref, y_ref = _episodes(train_z)
    test, _q, y_ref_test = _episodes(test_z)
    if not np.allclose(y_ref, y_ref_test) or q_ref is None:
        raise RuntimeError('the training and test sets do not start from the same rest shape')
    long = None
    if 'era' in cfg.methods:
        long_z = _recorded_set(root, bags, tag, 'long', cfg, amplitude, 1, cfg.seed + 2,
                               n_max * cfg.duration, progress)
        long = _episodes(long_z, states=False)[0][0]
    test = [Episode(t=ep.t, U=ep.U, Y=ep.Y, name=ep.name) for ep in test]   # no states
    return CurveData(train=train, test=test, q_ref=q_ref, y_ref=y_ref, long=long,
                     info={'amplitude_pa': float(amplitude), 'tag': tag})


def run_learning_curve(out_dir: str | Path, cfg: CurveConfig | None = None, *,
                       progress: bool = True, bag_root: str | Path | None = None
                       ) -> dict[str, Any]:
    """Run the learning-curve study; returns the summary (also ``summary.json``).

    Writes ``learning_curve.png`` (deviation error against training size, per method and
    amplitude, with the spread over the test episodes), ``report.md`` and ``summary.json``
    into ``out_dir``; bags under ``bags/``, training sets under ``data/``.
    """
    from soft_rom.study.curve.report import curve_figure, curve_report
    from soft_rom.study.run import _jsonable
    cfg = cfg or CurveConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    curves: dict[str, Any] = {}
    for amplitude in cfg.amplitudes:
        tag = amplitude_tag(amplitude)
        t0 = time.perf_counter()
        data = load_curve_data(out, cfg, amplitude, progress=progress,
                               bag_root=None if bag_root is None else Path(bag_root))
        timings[f'{tag}: simulate + convert'] = time.perf_counter() - t0
        t0 = time.perf_counter()
        data.info['fom_vs_linearization'] = linearization_distance(
            data.test, data.y_ref, cfg.resolution)
        timings[f'{tag}: FOM linearization'] = time.perf_counter() - t0
        t0 = time.perf_counter()

        def tick(label: str, tag: str = tag, start: float = t0) -> None:
            if progress:
                print(f'learning curve {tag}: {label} done '
                      f'({time.perf_counter() - start:.0f} s)', file=sys.stderr, flush=True)

        curves[tag] = learning_curve(data, cfg, tick)
        timings[f'{tag}: fit + score'] = time.perf_counter() - t0
    summary: dict[str, Any] = {'config': asdict(cfg), 'curves': curves, 'timings': timings,
                               'peak_memory_mb': _peak_memory_mb()}
    summary['verdict'] = verdict(summary)
    curve_figure(out / 'learning_curve.png', summary)
    (out / 'summary.json').write_text(json.dumps(_jsonable(summary), indent=2,
                                                 allow_nan=False))
    (out / 'report.md').write_text(curve_report(summary))
    return summary


def verdict(summary: dict[str, Any]) -> list[str]:
    """One line per amplitude: the cubic model against the linear one at the largest size."""
    out = []
    for tag, curve in summary['curves'].items():
        last = curve['points'][-1]
        cub = last.get('lopinf_cubic')
        if not cub or cub.get('choice') is None:
            continue
        wins = sum(1 for x in cub['ratio'] if x <= 0.5)
        dist = curve.get('fom_vs_linearization') or [float('nan')]
        bounded = all((p.get('lopinf_cubic') or {}).get('long_inputs', {}) is None
                      or (p['lopinf_cubic']['long_inputs'] or {}).get('bounded', False)
                      for p in curve['points'] if p.get('lopinf_cubic'))
        out.append(
            f'{tag} (FOM {np.median(dist):.3g} from its linearization), {last["n"]} training '
            f'episodes, r = {cub["r"]}: cubic / linear LOpInf test error '
            + ', '.join(f'{x:.2f}' for x in cub['ratio'])
            + f' (<= 0.5 on {wins} of {len(cub["ratio"])}); held-out {cub["choice"]["error"]:.3g}'
            f' vs {cub["held_out_linear"]:.3g}, so --forces auto keeps {cub["forces_auto"]} '
            f'(worst auto / linear {max(cub["ratio_auto"]):.2f}); cubic models '
            + ('all bounded' if bounded else 'NOT all bounded')
            + ' on 10x longer inputs.')
    return out
