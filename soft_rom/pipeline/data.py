"""Training data for a fit: episodes chosen from a training set, references, coordinates.

:func:`open_training_data` gathers the episodes a fit uses (by name, cut at ``--t-max``
lazily) with the training set's references and channel names into a
:class:`~soft_rom.reduce.data.TrainingData`. :func:`choose_coordinates` and
:func:`output_coordinates` decide what LOpInf and DMDc take as generalized coordinates: the
full states ``Q`` (POD of ``Q - q_ref``), or, for a recording of a real robot whose training
set has no ``Q``, the measured outputs (``Q := Y``, ``q_ref := y_ref``).
"""

from __future__ import annotations

from collections.abc import Sequence
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DatasetError
from soft_rom.reduce import episode_head, TrainingData

__all__ = ['CHANNEL_KEYS', 'COORDINATES', 'choose_coordinates', 'open_training_data',
           'output_coordinates', 'select_episodes']

#: Choices of generalized coordinates for LOpInf and DMDc.
COORDINATES = ('state', 'outputs')
#: Channel names and units a training set and a model carry.
CHANNEL_KEYS = ('input_names', 'input_units', 'output_names', 'output_units')


def _wanted(available: Sequence[str], names: str | Sequence[str] | None,
            where: str) -> list[str]:
    """Episode names asked for (comma-separated or a list; default all), checked."""
    if names is None:
        wanted = list(available)
    else:
        items = [n.strip() for n in (names.split(',') if isinstance(names, str) else names)]
        if len(items) > 1 and not all(items):
            raise DatasetError(f'episodes {names!r}: an empty name (two commas in a row?); '
                               'separate the names with single commas.')
        wanted = [n for n in items if n]
    missing = [n for n in wanted if n not in available]
    if missing:
        raise DatasetError(f'unknown episode(s) {missing} in {where}; available: '
                           f'{list(available)}.')
    if not wanted:
        raise DatasetError('no episodes selected.')
    twice = sorted({n for n in wanted if wanted.count(n) > 1})
    if twice:
        raise DatasetError(f'episode(s) {twice} selected more than once; a repeated episode '
                           'would count double in a fit and in the pooled errors.')
    return wanted


def _check_t_max(t_max: float | None) -> None:
    if t_max is not None and not t_max > 0:
        raise ConfigError(f'--t-max must be positive; got {t_max}.')


def select_episodes(ts: Any, names: str | list[str] | None,
                    t_max: float | None = None) -> list[Episode]:
    """Episodes ``names`` of a training set (comma-separated or list; default all).

    With ``t_max``, each is cut at ``t_max`` seconds from its start (read into memory).
    """
    wanted = _wanted(list(ts.episode_names), names, str(getattr(ts, 'path', '')))
    eps = [ts[n] for n in wanted]
    _check_t_max(t_max)
    if t_max is not None:
        eps = [ep.time_slice(None, ep.t[0] + t_max) if ep.n_samples else ep for ep in eps]
        short = [ep.name for ep in eps if ep.n_samples < 3]
        if short:
            raise DatasetError(f'episodes {short} have fewer than 3 samples before --t-max '
                               f'{t_max} s.')
    return eps


