"""Hostile ``convert --mapping`` files, written as a user writes them.

Each is refused with a :class:`ConfigError` naming the file and the key; through the CLI:
exit code 2, one line, no traceback, nothing written.
"""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.bags import EpisodeBagWriter
from soft_rom.cli import main
from soft_rom.convert import BagMapping, load_mapping
from soft_rom.errors import ConfigError

# (YAML text, key named in the message)
HOSTILE = [
    ('inputs: 5\n', "'inputs'"),
    ('output: 5\n', "'output'"),
    ('time: 5\n', "'time'"),
    ('state: [1]\n', "'state'"),
    ('inputs: "abc"\n', "'inputs'"),
    ('output: {points: 5}\n', 'output.points'),
    ('output: {points: [a]}\n', 'output.points must be a list of integers'),
    ('output: {points: [1.5, 2.7]}\n', 'output.points'),
    ('output: {points: [true]}\n', 'output.points'),
    ('output: {points: [-1]}\n', 'output.points'),
    ('output: {points: []}\n', 'output.points'),
    ('output: {points: [1, 1]}\n', 'output.points'),
    ('output: {n_points: abc}\n', 'output.n_points'),
    ('output: {n_points: 2.5}\n', 'output.n_points'),
    ('output: {components: 5}\n', 'output.components'),
    ('output: {components: [[x]]}\n', 'output.components'),
    ('output: {topic: [1]}\n', 'output.topic'),
    ('output: {order: [1]}\n', 'output.order'),
    ('output: {units: {a: 1}}\n', 'output.units'),
    ('output: {1: a, b: 2}\n', "section 'output'"),
    ('state: {include: "no"}\n', 'state.include'),
    ('state: {topic: null}\n', 'state.topic'),
    ('inputs: {names: 5}\n', 'inputs.names'),
    ('inputs: {names: [[a]]}\n', 'inputs.names'),
    ('inputs: {units: 5}\n', 'inputs.units'),
    ('inputs: {scale: null}\n', 'inputs.scale'),
    ('inputs: {offset: [a]}\n', 'inputs.offset'),
    ('inputs: {topics: [[1]]}\n', 'inputs.topics'),
    ('inputs: {sources: 5}\n', 'inputs.sources'),
    ('inputs: {sources: [5]}\n', 'inputs.sources'),
    ('inputs: {sources: [{topic: /p, slice: 5}]}\n', 'slice'),
    ('inputs: {sources: [{topic: /p, slice: [3, 1]}]}\n', 'slice'),
    ('inputs: {sources: [{topic: /p, slise: [0, 3]}]}\n', 'slise'),
    ('inputs: {topic: /p, indices: [x]}\n', 'indices'),
    ('inputs: {topic: /p, indices: [0.5]}\n', 'indices'),
    ('time: {dt: true}\n', 'time.dt'),
    ('time: {stamps: [1]}\n', 'time.stamps'),
    ('time: {min_samples: 2.5}\n', 'time.min_samples'),
    ('[1, 2]\n', 'must hold a mapping'),
    ('a: [\n', 'not valid YAML'),
]


def _bag(path):
    with EpisodeBagWriter(path, storage='mcap', n_nodes=None) as w:
        for j in range(5):
            w.write(0.001 * (j + 1), np.full(6, float(j)), np.zeros((20, 3)))
    return path


@pytest.mark.parametrize('text, key', HOSTILE, ids=[t.strip() for t, _ in HOSTILE])
def test_hostile_mapping_file_is_a_config_error_naming_file_and_key(tmp_path, text, key):
    path = tmp_path / 'm.yaml'
    path.write_text(text, encoding='utf-8')
    with pytest.raises(ConfigError) as info:
        load_mapping(path)
    assert str(path) in str(info.value) and key in str(info.value)


@pytest.mark.parametrize('data', [b'\xff\xfe\x00inputs: 5\n', bytes(range(256)),
                                  'output:\n  topic: /\u00e9\n'.encode('latin-1')])
def test_non_utf8_mapping_file(tmp_path, data):
    path = tmp_path / 'm.yaml'
    path.write_bytes(data)
    with pytest.raises(ConfigError, match='not UTF-8'):
        load_mapping(path)


def test_valid_spellings_still_accepted():
    m = BagMapping.from_dict({
        'inputs': {'topic': '/p', 'slice': [0, 3], 'names': ['a', 'b', 1], 'units': ['kPa'],
                   'scale': [1, 2.5, '1e3'], 'offset': 0},
        'output': {'points': [0, 19], 'n_points': 20, 'components': 'xz'},
        'state': {'include': False}, 'time': {'dt': 0.002, 'max_gap': 0}})
    assert m.inputs is not None and m.inputs[0].indices == (0, 1, 2)
    assert m.input_names == ('a', 'b', '1') and m.scale == (1.0, 2.5, 1000.0)
    assert m.output.points == (0, 19) and m.output.components == ('x', 'z')
    assert m.state.include is False
    assert BagMapping.from_dict(m.to_yaml_dict()) == m
    assert m.replace(dt=0.001).dt == 0.001


@pytest.mark.parametrize('text, key', [
    ('output: {points: [a]}\n', 'output.points'),
    ('output: {points: [1.5, 2.7]}\n', 'output.points'),
    ('inputs: 5\n', "'inputs'"),
    ('state: [1]\n', "'state'"),
    ('time: {dt: abc}\n', 'time.dt'),
    (b'\x89PNG\r\n\x1a\n\x00\x00\xff', 'not UTF-8'),
])
def test_cli_convert_bad_mapping_exit_2_one_line(tmp_path, capsys, text, key):
    bag = _bag(tmp_path / 'ep1')
    path = tmp_path / 'm.yaml'
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding='utf-8')
    capsys.readouterr()
    rc = main(['convert', str(bag), '-o', str(tmp_path / 'c.zarr'), '--mapping', str(path),
               '--quiet'])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and 'Traceback' not in err, err
    assert lines[0].startswith('soft-rom convert: error: ')
    assert str(path) in lines[0] and key in lines[0]
    assert not (tmp_path / 'c.zarr').exists()
