"""Safe outputs: nothing soft_rom did not write is replaced; outputs appear whole."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from soft_rom import outputs
from soft_rom.errors import OutputExistsError, ResourceError


def _make(path: Path, text: str) -> None:
    path.mkdir()
    (path / 'data.txt').write_text(text)


def test_new_folder_appears_with_marker(tmp_path: Path) -> None:
    dest = tmp_path / 'set'
    with outputs.atomic_dir(dest, overwrite=False, kind='training_set', what='training set') as d:
        (d / 'x').write_text('1')
        assert not dest.exists()
    assert (dest / 'x').read_text() == '1'
    assert outputs.is_marked(dest, ['training_set'])
    assert not outputs.is_marked(dest, ['bag'])


def test_existing_needs_overwrite_and_ours(tmp_path: Path) -> None:
    rec = tmp_path / 'recording'
    _make(rec, 'precious')
    with pytest.raises(OutputExistsError, match='--overwrite'):
        with outputs.atomic_dir(rec, overwrite=False, kind='training_set', what='training set'):
            pass
    with pytest.raises(OutputExistsError, match='not written by soft_rom'):
        with outputs.atomic_dir(rec, overwrite=True, kind='training_set', what='training set'):
            pass
    assert (rec / 'data.txt').read_text() == 'precious'
    assert [p.name for p in tmp_path.iterdir()] == ['recording']


def test_a_file_output_never_replaces_a_folder_even_ours(tmp_path: Path) -> None:
    dest = tmp_path / 'set'
    with outputs.atomic_dir(dest, overwrite=False, kind='training_set', what='training set') as d:
        (d / 'x').write_text('1')
    with pytest.raises(OutputExistsError, match='is a folder'):
        with outputs.atomic_files([dest], overwrite=True, what='summary',
                                  is_ours=lambda p: True) as staged:
            staged[dest].write_text('{}')
    assert (dest / 'x').read_text() == '1' and outputs.is_marked(dest, ['training_set'])


def test_overwrite_ours_replaces_and_failure_keeps_old(tmp_path: Path) -> None:
    dest = tmp_path / 'set'
    with outputs.atomic_dir(dest, overwrite=False, kind='t', what='set') as d:
        (d / 'v').write_text('old')
    with pytest.raises(RuntimeError):
        with outputs.atomic_dir(dest, overwrite=True, kind='t', what='set') as d:
            (d / 'v').write_text('half')
            raise RuntimeError('killed')
    assert (dest / 'v').read_text() == 'old'
    with outputs.atomic_dir(dest, overwrite=True, kind='t', what='set') as d:
        (d / 'v').write_text('new')
    assert (dest / 'v').read_text() == 'new'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['set']


def test_crash_between_two_renames_is_recovered(tmp_path: Path, monkeypatch) -> None:
    dest = tmp_path / 'set'
    with outputs.atomic_dir(dest, overwrite=False, kind='t', what='set') as d:
        (d / 'v').write_text('old')
    monkeypatch.setattr(outputs, '_exchange', lambda a, b: False)
    real_rename = os.rename
    calls = []

    def dying_rename(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the crash comes after the old set was parked
            raise KeyboardInterrupt
        return real_rename(src, dst)

    monkeypatch.setattr(outputs.os, 'rename', dying_rename)
    with pytest.raises(KeyboardInterrupt):
        # the handler's own rename back is the third call and succeeds
        with outputs.atomic_dir(dest, overwrite=True, kind='t', what='set') as d:
            (d / 'v').write_text('new')
    assert (dest / 'v').read_text() == 'old'
    # a hard kill leaves the old set parked and dest missing: the next run restores it
    monkeypatch.setattr(outputs.os, 'rename', real_rename)
    parked = tmp_path / f'.set{outputs._OLD}99999-abcd'
    os.rename(dest, parked)
    outputs.check_output(dest, overwrite=True, what='set', kinds=['t'])
    assert (dest / 'v').read_text() == 'old'
    assert not parked.exists()


def test_stale_stage_of_killed_run_removed(tmp_path: Path) -> None:
    stale = tmp_path / f'.x{outputs._STAGE}999999999-deadbeef'
    stale.mkdir()
    (stale / 'big').write_bytes(b'0' * 100)
    with outputs.atomic_dir(tmp_path / 'x', overwrite=False, kind='t', what='set'):
        pass
    assert not stale.exists()


def test_atomic_files_all_or_nothing(tmp_path: Path) -> None:
    a, b = tmp_path / 'a.npz', tmp_path / 'b.npz'
    a.write_text('mine-a')

    def ours(p: Path) -> bool:
        return p.read_text().startswith('mine')

    with pytest.raises(OutputExistsError):
        with outputs.atomic_files([a, b], overwrite=False, what='model file', is_ours=ours):
            pass
    with pytest.raises(ValueError):
        with outputs.atomic_files([a, b], overwrite=True, what='model file',
                                  is_ours=ours) as m:
            m[a].write_text('mine-new-a')
            raise ValueError('second method failed')
    assert a.read_text() == 'mine-a' and not b.exists()
    with outputs.atomic_files([a, b], overwrite=True, what='model file', is_ours=ours) as m:
        m[a].write_text('mine-new-a')
        m[b].write_text('mine-new-b')
    assert a.read_text() == 'mine-new-a' and b.read_text() == 'mine-new-b'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['a.npz', 'b.npz']
    foreign = tmp_path / 'c.npz'
    foreign.write_text('someone else')
    with pytest.raises(OutputExistsError, match='not written by soft_rom'):
        with outputs.atomic_files([foreign], overwrite=True, what='model file', is_ours=ours):
            pass
    assert foreign.read_text() == 'someone else'


def test_free_space_refusal(tmp_path: Path) -> None:
    outputs.check_free_space(tmp_path, 1.0, 'tiny')
    with pytest.raises(ResourceError, match='GB'):
        outputs.check_free_space(tmp_path / 'not' / 'yet', 1e18, 'a huge grid')


def test_atomic_new_dir_for_writers_that_create_their_folder(tmp_path: Path) -> None:
    dest = tmp_path / 'bag'
    with outputs.atomic_new_dir(dest, overwrite=False, kind='replay', what='bag') as stage:
        assert not stage.exists()
        _make(stage, 'one')
    assert (dest / 'data.txt').read_text() == 'one' and outputs.is_marked(dest, ['replay'])
    with pytest.raises(OutputExistsError, match='--overwrite'):
        with outputs.atomic_new_dir(dest, overwrite=False, kind='replay', what='bag'):
            pass
    with pytest.raises(OutputExistsError, match='not written'):   # kind must match
        with outputs.atomic_new_dir(dest, overwrite=True, kind='simulated', what='bag'):
            pass
    with pytest.raises(OutputExistsError, match='not written'):   # the writer wrote nothing
        with outputs.atomic_new_dir(dest, overwrite=True, kind='replay', what='bag'):
            pass
    with outputs.atomic_new_dir(dest, overwrite=True, kind='replay', what='bag') as stage:
        _make(stage, 'two')
    assert (dest / 'data.txt').read_text() == 'two'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag']


@pytest.mark.parametrize('no_renameat2', [False, True])
def test_output_that_appears_while_writing_is_never_replaced(tmp_path: Path, monkeypatch,
                                                             no_renameat2) -> None:
    """The checks run before a long write; what appears at the path meanwhile is re-checked.

    Two runs writing the same new path (a user starting `convert` twice): the later one to
    finish must not replace the earlier one's output without --overwrite, and no run may
    replace a folder it did not write (a recording copied there meanwhile) even with it.
    Also without ``renameat2`` (another C library, another kernel).
    """
    if no_renameat2:
        monkeypatch.setattr(outputs, '_renameat2', lambda a, b, flags: -1)
    dest = tmp_path / 'set'
    with pytest.raises(OutputExistsError, match='appeared while the training set'):
        with outputs.atomic_dir(dest, overwrite=False, kind='t', what='training set') as d:
            (d / 'v').write_text('mine')
            with outputs.atomic_dir(dest, overwrite=False, kind='t', what='training set') as e:
                (e / 'v').write_text('the other run')
    assert (dest / 'v').read_text() == 'the other run'
    # with --overwrite a soft_rom output that appeared is replaced ...
    with outputs.atomic_dir(dest, overwrite=True, kind='t', what='training set') as d:
        (d / 'v').write_text('mine')
        with outputs.atomic_dir(dest, overwrite=True, kind='t', what='training set') as e:
            (e / 'v').write_text('the other run')
    assert (dest / 'v').read_text() == 'mine'
    # ... but never a folder soft_rom did not write
    new = tmp_path / 'new'
    with pytest.raises(OutputExistsError, match='not written by soft_rom'):
        with outputs.atomic_dir(new, overwrite=True, kind='t', what='training set') as d:
            (d / 'v').write_text('mine')
            _make(new, 'a recording')
    assert (new / 'data.txt').read_text() == 'a recording'
    with pytest.raises(OutputExistsError, match='appeared while the bag'):
        with outputs.atomic_new_dir(tmp_path / 'bag', overwrite=False, kind='r',
                                    what='bag') as stage:
            _make(stage, 'mine')
            _make(tmp_path / 'bag', 'the other run')
    assert (tmp_path / 'bag' / 'data.txt').read_text() == 'the other run'
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.')]


def test_file_that_appears_while_writing_is_never_replaced(tmp_path: Path) -> None:
    a, b = tmp_path / 'a.npz', tmp_path / 'b.npz'

    def ours(p: Path) -> bool:
        return p.read_text().startswith('mine')

    with pytest.raises(OutputExistsError, match='appeared while the model file'):
        with outputs.atomic_files([a, b], overwrite=False, what='model file',
                                  is_ours=ours) as m:
            m[a].write_text('mine-a')
            m[b].write_text('mine-b')
            b.write_text('mine, from the other run')
    assert not a.exists() and b.read_text() == 'mine, from the other run'
    with pytest.raises(OutputExistsError, match='not written by soft_rom'):
        with outputs.atomic_files([a, b], overwrite=True, what='model file',
                                  is_ours=ours) as m:
            m[a].write_text('mine-a')
            m[b].write_text('mine-b')
            b.write_text('a file of the user')
    assert not a.exists() and b.read_text() == 'a file of the user'
    b.unlink()
    with outputs.atomic_files([a, b], overwrite=True, what='model file', is_ours=ours) as m:
        m[a].write_text('mine-a')
        m[b].write_text('mine-b')
        b.write_text('mine, from the other run')
    assert a.read_text() == 'mine-a' and b.read_text() == 'mine-b'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['a.npz', 'b.npz']
