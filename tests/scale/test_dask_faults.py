"""Faults on a real dask.distributed cluster: scheduler and workers as subprocesses.

A chunk that only a worker finds missing, chunks with flipped mantissa bits, a worker killed
in the middle of the POD, a scheduler killed in the middle of it, a scheduler that is not
there. The workers read the training set themselves (as on a cluster sharing a file system);
``_slow_reads.py`` (a worker preload) makes each block read last long enough to kill a
process in the middle of a pass.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
import re
import signal
import socket
import subprocess
import sys
import time

from _scale_data import system_episodes
import numpy as np
import pytest

from soft_rom.dataset import TrainingSet
from soft_rom.errors import DatasetError
from soft_rom.models import load_model

distributed = pytest.importorskip('dask.distributed')

HERE = Path(__file__).resolve().parent
PRELOAD = str(HERE / '_slow_reads.py')


class Cluster:
    """``dask scheduler`` and ``n`` workers (``--nthreads 1``, no nanny) as subprocesses."""

    def __init__(self, tmp: Path, n_workers: int, delay: float = 0.0) -> None:
        self.file = tmp / f'scheduler-{time.monotonic_ns()}.json'
        env = dict(os.environ, SOFT_ROM_TEST_READ_DELAY=str(delay),
                   PYTHONPATH=os.pathsep.join([str(HERE), os.environ.get('PYTHONPATH', '')]))
        quiet = {'stdout': subprocess.DEVNULL, 'stderr': subprocess.DEVNULL, 'env': env}
        self.scheduler = subprocess.Popen(
            [sys.executable, '-m', 'distributed.cli.dask_scheduler', '--host', '127.0.0.1',
             '--port', '0', '--no-dashboard', '--scheduler-file', str(self.file)], **quiet)
        deadline = time.monotonic() + 120
        while not self.file.exists() or not self.file.read_text().strip():
            assert self.scheduler.poll() is None and time.monotonic() < deadline
            time.sleep(0.1)
        time.sleep(0.1)
        self.address = json.loads(self.file.read_text())['address']
        self.workers = [subprocess.Popen(
            [sys.executable, '-m', 'distributed.cli.dask_worker', self.address, '--nthreads',
             '1', '--no-nanny', '--no-dashboard', '--preload', PRELOAD], **quiet)
            for _ in range(n_workers)]
        self.client = distributed.Client(self.address, timeout=60)
        self.client.wait_for_workers(n_workers, timeout=120)

    def worker_of(self, pid: int) -> str:
        """The address of the worker process ``pid``."""
        pids = self.client.run(os.getpid)
        return next(addr for addr, p in pids.items() if p == pid)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.client.close()
        for proc in [*self.workers, self.scheduler]:
            if proc.poll() is None:
                proc.kill()
            proc.wait()


@pytest.fixture(scope='module')
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp('dask'), 2)
    yield c
    c.close()


def _set(path: Path) -> TrainingSet:
    eps, q_ref, y_ref = system_episodes(ks=(160, 160))
    return TrainingSet.from_episodes(path, eps, q_ref=q_ref, y_ref=y_ref, q_chunks=(256, 80))


def _fit(args: list[str], **kw) -> subprocess.Popen:
    code = 'import sys; from soft_rom.cli import main; sys.exit(main())'
    return subprocess.Popen([sys.executable, '-c', code, 'fit', *args, '--quiet'],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def test_a_chunk_only_the_worker_finds_missing_is_refused_there(tmp_path, cluster):
    from soft_rom.scale.blocks import SnapshotSet
    from soft_rom.scale.dask_backend import DaskExecutor
    from soft_rom.scale.pod import StreamingPOD
    ts = _set(tmp_path / 'ts.zarr')
    arrays = [ts.q_array(n) for n in ts.episode_names]
    for a in arrays:
        a.check()                                  # the client's check passes ...
    (tmp_path / 'ts.zarr/episodes/ep2/Q/1.1').unlink()          # ... then a chunk goes
    snaps = SnapshotSet(arrays, ts.q_ref)
    with pytest.raises(DatasetError) as err:
        StreamingPOD(r=4, n_coords=8, executor=DaskExecutor(cluster.client)).fit(snaps)
    text = str(err.value)
    assert "episode 'ep2', array Q: chunk 1.1 is missing on Dask worker tcp://127.0.0.1:" \
        in text, text
    assert 'does this worker see the same storage as the client?' in text
    assert re.search(r'on Dask worker (tcp://[0-9.:]+)', text).group(1) in \
        cluster.client.scheduler_info()['workers']


def _flip(chunk: Path) -> None:
    data = np.frombuffer(bytearray(chunk.read_bytes()), dtype=np.uint8)
    data[:80].view('<u8')[:] ^= np.uint64(0xFFFF)            # low 16 bits of 10 values
    chunk.write_bytes(data.tobytes())


@pytest.mark.parametrize('how', ['fit', 'streaming', 'dask', 'info'])
def test_flipped_mantissa_bits_are_refused_everywhere(tmp_path, cluster, capsys, how):
    from soft_rom.cli import main
    ts = _set(tmp_path / 'ts.zarr')
    before = np.asarray(ts.q_array('ep1')[256:512, 80:160])
    _flip(tmp_path / 'ts.zarr/episodes/ep1/Q/1.1')
    out = tmp_path / 'models'
    argv = {'fit': ['fit', str(ts.path), '--method', 'dmdc', '--r', '4', '-o', str(out)],
            'streaming': ['fit', str(ts.path), '--method', 'dmdc', '--r', '4', '--streaming',
                          '-o', str(out)],
            'dask': ['fit', str(ts.path), '--method', 'dmdc', '--r', '4', '--dask',
                     cluster.address, '-o', str(out)],
            'info': ['info', str(ts.path)]}[how]
    assert main([*argv, '--quiet'] if how != 'info' else argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'Traceback' not in err, err
    assert "episode 'ep1', array Q: chunk 1.1 fails its CRC-32C checksum" in err, err
    assert ('on Dask worker tcp://' in err) == (how == 'dask')
    assert not out.exists()
    assert np.max(np.abs(before)) > 0


def _models(folder: Path) -> dict[str, np.ndarray]:
    (path,) = folder.glob('*.npz')
    return load_model(path).matrices()


def _processing(client, worker: str) -> bool:
    return bool(client.processing().get(worker))


def test_a_worker_killed_mid_pod_gives_the_same_model(tmp_path):
    ts = _set(tmp_path / 'ts.zarr')
    c = Cluster(tmp_path, 2, delay=0.4)
    fit = None
    try:
        clean = _fit([str(ts.path), '--method', 'dmdc', '--r', '4', '--dask', c.address,
                      '-o', str(tmp_path / 'clean')])
        assert clean.wait(300) == 0, clean.stderr.read()
        victim = c.workers[0]
        addr = c.worker_of(victim.pid)
        fit = _fit([str(ts.path), '--method', 'dmdc', '--r', '4', '--dask', c.address, '-o',
                    str(tmp_path / 'killed')])
        deadline = time.monotonic() + 120
        while not _processing(c.client, addr):
            assert fit.poll() is None and time.monotonic() < deadline
            time.sleep(0.02)
        victim.send_signal(signal.SIGKILL)               # in the middle of a block read
        assert fit.wait(300) == 0, fit.stderr.read()
        assert victim.wait() == -signal.SIGKILL
        a, b = _models(tmp_path / 'clean'), _models(tmp_path / 'killed')
        for name in a:
            assert np.array_equal(a[name], b[name]), name        # bit for bit
    finally:
        if fit is not None and fit.poll() is None:
            fit.kill()
            fit.wait()
        c.close()


def test_a_lost_scheduler_is_one_line_and_exit_1(tmp_path):
    ts = _set(tmp_path / 'ts.zarr')
    c = Cluster(tmp_path, 1, delay=0.4)
    try:
        addr = c.worker_of(c.workers[0].pid)
        fit = _fit([str(ts.path), '--method', 'dmdc', '--r', '4', '--dask', c.address,
                    '--dask-timeout', '2', '-o', str(tmp_path / 'out')])
        deadline = time.monotonic() + 120
        while not _processing(c.client, addr):
            assert fit.poll() is None and time.monotonic() < deadline
            time.sleep(0.02)
        c.scheduler.send_signal(signal.SIGKILL)
        code = fit.wait(300)
        err = fit.stderr.read().strip()
    finally:
        c.close()
    assert code == 1, err
    assert err == (f'soft-rom fit: error: lost the connection to the Dask scheduler at '
                   f'{c.address} during the POD; nothing was written'), err
    assert not (tmp_path / 'out').exists()


def test_no_scheduler_is_one_line_after_the_timeout(tmp_path, capsys):
    from soft_rom.cli import main
    ts = _set(tmp_path / 'ts.zarr')
    with socket.socket() as s:                      # a port nobody listens on
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    addr = f'tcp://127.0.0.1:{port}'
    assert main(['fit', str(ts.path), '--method', 'dmdc', '--r', '4', '--dask', addr,
                 '--dask-timeout', '1', '-o', str(tmp_path / 'out'), '--quiet']) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f'soft-rom fit: error: cannot connect to the Dask scheduler at {addr}'
                          ' within 1 s (')
    assert '--dask-timeout' in err and not (tmp_path / 'out').exists()
    assert main(['fit', str(ts.path), '--method', 'dmdc', '--dask', addr, '--dask-timeout',
                 '0', '-o', str(tmp_path / 'out'), '--quiet']) == 2
    assert '--dask-timeout must be a number of seconds > 0' in capsys.readouterr().err


def test_a_worker_that_cannot_see_the_folder_says_so(tmp_path, cluster):
    # what a worker on a host without the shared mount sees: no folder at the path
    ts = _set(tmp_path / 'ts.zarr')
    q = ts.q_array('ep1')
    q.check()                                      # the client sees it
    (tmp_path / 'ts.zarr').rename(tmp_path / 'elsewhere.zarr')
    with pytest.raises(DatasetError) as err:
        cluster.client.submit(lambda a: a[:, 0:8], q, pure=False).result()
    text = str(err.value)
    assert f"episode 'ep1', array Q: its folder {tmp_path / 'ts.zarr/episodes/ep1/Q'} is " \
        'missing or empty on Dask worker tcp://' in text, text
    assert 'chunk 0.0 and every other chunk are missing (does this worker see the same ' \
        'storage as the client?' in text
