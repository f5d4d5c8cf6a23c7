"""Tests of soft_rom.dataset.stored: damaged training sets are refused, never read as zeros.

Each set is written by the project's own writer, then damaged on disk the way the outside
world does it: a chunk truncated (an interrupted copy, ``head -c``), overwritten with random
bytes, deleted (zarr would read it as its fill value, zeros), a ``.zattrs`` replaced.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
import re
import shutil
from unittest import mock

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from soft_rom.cli import main
from soft_rom.data import Episode
from soft_rom.dataset import direct, StoredArray, TrainingSet
from soft_rom.errors import DatasetError

K, N = 40, 9
Q_CHUNKS = (4, 8)          # Q: a 3 x 5 grid of chunks


def _episodes() -> list[Episode]:
    rng = np.random.default_rng(7)
    t = 0.001 * np.arange(K)
    smooth = np.sin(np.outer(np.arange(1, 4), t * 50.0))        # compresses: blosc decodes it
    ep1 = Episode(t=t, U=rng.normal(size=(2, K)), Y=np.round(smooth, 3),
                  Q=rng.normal(size=(N, K)), name='ep1', metadata={'source_bag': '/rec/ep1'})
    ep2 = Episode(t=t, U=np.zeros((2, K)), Y=rng.normal(size=(3, K)),    # inputs all zero
                  Q=rng.normal(size=(N, K)), name='ep2')
    return [ep1, ep2]


@pytest.fixture(scope='module')
def intact(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp('sets') / 'ts.zarr'
    TrainingSet.from_episodes(path, _episodes(), q_chunks=Q_CHUNKS,
                              attrs={'provenance': {'bags': ['/rec/ep1', '/rec/ep2']}})
    return path


@pytest.fixture
def damaged(intact, tmp_path) -> Path:
    """A fresh copy of the intact set, to damage."""
    return Path(shutil.copytree(intact, tmp_path / 'a.zarr'))


def _chunks(array_dir: Path) -> list[Path]:
    """The chunk files of an array, as the store names them (zarr version dependent)."""
    return sorted(p for p in array_dir.iterdir() if not p.name.startswith('.'))


def _truncate(path: Path, n: int = 100) -> None:
    path.write_bytes(path.read_bytes()[:n])                # what `head -c 100` leaves


def _random_bytes(path: Path, n: int = 1000) -> None:
    path.write_bytes(np.random.default_rng(3).bytes(n))    # `head -c 1000 /dev/urandom`


def _scramble_payload(path: Path) -> None:
    """Keep the (blosc) header and length, flip every 5th byte after it."""
    data = bytearray(path.read_bytes())
    for i in range(40, len(data), 5):
        data[i] ^= 0x5A
    path.write_bytes(bytes(data))


def _read(ts: TrainingSet, key: str) -> object:
    ep = ts['ep1']
    return ep.Q[:, 0:8] if key == 'Q' else getattr(ep, key)


# -- an intact set --------------------------------------------------------------------------
def test_intact_set_reads_bit_identically_and_stores_chunks_of_zeros(intact):
    ts = TrainingSet.open(intact)
    for ref in _episodes():
        got = ts[ref.name]
        np.testing.assert_array_equal(got.t, ref.t)
        np.testing.assert_array_equal(got.U, ref.U)
        np.testing.assert_array_equal(got.Y, ref.Y)
        assert isinstance(got.Q, StoredArray) and got.Q.chunks == Q_CHUNKS
        np.testing.assert_array_equal(got.Q[:, :], ref.Q)
        np.testing.assert_array_equal(np.asarray(got.Q), ref.Q)
        np.testing.assert_array_equal(got.Q[2:7, 5:29], ref.Q[2:7, 5:29])
    np.testing.assert_array_equal(ts.q_ref, _episodes()[0].Q[:, 0])
    # zarr 3 leaves chunks of zeros out unless told not to: the all-zero U must be stored
    assert [p.name for p in _chunks(intact / 'episodes/ep2/U')] == \
        [p.name for p in _chunks(intact / 'episodes/ep1/U')]
    assert len(_chunks(intact / 'episodes/ep1/Q')) == 3 * 5
    assert ts.attrs['all_chunks_stored'] is True
    # dask ships it to worker processes through its reduce protocol; deepcopy uses the same
    q = copy.deepcopy(ts.q_array('ep2'))
    np.testing.assert_array_equal(q[:, 8:16], _episodes()[1].Q[:, 8:16])


def test_to_dask_reads_the_stored_chunks(intact):
    pytest.importorskip('dask.array')
    q = TrainingSet.open(intact).q_array('ep1').to_dask()
    assert q.chunks[1] == (8,) * 5
    np.testing.assert_array_equal(q.compute(), _episodes()[0].Q)


def test_every_dask_read_carries_its_own_array(intact):
    # No task holds the array for the reads to depend on: a Dask worker killed while holding
    # such a key left queued reads whose dependency was gone, and distributed 2024.1's
    # scheduler then failed an assertion and dropped the other workers (a fit waited for ever)
    pytest.importorskip('dask.array')
    from dask.core import get_dependencies
    q = TrainingSet.open(intact).q_array('ep1').to_dask()
    graph = dict(q.__dask_graph__())
    assert len(graph) == q.npartitions == 15                    # one task per chunk
    assert all(not get_dependencies(graph, key) for key in graph)


# -- damaged chunks -------------------------------------------------------------------------
@pytest.mark.parametrize('key', ['t', 'U', 'Y', 'Q'])
@pytest.mark.parametrize('damage, words', [
    (lambda p: p.unlink(), r'chunk {name} is missing \(was the copy interrupted\?\)'),
    (_truncate, r'chunk {name} is truncated'),
    (_random_bytes, r'chunk {name} is truncated or overwritten'),
], ids=['deleted', 'truncated', 'random'])
def test_damaged_chunk_is_a_clear_error(damaged, key, damage, words):
    chunk = _chunks(damaged / 'episodes/ep1' / key)[-1]
    damage(chunk)
    ts = TrainingSet.open(damaged)
    with pytest.raises(DatasetError) as err:
        _read(ts, key)
    text = str(err.value)
    assert text.startswith(f'training set {damaged} is corrupt or incomplete: '
                           f"episode 'ep1', array {key}: ")
    assert re.search(words.format(name=chunk.name), text), text
    assert text.endswith(f'convert the bags again: soft-rom convert /rec/ep1 /rec/ep2 -o '
                         f'{damaged} --overwrite')
    assert '\n' not in text
    np.testing.assert_array_equal(ts['ep2'].Y, _episodes()[1].Y)     # the rest still reads


def test_damaged_q_fails_only_when_q_is_read(damaged):
    """ERA reads only inputs and outputs: a damaged Q does not stop it, any read of Q does."""
    _chunks(damaged / 'episodes/ep1/Q')[0].unlink()
    _chunks(damaged / 'episodes/ep1/Q')[-1].unlink()
    ts = TrainingSet.open(damaged)
    ep = ts['ep1']
    np.testing.assert_array_equal(ep.Y, _episodes()[0].Y)
    with pytest.raises(DatasetError, match=r'array Q: 2 of its 15 chunks are missing'):
        ep.Q[:, 8:16]                                         # chunks that are there
    with pytest.raises(DatasetError, match='array Q'):
        np.asarray(ts.q_array('ep1'))
    pytest.importorskip('dask.array')
    with pytest.raises(DatasetError, match='array Q'):
        ts.q_array('ep1').to_dask()


def test_scrambled_compressed_chunk_is_translated(damaged):
    """A chunk of the right length whose bytes are damaged: blosc's error, named."""
    _scramble_payload(_chunks(damaged / 'episodes/ep1/Y')[0])
    with pytest.raises(DatasetError, match=r"episode 'ep1', array Y: chunk 0.0 cannot be "
                                           r'decoded \(RuntimeError: error during blosc'):
        TrainingSet.open(damaged)['ep1']