def open_training_data(source: Any, *, episodes: str | Sequence[str] | None = None,
                       t_max: float | None = None, q_ref: ArrayLike | None = None,
                       y_ref: ArrayLike | None = None,
                       channels: dict[str, Any] | None = None,
                       provenance: dict[str, Any] | None = None) -> TrainingData:
    """The episodes of a fit with their references, names and provenance.

    Parameters
    ----------
    source : str, os.PathLike, TrainingSet, or sequence of Episode
        A training set (opened here from a path) or episodes in memory.
    episodes : str or sequence of str, optional
        Names of the episodes (comma-separated or a list; default all).
    t_max : float, optional
        Use only samples with ``t - t_start < t_max`` (seconds), kept lazy on disk.
    q_ref, y_ref : array_like, optional
        References; default those stored in the training set, else the first sample of the
        first episode.
    channels : dict, optional
        Input and output names and units (default the training set's, else the first
        episode's metadata).
    provenance : dict, optional
        Extra provenance (stored in the models' ``metadata['training']``).
    """
    ts = None
    if isinstance(source, (str, bytes)) or hasattr(source, '__fspath__'):
        from soft_rom.dataset import TrainingSet
        source = TrainingSet.open(os.fsdecode(source))
    if hasattr(source, 'episode_names'):
        ts = source
        wanted = _wanted(list(ts.episode_names), episodes, str(getattr(ts, 'path', '')))
        eps = [ts[name] for name in wanted]
        names = {key: getattr(ts, key, None) for key in CHANNEL_KEYS}
        prov: dict[str, Any] = {'training_set': str(getattr(ts, 'path', '')),
                                'episodes': wanted}
    else:
        eps = [source] if isinstance(source, Episode) else list(source)
        if episodes is not None:
            by_name = {ep.name: ep for ep in eps}
            eps = [by_name[n] for n in _wanted(list(by_name), episodes, 'the episodes given')]
        meta = eps[0].metadata if eps and isinstance(eps[0].metadata, dict) else {}
        names = {key: meta.get(key) for key in CHANNEL_KEYS}
        prov = {'episodes': [ep.name for ep in eps]}
    if not eps:
        raise DatasetError('no episodes to fit.')
    _check_t_max(t_max)
    if t_max is not None:
        eps = [_cut(ep, t_max) for ep in eps]
        prov['t_max'] = float(t_max)
    prov['t0_ns'] = {ep.name: int(ep.metadata.get('t0_ns', 0)) for ep in eps}
    prov.update(provenance or {})
    names.update({k: v for k, v in (channels or {}).items() if v is not None})
    if q_ref is None and ts is not None:
        q_ref = getattr(ts, 'q_ref', None)
    if q_ref is None and eps[0].Q is not None:
        q_ref = np.asarray(eps[0].Q[:, 0:1], dtype=np.float64)[:, 0]
    if y_ref is None:
        ts_y = getattr(ts, 'y_ref', None) if ts is not None else None
        y_ref = ts_y if ts_y is not None else eps[0].Y[:, 0]
    return TrainingData(
        episodes=eps,
        q_ref=None if q_ref is None else np.asarray(q_ref, dtype=np.float64).reshape(-1),
        y_ref=np.asarray(y_ref, dtype=np.float64).reshape(-1), names=names, provenance=prov)


def _cut(ep: Episode, t_max: float) -> Episode:
    """``ep`` up to ``t_max`` seconds from its start; a lazy ``Q`` stays lazy."""
    k = int(np.searchsorted(ep.t - ep.t[0], float(t_max) - 1e-12, 'left'))
    if k < 3:
        raise DatasetError(f'episode {ep.name!r} has fewer than 3 samples before --t-max '
                           f'{t_max} s.')
    if k >= ep.n_samples:
        return ep
    return episode_head(ep, k)


def choose_coordinates(episodes: Sequence[Episode], coordinates: str | None) -> str:
    """``'state'`` or ``'outputs'``: the choice, or the default for these episodes."""
    if coordinates is not None and coordinates not in COORDINATES:
        raise ConfigError(f'--coordinates must be one of {", ".join(COORDINATES)}; got '
                          f'{coordinates!r}.')
    if coordinates is None:
        return 'state' if all(ep.Q is not None for ep in episodes) else 'outputs'
    if coordinates == 'state':
        missing = [ep.name for ep in episodes if ep.Q is None]
        if missing:
            raise DatasetError(f'--coordinates state needs full states Q but episodes '
                               f'{missing} have none (converted with --no-state?); use '
                               '--coordinates outputs (the default without Q).')
    return coordinates


def output_coordinates(data: TrainingData) -> TrainingData:
    """The same data with the measured outputs as the coordinates (``Q := Y``)."""
    eps = [Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=ep.Y, name=ep.name, metadata=ep.metadata)
           for ep in data.episodes]
    return TrainingData(episodes=eps, q_ref=data.y_ref, y_ref=data.y_ref, names=data.names,
                        provenance=dict(data.provenance))
