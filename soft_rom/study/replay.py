"""The study's replay: a test bag through the predictor core, and the Kalman check.

:func:`replay_check` runs what ``soft-rom replay --compare`` runs, through the same API
(:class:`~soft_rom.predictor.Predictor`, :func:`~soft_rom.bags.replay_io.replay_to_bag`,
:func:`~soft_rom.predictor.kalman_vs_open_loop`): the prediction bag has the node's topics.
"""

from __future__ import annotations

from collections.abc import Sequence
import json
from pathlib import Path
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.study.studies import _in_memory, sweep

__all__ = ['kalman_check', 'replay_check']


def replay_check(out: Path, bags: Sequence[Path], s2: dict[str, Any]) -> dict[str, Any]:
    """Replay the study-2 LOpInf ROM over a test bag through the predictor core.

    Writes the prediction bag ``replay_<bag>`` (the node's topics) and its summary
    ``replay_<bag>.json``; returns the errors open loop and the Kalman check.
    """
    from soft_rom.bags.replay_io import replay_to_bag
    from soft_rom.convert import load_mapping, read_episode
    from soft_rom.layout import layout_of, replay_components
    from soft_rom.outputs import atomic_new_dir
    from soft_rom.predictor import kalman_vs_open_loop, Predictor
    from soft_rom.predictor.params import predictor_config

    chosen = s2['chosen']['lopinf']
    model_path = out / 'models' / f'eel_lopinf_r{chosen["r"]}.npz'
    bag = next(b for b in bags if b.name == s2['shape_episode'])
    out_bag = out / f'replay_{bag.name}'
    config = predictor_config({})
    predictor = Predictor(model_path, config)
    model = predictor.model
    episode, _report = read_episode(bag, load_mapping(None))
    components = replay_components(layout_of(model.metadata), layout_of(episode.metadata))
    with atomic_new_dir(out_bag, overwrite=True, kind='replay', what='replay bag') as stage:
        result = replay_to_bag(predictor, episode, stage, publish_every=1,
                               components=components or 'xz')
    summary = dict(result.summary)
    summary['output_bag'] = str(out_bag)
    summary['final_status'] = predictor.health().level.name
    summary['compare'] = kalman_vs_open_loop(model, episode, config=config)
    (out / f'replay_{bag.name}.json').write_text(json.dumps(summary, indent=2, default=str))
    keep = {'model': model_path.name, 'bag': bag.name, 'output bag': out_bag.name}
    for key in ('samples', 'relative_error', 'relative_deviation_error', 'final_status',
                'wall_seconds'):
        if key in summary:
            keep[key] = summary[key]
    keep.update(kalman_check(model_path, out / 'data.zarr', s2['shape_episode']))
    return keep


def kalman_check(model_path: Path, data_path: Path, episode: str, *, noise: float = 1e-3,
                 r_values: Sequence[int] = (4, 8), seed: int = 0) -> dict[str, Any]:
    """State correction on the FOM: deliberately mismatched ROMs and noisy measurements.

    The ROMs are LOpInf ROMs fitted on Ep 1 + Ep 2 with small ``r`` (worse models than the
    study's), the measured centerline is the FOM's plus white noise of ``noise`` metres; the
    Kalman-corrected (predictor defaults, measurement variance ``noise²``) and open-loop
    predictions are scored against the clean FOM outputs
    (:func:`soft_rom.predictor.kalman_vs_open_loop`).
    """
    from soft_rom.dataset import TrainingSet
    from soft_rom.predictor import kalman_vs_open_loop, PredictorConfig
    ts = TrainingSet.open(data_path)
    train = [_in_memory(ts['ep1']), _in_memory(ts['ep2'])]
    models = sweep('lopinf', r_values, train, ts)
    ep = ts[episode]
    rng = np.random.default_rng(seed)
    noisy = Episode(t=ep.t, U=ep.U, Y=ep.Y + noise * rng.standard_normal(ep.Y.shape),
                    name=ep.name)
    cfg = PredictorConfig(measurement_noise=noise ** 2)
    out: dict[str, Any] = {'Kalman check: measurement noise [m]': noise}
    for r, model in models.items():
        res = kalman_vs_open_loop(model, noisy, config=cfg, Y_true=ep.Y)
        out[f'Kalman check LOpInf r={r}: open-loop / Kalman deviation error'] = (
            f'{res["open_loop"]:.4f} / {res["kalman"]:.4f}')
        out[f'Kalman check LOpInf r={r}: ratio (target <= 0.5)'] = res['ratio']
    return out
