"""The output layout is data: stored by the converter, carried into model files, read by replay."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.bags import EpisodeBagWriter
from soft_rom.convert import BagMapping, convert, read_episode
from soft_rom.errors import ConfigError, DatasetError
from soft_rom.layout import layout_of, OutputLayout, replay_components
from soft_rom.models import load_model
from soft_rom.pipeline import fit_method, FitSettings, open_training_data


def test_names_and_round_trip_for_both_orders() -> None:
    cm = OutputLayout(('x', 'z'), 'component_major', (0, 1, 2))
    pm = OutputLayout(('x', 'z'), 'point_major', (0, 1, 2))
    assert cm.names() == ['x1', 'x2', 'x3', 'z1', 'z2', 'z3']
    assert pm.names() == ['x1', 'z1', 'x2', 'z2', 'x3', 'z3']
    assert cm.size == pm.size == 6 and cm.component_string == 'xz'
    assert pm.index()[('z', 1)] == 3 and cm.index()[('z', 1)] == 4
    for lay in (cm, pm):
        assert OutputLayout.from_dict(lay.to_dict()) == lay
        assert OutputLayout.from_names(lay.names()) == lay
    assert OutputLayout.from_names(['x1', 'q2']) is None
    assert OutputLayout.from_names(['z3', 'x1']) is None        # neither order spells it
    with pytest.raises(DatasetError, match='components'):
        OutputLayout(('x', 'w'), 'component_major', (0,))
    with pytest.raises(DatasetError, match='order'):
        OutputLayout(('x',), 'diagonal', (0,))
    with pytest.raises(DatasetError, match='malformed'):
        OutputLayout.from_dict({'components': ['x']})


def test_replay_components_prefers_the_model_and_refuses_a_mismatch() -> None:
    xz = OutputLayout(('x', 'z'), 'component_major', (0, 1))
    xyz = OutputLayout(('x', 'y', 'z'), 'component_major', (0, 1))
    assert replay_components(xz, None) == 'xz'
    assert replay_components(None, xyz) == 'xyz'
    assert replay_components(None, None) is None
    with pytest.raises(ConfigError, match='trained with'):
        replay_components(xz, xyz)
    with pytest.raises(ConfigError, match='component-major'):
        replay_components(OutputLayout(('x', 'z'), 'point_major', (0, 1)), None)


def test_converter_stores_the_layout_and_fitted_models_carry_it(tmp_path) -> None:
    rng = np.random.default_rng(3)
    k, n_nodes = 60, 9
    bag = tmp_path / 'ep1'
    with EpisodeBagWriter(bag, storage='mcap', n_chambers=6, n_nodes=n_nodes) as w:
        for j in range(k):
            w.write(1.7e9 + 0.001 * j, rng.normal(size=6) * 3e4, rng.normal(size=(20, 3)),
                    rng.normal(size=(n_nodes, 3)))
    mapping = BagMapping.from_dict({'output': {'points': [2, 5, 7],
                                               'components': ['x', 'y'],
                                               'order': 'point_major'}})
    want = OutputLayout(('x', 'y'), 'point_major', (2, 5, 7))
    ts, _ = convert([bag], tmp_path / 'train.zarr', mapping=mapping, progress=False)
    assert ts.output_layout == want
    assert ts.output_names == want.names() == ['x3', 'y3', 'x6', 'y6', 'x8', 'y8']
    ep, _ = read_episode(bag, mapping)
    assert layout_of(ep.metadata) == want
    fitted, = fit_method(open_training_data(ts), 'dmdc', (3,),
                         FitSettings(coordinates='outputs'), layout=ts.output_layout.to_dict())
    model = fitted.model
    assert layout_of(model.metadata) == want
    path = model.save(tmp_path / 'm.npz')
    assert layout_of(load_model(path).metadata) == want
