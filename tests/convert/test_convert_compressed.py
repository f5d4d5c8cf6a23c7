"""Bags recorded with rosbag2's zstd compression convert like the uncompressed ones.

``ros2 bag record --compression-mode file --compression-format zstd`` leaves
``<bag>/<bag>_0.mcap.zstd`` (or ``.db3.zstd``) beside ``metadata.yaml``; ``--compression-mode
message`` compresses each message inside an ordinary file. The recordings here are the lab
rig's (epoch stamps, six chamber clocks, a 120 Hz motion capture; :mod:`tests._rig`),
written through rosbags with each compression, and converted with the CLI.
"""

from __future__ import annotations

from pathlib import Path

from _rig import record, Robot
import numpy as np
import pytest

from soft_rom.bags.reader import bag_storage, is_bag
from soft_rom.cli import main
from soft_rom.dataset import TrainingSet
from soft_rom.errors import BagError


@pytest.fixture(scope='module')
def recordings(tmp_path_factory):
    root = tmp_path_factory.mktemp('compressed')
    robot = Robot.make()
    out = {}
    for storage in ('mcap', 'sqlite3'):
        for mode in ('none', 'file', 'message'):
            name = f'{storage}_{mode}'
            record(robot, root / name, duration=2.0, seed=3, storage=storage, compression=mode)
            out[storage, mode] = root / name
    return root, out


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
@pytest.mark.parametrize('mode', ['file', 'message'])
def test_compressed_bag_converts_to_the_same_episode(recordings, monkeypatch, storage, mode):
    root, bags = recordings
    monkeypatch.chdir(root)
    bag = bags[storage, mode]
    if mode == 'file':
        assert [f.name for f in bag.iterdir() if f.name.endswith('.zstd')]
    assert is_bag(bag) and bag_storage(bag) == storage
    plain, packed = f'{storage}_plain_{mode}.zarr', f'{storage}_{mode}.zarr'
    assert main(['convert', str(bags[storage, 'none']), '-o', plain, '--quiet']) == 0
    assert main(['convert', str(bag), '-o', packed, '--quiet']) == 0
    a, b = TrainingSet.open(plain), TrainingSet.open(packed)
    ea, eb = a[a.episode_names[0]], b[b.episode_names[0]]
    assert ea.Y.shape == eb.Y.shape and ea.Y.shape[1] > 200
    np.testing.assert_array_equal(ea.U, eb.U)
    np.testing.assert_array_equal(ea.Y, eb.Y)
    assert a.t0_ns(a.episode_names[0]) == b.t0_ns(b.episode_names[0])


def test_info_describes_a_file_compressed_bag(recordings, capsys):
    _, bags = recordings
    assert main(['info', str(bags['mcap', 'file'])]) == 0
    out = capsys.readouterr().out
    assert '(mcap)' in out and '/soft_robot/centerline' in out


def test_one_file_of_a_compressed_bag_is_refused_with_advice(recordings, tmp_path, capsys):
    _, bags = recordings
    (part,) = [f for f in bags['mcap', 'file'].iterdir() if f.name.endswith('.mcap.zstd')]
    out = tmp_path / 'x.zarr'
    assert main(['convert', str(part), '-o', str(out)]) == 2
    err = capsys.readouterr().err
    assert 'file-compressed bag' in err and 'metadata.yaml' in err
    assert 'Traceback' not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_storage_plugin_soft_rom_cannot_read_is_named(recordings, tmp_path, capsys):
    _, bags = recordings
    src = bags['mcap', 'none']
    bag = tmp_path / 'other'
    bag.mkdir()
    for f in src.iterdir():
        text = f.read_bytes()
        if f.name == 'metadata.yaml':
            text = text.replace(b'storage_identifier: mcap', b'storage_identifier: rosbag_v1')
            assert b'rosbag_v1' in text
        (bag / f.name).write_bytes(text)
    with pytest.raises(BagError, match="storage 'rosbag_v1'"):
        bag_storage(bag)
    assert main(['convert', str(bag), '-o', str(tmp_path / 'x.zarr')]) == 2
    err = capsys.readouterr().err
    assert "storage 'rosbag_v1'" in err and 'Traceback' not in err


def test_overwrite_never_removes_a_compressed_recording(recordings, capsys):
    _, bags = recordings
    bag = bags['sqlite3', 'file']
    before = sorted(f.name for f in bag.iterdir())
    assert main(['convert', str(bags['mcap', 'none']), '-o', str(bag), '--overwrite']) == 2
    assert sorted(f.name for f in bag.iterdir()) == before
    assert 'Traceback' not in capsys.readouterr().err


def test_unreadable_metadata_falls_back_to_the_files(tmp_path):
    bag = tmp_path / 'b'
    bag.mkdir()
    (bag / 'metadata.yaml').write_bytes(b'\xff\xfe: [unclosed')
    (bag / 'b_0.db3').write_bytes(b'')
    assert bag_storage(bag) == 'sqlite3'
    assert is_bag(bag) and is_bag(Path(tmp_path / 'b' / 'b_0.db3'))


def test_message_compressed_file_without_its_metadata_says_so(recordings, tmp_path, capsys):
    """The .db3 of a --compression-mode message bag copied alone: compressed, not corrupt."""
    _, bags = recordings
    (db3,) = [f for f in bags['sqlite3', 'message'].iterdir() if f.suffix == '.db3']
    bag = tmp_path / 'copied'
    bag.mkdir()
    (bag / db3.name).write_bytes(db3.read_bytes())
    assert main(['convert', str(bag), '-o', str(tmp_path / 'x.zarr')]) == 2
    err = capsys.readouterr().err
    assert 'zstd-compressed' in err and 'ros2 bag reindex' in err
    assert 'Traceback' not in err and len(err.strip().splitlines()) == 1


def test_mcap_cut_short_asks_for_mcap_recover(recordings, tmp_path, capsys):
    """A recorder killed mid-file leaves an MCAP without its end: named, with the tool."""
    _, bags = recordings
    (mcap,) = [f for f in bags['mcap', 'none'].iterdir() if f.suffix == '.mcap']
    bag = tmp_path / 'killed'
    bag.mkdir()
    data = mcap.read_bytes()
    (bag / 'killed_0.mcap').write_bytes(data[:len(data) * 7 // 10])
    assert main(['convert', str(bag), '-o', str(tmp_path / 'x.zarr')]) == 2
    err = capsys.readouterr().err
    assert 'mcap recover' in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 1
