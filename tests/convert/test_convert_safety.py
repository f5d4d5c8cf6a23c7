"""Converter data safety: each case of the adversarial audit, in the exact situation found.

Pairing with a 30 s input prefix and one missing state; a lying ``metadata.yaml``; bad first
messages that used to fix a size; ``--overwrite`` onto a recording; a kill between the two
renames of a replace and in the middle of a run; a huge grid from ``--dt 1e-12``.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
import signal
import subprocess
import sys
import time

from _rig import _header, _pose_array, T, T0_NS, write_messages
import numpy as np
import pytest
import yaml

from soft_rom.cli import main
from soft_rom.convert import BagMapping, convert, read_episode
from soft_rom.dataset import TrainingSet
from soft_rom.errors import BagError, OutputExistsError

K = 300
DT_NS = 1_000_000
N_PTS, N_NODES = 3, 2
FP = T['sensor_msgs/msg/FluidPressure']
ARR = T['std_msgs/msg/Float64MultiArray']
DIM = T['std_msgs/msg/MultiArrayDimension']
E = np.random.default_rng(1).standard_normal((2 * N_PTS, 3 * N_NODES))


def _array(values, dims=None):
    values = np.ascontiguousarray(values, dtype=np.float64)
    dims = dims or [('values', values.size)]
    layout = T['std_msgs/msg/MultiArrayLayout'](
        dim=[DIM(label=lab, size=int(n), stride=int(n)) for lab, n in dims], data_offset=0)
    return ARR(layout=layout, data=values)


def _signals(k=K, seed=0):
    rng = np.random.default_rng(seed)
    Q = np.cumsum(rng.normal(size=(3 * N_NODES, k)), axis=1) * 1e-3
    U = rng.normal(size=(2, k))
    return U, Q, E @ Q


def _bag(path, *, k=K, prefix_s=0.0, skip_state=(), hooks=None, storage='mcap',
         pressures='chambers', seed=0):
    """Inputs (2 chambers, or one 2-value array), centerline ``Y = E Q`` and states, 1 kHz.

    ``hooks[(kind, j)]`` replaces message ``j`` of ``kind`` ('u', 'y', 'q') by the
    ``(stamp_ns, msg)`` it returns (or drops it when it returns None).
    """
    U, Q, Y = _signals(k, seed)
    hooks = hooks or {}
    msgs = []
    n_pre = int(round(prefix_s * 1000))
    for j in range(-n_pre, k):                       # inputs, possibly 30 s early
        ns = T0_NS + j * DT_NS
        u = U[:, max(j, 0)]
        if pressures == 'chambers':
            for i in range(2):
                msgs.append((ns, f'/soft_robot/pressure/chamber_{i + 1}', FP.__msgtype__,
                             FP(header=_header(ns), fluid_pressure=float(u[i]), variance=0.0)))
        else:
            item = hooks.get(('u', j), lambda ns, u=u: (ns, _array(u)))(ns)
            if item is not None:
                msgs.append((item[0], '/soft_robot/pressures', ARR.__msgtype__, item[1]))
    for j in range(k):
        ns = T0_NS + j * DT_NS
        pts = np.stack([Y[:N_PTS, j], np.zeros(N_PTS), Y[N_PTS:, j]], axis=1)
        item = hooks.get(('y', j), lambda ns, pts=pts: (ns, _pose_array(ns, pts)))(ns)
        if item is not None:
            msgs.append((item[0] if len(item) == 2 else item[2], '/soft_robot/centerline',
                         'geometry_msgs/msg/PoseArray', item[1]))
        if j in skip_state:
            continue
        q = Q[:, j]
        item = hooks.get(('q', j), lambda ns, q=q: (ns, _array(q, [('nodes', N_NODES),
                                                                    ('xyz', 3)])))(ns)
        if item is not None:
            msgs.append((item[0], '/soft_robot/state', ARR.__msgtype__, item[1]))
    write_messages(Path(path), msgs, storage)
    return U, Q, Y


def _hidden(folder):
    return sorted(p.name for p in Path(folder).iterdir() if p.name.startswith('.'))


def _tree_digest(folder):
    h = hashlib.sha256()
    for p in sorted(Path(folder).rglob('*')):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


# -- pairing ------------------------------------------------------------------------------
def test_input_prefix_and_one_missing_state_keep_every_sample_aligned(tmp_path):
    bag = tmp_path / 'rec'
    U, Q, Y = _bag(bag, prefix_s=30.0, skip_state={100})
    ts, (rep,) = convert([bag], tmp_path / 'o.zarr', progress=False)
    ep = ts['rec']
    Qc = np.asarray(ep.Q[...])
    assert ep.n_samples == K and ts.t0_ns('rec') == T0_NS          # not the input start
    # every sample pairs an output with the state of the same stamp: Y = E Q throughout
    np.testing.assert_allclose(ep.Y, E @ Qc, rtol=0, atol=1e-12)
    keep = np.arange(K) != 100
    np.testing.assert_array_equal(Qc[:, keep], Q[:, keep])
    np.testing.assert_allclose(Qc[:, 100], 0.5 * (Q[:, 99] + Q[:, 101]), atol=1e-15)
    out = rep.topics['/soft_robot/centerline']
    assert out.dropped == {'no state message within 0.45 output periods': 1}
    assert out.grid_gap_interpolated == 1 and out.grid_exact == K - 1
    assert 'stamp 1700000000223456789 ns' in out.examples[0]


def test_lying_metadata_yaml_changes_nothing(tmp_path):
    honest, lying = tmp_path / 'honest', tmp_path / 'lying'
    _bag(honest, storage='sqlite3', prefix_s=0.5, skip_state={40})
    _bag(lying, storage='sqlite3', prefix_s=0.5, skip_state={40})
    meta_file = lying / 'metadata.yaml'
    meta = yaml.safe_load(meta_file.read_text())
    info = meta['rosbag2_bagfile_information']
    info['starting_time']['nanoseconds_since_epoch'] -= 30 * 10 ** 9    # 30 s too early
    info['duration']['nanoseconds'] //= 7
    info['message_count'] //= 3
    for t in info['topics_with_message_count']:
        t['message_count'] = max(1, t['message_count'] // 3)
    meta_file.write_text(yaml.safe_dump(meta))
    a, _ = convert([honest], tmp_path / 'a.zarr', progress=False)
    b, _ = convert([lying], tmp_path / 'b.zarr', progress=False)
    ea, eb = a['honest'], b['lying']
    np.testing.assert_array_equal(ea.t, eb.t)
    np.testing.assert_array_equal(ea.U, eb.U)
    np.testing.assert_array_equal(ea.Y, eb.Y)
    np.testing.assert_array_equal(np.asarray(ea.Q[...]), np.asarray(eb.Q[...]))
    assert a.t0_ns('honest') == b.t0_ns('lying') == T0_NS


# -- bad first messages -------------------------------------------------------------------
def _pose0(ns):
    return ns, T['geometry_msgs/msg/PoseArray'](header=_header(ns), poses=[])


@pytest.mark.parametrize('case', ['empty first state', 'first centerline with 0 poses',
                                  'first pressure array of length 5',
                                  'first stamp far ahead'])
def test_bad_first_message_does_not_fix_a_size(tmp_path, case):
    hooks = {
        'empty first state': {('q', 0): lambda ns: (ns, _array(np.zeros(0), [('nodes', 0)]))},
        'first centerline with 0 poses': {('y', 0): _pose0},
        'first pressure array of length 5': {('u', 0): lambda ns: (ns, _array(np.ones(5)))},
        # a clock glitch: the first frame is stamped 1000 s ahead (logged on time)
        'first stamp far ahead': {('y', 0): lambda ns: (ns + 10 ** 12, _pose_array(
            ns + 10 ** 12, np.zeros((N_PTS, 3))), ns)},
    }[case]
    bag = tmp_path / 'rec'
    U, Q, Y = _bag(bag, k=50, hooks=hooks, pressures='array' if 'pressure' in case
                   else 'chambers')
    ts, (rep,) = convert([bag], tmp_path / 'o.zarr', progress=False)
    ep = ts['rec']
    assert len(ts.input_names) == 2 and len(ts.output_names) == 2 * N_PTS
    assert ts.n_states == 3 * N_NODES
    assert ep.n_samples == 49                       # only the first sample is lost
    np.testing.assert_array_equal(np.asarray(ep.Q[...]), Q[:, 1:])
    np.testing.assert_array_equal(ep.Y[:N_PTS], Y[:N_PTS, 1:])
    dropped = {k: v for r in rep.topics.values() for k, v in r.dropped.items()}
    reason = {'empty first state': '0 values instead of 6',
              'first centerline with 0 poses': 'fewer than 3 points',
              'first pressure array of length 5': '5 values instead of 2',
              'first stamp far ahead': 'stamp more than 1 s away from its log time'}[case]
    assert dropped[reason] == 1


def test_descending_header_stamps_are_refused_with_the_fix(tmp_path):
    hooks = {('y', j): (lambda ns, j=j: (T0_NS + (60 - j) * DT_NS, _pose_array(
        T0_NS + (60 - j) * DT_NS, np.zeros((N_PTS, 3))), ns)) for j in range(50)}
    bag = tmp_path / 'rec'
    _bag(bag, k=50, hooks=hooks)
    with pytest.raises(BagError, match=r'header stamps go backwards in 100% .*stamps: log'):
        convert([bag], tmp_path / 'o.zarr', progress=False)
    assert not (tmp_path / 'o.zarr').exists() and not _hidden(tmp_path)
    ep, _ = read_episode(bag, BagMapping.from_dict({'time': {'stamps': 'log'}}),
                         include_state=True)
    assert ep.n_samples == 50


def test_log_times_that_do_not_advance_are_named_as_log_times(tmp_path):
    # a recorder whose clock stood still: every centerline logged at the same time, timed by
    # log time as the mapping asks; the message must not blame header stamps nor offer 'log'
    hooks = {('y', j): (lambda ns, j=j: (ns, _pose_array(ns, np.full((N_PTS, 3), 1e-3 * j)),
                                         T0_NS)) for j in range(50)}
    bag = tmp_path / 'rec'
    _bag(bag, k=50, hooks=hooks)
    with pytest.raises(BagError, match=r'log times do not advance in 100% .*broken') as err:
        convert([bag], tmp_path / 'o.zarr', BagMapping.from_dict({'time': {'stamps': 'log'}}),
                progress=False)
    assert 'header stamps' not in str(err.value).split(';')[0]
    assert not (tmp_path / 'o.zarr').exists() and not _hidden(tmp_path)


@pytest.mark.parametrize('stamps', ['log', 'header'])
def test_log_times_beyond_int64_are_refused_in_one_line(tmp_path, capsys, stamps):
    # an MCAP stores log times as uint64; ROS 2 time is int64 ns: from the 21st message on
    # the log times are 2**63 and more (the header stamps are ordinary epoch stamps)
    start = 2 ** 63 - 20 * DT_NS
    hooks = {('y', j): (lambda ns, j=j: (ns, _pose_array(ns, np.zeros((N_PTS, 3))),
                                         start + j * DT_NS)) for j in range(50)}
    bag = tmp_path / 'rec'
    _bag(bag, k=50, hooks=hooks)
    mapping = tmp_path / 'map.yaml'
    mapping.write_text(f'time:\n  stamps: {stamps}\n')
    out = tmp_path / 'o.zarr'
    assert main(['convert', str(bag), '--mapping', str(mapping), '-o', str(out),
                 '--quiet']) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f'/soft_robot/centerline in bag {bag}: log time {2 ** 63} ns is beyond' in err
    assert 'Traceback' not in err and 'a bug' not in err
    assert not out.exists() and not _hidden(tmp_path)


# -- overwrite ----------------------------------------------------------------------------
def test_overwrite_onto_a_bag_or_foreign_folder_is_refused_untouched(tmp_path, capsys):
    rec = tmp_path / 'rec'
    rec.mkdir()
    _bag(rec / 'ep1', k=50)
    (rec / 'notes.txt').write_text('lab book')
    before = _tree_digest(rec)
    for out in (rec, rec / 'ep1'):
        assert main(['convert', str(rec / 'ep1'), '-o', str(out), '--overwrite',
                     '--quiet']) == 2
        err = capsys.readouterr().err.strip()
        assert 'not written by soft_rom' in err and len(err.splitlines()) == 1
    assert _tree_digest(rec) == before and not _hidden(tmp_path)
    out = tmp_path / 'o.zarr'           # a set soft_rom wrote is replaced
    assert main(['convert', str(rec / 'ep1'), '-o', str(out), '--quiet']) == 0
    assert main(['convert', str(rec / 'ep1'), '-o', str(out), '--quiet']) == 2
    assert 'exists already' in capsys.readouterr().err
    assert main(['convert', str(rec / 'ep1'), '-o', str(out), '--overwrite', '--quiet']) == 0
    assert TrainingSet.open(out)['ep1'].n_samples == 50


def test_overwrite_keeps_a_recording_put_inside_the_set_it_would_replace(tmp_path, capsys):
    """The audit's case: the input bag moved into the training set, then converted onto it.

    ``--overwrite`` used to delete the set with the bag in it (exit 0); so a model file that
    ``soft-rom fit`` wrote into the set (fit now refuses to). The set's list of its own files
    stops both.
    """
    out = tmp_path / 'copy.zarr'
    _bag(tmp_path / 'rec1', k=50)
    assert main(['convert', str(tmp_path / 'rec1'), '-o', str(out), '--quiet']) == 0
    os.rename(tmp_path / 'rec1', out / 'rec1')
    before = _tree_digest(out)
    assert main(['convert', str(out / 'rec1'), '-o', str(out), '--overwrite', '--quiet']) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'did not write there (rec1/' in err, err
    assert _tree_digest(out) == before and read_episode(out / 'rec1')[0].n_samples == 50
    os.rename(out / 'rec1', tmp_path / 'rec1')  # moved out: the set is replaced as before
    assert main(['convert', str(tmp_path / 'rec1'), '-o', str(out), '--overwrite',
                 '--quiet']) == 0
    assert main(['fit', str(out), '--method', 'dmdc', '--r', '2', '-o', str(out),
                 '--quiet']) == 2                  # fit no longer writes into the set ...
    assert 'inside the training set' in capsys.readouterr().err
    assert main(['fit', str(out), '--method', 'dmdc', '--r', '2', '-o', str(tmp_path / 'm'),
                 '--quiet']) == 0
    os.rename(tmp_path / 'm' / 'copy_dmdc_r2.npz', out / 'copy_dmdc_r2.npz')   # ... a user may
    assert main(['convert', str(tmp_path / 'rec1'), '-o', str(out), '--overwrite',
                 '--quiet']) == 2
    assert 'copy_dmdc_r2.npz' in capsys.readouterr().err
    assert (out / 'copy_dmdc_r2.npz').is_file()


def test_failed_swap_restores_the_old_set(tmp_path, monkeypatch):
    from soft_rom import outputs
    bag = tmp_path / 'rec'
    _bag(bag, k=50)
    out = tmp_path / 'o.zarr'
    convert([bag], out, BagMapping(dt=0.002), progress=False)
    monkeypatch.setattr(outputs, '_exchange', lambda a, b: False)
    real = os.rename

    def rename(a, b):
        if str(b) == str(out):                  # the second rename: stage -> out
            raise OSError(28, 'No space left on device')
        real(a, b)
    monkeypatch.setattr(os, 'rename', rename)
    with pytest.raises(OSError, match='No space'):
        convert([bag], out, overwrite=True, progress=False)
    monkeypatch.setattr(os, 'rename', real)
    assert TrainingSet.open(out)['rec'].n_samples == 25        # the old one, whole
    assert _hidden(tmp_path) == []


_KILL_BETWEEN_RENAMES = """
import os, sys
from soft_rom import outputs
from soft_rom.convert import convert
outputs._exchange = lambda a, b: False            # the two-rename path
real = os.rename
def rename(a, b):
    real(a, b)
    if '.soft_rom-old-' in str(b):                 # out parked, new one not yet in place
        os._exit(9)
