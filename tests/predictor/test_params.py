"""Hostile ``replay --config`` params files, written as a user writes them.

Each is refused with a :class:`ConfigError` naming the file and the parameter; through the
CLI: exit code 2, one line, no traceback. The same checks serve the ROS node
(:func:`predictor_config` on the node's values), where a refused value is reported.
"""

from __future__ import annotations

import array
import re

import numpy as np
import pytest

from soft_rom.bags import EpisodeBagWriter
from soft_rom.cli import main
from soft_rom.errors import ConfigError
from soft_rom.models import DiscreteModel
from soft_rom.predictor import PredictorConfig
from soft_rom.predictor.params import (
    check_param,
    load_params_file,
    loop_settings,
    PARAMS,
    predictor_config,
)

# (the ros__parameters value, words of the message)
HOSTILE = [
    ('{rate_hz: abc}', 'parameter rate_hz must be a number'),
    ('{rate_hz: null}', 'rate_hz'),
    ('{rate_hz: true}', 'rate_hz'),
    ('{rate_hz: [1]}', 'rate_hz'),
    ('{rate_hz: 1e9}', 'rate_hz must be a number in 0..100000'),
    ('{max_catchup_steps: 1e30}', 'max_catchup_steps must be an integer'),
    ('{max_catchup_steps: 2.5}', 'max_catchup_steps'),
    ('{max_catchup_steps: 0}', 'max_catchup_steps'),
    ('{error_window: abc}', 'error_window'),
    ('{kalman: "yes"}', 'kalman must be true or false'),
    ('{input_scale: 0}', 'input_scale must not be 0'),
    ('{stepping: sometimes}', 'stepping must be one of event, fixed, input'),
    ('{frame_id: [a]}', 'frame_id must be a string'),
    ('{input_min: 5}', 'input_min must be a list of numbers'),
    ('{input_min: [a]}', 'input_min'),
    ('{input_topics: /a}', 'input_topics must be a list of strings'),
    ('{input_topics: [1]}', 'input_topics'),
    ('{centerline_rate_hz: abc}', 'centerline_rate_hz'),
    ('5', "ros__parameters of '/**' must be a mapping"),
    ('[1]', "ros__parameters of '/**' must be a mapping"),
    ('abc', "ros__parameters of '/**' must be a mapping"),
]


def _write(path, params_text):
    path.write_text(f'/**:\n  ros__parameters: {params_text}\n', encoding='utf-8')
    return path


@pytest.mark.parametrize('text, words', HOSTILE, ids=[t for t, _ in HOSTILE])
def test_hostile_params_file_is_a_config_error_naming_file_and_parameter(tmp_path, text,
                                                                          words):
    path = _write(tmp_path / 'p.yaml', text)
    with pytest.raises(ConfigError) as info:
        load_params_file(path)
    assert str(path) in str(info.value) and words in str(info.value)


@pytest.mark.parametrize('text, words', [
    ('/**: 5\n', "section '/**' must be a mapping"),
    ('soft_rom_predictor: [1]\n', "section 'soft_rom_predictor'"),
    ('[1, 2]\n', "map node names ('/**:')"),
    ('- a\n', "map node names ('/**:')"),
])
def test_hostile_params_file_layout(tmp_path, text, words):
    path = tmp_path / 'p.yaml'
    path.write_text(text, encoding='utf-8')
    with pytest.raises(ConfigError, match=re.escape(words)):
        load_params_file(path)


def test_non_utf8_params_file(tmp_path):
    path = tmp_path / 'p.yaml'
    path.write_bytes(b'/**:\n  ros__parameters:\n    frame_id: \xff\xfe\n')
    with pytest.raises(ConfigError, match='not UTF-8'):
        load_params_file(path)


def test_other_nodes_sections_and_numbers_spelled_as_strings(tmp_path):
    # another node's section is not ours; '1e3' is a string to PyYAML, a double to ROS
    path = tmp_path / 'p.yaml'
    path.write_text('other_node: {ros__parameters: {rate_hz: abc}}\n'
                    '/**:\n  ros__parameters:\n'
                    '    rate_hz: 1e3\n    input_scale: 2\n    max_catchup_steps: 100\n'
                    '    input_min: [0, 1]\n    input_max: [1, 2]\n', encoding='utf-8')
    values = load_params_file(path)
    assert values['rate_hz'] == 1000.0 and type(values['input_scale']) is float
    assert values['input_min'] == [0.0, 1.0]
    cfg = predictor_config(values)
    assert cfg.rate_hz == 1000.0 and cfg.max_catchup_steps == 100
    assert cfg.input_min == (0.0, 1.0)


def test_node_values_checked_the_same_way() -> None:
    # the node passes rclpy's values: ints, floats, array.array for double arrays
    values = {p.name: p.default for p in PARAMS}
    values.update(input_min=array.array('d', [0.0]), input_max=array.array('d', [0.0]),
                  rate_hz=500.0)
    assert predictor_config(values) == PredictorConfig(rate_hz=500.0)
    assert loop_settings(values).output_rate_hz == 0.0
    with pytest.raises(ConfigError, match='parameter max_catchup_steps must be an integer'):
        predictor_config({'max_catchup_steps': 'abc'})
    with pytest.raises(ConfigError, match='parameter publish_rate_hz'):
        loop_settings({'publish_rate_hz': 'abc'})
    assert check_param('use_sim_time', 'anything') == 'anything'
    assert check_param('qos_depth', np.int64(5)) == 5


@pytest.mark.parametrize('text, words', [
    ('{rate_hz: abc}', 'rate_hz'),
    ('{max_catchup_steps: 1e30}', 'max_catchup_steps'),
    ('5', 'ros__parameters'),
    ('[1]', 'ros__parameters'),
    (b'\xff\xfe\x00\x01', 'not UTF-8'),
])
def test_cli_replay_bad_config_exit_2_one_line(tmp_path, capsys, text, words):
    model = DiscreteModel(np.eye(2) * 0.5, np.ones((2, 6)), np.ones((40, 2)), dt=1e-3,
                          method='dmdc').save(tmp_path / 'm.npz')
    bag = tmp_path / 'ep1'
    with EpisodeBagWriter(bag, storage='mcap', n_nodes=None) as w:
        for j in range(5):
            w.write(0.001 * (j + 1), np.full(6, float(j)), np.zeros((20, 3)))
    path = tmp_path / 'p.yaml'
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        _write(path, text)
    capsys.readouterr()
    rc = main(['replay', str(model), str(bag), '-o', str(tmp_path / 'r'), '--config',
               str(path), '--quiet'])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and 'Traceback' not in err, err
    assert lines[0].startswith('soft-rom replay: error: ')
    assert str(path) in lines[0] and words in lines[0]
    assert not (tmp_path / 'r').exists()
