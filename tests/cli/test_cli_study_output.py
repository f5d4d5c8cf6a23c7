"""``study`` / ``demo`` output folders: refused unless ``--overwrite``, never left mixed.

The folder is built in place with the previous one parked aside
(:func:`soft_rom.outputs.rebuilt_dir`): a second run is refused without ``--overwrite``;
with it the previous folder is replaced whole (its recorded episodes reused); a run that
stops -- an error, Ctrl-C at any moment, a kill -- leaves the previous folder as it was,
or no folder.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

import pytest

from soft_rom.cli import main
from soft_rom.outputs import mark, MARKER
from soft_rom.outputs_inplace import rebuilt_dir, restore_interrupted

ROOT = Path(__file__).resolve().parents[2]


def _tree(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob('*')):
        if p.is_file():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _old_study(folder: Path) -> dict[str, str]:
    """A finished study folder of an earlier run (what a rerun must not mix with)."""
    folder.mkdir(parents=True)
    (folder / 'report.md').write_text('# the previous report\n')
    (folder / 'summary.json').write_text('{"previous": true}\n')
    (folder / 'bars.png').write_bytes(b'previous figure')
    mark(folder, 'study')
    return _tree(folder)


def _leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith('.'))


@pytest.fixture
def fake_study(monkeypatch):
    """``run_study`` replaced by one that writes a report, a figure and reuses ``bags/``."""
    calls = []

    def run_study(out, cfg, *, progress=True, studies=(1, 2), replay=False, bag_dir=None):
        out = Path(out)
        calls.append({'out': out, 'bags': sorted(p.name for p in (out / 'bags').glob('*'))
                      if (out / 'bags').is_dir() else []})
        (out / 'bars.png').write_bytes(b'new figure')
        if os.environ.get('FAKE_STUDY_FAIL'):
            raise RuntimeError('solver exploded')
        (out / 'report.md').write_text('# the new report\n')
        summary = {'timings': {'simulate': 1.0}, 'machine': {'description': 'a test'}}
        (out / 'summary.json').write_text(json.dumps(summary))
        return summary

    monkeypatch.setattr('soft_rom.study.run.run_study', run_study)
    return calls


@pytest.mark.parametrize('verb', ['study', 'demo'])
def test_an_existing_folder_is_refused_unless_overwrite(verb, tmp_path, capsys,
                                                          fake_study) -> None:
    out = tmp_path / 'out'
    before = _old_study(out)
    assert main([verb, '-o', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert f'{out} exists already; pass --overwrite' in err and len(err.splitlines()) == 1
    assert _tree(out) == before and not fake_study
    assert main([verb, '-o', str(out), '--quiet', '--overwrite']) == 0
    assert (out / 'report.md').read_text() == '# the new report\n'
    assert (out / 'bars.png').read_bytes() == b'new figure'
    assert json.loads((out / MARKER).read_text())['kind'] == 'study'
    assert _leftovers(tmp_path) == []


def test_overwrite_reuses_the_recorded_episodes_of_the_same_settings(tmp_path,
                                                                    fake_study) -> None:
    out = tmp_path / 'out'
    _old_study(out)
    bags = out / 'bags'
    for i, seed in ((1, 0), (2, 0), (3, 7)):      # ep3 recorded with another seed
        (bags / f'ep{i}').mkdir(parents=True)
        (bags / f'ep{i}' / 'ep.mcap').write_bytes(b'messages')
        (bags / f'ep{i}.json').write_text(json.dumps(
            {'seed': seed, 'storage': 'mcap', 'n_steps': 2000, 'dt': 0.001, 'resolution': 1}))
    mark(out, 'study')                            # the study wrote its bags before its marker
    inode = (bags / 'ep1' / 'ep.mcap').stat().st_ino
    assert main(['study', '-o', str(out), '--quiet', '--overwrite', '--episodes', '3']) == 0
    assert fake_study[0]['bags'] == ['ep1', 'ep1.json', 'ep2', 'ep2.json']
    assert (out / 'bags' / 'ep1' / 'ep.mcap').stat().st_ino == inode   # a link, not a copy


def test_a_failed_run_leaves_the_previous_folder(tmp_path, capsys, fake_study,
                                                 monkeypatch) -> None:
    out = tmp_path / 'out'
    before = _old_study(out)
    monkeypatch.setenv('FAKE_STUDY_FAIL', '1')
    assert main(['demo', '-o', str(out), '--quiet', '--overwrite']) == 1
    assert 'solver exploded' in capsys.readouterr().err
    assert _tree(out) == before and _leftovers(tmp_path) == []
    new = tmp_path / 'new'
    assert main(['demo', '-o', str(new), '--quiet']) == 1
    assert not new.exists() and _leftovers(tmp_path) == []


def test_files_added_to_a_study_folder_stop_overwrite(tmp_path, capsys, fake_study) -> None:
    """A model fitted into it, notes, an input of the run: --overwrite would delete them."""
    out = tmp_path / 'out'
    _old_study(out)
    (out / 'models').mkdir()
    (out / 'models' / 'mine.npz').write_bytes(b'my model')
    before = _tree(out)
    assert main(['study', '-o', str(out), '--quiet', '--overwrite']) == 2
    err = capsys.readouterr().err
    assert 'holds files soft_rom did not write there (models/mine.npz)' in err
    assert len(err.strip().splitlines()) == 1 and _tree(out) == before
    (out / 'models' / 'mine.npz').unlink()
    (out / 'models').rmdir()                      # an empty folder left is no one's file
    assert main(['study', '-o', str(out), '--quiet', '--overwrite']) == 0


def test_not_a_study_folder_is_never_replaced(tmp_path, capsys, fake_study) -> None:
    mine = tmp_path / 'mine'
    mine.mkdir()
    (mine / 'notes.txt').write_text('mine')
    assert main(['study', '-o', str(mine), '--quiet', '--overwrite']) == 2
    assert 'not a soft_rom study folder' in capsys.readouterr().err
    assert _tree(mine) == {'notes.txt': hashlib.sha256(b'mine').hexdigest()}


_KILLED = """
import sys, time
from pathlib import Path
from soft_rom.outputs_inplace import rebuilt_dir
with rebuilt_dir(sys.argv[1], overwrite=True, kind='study', what='study folder') as out:
    (Path(out) / 'bars.png').write_bytes(b'half-written')
    print('ready', flush=True)
    time.sleep(60)