# -- checksums (format version 3) -----------------------------------------------------------
def flip_low_mantissa_bits(chunk: Path, values: int = 10, bits: int = 16) -> None:
    """Flip the lowest ``bits`` mantissa bits of the first ``values`` float64 of a raw chunk.

    The values stay finite and within 1e-11 relative of what they were: read as data, they
    would pass every plausibility check.
    """
    data = np.frombuffer(bytearray(chunk.read_bytes()), dtype=np.uint8)
    words = data[:8 * values].view('<u8')
    words ^= np.uint64((1 << bits) - 1)
    chunk.write_bytes(data.tobytes())


def test_every_array_carries_a_checksum(intact):
    ts = TrainingSet.open(intact)
    assert ts.checksummed and ts.attrs['format_version'] == 3
    for key in ('t', 'U', 'Y', 'Q'):
        meta = json.loads((intact / 'episodes/ep1' / key / '.zarray').read_text())
        assert meta['filters'] == [{'id': 'crc32c'}], key
    for key in ('q_ref', 'y_ref'):
        meta = json.loads((intact / key / '.zarray').read_text())
        assert meta['filters'] == [{'id': 'crc32c'}], key


def test_flipped_mantissa_bits_are_refused_with_the_chunk_named(damaged):
    chunk = damaged / 'episodes/ep1/Q' / '1.1'               # rows 4..7, columns 8..15
    flip_low_mantissa_bits(chunk)
    ts = TrainingSet.open(damaged)
    ep = ts['ep1']
    np.testing.assert_array_equal(np.asarray(ep.Q[:, 0:8]), _episodes()[0].Q[:, 0:8])
    with pytest.raises(DatasetError) as err:
        ep.Q[:, 8:16]
    text = str(err.value)
    assert f"episode 'ep1', array Q: chunk {chunk.name} fails its CRC-32C checksum" in text
    assert '\n' not in text
    with pytest.raises(DatasetError, match=f'chunk {re.escape(chunk.name)} fails its CRC-32C'):
        ts.describe()                       # info reads every chunk


