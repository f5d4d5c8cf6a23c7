"""Tests of soft_rom.dataset: the zarr training set (round trip, laziness, atomicity, errors)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.dataset import FORMAT, TrainingSet, TrainingSetWriter
from soft_rom.errors import DatasetError, DimensionError, OutputExistsError

NAMES = dict(input_names=['p1', 'p2'], input_units=['Pa', 'Pa'],
             output_names=['x1', 'z1', 'x2'], output_units=['m', 'm', 'm'])


def _episode(k, n=None, seed=0, name='ep'):
    rng = np.random.default_rng(seed)
    t = 0.001 * np.arange(1, k + 1)
    Q = None if n is None else rng.normal(size=(n, k))
    return Episode(t=t, U=rng.normal(size=(2, k)), Y=rng.normal(size=(3, k)), Q=Q, name=name,
                   metadata={'source_bag': f'/bags/{name}', 'n': np.int64(3)})


def test_streamed_round_trip_bit_exact_and_lazy(tmp_path):
    path = tmp_path / 'train.zarr'
    e1, e2 = _episode(75, n=11, seed=1, name='ep1'), _episode(40, n=11, seed=2, name='ep2')
    with TrainingSetWriter(path, **NAMES, attrs={'provenance': {'bags': ['a']}},
                           q_chunks=(4, 8)) as w:
        for ep in (e1, e2):
            ew = w.begin_episode(ep.name, n_states=11, metadata=ep.metadata)
            for a, b in ((0, 3), (3, 20), (20, ep.n_samples)):  # uneven appends
                ew.append(ep.t[a:b], ep.U[:, a:b], ep.Y[:, a:b], ep.Q[:, a:b])
    ts = TrainingSet.open(path)
    assert ts.episode_names == ['ep1', 'ep2'] and len(ts) == 2
    assert ts.input_names == ['p1', 'p2'] and ts.output_units == ['m'] * 3
    assert ts.attrs['format'] == FORMAT and ts.provenance == {'bags': ['a']}
    for ref, got in zip((e1, e2), ts.episodes()):
        np.testing.assert_array_equal(got.t, ref.t - ref.t[0])     # from the episode start
        assert got.metadata['t0_ns'] == 1_000_000                  # the first time, in ns
        np.testing.assert_array_equal(got.U, ref.U)
        np.testing.assert_array_equal(got.Y, ref.Y)
        assert not isinstance(got.Q, np.ndarray)            # lazy zarr array
        assert tuple(got.Q.chunks) == (4, 8)
        np.testing.assert_array_equal(got.Q[:, 5:29], ref.Q[:, 5:29])
        np.testing.assert_array_equal(np.asarray(ts.q_array(ref.name)[...]), ref.Q)
        assert got.metadata['source_bag'] == ref.metadata['source_bag']
        assert got.metadata['n_samples'] == ref.n_samples
    np.testing.assert_array_equal(ts.q_ref, e1.Q[:, 0])    # default reference
    np.testing.assert_array_equal(ts.y_ref, e1.Y[:, 0])
    assert ts.n_states == 11
    assert not list(tmp_path.glob('.*'))                    # no temporary left


def test_epoch_start_is_integer_nanoseconds(tmp_path):
    t0_ns = 1_700_000_000_123_456_789
    ep = Episode(t=0.001 * np.arange(100), U=np.zeros((2, 100)), Y=np.ones((3, 100)),
                 metadata={'t0_ns': t0_ns})
    ts = TrainingSet.from_episodes(tmp_path / 't.zarr', [ep], **NAMES)
    assert ts.t0_ns('ep1') == t0_ns and isinstance(ts.t0_ns('ep1'), int)
    assert ts['ep1'].is_uniform(rtol=1e-12) and ts['ep1'].t[0] == 0.0
    assert ts.describe()['episodes']['ep1']['t0_ns'] == t0_ns


def test_dask_reads_q(tmp_path):
    da = pytest.importorskip('dask.array')
    ep = _episode(50, n=7)
    ts = TrainingSet.from_episodes(tmp_path / 't.zarr', [ep], q_chunks=(3, 16))
    q = da.from_zarr(str(tmp_path / 't.zarr'), component='episodes/ep/Q')
    assert q.chunks[1][0] == 16
    np.testing.assert_allclose(q.sum(axis=1).compute(), ep.Q.sum(axis=1), rtol=1e-13)
    assert ts.input_names == ['u1', 'u2'] and ts.output_names == ['y1', 'y2', 'y3']


def test_explicit_reference_and_no_state(tmp_path):
    ep = _episode(10)
    ts = TrainingSet.from_episodes(tmp_path / 't.zarr', [ep], y_ref=[1.0, 2.0, 3.0], **NAMES)
    assert ts.q_ref is None and ts.n_states is None and ts['ep'].Q is None
    np.testing.assert_array_equal(ts.y_ref, [1.0, 2.0, 3.0])
    with pytest.raises(DatasetError, match='no states'):
        ts.q_array('ep')
    with pytest.raises(DatasetError, match="no episode 'nope'"):
        ts['nope']


def test_failure_leaves_nothing_and_overwrite_is_atomic(tmp_path):
    path = tmp_path / 't.zarr'
    with pytest.raises(DimensionError):
        with TrainingSetWriter(path, **NAMES) as w:
            ew = w.begin_episode('ep')
            ew.append([0.0, 0.1], np.zeros((2, 2)), np.zeros((3, 2)))
            ew.append([0.05], np.zeros((2, 1)), np.zeros((3, 1)))   # goes back in time
    assert not path.exists() and list(tmp_path.iterdir()) == []
    TrainingSet.from_episodes(path, [_episode(5)], **NAMES)
    with pytest.raises(OutputExistsError, match='exists already'):
        TrainingSetWriter(path, **NAMES)
    with pytest.raises(DimensionError, match='NaN'):
        with TrainingSetWriter(path, overwrite=True, **NAMES) as w:
            ew = w.begin_episode('ep')
            ew.append([0.0], np.zeros((2, 1)), np.full((3, 1), np.nan))
    assert TrainingSet.open(path)['ep'].n_samples == 5           # old one intact
    TrainingSet.from_episodes(path, [_episode(8)], overwrite=True, **NAMES)
    assert TrainingSet.open(path)['ep'].n_samples == 8
    assert [p.name for p in tmp_path.iterdir()] == ['t.zarr']
    foreign = tmp_path / 'f.zarr'          # a zarr folder soft_rom did not write
    foreign.mkdir()
    (foreign / '.zgroup').write_text('{"zarr_format": 2}')
    with pytest.raises(OutputExistsError, match='not written by soft_rom'):
        TrainingSetWriter(foreign, overwrite=True, **NAMES)
    assert sorted(p.name for p in foreign.iterdir()) == ['.zgroup']


def test_legacy_unmarked_training_set_is_overwritable(tmp_path):
    from soft_rom.outputs import MARKER
    path = tmp_path / 't.zarr'
    TrainingSet.from_episodes(path, [_episode(5)], **NAMES)
    (path / MARKER).unlink()               # as written by soft_rom before the marker
    TrainingSet.from_episodes(path, [_episode(8)], overwrite=True, **NAMES)
    assert TrainingSet.open(path)['ep'].n_samples == 8


def test_writer_argument_errors(tmp_path):
    with TrainingSetWriter(tmp_path / 'a.zarr', **NAMES) as w:
        ew = w.begin_episode('e1')
        with pytest.raises(DimensionError):
            ew.append([0.0], np.zeros((3, 1)), np.zeros((3, 1)))     # m = 2 expected
        ew.append([0.0], np.zeros((2, 1)), np.zeros((3, 1)), np.zeros((4, 1)))
        with pytest.raises(DimensionError, match='every append'):
            ew.append([1.0], np.zeros((2, 1)), np.zeros((3, 1)))
        with pytest.raises(DimensionError, match='4 rows'):
            ew.append([1.0], np.zeros((2, 1)), np.zeros((3, 1)), np.zeros((5, 1)))
        with pytest.raises(DatasetError, match='unique'):
            w.begin_episode('e1')
        with pytest.raises(DatasetError, match='not valid'):
            w.begin_episode('a/b')
    with pytest.raises(DatasetError, match='no samples'):
        with TrainingSetWriter(tmp_path / 'b.zarr', **NAMES) as w:
            w.begin_episode('empty')
    assert not (tmp_path / 'b.zarr').exists()


def test_open_refuses_missing_foreign_and_unknown_version(tmp_path):
    with pytest.raises(DatasetError, match='does not exist'):
        TrainingSet.open(tmp_path / 'none.zarr')
    path = tmp_path / 't.zarr'
    TrainingSet.from_episodes(path, [_episode(5)], **NAMES)
    attrs_file = path / '.zattrs'
    attrs = json.loads(attrs_file.read_text())
    attrs['format_version'] = 99
    attrs['provenance'] = {'bags': ['/rec/a', '/rec/b']}
    attrs_file.write_text(json.dumps(attrs))
    with pytest.raises(DatasetError, match=r'version 99.*soft-rom convert /rec/a /rec/b -o '):
        TrainingSet.open(path)
    attrs['format_version'] = 1
    attrs['format'] = 'something.else'
    attrs_file.write_text(json.dumps(attrs))
    with pytest.raises(DatasetError, match='not a soft_rom training set'):
        TrainingSet.open(path)
    (tmp_path / 'junk').mkdir()
    (tmp_path / 'junk' / '.zgroup').write_text('{not json')
    with pytest.raises(DatasetError):
        TrainingSet.open(tmp_path / 'junk')


def _as_v1(path, t_abs):
    """Rewrite a set as format version 1 wrote it: absolute times, no t0_ns."""
    import zarr
    root = zarr.open_group(str(path), mode='r+')
    root['episodes/ep/t'][...] = t_abs
    meta = dict(root['episodes/ep'].attrs['metadata'])
    meta.pop('t0_ns', None)
    root['episodes/ep'].attrs['metadata'] = meta
    attrs = json.loads((path / '.zattrs').read_text())
    attrs.update(format_version=1, provenance={'bags': ['/rec/lab 1']})
    (path / '.zattrs').write_text(json.dumps(attrs))


def test_version_1_read_or_refused_with_the_command(tmp_path):
    path = tmp_path / 'old.zarr'
    TrainingSet.from_episodes(path, [_episode(20)], **NAMES)
    _as_v1(path, 0.5 + 0.001 * np.arange(20))          # small stamps: exact, read
    ts = TrainingSet.open(path)
    np.testing.assert_allclose(ts['ep'].t, 0.001 * np.arange(20), atol=1e-15)
    assert ts['ep'].is_uniform() and ts.t0_ns('ep') == 500_000_000
    _as_v1(path, 1.7e9 + 0.001 * np.arange(20))        # epoch stamps: lost, refused
    with pytest.raises(DatasetError, match=r"absolute times.*soft-rom convert '/rec/lab 1' "
                                           r'-o .*old.zarr --overwrite'):
        TrainingSet.open(path)


def test_q_has_one_write_path_and_chunk_files_match_zarr(tmp_path):
    import zarr
    ep = _episode(45, n=9)
    ts = TrainingSet.from_episodes(tmp_path / 'a.zarr', [ep], q_chunks=(4, 8))
    np.testing.assert_array_equal(np.asarray(ts.q_array('ep')[...]), ep.Q)
    from soft_rom.dataset.checksum import codec
    # zarr's own encoding with the crc32c filter: the same bytes, checksums included
    kw = {'zarr_format': 2} if int(zarr.__version__.split('.')[0]) >= 3 else {}
    ref = zarr.open_array(str(tmp_path / 'z.zarr'), mode='w', shape=ep.Q.shape, chunks=(4, 8),
                          dtype='f8', order='F', compressor=None, fill_value=0.0,
                          filters=[codec()], **kw)
    ref[...] = ep.Q
    names = sorted(p.name for p in (tmp_path / 'a.zarr/episodes/ep/Q').iterdir()
                   if p.name != '.zarray')
    assert names == sorted(p.name for p in (tmp_path / 'z.zarr').iterdir()
                           if p.name != '.zarray')
    for name in names:
        assert (tmp_path / 'a.zarr/episodes/ep/Q' / name).read_bytes() == \
            (tmp_path / 'z.zarr' / name).read_bytes()


def test_episodes_of_one_name_given_as_a_string(tmp_path):
    """``ts.episodes('ep12')`` iterated the letters: "no episode 'e'"."""
    ts = TrainingSet.from_episodes(tmp_path / 't.zarr', [_episode(10, name='ep12'),
                                                         _episode(12, seed=1, name='ep3')],
                                   **NAMES)
    (one,) = ts.episodes('ep12')
    assert one.name == 'ep12' and one.n_samples == 10
    assert [e.name for e in ts.episodes(['ep3', 'ep12'])] == ['ep3', 'ep12']


def test_one_unit_string_is_every_channel_s_unit(tmp_path):
    """``input_units='Pa'`` for two inputs was stored as units ['P', 'a']."""
    ts = TrainingSet.from_episodes(tmp_path / 't.zarr', [_episode(10)], input_units='Pa',
                                   output_units='m')
    assert ts.input_units == ['Pa', 'Pa'] and ts.output_units == ['m'] * 3
    with pytest.raises(DatasetError, match='input_names and input_units must be non-empty '
                                           'and of equal length; got 1 and 2'):
        TrainingSet.from_episodes(tmp_path / 'u.zarr', [_episode(10)], input_names='p',
                                  input_units=['Pa', 'Pa'])