"""


def test_a_killed_build_is_undone_by_the_next_run(tmp_path) -> None:
    out = tmp_path / 'out'
    before = _old_study(out)
    proc = subprocess.Popen([sys.executable, '-c', _KILLED, str(out)], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == 'ready'
    proc.kill()                                    # no cleanup at all
    proc.wait()
    assert (out / 'bars.png').read_bytes() == b'half-written'        # marked incomplete
    assert json.loads((out / MARKER).read_text())['kind'] == 'incomplete'
    restore_interrupted(out)
    assert _tree(out) == before and _leftovers(tmp_path) == []


def test_a_build_in_progress_is_not_touched(tmp_path) -> None:
    from soft_rom.errors import OutputExistsError

    out = tmp_path / 'out'
    _old_study(out)
    proc = subprocess.Popen([sys.executable, '-c', _KILLED, str(out)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == 'ready'
        with pytest.raises(OutputExistsError, match=f'another soft-rom run .process {proc.pid}'):
            with rebuilt_dir(out, overwrite=True, kind='study', what='study folder'):
                pass
        assert (out / 'bars.png').read_bytes() == b'half-written'
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.slow
def test_ctrl_c_while_simulating_and_fitting_leaves_no_mixed_folder(tmp_path) -> None:
    """The real demo, interrupted (SIGINT to its process group, as Ctrl-C) twice at once.

    At 10 s it replaces an earlier demo folder (simulating with worker processes); the
    second writes a new one (in place) and is interrupted 5 s after its training set
    appeared there (converting or fitting: the whole demo now takes under a minute, so a
    fixed 60 s found it finished). Whatever they were doing then, the earlier folder must
    be back exactly, the new one must not exist, and nothing hidden is left.
    """
    old = tmp_path / 'old'
    before = _old_study(old)
    new = tmp_path / 'new'
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    runs = []
    for out, extra, at in ((old, ['--overwrite'], 10.0), (new, [], None)):
        proc = subprocess.Popen(
            # Ctrl-C reaches it even where pytest runs in the background (a shell starts
            # background jobs with SIGINT ignored, and children inherit that).
            [sys.executable, '-c', 'import signal, sys; '
             'signal.signal(signal.SIGINT, signal.default_int_handler); '
             'from soft_rom.cli import main; sys.exit(main())',
             'demo', '-o', str(out), '--quiet', *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
            start_new_session=True, cwd=tmp_path)
        runs.append((proc, at))
    start = time.monotonic()

    def fitting() -> bool:          # the second demo wrote its training set (in place)
        return (new / 'data.zarr').exists()

    for proc, at in runs:
        if at is None:
            while not fitting() and proc.poll() is None and time.monotonic() < start + 300:
                time.sleep(0.2)
            time.sleep(5.0)
        else:
            time.sleep(max(0.0, start + at - time.monotonic()))
        assert proc.poll() is None, proc.communicate()
        os.killpg(proc.pid, signal.SIGINT)
    for proc, _at in runs:
        _out, err = proc.communicate(timeout=120)
        assert proc.returncode == 130, err
        assert 'soft-rom demo: interrupted' in err and 'Traceback' not in err, err
    assert _tree(old) == before
    assert not new.exists()
    assert _leftovers(tmp_path) == []