def test_chunk_deleted_after_the_check_is_refused_where_it_is_read(damaged):
    import copy
    ts = TrainingSet.open(damaged)
    q = ts.q_array('ep1')
    np.asarray(q[:, 0:8])                   # the first read checks every chunk
    # What a Dask worker gets: a copy made through the same __reduce_ex__ / __getstate__ /
    # __setstate__ that serializing it uses (without loading a pickle here).
    worker_copy = copy.deepcopy(q)
    chunk = damaged / 'episodes/ep1/Q' / _chunks(damaged / 'episodes/ep1/Q')[-1].name
    chunk.unlink()
    with pytest.raises(DatasetError, match=f'array Q: chunk {re.escape(chunk.name)} is '
                                           'missing'):
        q[:, 32:40]
    np.testing.assert_array_equal(np.asarray(q[:, 0:8]), _episodes()[0].Q[:, 0:8])
    assert worker_copy._array is None       # opened again where it is read
    with pytest.raises(DatasetError, match=f'chunk {re.escape(chunk.name)} is missing'):
        worker_copy[:, 0:8]                 # ... and checked there again


def _as_version_2(path: Path) -> None:
    """Rewrite a set as soft_rom wrote it before checksums: no filter, format version 2."""
    import zarr
    kw: dict = {'zarr_format': 2, 'config': {'write_empty_chunks': True}} \
        if int(zarr.__version__.split('.')[0]) >= 3 else {'write_empty_chunks': True}
    dirs = [p.parent for p in path.rglob('.zarray')]
    for d in dirs:
        old = zarr.open_array(str(d), mode='r')
        data, meta = np.asarray(old[...]), json.loads((d / '.zarray').read_text())
        shutil.rmtree(d)
        new = zarr.open_array(str(d), mode='w', shape=data.shape, chunks=tuple(meta['chunks']),
                              dtype='f8', order=meta['order'], fill_value=0.0,
                              compressor=None, **kw)
        new[...] = data
    attrs = json.loads((path / '.zattrs').read_text())
    attrs['format_version'] = 2
    (path / '.zattrs').write_text(json.dumps(attrs))


