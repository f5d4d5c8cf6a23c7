"""The study's replay: a test bag through the predictor core, and the Kalman check.

:func:`replay_check` does what ``soft-rom replay MODEL BAG -o OUT`` does, through the same
API (:class:`~soft_rom.predictor.Predictor`, :func:`~soft_rom.bags.replay_io.replay_to_bag`,
:func:`~soft_rom.predictor.kalman_vs_open_loop`), never through the CLI.
"""

from __future__ import annotations

from collections.abc import Sequence
import json
from pathlib import Path
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.models.labels import model_label

__all__ = ['replay_check']


def replay_check(out: Path, bags: Sequence[Path], s2: dict[str, Any], *,
                 noise: float = 1e-3, seed: int = 0) -> dict[str, Any]:
    """Replay the study-2 LOpInf ROM over a test bag through the predictor core.

    The prediction bag ``replay_<bag>`` has the node's topics, and the predictor's final
    health uses the monitor thresholds the model file implies
    (:mod:`soft_rom.predictor.thresholds`).

    Then the Kalman correction of the same model on the same episode, once: the measured
    centerline is the bag's plus white noise of ``noise`` metres, the filter is designed
    for that noise (measurement variance ``noise²``, predictor defaults otherwise), and both
    the open-loop and the corrected predictions are scored against the noise-free outputs
    (:func:`soft_rom.predictor.kalman_vs_open_loop`).
    """
    from soft_rom.bags.replay_io import replay_to_bag
    from soft_rom.convert import read_episode
    from soft_rom.layout import layout_of, replay_components
    from soft_rom.outputs import atomic_new_dir
    from soft_rom.predictor import kalman_vs_open_loop, Predictor, PredictorConfig
    from soft_rom.study.studies import _jsonable

    chosen = s2['chosen']['lopinf']
    model_path = out / 'models' / f'eel_lopinf_r{chosen["r"]}.npz'
    bag = next(b for b in bags if b.name == s2['shape_episode'])
    out_bag = out / f'replay_{bag.name}'
    predictor = Predictor(model_path, PredictorConfig())
    model = predictor.model
    episode, _report = read_episode(bag)
    components = replay_components(layout_of(model.metadata), layout_of(episode.metadata))
    with atomic_new_dir(out_bag, overwrite=True, kind='replay', what='replay bag') as stage:
        result = replay_to_bag(predictor, episode, stage, components=components or 'xz',
                               overwrite=False)
    health = predictor.health()
    summary = dict(result.summary, output_bag=str(out_bag), final_status=health.level.name,
                   final_message=health.message, thresholds=predictor.thresholds.summary())
    rng = np.random.default_rng(seed)
    noisy = Episode(t=episode.t, U=episode.U,
                    Y=episode.Y + noise * rng.standard_normal(episode.Y.shape), name=episode.name)
    kalman = kalman_vs_open_loop(model, noisy, Y_true=episode.Y,
                                 config=PredictorConfig(measurement_noise=noise ** 2))
    summary['kalman'] = kalman
    (out / f'replay_{bag.name}.json').write_text(
        json.dumps(_jsonable(summary), indent=2, default=str, allow_nan=False))
    return {'model': model_path.name, 'label': model_label(model), 'bag': bag.name,
            'output bag': out_bag.name, 'samples': summary['samples'],
            'relative_error': summary['relative_error'],
            'relative_deviation_error': summary['relative_deviation_error'],
            'final_status': health.level.name, 'final_message': health.message,
            'warn_threshold': predictor.thresholds.warn,
            'error_threshold': predictor.thresholds.error,
            'threshold_source': predictor.thresholds.source,
            'kalman': {'noise_mm': noise * 1e3, 'open_loop': kalman['open_loop'],
                       'kalman': kalman['kalman'], 'ratio': kalman['ratio']}}
