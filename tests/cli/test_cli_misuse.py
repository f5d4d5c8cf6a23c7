"""Table-driven misuse of every ``soft-rom`` verb.

Each case: the right exit code, one line, no traceback, nothing clobbered.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
import subprocess
import sys

import _hostile as h
from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.bags import EpisodeBagWriter
from soft_rom.cli import main
from soft_rom.models import DiscreteModel

pytest.importorskip('zarr')
from soft_rom.dataset import TrainingSet  # noqa: E402


def _tree(root: Path) -> dict[str, str]:
    """Path -> content hash of every file under ``root`` (what 'nothing clobbered' means)."""
    out = {}
    for p in sorted(root.rglob('*')):
        if p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
        elif p.is_dir():
            out[str(p.relative_to(root)) + '/'] = 'dir'
    return out


@pytest.fixture(scope='module')
def ws(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp('ws')
    eps = spring_chain_episodes(n_dof=12, m=2, p=4, k=300, dt=2e-3, seed=0, stiffness=400.0,
                                drive_nodes=(4, 8), input_gain=1e-3, amplitude=30e3, hold=25,
                                q_span=1.0)
    ts = TrainingSet.from_episodes(root / 'chain.zarr', eps, input_units=['Pa', 'Pa'],
                                   output_units=['m'] * 4, q_ref=eps[0].Q[:, 0],
                                   y_ref=eps[0].Y[:, 0]).path
    model = DiscreteModel(np.eye(2) * 0.5, np.ones((2, 2)), np.ones((4, 2)), dt=2e-3,
                          method='dmdc').save(root / 'good.npz')
    bag = root / 'ep2'
    with EpisodeBagWriter(bag, storage='mcap', n_nodes=2) as w:   # a recording
        for j in range(11):
            w.write(0.5 + 0.01 * j, np.full(6, float(j)), np.zeros((20, 3)), np.zeros((2, 3)))
    (root / 'mapdir').mkdir()
    (root / 'user.json').write_text('{"mine": true}\n')
    (root / 'sims').mkdir()
    (root / 'sims' / 'ep1.json').write_text('{"my": "notes"}\n')
    models = root / 'models'
    models.mkdir()
    (models / 'chain_dmdc_r4.npz').write_bytes(b'a file that is not a model: my notes')
    h.with_header(h.discrete(), root / 'hostile.npz', dt=1e300)
    h.with_metadata_text(h.second_order(), root / 'surrogate.npz',
                         json.dumps(h.second_order().header()).replace(
                             '"note": "ok"', '"note": "\\ud800"'))
    return {'root': root, 'ts': Path(ts), 'model': model, 'bag': bag, 'models': models}


# (argv, exit code, words of the one error line)
CASES = [
    # numbers: NaN, out of range, negative
    (['fit', '{ts}', '--method', 'dmdc', '--t-max', 'nan', '-o', '{root}/m1'], 2, '--t-max'),
    (['fit', '{ts}', '--method', 'era', '--hsv-tol', '2', '-o', '{root}/m1'], 2, '--hsv-tol'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '0', '-o', '{root}/m1'], 2, 'positive'),
    (['fit', '{ts}', '--method', 'dmdc', '--energy', 'inf', '-o', '{root}/m1'], 2, '--energy'),
    (['fit', '{ts}', '--method', 'nope', '-o', '{root}/m1'], 2, '--method'),
    (['fit', '{ts}', '--method', 'lopinf', '--r', '200', '-o', '{root}/m1'], 2, 'r <= 128'),
    (['evaluate', '{model}', '--data', '{ts}', '--t-split', '-1'], 2, '--t-split'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--publish-rate', 'nan'], 2,
     '--publish-rate'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--publish-rate', '-5'], 2,
     '--publish-rate'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--process-noise', '0'], 2,
     '--process-noise'),
    (['simulate', '-o', '{root}/s1', '--amplitude', 'nan'], 2, '--amplitude'),
    (['simulate', '-o', '{root}/s1', '--amplitude', '-5e4'], 2, '--amplitude'),
    (['simulate', '-o', '{root}/s1', '--jobs', '0'], 2, '--jobs'),
    (['simulate', '-o', '{root}/s1', '--dt', '0'], 2, '--dt'),
    (['simulate', '-o', '{root}/s1', '--steps', '-3'], 2, '--steps'),
    (['study', '-o', '{root}/st', '--t-train', 'nan'], 2, '--t-train'),
    (['demo', '-o', '{root}/d', '--episodes', '0'], 2, '--episodes'),
    (['convert', '{bag}', '-o', '{root}/c.zarr', '--dt', 'nan'], 2, '--dt'),
    (['convert', '{bag}', '-o', '{root}/c.zarr', '--split-gap', 'inf'], 2, '--split-gap'),
    # a typo that drops a value is not a shorter list; bounds where arithmetic overflowed
    (['fit', '{ts}', '--method', 'dmdc', '--r', '1,,2', '-o', '{root}/m1'], 2, 'empty item'),
    (['fit', '{ts}', '--method', 'dmdc,,era', '-o', '{root}/m1'], 2, 'empty item'),
    (['evaluate', '{model}', '--data', '{ts}', '--episodes', 'ep1,,ep2'], 2, 'empty name'),
    (['evaluate', '{model}', '--data', '{ts}', '--outputs', 'y1'], 2, 'give --plots'),
    (['evaluate', '{model}', '--data', '{bag}'], 2, 'is a rosbag2 bag, not a training set'),
    (['evaluate', '{model}', '--data', '{root}/user.json'], 2, 'is a file, not a training set'),
    (['convert', '{root}/user.json', '-o', '{root}/c.zarr'], 2, 'not a ROS 2 bag (no .mcap or '
     '.db3 file); to convert every bag in'),                # a bag beside it: the hint
    (['convert', '{root}/mapdir/../sims/ep1.json', '-o', '{root}/c.zarr'], 2,
     'no .mcap or .db3 file).'),                            # none beside it: no hint
    (['simulate', '-o', '', '--episodes', '1', '--steps', '3'], 2, 'an empty path'),
    (['study', '--learning-curve', '-o', '{root}/lc', '--sizes', '0'], 2,
     'training size values must be positive'),
    (['convert', '{bag}', '-o', '{root}/c.zarr', '--max-gap', '1e308'], 2, 'at most 1e+06'),
    (['convert', '{bag}', '-o', '{root}/c.zarr', '--dt', '1e300'], 2, 'at most 86400'),
    (['simulate', '-o', '{root}/s1', '--dt', '1e-300'], 2, '--dt'),
    # a second audit: options no method asked for reads, names and paths that are no names
    (['fit', '{ts}', '--method', 'dmdc', '--forces', 'cubic', '-o', '{root}/m1'], 2,
     '--forces applies to lopinf, not to --method dmdc'),
    (['fit', '{ts}', '--method', 'era', '--dmdc-variant', 'stable', '-o', '{root}/m1'], 2,
     '--dmdc-variant applies to dmdc'),
    (['fit', '{ts}', '--method', 'lopinf', '--decimation', '5', '-o', '{root}/m1'], 2,
     '--decimation applies to era'),
    (['fit', '{ts}', '--method', 'dmdc', '--ddt', 'foo', '-o', '{root}/m1'], 2, '--ddt must be'),
    (['fit', '{ts}', '--method', 'dmdc', '--prefix', ' ', '-o', '{root}/m1'], 2,
     'not a file-name prefix'),
    (['fit', '{ts}', '--method', 'dmdc', '--dask', '', '-o', '{root}/m1'], 2,
     'not a scheduler address'),
    (['fit', '{ts}', '--method', 'dmdc', '-o', '{ts}/sub'], 2, 'inside the training set'),
    (['fit', '{ts}', '--method', 'dmdc', '-o', '{bag}', '--overwrite'], 2, 'inside the bag'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--node-name', 'a b'], 2,
     'not a ROS 2 node name'),
    (['evaluate', '{model}', '--data', '{ts}', '--plots', '{root}/pp', '--outputs', '0,0'], 2,
     'given twice'),
    (['evaluate', '{model}', '--data', '{ts}', '--json', ''], 2, 'an empty path'),
    (['info', ''], 2, 'an empty path'),
    (['study', '-o', '{root}/st', '--only', '2', '--episodes', '2'], 2, 'leaves none to test'),
    (['study', '-o', '{root}/st', '--t-train', '0.001'], 2, 'fewer than 32 samples'),
    (['study', '-o', '{root}/st', '--bags', '{ts}'], 2, 'is, or is inside, the training set'),
    (['study', '-o', '{root}/st', '--bags', '{bag}'], 2, 'is, or is inside, the bag'),
    # options that would do nothing: refused, not ignored
    (['study', '-o', '{root}/st', '--sizes', '2,4'], 2,
     '--sizes is for the learning curve; add --learning-curve'),
    (['study', '--learning-curve', '-o', '{root}/lc', '--r-lopinf', '4', '--episodes', '8'], 2,
     '--episodes, --r-lopinf are for studies 1 and 2; the learning curve does not use them'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--process-noise', '1e-6'], 2,
     '--process-noise sets the Kalman filter, which is off; add --kalman'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--kalman', '--no-measured'], 2,
     'which --no-measured ignores'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--stream', '--compare'], 2,
     'does not run with --stream'),
    # resources
    (['simulate', '-o', '{root}/s1', '--resolution', '9'], 1, 'GB of memory'),
    (['study', '-o', '{root}/st', '--resolution', '20'], 1, 'GB of memory'),
    # wrong kinds of path
    (['convert', '{bag}', '-o', '{root}/c.zarr', '--mapping', '{root}/mapdir'], 2, 'mapdir'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--mapping', '{root}/mapdir'], 2,
     'mapdir'),
    (['evaluate', '{model}', '--data', '{ts}', '--json', '{root}/mapdir'], 2, 'mapdir'),
    (['fit', '{root}/missing.zarr', '-o', '{root}/m1'], 2, 'does not exist'),
    (['fit', '{ts}', '--method', 'dmdc', '-o', '{model}'], 2, 'not a folder'),
    (['info', '{root}/nothing'], 2, 'does not exist'),
    (['info', '{root}/user.json'], 2, 'neither'),
    (['evaluate', '{root}/missing.npz', '--data', '{ts}'], 2, 'not found'),
    # hostile model files
    (['info', '{root}/hostile.npz'], 2, 'dt'),
    (['info', '{root}/surrogate.npz'], 2, 'surrogate'),
    (['evaluate', '{root}/hostile.npz', '--data', '{ts}'], 2, 'dt'),
    (['replay', '{root}/hostile.npz', '{bag}', '-o', '{root}/p1'], 2, 'dt'),
    # clobbering
    (['fit', '{ts}', '--method', 'dmdc', '--r', '4', '-o', '{models}', '--quiet'], 2,
     'exists'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '4', '-o', '{models}', '--quiet',
      '--overwrite'], 2, 'not written by soft_rom'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '2', '-o', '{root}/m2', '--quiet', '--json',
      '{root}/user.json'], 2, 'exists'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '2', '-o', '{root}/m2', '--quiet', '--json',
      '{root}/user.json', '--overwrite'], 2, 'not written by soft_rom'),
    (['evaluate', '{model}', '--data', '{ts}', '--json', '{root}/user.json'], 2, 'exists'),
    (['evaluate', '{model}', '--data', '{ts}', '--json', '{root}/user.json', '--overwrite'],
     2, 'not written by soft_rom'),
    (['replay', '{model}', '{bag}', '-o', '{bag}', '--overwrite'], 2, 'input bag'),
    (['replay', '{model}', '{bag}', '-o', '{root}/chain.zarr', '--overwrite'], 2,
     'not written by soft_rom'),
    (['simulate', '-o', '{root}', '--episodes', '2', '--steps', '3', '--overwrite'], 2,
     'not written by soft-rom simulate'),
    (['simulate', '-o', '{root}/sims', '--episodes', '1', '--steps', '3', '--overwrite'], 2,
     'not written by soft-rom simulate'),
    (['convert', '{bag}', '-o', '{ts}', '--quiet'], 2, 'exists'),
    (['study', '-o', '{bag}', '--quiet'], 2, 'exists already; pass --overwrite'),
    (['study', '-o', '{bag}', '--quiet', '--overwrite'], 2, 'not a soft_rom study folder'),
    (['demo', '-o', '{models}', '--quiet', '--overwrite'], 2, 'not a soft_rom study folder'),
    (['convert', '{bag}', '-o', '{bag}', '--quiet', '--overwrite'], 2, 'not written by soft_rom'),
    (['convert', '{bag}', '-o', '{root}/mapdir', '--quiet', '--overwrite'], 2,
     'not written by soft_rom'),
    (['convert', '{bag}', '-o', '{root}/user.json', '--quiet', '--overwrite'], 2,
     'not written by soft_rom'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '2', '-o', '{root}/m2', '--quiet', '--json',
      '{model}/fit.json'], 2, 'not a folder'),
    # --json onto a folder or onto another path of the run: never replaced, even if soft_rom
    # wrote it (it deleted the training set once), nothing created
    (['evaluate', '{model}', '--data', '{ts}', '--json', '{ts}', '--overwrite'], 2,
     'training set'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '2', '-o', '{root}/m2', '--quiet', '--json',
      '{ts}', '--overwrite'], 2, 'training set'),
    (['info', '{model}', '--json', '{ts}', '--overwrite'], 2, 'is a folder'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p1', '--json', '{bag}', '--overwrite'], 2,
     'input bag'),
    (['replay', '{model}', '{bag}', '-o', '{root}/p5', '--json', '{root}/p5'], 2,
     'output bag'),
    (['fit', '{ts}', '--method', 'dmdc', '--r', '2', '-o', '{root}/m6', '--quiet', '--json',
      '{root}/m6'], 2, 'model folder'),
    # a file where a folder of the output path should be
    (['convert', '{bag}', '-o', '{root}/user.json/x.zarr', '--quiet'], 2, 'is not a directory'),
    (['info', '{model}', '--json', '{root}/user.json/i.json'], 2, 'is not a directory'),
    # a location where nothing can be created: named, not a staging path
    (['evaluate', '{model}', '--data', '{ts}', '--json', '/proc/soft_rom_test.json'], 2,
     'cannot write the evaluation summary in /proc'),
    # a later method fails: no model at all is written
    (['fit', '{ts}', '--method', 'dmdc,era', '--r', '3', '--decimation', '100000',
      '--era-episode', 'ep1', '-o', '{root}/m3', '--quiet'], 2, 'decimation'),
]


@pytest.mark.parametrize('argv, code, words', CASES,
                         ids=[' '.join(c[0][:1] + c[0][-2:]) for c in CASES])
def test_misuse(ws, capsys, argv, code, words) -> None:
    subs = {k: str(v) for k, v in ws.items()}
    before = _tree(ws['root'])
    rc = main([a.format(**subs) for a in argv])
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == code, err
    assert len(lines) == 1, err
    assert 'Traceback' not in err and lines[0].startswith('soft-rom ')
    assert words in lines[0]
    assert _tree(ws['root']) == before


def test_debug_shows_the_traceback(ws, capsys, monkeypatch) -> None:
    argv = ['evaluate', str(ws['root'] / 'hostile.npz'), '--data', str(ws['ts'])]
    assert main(argv + ['--debug']) == 2
    assert 'Traceback' in capsys.readouterr().err
    monkeypatch.setenv('SOFT_ROM_DEBUG', '1')
    assert main(argv) == 2
    assert 'Traceback' in capsys.readouterr().err


def test_overwrite_replaces_what_soft_rom_wrote(ws, tmp_path, capsys) -> None:
    out = tmp_path / 'models'
    js = tmp_path / 'fit.json'
    argv = ['fit', str(ws['ts']), '--method', 'dmdc', '--r', '3,4', '-o', str(out),
            '--quiet', '--json', str(js)]
    assert main(argv) == 0
    first = _tree(tmp_path)
    assert main(argv) == 2                      # exists, no --overwrite
    assert _tree(tmp_path) == first
    assert main(argv + ['--overwrite']) == 0    # ours: replaced
    assert sorted(p.name for p in out.iterdir()) == ['chain_dmdc_r3.npz', 'chain_dmdc_r4.npz']
    ev = tmp_path / 'ev.json'
    ev_argv = ['evaluate', str(out / 'chain_dmdc_r3.npz'), '--data', str(ws['ts']),
               '--json', str(ev)]
    assert main(ev_argv) == 0 and main(ev_argv) == 2 and main(ev_argv + ['--overwrite']) == 0
    capsys.readouterr()


def test_replay_output_marked_and_recording_never_replaced(tmp_path, capsys) -> None:
    from _bags import small_episode, small_model, write_input_bag

    from soft_rom.outputs import is_marked

    model = small_model()
    path = model.save(tmp_path / 'm.npz')
    bag = write_input_bag(tmp_path / 'in', small_episode(model), storage='mcap')
    recorded = _tree(Path(bag))
    out = tmp_path / 'pred'
    argv = ['replay', str(path), str(bag), '-o', str(out), '--quiet']
    assert main(argv) == 0 and is_marked(out, ('replay',))
    assert main(argv) == 2                                   # exists
    assert main(argv + ['--overwrite']) == 0                 # ours: replaced
    assert main(['replay', str(path), str(bag), '-o', str(bag), '--overwrite']) == 2
    other = tmp_path / 'other'
    other_bag = write_input_bag(other, small_episode(model), storage='mcap')
    kept = _tree(Path(other_bag))
    assert main(['replay', str(path), str(bag), '-o', str(other_bag), '--overwrite']) == 2
    assert _tree(Path(other_bag)) == kept and _tree(Path(bag)) == recorded
    capsys.readouterr()


def test_old_spellings_are_hidden_aliases(ws, tmp_path, capsys) -> None:
    from soft_rom.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == 'verb').choices
    for verb in ('simulate', 'study', 'demo'):
        text = sub[verb].format_help()
        assert '-o PATH, --output PATH' in text and '--out ' not in text
        assert '--quiet' in text and '--no-progress' not in text
        assert 'default: None' not in text
    for verb, verb_parser in sub.items():
        assert 'default: None' not in verb_parser.format_help(), verb
        assert '--debug' in verb_parser.format_help(), verb
    assert 'default: soft_rom_demo' in sub['demo'].format_help()
    assert 'default: soft_rom_study' in sub['study'].format_help()
    assert '--summary-json' not in sub['replay'].format_help()
    for verb in ('fit', 'evaluate', 'replay'):
        assert '--json FILE' in sub[verb].format_help()
    a = parser.parse_args(['simulate', '--out', 'x', '--no-progress'])
    assert str(a.output) == 'x' and a.quiet
    a = parser.parse_args(['replay', 'm', 'b', '-o', 'x', '--summary-json', 's.json'])
    assert str(a.json) == 's.json'
    a = parser.parse_args(['fit', 'ts', '-o', 'x', '--no-progress'])
    assert a.quiet


def test_info_prints_trust(ws, tmp_path, capsys) -> None:
    bad = h.discrete(radius=1.5).save(tmp_path / 'unstable.npz')
    assert main(['info', str(bad)]) == 0
    assert 'trust: NOT TRUSTED: unstable: spectral radius' in capsys.readouterr().out
    assert main(['info', str(ws['model'])]) == 0
    assert 'trust: ok' in capsys.readouterr().out
    assert main(['info', str(bad), '--strict']) == 2
    assert 'cannot be trusted' in capsys.readouterr().err
    assert main(['info', '--json', str(bad)]) == 0
    assert json.loads(capsys.readouterr().out)['trust'][0].startswith('unstable')
    assert main(['evaluate', str(bad), '--data', str(ws['ts']), '--strict']) == 2
    assert 'cannot be trusted' in capsys.readouterr().err


_READ_ONLY = [
    ['fit', '{ts}', '--method', 'dmdc', '--r', '3', '-o', '{ro}/models', '--quiet'],
    ['simulate', '-o', '{ro}/bags', '--episodes', '1', '--steps', '3', '--quiet'],
    ['convert', '{bag}', '-o', '{ro}/c.zarr', '--quiet'],
]


@pytest.mark.parametrize('argv', _READ_ONLY, ids=[a[0] for a in _READ_ONLY])
def test_read_only_output_folder(ws, tmp_path, argv) -> None:
    """Exit 1, one line. Root runs it without the capability to override permissions."""
    import shutil

    ro = tmp_path / 'ro'
    ro.mkdir()
    os.chmod(ro, 0o555)
    args = [a.format(ts=ws['ts'], bag=ws['bag'], ro=ro) for a in argv]
    cmd = [sys.executable, '-c',
           'import sys; from soft_rom.cli import main; sys.exit(main(sys.argv[1:]))', *args]
    if os.geteuid() == 0:
        setpriv = shutil.which('setpriv')
        if setpriv is None:
            pytest.skip('running as root without setpriv: permissions cannot be enforced')
        cmd = [setpriv, '--bounding-set=-dac_override,-dac_read_search', '--inh-caps=-all',
               *cmd]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=180, cwd=tmp_path)
    os.chmod(ro, 0o755)
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 1, res.stderr
    assert len(lines) == 1 and 'ermission' in lines[0] and 'Traceback' not in res.stderr
    assert list(ro.iterdir()) == []


def test_undecodable_path_names_print(tmp_path) -> None:
    """A model at a path that is not UTF-8 (a lone surrogate in Python) prints, exit 0."""
    name = os.fsdecode(b'model_\xff.npz')
    path = h.second_order().save(tmp_path / name)
    code = 'import sys; from soft_rom.cli import main; sys.exit(main(sys.argv[1:]))'
    res = subprocess.run([sys.executable, '-c', code, 'info', os.fsencode(path)],
                         capture_output=True, timeout=120, env=dict(os.environ, LANG='C.UTF-8',
                                                                   PYTHONIOENCODING='utf-8'))
    assert res.returncode == 0, res.stderr
    assert b'model_\\udcff.npz' in res.stdout and b'Traceback' not in res.stderr


def test_fit_from_a_path_that_is_not_utf8_writes_a_model_that_loads(ws, tmp_path,
                                                                   capsys) -> None:
    """Provenance paths with bytes that are not UTF-8 are stored escaped, not refused later."""
    from soft_rom.models import load_model
    folder = tmp_path / os.fsdecode(b'runs_\xff\xfe')
    folder.mkdir()
    eps = [TrainingSet.open(ws['ts'])[name] for name in ('ep1', 'ep2')]
    ts = TrainingSet.from_episodes(folder / 'chain.zarr', eps, q_ref=eps[0].Q[:, 0],
                                   y_ref=eps[0].Y[:, 0]).path
    assert main(['fit', str(ts), '--method', 'dmdc', '--r', '2', '-o', str(folder / 'm'),
                 '--quiet']) == 0, capsys.readouterr().err
    (path,) = (folder / 'm').glob('*.npz')
    model = load_model(path)
    assert r'runs_\xff\xfe' in model.metadata['training']['training_set']
    assert main(['info', str(path)]) == 0


def test_convert_overwrite_replaces_a_training_set(ws, tmp_path, capsys) -> None:
    out = tmp_path / 'set.zarr'
    argv = ['convert', str(ws['bag']), '-o', str(out), '--quiet']
    assert main(argv) == 0
    assert main(argv) == 2
    assert main(argv + ['--overwrite']) == 0
    capsys.readouterr()


def test_numpy_warnings_before_an_error_do_not_bury_its_line(ws, monkeypatch, capsys) -> None:
    """Warnings on the way to an error are held back; after a success they are shown.

    An overflow warned before a simulation diverges buried the error's one line.
    """
    import soft_rom.cli.info as info
    from soft_rom.errors import SolverError

    def fails(args):
        np.exp(np.array([1e4]))                    # RuntimeWarning: overflow
        raise SolverError('the simulation diverged at step 1')

    def succeeds(args):
        np.exp(np.array([1e4]))
        return 0

    monkeypatch.setattr(info, 'run', fails)
    assert main(['info', str(ws['model'])]) == 1
    assert capsys.readouterr().err.splitlines() == [
        'soft-rom info: error: the simulation diverged at step 1']
    monkeypatch.setattr(info, 'run', succeeds)
    with pytest.warns(RuntimeWarning, match='overflow'):
        assert main(['info', str(ws['model'])]) == 0