os.rename = rename
convert([sys.argv[1]], sys.argv[2], overwrite=True, progress=False)
"""

_KILL_MID_RUN = """
import sys, time
from soft_rom.convert import stream
slow = stream.BagConverter._emit
def emit(self, *a):
    time.sleep(0.005)
    return slow(self, *a)
stream.BagConverter._emit = emit
from soft_rom.convert import convert
convert([sys.argv[1]], sys.argv[2], overwrite=True, progress=False)
"""


def test_kill_between_renames_then_recovered(tmp_path):
    bag = tmp_path / 'rec'
    _bag(bag, k=60)
    out = tmp_path / 'o.zarr'
    convert([bag], out, BagMapping(dt=0.002), progress=False)
    proc = subprocess.run([sys.executable, '-c', _KILL_BETWEEN_RENAMES, str(bag), str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 9, proc.stderr
    assert not out.exists()                                  # killed between the renames
    assert any('.soft_rom-old-' in n for n in _hidden(tmp_path))
    ts = TrainingSet.open(out)                               # the old set is put back
    assert ts['rec'].n_samples == 30 and not _hidden(tmp_path)


def test_kill_mid_run_leaves_nothing_valid_and_is_cleaned(tmp_path):
    bag = tmp_path / 'rec'
    _bag(bag, k=K)
    out = tmp_path / 'o.zarr'
    proc = subprocess.Popen([sys.executable, '-c', _KILL_MID_RUN, str(bag), str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not _hidden(tmp_path) and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    stages = _hidden(tmp_path)
    assert len(stages) == 1 and not out.exists()
    with pytest.raises(Exception, match='not a soft_rom training set|not a readable'):
        TrainingSet.open(tmp_path / stages[0])               # a partial run is not valid
    convert([bag], out, progress=False)                       # the next run cleans it up
    assert _hidden(tmp_path) == [] and TrainingSet.open(out)['rec'].n_samples == K


# -- grid size ----------------------------------------------------------------------------
def test_huge_grid_is_refused_before_writing(tmp_path, capsys, monkeypatch):
    bag = tmp_path / 'rec'
    _bag(bag, k=50)
    out = tmp_path / 'o.zarr'
    t0 = time.perf_counter()
    assert main(['convert', str(bag), '-o', str(out), '--dt', '1e-12', '--quiet']) == 2
    assert time.perf_counter() - t0 < 30
    err = capsys.readouterr().err.strip()
    assert 'finer than the recording supports' in err and '--dt >= 0.0001 s' in err
    assert len(err.splitlines()) == 1
    assert not out.exists() and not _hidden(tmp_path)
    from soft_rom import outputs
    monkeypatch.setattr(outputs.shutil, 'disk_usage',
                        lambda p: type('U', (), {'free': 10_000})())
    # not enough disk is a run-time refusal (exit 1), like every resource refusal
    assert main(['convert', str(bag), '-o', str(out), '--dt', '0.0002', '--quiet']) == 1
    assert 'needs about' in capsys.readouterr().err
    assert not out.exists() and not _hidden(tmp_path)
    with pytest.raises(OutputExistsError):
        out.mkdir()
        convert([bag], out, progress=False)


def test_stamps_drifting_from_log_time_are_kept(tmp_path):
    # a simulation at half real time, recorded with wall-clock log times: the stamps drift
    # 0.5 ms per sample (0.15 s over the bag) away from the log times, and start 40 s apart
    hooks = {('y', j): (lambda ns, j=j: (ns, _pose_array(ns, np.zeros((N_PTS, 3))),
                                         ns + 40 * 10 ** 9 + j * 500_000)) for j in range(K)}
    bag = tmp_path / 'sim'
    _bag(bag, hooks=hooks)
    ep, rep = read_episode(bag, include_state=True)
    assert ep.n_samples == K and not rep.topics['/soft_robot/centerline'].dropped