def test_sets_written_before_checksums_keep_loading(damaged, capsys):
    _as_version_2(damaged)
    ts = TrainingSet.open(damaged)
    assert not ts.checksummed and ts.describe()['checksums'] is None
    np.testing.assert_array_equal(np.asarray(ts['ep1'].Q[...]), _episodes()[0].Q)
    np.testing.assert_array_equal(ts['ep2'].Y, _episodes()[1].Y)
    assert main(['info', str(damaged)]) == 0
    out = capsys.readouterr().out
    assert '(format 2, no checksums)' in out and 'convert the bags again to add them' in out
    assert main(['info', str(_intact_copy(damaged))]) == 0
    out = capsys.readouterr().out
    assert '(format 3, checksums: CRC-32C per chunk)' in out and 'matching its checksum' in out


def _intact_copy(damaged: Path) -> Path:
    path = damaged.parent / 'fresh.zarr'
    TrainingSet.from_episodes(path, _episodes(), q_chunks=Q_CHUNKS)
    return path


def test_checksum_filter_removed_from_a_version_3_array_is_refused(damaged):
    meta_path = damaged / 'episodes/ep1/U/.zarray'
    meta = json.loads(meta_path.read_text())
    meta['filters'] = None
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"episode 'ep1', array U: its .zarray declares no "
                                           'crc32c checksum'):
        TrainingSet.open(damaged)['ep1']


@pytest.mark.parametrize('key', ['q_ref', 'y_ref'])
def test_damaged_reference_is_refused_at_open(damaged, key):
    _chunks(damaged / key)[0].unlink()
    with pytest.raises(DatasetError, match=f'array {key}: chunk 0 is missing'):
        TrainingSet.open(damaged)


def test_missing_arrays_are_refused(damaged):
    shutil.rmtree(damaged / 'episodes/ep2/Q')      # not a set without states: one that lost them
    with pytest.raises(DatasetError, match=r"episode 'ep2', array Q: it is missing, but the "
                                           "episode's metadata says it has states"):
        TrainingSet.open(damaged)
    shutil.rmtree(damaged / 'episodes/ep1/Y')      # the whole array, metadata and all
    with pytest.raises(DatasetError, match=r"episode 'ep1', array Y: it is missing \(was"):
        TrainingSet.open(damaged)
    shutil.rmtree(damaged / 'episodes/ep1')
    with pytest.raises(DatasetError, match=r"episode 'ep1': its group is missing"):
        TrainingSet.open(damaged)


def test_set_from_before_every_chunk_was_stored_names_the_likely_cause(damaged):
    attrs = json.loads((damaged / '.zattrs').read_text())
    del attrs['all_chunks_stored']
    (damaged / '.zattrs').write_text(json.dumps(attrs))
    _chunks(damaged / 'episodes/ep1/Y')[0].unlink()
    with pytest.raises(DatasetError, match=r'missing \(was the copy interrupted\? Sets '
                                           r'written with zarr 3 .* all zeros\)'):
        TrainingSet.open(damaged)['ep1']


# -- damaged attributes and metadata --------------------------------------------------------
@pytest.mark.parametrize('where, text, words', [
    ('episodes/ep1/.zattrs', '[1, 2]', "episode 'ep1'"),
    ('episodes/ep1/.zattrs', '{"metadata": [1]}', "'metadata' is \\[1\\], not a JSON object"),
    ('episodes/ep1/.zattrs', '{"metadata": {"t0_ns": "12:00"}}', "'t0_ns' is '12:00'"),
    ('episodes/ep1/.zattrs', '{"metadata": {"t0_ns": 1.5}}', "'t0_ns' is 1.5"),
    ('episodes/ep1/.zattrs', '{"meta', "episode 'ep1'"),
    ('episodes/ep1/Y/.zarray', '[]', "episode 'ep1', array Y"),
    ('episodes/ep1/Y/.zarray', '{"shape": [3', "episode 'ep1', array Y"),
    ('episodes/ep1/.zgroup', '[', "episode 'ep1'"),
], ids=['attrs-list', 'metadata-list', 't0-text', 't0-float', 'attrs-json', 'zarray-list',
        'zarray-json', 'zgroup-json'])
