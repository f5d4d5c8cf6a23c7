"""The learning-curve study: choices made on training episodes only; linear systems stay linear."""

from __future__ import annotations

import json
import math

from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.errors import ConfigError
from soft_rom.study.curve import CurveConfig, CurveData, learning_curve
from soft_rom.study.curve.report import curve_figure, curve_report
from soft_rom.study.curve.select import folds_of, held_out
from soft_rom.study.run import _jsonable

CFG = CurveConfig(sizes=(2, 3), n_test=2, amplitudes=(1.0,),
                  methods=('lopinf', 'lopinf_cubic', 'dmdc_stable'), r_lopinf=(2, 4),
                  r_dmdc=(2, 4), folds=2, cubic_grid=((1e-2, 1e-6), (1e-1, 1e-6)),
                  dmdc_coordinates=8)


class _Untouchable:
    """A lazy state array that fails the test if anything reads it."""

    def __init__(self, shape: tuple[int, int]) -> None:
        self.shape = shape

    def __getitem__(self, item: object) -> np.ndarray:
        raise AssertionError('the states of a test episode were read')

    def __array__(self, *args: object, **kwargs: object) -> np.ndarray:
        raise AssertionError('the states of a test episode were read')


def _chain(seed: int, n_episodes: int) -> list[Episode]:
    return spring_chain_episodes(n_dof=8, m=2, p=4, k=400, dt=0.01, seed=seed, stiffness=40.0,
                                 drive_nodes=[3, 7], input_gain=1.0, amplitude=1.0, hold=40,
                                 q_span=1.0, n_episodes=n_episodes)


def _data(test_seed: int) -> CurveData:
    train = _chain(3, 3)
    test = [Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=_Untouchable(ep.Q.shape), name=f'test{i}')
            for i, ep in enumerate(_chain(test_seed, 2))]
    return CurveData(train=train, test=test, q_ref=train[0].Q[:, 0].copy(),
                     y_ref=train[0].Y[:, 0].copy())


def _choices(curve: dict) -> list:
    """Everything the fits and choices produced, without the test scores."""
    out = []
    for p in curve['points']:
        c = p['lopinf_cubic']
        out.append((p['n'], p['lopinf']['r'], p['lopinf']['held_out'], c['held_out'],
                    c['held_out_linear'], c['choice'], c['forces_auto'], p['dmdc_stable']['r'],
                    p['dmdc_stable']['held_out']))
    return out


@pytest.fixture(scope='module')
def curves() -> tuple[dict, dict]:
    return learning_curve(_data(11), CFG), learning_curve(_data(12), CFG)


def test_test_episodes_never_reach_a_fit_or_a_choice(curves: tuple[dict, dict]) -> None:
    first, other = curves
    # Another test set (other inputs and outputs): every choice and held-out table equal,
    # only the test scores differ; and no state of a test episode was ever read.
    assert _choices(first) == _choices(other)
    scores = [p['lopinf']['test'] for p in first['points']]
    assert scores != [p['lopinf']['test'] for p in other['points']]
    assert all(len(s) == 2 and all(math.isfinite(e) for e in s) for s in scores)


def test_a_linear_system_falls_back_to_the_linear_model(curves: tuple[dict, dict]) -> None:
    for p in curves[0]['points']:
        c = p['lopinf_cubic']
        assert c['r'] == p['lopinf']['r']
        # the cubic candidate is no better than the linear one on held-out episodes ...
        assert c['choice']['error'] > 0.9 * c['held_out_linear']
        # ... so --forces auto keeps the linear model, exactly
        assert c['forces_auto'] == 'linear'
        assert c['ratio_auto'] == [1.0, 1.0]
        # the cubic model itself is close to it and bounded on 10 x longer inputs
        assert max(c['ratio']) < 1.1
        assert c['long_inputs']['bounded'] and c['long_inputs']['samples'] == 4000


def test_held_out_errors_pool_the_left_out_episodes() -> None:
    eps = _chain(5, 4)
    y_ref = eps[0].Y[:, 0].copy()
    seen: list[list[int]] = []

    def fit(idx: list[int]) -> dict:
        seen.append(idx)
        return {'a': 1, 'b': 2}

    import soft_rom.study.curve.select as select

    def squares(model: int, ep: Episode, y: np.ndarray) -> tuple[float, float]:
        return float(model), 1.0

    orig = select._squares
    select._squares = squares
    try:
        table = held_out(fit, eps, folds_of(4, 3), y_ref)
    finally:
        select._squares = orig
    assert seen == [[1, 2], [0, 2, 3], [0, 1, 3]]      # folds {0, 3}, {1}, {2} held out
    assert table == {'a': 1.0, 'b': pytest.approx(math.sqrt(2.0))}


def test_report_and_figure(curves: tuple[dict, dict], tmp_path) -> None:
    summary = {'config': {**CFG.__dict__, 'sizes': list(CFG.sizes)},
               'curves': {'chain': {**curves[0], 'fom_vs_linearization': [0.0, 0.0]}},
               'timings': {'chain: fit + score': 1.0}, 'peak_memory_mb': {'study': 10.0}}
    json.dumps(_jsonable(summary), allow_nan=False)
    text = curve_report(summary)
    assert '## Learning curve' in text and '| 3 | 4 |' in text and 'auto keeps' in text
    png = curve_figure(tmp_path / 'curve.png', summary)
    assert png.stat().st_size > 10_000


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ConfigError, match='sizes'):
        CurveConfig(sizes=(4, 2))
    with pytest.raises(ConfigError, match='methods'):
        CurveConfig(methods=('lopinf', 'sindy'))
    with pytest.raises(ConfigError, match='at least 2 training episodes'):
        learning_curve(_data(11), CurveConfig(sizes=(1, 2), methods=('lopinf',)))
