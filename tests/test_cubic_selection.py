"""The one held-out selection of the cubic LOpInf (``soft_rom.pipeline.cubic``), on known truth.

A chain of Duffing springs (a cubic system: the cubic model class holds the truth) and the same
chain without its nonlinear springs (a linear system), each episode simulated from rest with
its own inputs. The verdict keeps the cubic model on the cubic system from 4 folds on, never
with fewer folds, and never on the linear system.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_lopinf_cubic import DT, duffing_chain, exact_data

from soft_rom.errors import ConfigError
from soft_rom.learners.lopinf import LOpInf
from soft_rom.models import CubicSecondOrderModel
from soft_rom.pipeline import CUBIC_GRID, folds_of, HeldOutCubicSelection
from soft_rom.reduce import ReducedData


def _data(model: CubicSecondOrderModel, n: int) -> ReducedData:
    """``n`` episodes of 0.6 s from rest (inputs of seeds 1..n), states as coordinates."""
    runs = [exact_data(model, T=0.6, seed=i + 1) for i in range(n)]
    Qs = [q for q, _qd, _qdd, _u in runs]
    Us = [u for _q, _qd, _qdd, u in runs]
    Ys = [model.E @ q + 1.0 for q in Qs]
    return ReducedData.from_arrays(Qs, Us, Ys, DT, np.ones(model.E.shape[0]),
                                   names=[f'ep{i + 1}' for i in range(n)])


@pytest.fixture(scope='module')
def chains() -> dict[str, ReducedData]:
    cubic = duffing_chain(3)
    linear = CubicSecondOrderModel(cubic.K, cubic.C, np.zeros_like(cubic.G),
                                   np.zeros_like(cubic.H), cubic.B, cubic.E, dt=DT)
    return {'cubic': _data(cubic, 4), 'linear': _data(linear, 4)}


def test_folds_are_interleaved_and_cover_every_episode() -> None:
    assert folds_of(2, 4) == [[0], [1]]
    assert folds_of(6, 4) == [[0, 4], [1, 5], [2], [3]]
    for n in range(1, 9):
        assert sorted(sum(folds_of(n, 4), [])) == list(range(n))


def test_cubic_system_keeps_cubic_from_four_folds(chains: dict[str, ReducedData]) -> None:
    data = chains['cubic']
    v = HeldOutCubicSelection().select(data, LOpInf(), 3)
    assert v.scheme == 'episodes' and v.folds == [[0], [1], [2], [3]] and v.episodes == 4
    assert [(c['reg'], c['eps4']) for c in v.candidates] == list(CUBIC_GRID)
    # the cubic class holds the truth: clearly better than linear on held-out episodes
    assert v.ratio <= 0.9 and v.forces == 'cubic'
    assert 'x the linear one (at most 0.90 needed, on 4 folds)' in v.reason()
    assert v.lines('auto')[1].startswith('--forces auto keeps cubic')
    d = v.as_dict()
    assert d['forces_auto'] == 'cubic' and d['choice']['error'] == pytest.approx(v.cubic_error)
    # Two episodes: the same cubic advantage on two folds is not enough.
    two = HeldOutCubicSelection().select(data.subset([0, 1]), LOpInf(), 3)
    assert len(two.folds) == 2 and two.ratio <= 0.9 and two.forces == 'linear'
    assert 'on 2 folds only; a cubic model is kept from 4 folds on' in two.reason()
    assert 'cubic as asked; --forces auto would keep linear' in two.lines('cubic')[1]


def test_linear_system_keeps_linear(chains: dict[str, ReducedData]) -> None:
    v = HeldOutCubicSelection().select(chains['linear'], LOpInf(), 3)
    assert len(v.folds) == 4 and v.choice is not None and math.isfinite(v.cubic_error)
    assert v.ratio > 0.9 and v.forces == 'linear'
    assert 'must be clearly better (at most 0.90 x)' in v.reason()


def test_one_episode_holds_out_its_tail(chains: dict[str, ReducedData]) -> None:
    v = HeldOutCubicSelection(((1e-2, 1e-6),)).select(chains['cubic'].subset([0]), LOpInf(), 3)
    assert v.scheme == 'tails' and v.folds == [[0]] and v.forces == 'linear'
    assert 'the last 20% of 1 training episode' in v.lines('auto')[0]


def test_bad_selection_settings_are_refused() -> None:
    with pytest.raises(ConfigError, match='folds must be at least 2'):
        HeldOutCubicSelection(folds=1)
    with pytest.raises(ConfigError, match='at least one'):
        HeldOutCubicSelection(())