def test_damaged_episode_metadata_is_a_clear_error(damaged, where, text, words):
    (damaged / where).write_text(text)
    with pytest.raises(DatasetError, match=f'training set .* is corrupt or incomplete: '
                                           f'.*{words}') as err:
        ts = TrainingSet.open(damaged)
        ts['ep1']
    assert '\n' not in str(err.value)


@pytest.mark.parametrize('change, words', [
    ({'episode_names': [1, 2]}, "'episode_names' is missing or not a list of strings"),
    ({'episode_names': ['ep1', '../../etc']}, "'episode_names' holds episode name"),
    ({'episode_names': ['ep1', 'ep1']}, 'repeats names'),
    ({'output_units': 'm'}, "'output_units' is missing or not a list"),
    ({'provenance': ['bags']}, "'provenance' is \\['bags'\\], not a JSON object"),
    ({'format_version': True}, 'format version True'),
])
def test_damaged_root_attributes_are_refused(damaged, change, words):
    attrs = json.loads((damaged / '.zattrs').read_text())
    attrs.update(change)
    (damaged / '.zattrs').write_text(json.dumps(attrs))
    with pytest.raises(DatasetError, match=words):
        TrainingSet.open(damaged)


def test_root_attributes_as_a_list_are_refused(damaged):
    (damaged / '.zattrs').write_text('[1, 2]')
    with pytest.raises(DatasetError, match='not a readable zarr training set'):
        TrainingSet.open(damaged)


# -- through the command line: exit 2, one line, no traceback --------------------------------
def _model(tmp_path: Path) -> Path:
    from soft_rom.models import DiscreteModel
    return DiscreteModel(np.eye(2) * 0.5, np.ones((2, 2)), np.ones((3, 2)), dt=1e-3,
                         method='dmdc').save(tmp_path / 'm.npz')


@pytest.mark.parametrize('target, damage, verb, words', [
    ('episodes/ep1/Y', 'deleted', 'evaluate', "episode 'ep1', array Y: chunk .* is missing"),
    ('episodes/ep1/Y', 'deleted', 'era', "episode 'ep1', array Y: chunk .* is missing"),
    ('episodes/ep1/U', 'random', 'fit', "episode 'ep1', array U: chunk .* overwritten"),
    ('episodes/ep1/Q', 'truncated', 'fit', "episode 'ep1', array Q: chunk .* truncated"),
    ('episodes/ep1/Q', 'deleted', 'fit', "episode 'ep1', array Q: chunk .* is missing"),
    ('episodes/ep1/.zattrs', 'list', 'info', "episode 'ep1'"),
    ('episodes/ep1/Q', 'deleted', 'info', "episode 'ep1', array Q: chunk .* is missing"),
    ('episodes/ep1/U', 'truncated', 'info', "episode 'ep1', array U: chunk .* truncated"),
    ('episodes/ep1/.zattrs', 'list', 'evaluate', "episode 'ep1'"),
])
def test_cli_exit_2_with_one_line(damaged, tmp_path, capsys, target, damage, verb, words):
    path = damaged / target
    if damage == 'list':
        path.write_text('[1, 2]')
    else:
        chunk = _chunks(path)[-1]
        {'deleted': Path.unlink, 'random': _random_bytes, 'truncated': _truncate}[damage](chunk)
    argv = {'evaluate': ['evaluate', str(_model(tmp_path)), '--data', str(damaged)],
            'era': ['fit', str(damaged), '--method', 'era', '--era-episode', 'ep1', '--r', '2',
                    '-o', str(tmp_path / 'o')],
            'fit': ['fit', str(damaged), '--method', 'dmdc', '--r', '2', '--no-progress',
                    '-o', str(tmp_path / 'o')],
            'info': ['info', str(damaged)]}[verb]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and 'Traceback' not in err, err
    assert re.search(f'corrupt or incomplete: .*{words}', lines[0])
    assert not (tmp_path / 'o').exists()


