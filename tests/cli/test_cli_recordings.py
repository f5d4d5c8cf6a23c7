"""A model meets recordings that do not match it: other units, layout, topic names.

Bags are recorded like a lab rig (:mod:`tests._rig`: epoch stamps, six chamber sensors on
independent jittered clocks, 120 Hz motion capture, no state). The counts of inputs and
outputs may agree while the numbers mean something else (kPa for a model fitted in Pa, a
point-major or ``xy`` centerline): ``evaluate`` and ``replay`` must refuse them in one line
(exit 2) instead of printing an error figure that is silently meaningless, and
``replay --stream`` must say which topic the bag lacks instead of failing inside.
"""

from __future__ import annotations

from pathlib import Path

import _rig
from _rig import record, Robot, T0_NS
import pytest

from soft_rom.cli import main

pytest.importorskip('zarr')


def _write(tmp: Path, name: str, text: str) -> str:
    path = tmp / name
    path.write_text(text)
    return str(path)


@pytest.fixture(scope='module')
def lab(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp('rec')
    robot = Robot.make()
    for i in (1, 2):
        record(robot, root / f'lab{i}', duration=3.0, seed=i,
               t0_ns=T0_NS + i * 60_000_000_000)
    original = _rig.write_messages

    def renamed(path, msgs, storage='mcap', compression='none'):
        msgs = [(t, topic.replace('/soft_robot/pressure/chamber_', '/rig/valve')
                 .replace('/soft_robot/centerline', '/mocap/spine'), kind, msg)
                for t, topic, kind, msg in msgs]
        return original(path, msgs, storage, compression)

    _rig.write_messages = renamed
    try:
        record(robot, root / 'renamed', duration=3.0, seed=2, t0_ns=T0_NS)
    finally:
        _rig.write_messages = original
    maps = {'kpa': 'inputs:\n  units: kPa\n  scale: 0.001\n',
            'pm': 'output:\n  order: point_major\n',
            'xy': 'output:\n  components: [x, y]\n',
            'four': 'inputs:\n  topics: [' + ', '.join(
                f'/soft_robot/pressure/chamber_{i}' for i in range(1, 5)) + ']\n'}
    paths = {name: Path(_write(root, f'{name}.yaml', text)) for name, text in maps.items()}
    for name in ('lab', 'kpa', 'pm', 'xy'):
        extra = [] if name == 'lab' else ['--mapping', str(paths[name])]
        assert main(['convert', str(root / 'lab1'), str(root / 'lab2'), '-o',
                     str(root / f'{name}.zarr'), '--quiet', *extra]) == 0
    assert main(['fit', str(root / 'lab.zarr'), '--method', 'dmdc', '--r', '2', '--episodes',
                 'lab1', '-o', str(root / 'm'), '--quiet']) == 0
    return {'root': root, 'model': root / 'm' / 'lab_dmdc_r2.npz', **paths}


@pytest.mark.parametrize('data, said', [
    ('kpa', "the model's inputs are in Pa but those of the training set"),
    ('pm', 'xz, component-major, points 1..10 but the training set'),
    ('xy', 'has xy, component-major, points 1..10'),
])
def test_evaluate_refuses_data_in_other_units_or_layout(lab, capsys, data, said) -> None:
    root = lab['root']
    out = root / f'eval_{data}.json'
    assert main(['evaluate', str(lab['model']), '--data', str(root / f'{data}.zarr'),
                 '--episodes', 'lab2', '--json', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert said in err and 'Traceback' not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    # the same recordings in the model's units and layout are evaluated
    assert main(['evaluate', str(lab['model']), '--data', str(root / 'lab.zarr'),
                 '--episodes', 'lab2', '--quiet']) == 0


@pytest.mark.parametrize('mapping, said', [
    ('kpa', "the model's inputs are in Pa but those of the bag"),
    ('four', 'the model has 6 inputs and 20 outputs but the bag'),
    ('xy', 'the model outputs xz, component-major, points 1..10 but the bag gives xy'),
])
def test_replay_refuses_a_bag_read_in_other_units_or_layout(lab, capsys, mapping,
                                                             said) -> None:
    root = lab['root']
    out = root / f'pred_{mapping}'
    assert main(['replay', str(lab['model']), str(root / 'lab2'), '-o', str(out),
                 '--mapping', str(lab[mapping]), '--quiet']) == 2
    err = capsys.readouterr().err
    assert said in err and 'a bug' not in err
    assert not out.exists()


def test_replay_stream_names_the_topics_the_bag_lacks(lab, capsys) -> None:
    root, model, bag = lab['root'], str(lab['model']), str(lab['root'] / 'renamed')
    # the node's default topics are not in the bag: said, nothing written (it was an
    # AttributeError: every message of the bag fed as a pressure array)
    assert main(['replay', model, bag, '-o', str(root / 's1'), '--stream', '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'has no input topic /soft_robot/pressure/chamber_1' in err and 'a bug' not in err
    assert "'/rig/valve1'" in err and not (root / 's1').exists()
    # a mapping is not what --stream reads: refused, not silently ignored
    ren = _write(root, 'ren.yaml', 'inputs:\n  topics: [' + ', '.join(
        f'/rig/valve{i}' for i in range(1, 7)) + ']\noutput:\n  topic: /mocap/spine\n')
    assert main(['replay', model, bag, '-o', str(root / 's2'), '--stream', '--mapping', ren,
                 '--quiet']) == 2
    assert '--stream reads the bag as the node does' in capsys.readouterr().err
    # a measured topic of another type
    wrong = _write(root, 'wrong.yaml', '/**:\n  ros__parameters:\n    input_topics: ['
                   + ', '.join(f"'/rig/valve{i}'" for i in range(1, 7))
                   + "]\n    measured_topic: '/rig/valve1'\n")
    assert main(['replay', model, bag, '-o', str(root / 's3'), '--stream', '--config', wrong,
                 '--quiet']) == 2
    assert 'is sensor_msgs/msg/FluidPressure, not geometry_msgs/msg/PoseArray' in \
        capsys.readouterr().err
    # the node's parameters naming the bag's topics: replayed as recorded
    cfg = _write(root, 'cfg.yaml', '/**:\n  ros__parameters:\n    input_topics: ['
                 + ', '.join(f"'/rig/valve{i}'" for i in range(1, 7))
                 + "]\n    measured_topic: '/mocap/spine'\n")
    assert main(['replay', model, bag, '-o', str(root / 's4'), '--stream', '--config', cfg,
                 '--quiet']) == 0
    out = capsys.readouterr().out
    assert 'relative deviation error' in out and 'nan' not in out


def test_fit_names_the_episode_too_short_for_the_derivatives(lab, capsys) -> None:
    root = lab['root']
    assert main(['fit', str(root / 'lab.zarr'), '--method', 'lopinf', '--r', '2',
                 '--episodes', 'lab2', '--t-max', '0.1', '-o', str(root / 'short'),
                 '--quiet']) == 2
    err = capsys.readouterr().err
    assert "episode(s) 'lab2' (" in err and 'samples) too short' in err and '--ddt' in err


def test_study_does_not_take_a_users_recordings_for_its_episodes(lab, capsys,
                                                                  tmp_path) -> None:
    bags = tmp_path / 'bags'
    bags.mkdir()
    (bags / 'ep1').symlink_to(lab['root'] / 'lab1', target_is_directory=True)
    before = sorted(p.name for p in (lab['root'] / 'lab1').iterdir())
    assert main(['study', '--bags', str(bags), '--episodes', '2', '--only', '1',
                 '-o', str(tmp_path / 'study'), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'was not recorded by soft-rom simulate' in err and 'overwrite=True' not in err
    assert sorted(p.name for p in (lab['root'] / 'lab1').iterdir()) == before
    # the study folder this run would have created is not left behind, empty but marked;
    # one that was there already stays
    assert not (tmp_path / 'study').exists()
    (tmp_path / 'mine').mkdir()
    assert main(['demo', '--bags', str(bags), '--episodes', '2',
                 '-o', str(tmp_path / 'mine'), '--quiet']) == 2
    assert (tmp_path / 'mine').is_dir()


def test_convert_refuses_the_same_recording_twice(lab, capsys) -> None:
    root = lab['root']
    out = root / 'twice.zarr'
    # (it became two identical episodes lab1 and lab1_: one could be fitted, the other
    # "held out")
    assert main(['convert', str(root / 'lab1'), str(root / 'lab2'),
                 str(root / '..' / root.name / 'lab1'), '-o', str(out), '--quiet']) == 2
    assert 'is given twice' in capsys.readouterr().err and not out.exists()


def test_fit_names_a_stable_dmdc_model_by_the_r_asked_for(lab, capsys) -> None:
    root = lab['root']
    out = root / 'stable'
    args = ['fit', str(root / 'lab.zarr'), '--method', 'dmdc', '--dmdc-variant', 'stable',
            '--r', '2,4', '--episodes', 'lab1', '-o', str(out), '--quiet']
    assert main(args) == 0
    # (they were lab_dmdc_r10 / r14: the 2r + m states of the lagged model); the variant is
    # named apart from the paper's
    assert sorted(p.name for p in out.glob('*.npz')) == ['lab_dmdc-stable_r2.npz',
                                                         'lab_dmdc-stable_r4.npz']
    rows = [row for row in capsys.readouterr().out.splitlines() if row.startswith('DMDc')]
    assert [row.split()[:3] for row in rows] == [['DMDc', 'stable', 'r=2'],
                                                 ['DMDc', 'stable', 'r=4']]
    # a second run is refused before fitting, by the names it would write
    assert main(args) == 2
    assert 'lab_dmdc-stable_r2.npz exists already' in capsys.readouterr().err


def test_evaluate_tells_apart_models_of_the_same_name(lab, capsys) -> None:
    root = lab['root']
    assert main(['fit', str(root / 'lab.zarr'), '--method', 'dmdc', '--r', '2', '--episodes',
                 'lab2', '-o', str(root / 'm_other'), '--quiet']) == 0
    first, second = str(lab['model']), str(root / 'm_other' / 'lab_dmdc_r2.npz')
    capsys.readouterr()
    assert main(['evaluate', first, second, '--data', str(root / 'lab.zarr'), '--episodes',
                 'lab2', '--plots', str(root / 'plots_same'), '--quiet']) == 0
    rows = capsys.readouterr().out.splitlines()[2:]
    # (both were 'lab_dmdc_r2.npz', and the second plot replaced the first)
    assert {row.split()[0] for row in rows} == {first, second}
    assert len(list((root / 'plots_same').glob('*__lab2.png'))) == 2


def test_json_summaries_are_strict_json_when_an_error_cannot_be_computed(lab) -> None:
    """``--t-split`` past an episode's end leaves its test part empty: ``null``, not NaN.

    Python writes NaN / Infinity by default, which strict JSON parsers (jq, JavaScript)
    refuse; the summaries are read by such tools.
    """
    import json

    def strict(text: str) -> object:
        def refuse(c: str) -> None:
            raise ValueError(f'non-JSON constant {c}')
        return json.loads(text, parse_constant=refuse)

    root = lab['root']
    out = root / 'eval_split.json'
    assert main(['evaluate', str(lab['model']), '--data', str(root / 'lab.zarr'),
                 '--episodes', 'lab2', '--t-split', '100', '--json', str(out), '--quiet']) == 0
    rows = strict(out.read_text())
    test = [r for r in rows if r['segment'] == 'test']
    assert test and all(r['n_samples'] == 0 and r['relative_error'] is None for r in test)
    assert all(isinstance(r['relative_error'], float) for r in rows if r['segment'] == 'all')


def test_an_episode_selected_twice_is_refused(lab, capsys) -> None:
    root = lab['root']
    for cmd in (['fit', str(root / 'lab.zarr'), '--method', 'dmdc', '--r', '2',
                 '-o', str(root / 'twice'), '--quiet'],
                ['evaluate', str(lab['model']), '--data', str(root / 'lab.zarr'), '--quiet']):
        assert main([*cmd, '--episodes', 'lab2, lab2']) == 2
        err = capsys.readouterr().err
        assert "['lab2'] selected more than once" in err and 'Traceback' not in err
    assert not (root / 'twice').exists()


def test_convert_says_one_line_per_bag_and_the_details_with_verbose(lab, capsys) -> None:
    root = lab['root']
    for extra, per_bag in (([], 1), (['-v'], 4)):
        out = root / f'lines{len(extra)}.zarr'
        assert main(['convert', str(root / 'lab1'), str(root / 'lab2'), '-o', str(out),
                     *extra]) == 0
        captured = capsys.readouterr()
        lines = [seg.strip() for line in captured.err.splitlines() for seg in line.split('\r')]
        heads = [seg for seg in lines if seg.startswith('bag ')]
        assert len(heads) == 2, captured.err
        assert all('samples' in h and 'ms grid' in h for h in heads), heads
        report = [seg for seg in lines if seg and not seg.startswith(('lab1', 'lab2'))
                  and '%|' not in seg]
        assert len(report) >= 2 * per_bag, report
        assert 'e-1' not in captured.err          # no float rests such as 'jitter 4e-16 ms'
        assert 'no states' in captured.out and 'n = None' not in captured.out
        if not extra:
            assert len(report) == 2 and '--verbose' in captured.out
            assert any('interpolated' in h or 'dropped' in h for h in heads), heads