# -- direct reads of the checksummed Q chunks --------------------------------------------
_bound = st.one_of(st.none(), st.integers(-45, 45))
_index = st.one_of(st.builds(slice, _bound, _bound, st.sampled_from([None, 1, 2, 3])),
                   st.integers(-40, 39), st.just(Ellipsis))   # zarr has no negative steps


def _whole_reads(*args):
    """direct._read_into, which must fill its buffers with the whole file (no fallback)."""
    assert _READ_INTO(*args)
    return True


_READ_INTO = direct._read_into


@settings(max_examples=300, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.one_of(_index, st.tuples(_index, _index)))
def test_any_key_reads_as_zarr_and_numpy_read_it(intact, key):
    # Q's raw checksummed chunks are read by read_region (one read, the CRC, the region
    # copied), every other key by zarr: either way, bit for bit what zarr and numpy give.
    ts = TrainingSet.open(intact)
    q, ref = ts.q_array('ep1'), _episodes()[0].Q
    try:
        want = ref[key]
    except IndexError:
        with pytest.raises(IndexError):
            q[key]
        return
    if isinstance(key, tuple) and key.count(Ellipsis) > 1:
        return                              # numpy allows one ellipsis; zarr raises its own
    zarr_read = q.array[key]
    for scatter_min, threads in ((direct.SCATTER_MIN, direct.CONCURRENCY), (0, 1), (0, 3)):
        # straight into the result (scatter_min 0: every run) or through a buffer; threads
        with mock.patch.object(direct, 'SCATTER_MIN', scatter_min), \
                mock.patch.object(direct, 'CONCURRENCY', threads), \
                mock.patch.object(direct, '_read_into', _whole_reads):
            got = q[key]
        assert q._stored is not None        # read directly where the key allows it
        assert isinstance(got, np.ndarray) or np.ndim(want) == 0
        assert np.shape(got) == np.shape(want)
        np.testing.assert_array_equal(got, want)
        np.testing.assert_array_equal(got, zarr_read)
        if np.ndim(got) == 2:               # in the stored order, as zarr gives it
            assert got.flags.f_contiguous == zarr_read.flags.f_contiguous


def test_chunk_overwritten_after_the_check_is_refused_with_its_name(damaged):
    ts = TrainingSet.open(damaged)
    q = ts.q_array('ep1')
    np.asarray(q[:, 0:8])                   # the first read checks every chunk
    name = _chunks(damaged / 'episodes/ep1/Q')[4].name
    _truncate(damaged / 'episodes/ep1/Q' / name, 40)
    with pytest.raises(DatasetError, match=rf'array Q: chunk {re.escape(name)} is truncated '
                                           r'or overwritten \(40 bytes; a chunk has 260\)'):
        q[...]
    flip_low_mantissa_bits(damaged / 'episodes/ep1/Q' / _chunks(damaged / 'episodes/ep1/Q')[0]
                           .name, values=1, bits=1)
    with pytest.raises(DatasetError, match=r'chunk 0\.0 fails its CRC-32C checksum'):
        q[0, 0]                             # one value of a chunk: the whole chunk is checked
    with mock.patch.object(direct, 'SCATTER_MIN', 0), \
            pytest.raises(DatasetError, match=r'chunk 0\.0 fails its CRC-32C checksum'):
        q[0:4, 0:8]                         # read straight into the result: refused too
    np.testing.assert_array_equal(q[4:8, 8:16], _episodes()[0].Q[4:8, 8:16])   # others read
