"""Benchmark: bag -> training-set conversion against a plain rosbags read of the same bag.

Writes a simulator-like bag (``--messages`` samples of ``--n-dof`` float64 state values plus
six ``FluidPressure`` and one 20-point ``PoseArray`` per sample) under ``--dir``, then, each in
a fresh child process so that peak memory (``ru_maxrss``) and CPU time are per phase:

- ``read``: a plain rosbags read of the whole bag (every message read and deserialised);
- ``convert``: :func:`soft_rom.convert.convert` to a zarr training set (with ``Q``);
- ``floor``: the plain read plus writing every state payload to one flat file (the I/O
  floor of any conversion that stores the states);
- ``floor-db``: the same with 1 MiB writes and drop-behind (``POSIX_FADV_DONTNEED`` 128 MiB
  behind the writer), the write pattern of the converter's chunk writer.

Each phase runs twice: ``cold`` (every file of the bag flushed and dropped from the page
cache with ``posix_fadvise(POSIX_FADV_DONTNEED)`` just before the clock starts, so the bag
comes from disk) and ``warm`` (the bag read once just before, so it comes from the page
cache). Between phases the parent calls ``sync`` so that one phase's dirty pages are not
written back during the next. The plain read never writes, the conversion writes as many
bytes as it reads: warm, the plain read is a memory copy and the conversion is bound by
writing to the page cache; cold, both are bound by the disk. Both ratios are printed.

It prints throughput (state messages/s and MB/s of bag), the ratios conversion / plain read
(target >= 0.5), CPU seconds, and the peak memory of the conversion (target <= 1 GB), then
deletes the bag and the training set (unless ``--keep``). The full run needs about
2 x 3.7 GB of disk.

Measured (2 cores, ext4 on a VM disk, 2026-11-23, full preset; wall seconds, ratios are
plain read / conversion):

========================= ========== ========== ============ ============ =========
code                      read warm  read cold  convert warm convert cold peak RSS
========================= ========== ========== ============ ============ =========
before (d20f44d)          0.84       5.34       12.49 (0.07) 9.28 (0.58)  327 MB
after                     0.93       4.03       3.25 (0.29)  6.14 (0.66)  129 MB
========================= ========== ========== ============ ============ =========

Conversion CPU seconds 12.5 -> 3.6 (warm). ``floor-db`` (read + write the states with the
same write pattern, nothing else) ran 2.6-3.0 s warm, i.e. 0.31-0.43 of the warm plain read:
the warm target of 0.5 is out of reach of any conversion that writes its states to disk;
the conversion runs at 0.8-0.95 of that floor. Timings vary by +-30 % between runs here.

Usage::

    .venv/bin/python benchmarks/bench_convert.py            # 2,000 x 231,336 DOF (~3.7 GB)
    .venv/bin/python benchmarks/bench_convert.py --small    # 300 x 23,136 DOF (seconds)
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu() -> float:
    """CPU seconds of this process, all threads (less sensitive to a loaded machine)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _drop_cache(bag: Path) -> None:
    """Flush every file of ``bag`` and evict it from the page cache (a cold read)."""
    for f in sorted(bag.iterdir()):
        fd = os.open(f, os.O_RDONLY)
        try:
            os.fdatasync(fd)               # DONTNEED drops clean pages only
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def _warm_cache(bag: Path) -> None:
    """Read every file of ``bag`` once (a warm read: the bag then comes from the page cache)."""
    buf = bytearray(1 << 24)
    for f in sorted(bag.iterdir()):
        with open(f, 'rb', buffering=0) as fh:
            while fh.readinto(buf):
                pass


def _prepare(bag: Path, cache: str) -> None:
    if cache == 'cold':
        _drop_cache(bag)
    else:
        _warm_cache(bag)


def phase_write(bag: Path, n_dof: int, messages: int, storage: str) -> dict:
    from soft_rom.bags import EpisodeBagWriter

    n_nodes = n_dof // 3
    rng = np.random.default_rng(0)
    base = rng.normal(size=(n_nodes, 3))
    cl = rng.normal(size=(20, 3))
    t0 = time.perf_counter()
    with EpisodeBagWriter(bag, storage=storage, n_chambers=6, n_nodes=n_nodes) as w:
        for j in range(messages):
            base[j % n_nodes, j % 3] += 1e-3          # every snapshot differs
            w.write(0.001 * (j + 1), np.full(6, float(j)), cl + 1e-4 * j, base)
    return {'seconds': time.perf_counter() - t0, 'maxrss_mb': _maxrss_mb()}


def phase_read(bag: Path) -> dict:
    """Plain rosbags: iterate every message and deserialise it (the rosbags API directly)."""
    from soft_rom.bags.reader import BagReader
    from soft_rom.bags.writer import typestore

    ts = typestore()
    t0, c0 = time.perf_counter(), _cpu()
    n_state = 0
    nbytes = 0
    checksum = 0.0
    with BagReader(bag) as wrapped:
        reader = wrapped.reader                       # rosbags.rosbag2.Reader
        for conn, _, raw in reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            nbytes += len(raw)
            if conn.topic == '/soft_robot/state':
                n_state += 1
                checksum += float(msg.data[0])       # touch the data
    return {'seconds': time.perf_counter() - t0, 'cpu': _cpu() - c0, 'state_messages': n_state,
            'bytes': nbytes, 'maxrss_mb': _maxrss_mb(), 'checksum': checksum}


def phase_copy(bag: Path, out: Path, drop_behind: bool = False) -> dict:
    """I/O floor: the plain read above plus writing every state payload to one flat file.

    With ``drop_behind`` the payloads are written in 1 MiB pieces and the file's pages are
    evicted from the page cache about 128 MiB behind the writer (``POSIX_FADV_DONTNEED``),
    as the converter's chunk writer does.
    """
    from soft_rom.bags.reader import BagReader
    from soft_rom.bags.writer import typestore

    ts = typestore()
    t0, c0 = time.perf_counter(), _cpu()
    n_state = 0
    out.mkdir(parents=True, exist_ok=True)
    lag, step, pos, dropped = 128 << 20, 8 << 20, 0, 0
    with BagReader(bag) as wrapped, open(out / 'flat.f8', 'wb', buffering=0) as fh:
        fd = fh.fileno()
        for conn, _, raw in wrapped.reader.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            if conn.topic == '/soft_robot/state':
                n_state += 1
                view = memoryview(msg.data).cast('B')
                if not drop_behind:
                    fh.write(view)
                    continue
                while view.nbytes:
                    view = view[os.write(fd, view[:1 << 20]):]
                pos += len(msg.data) * 8
                if pos - dropped >= lag + step:
                    os.posix_fadvise(fd, 0, pos, os.POSIX_FADV_DONTNEED)  # starts writeback
                    os.posix_fadvise(fd, 0, pos - lag, os.POSIX_FADV_DONTNEED)
                    dropped = pos - lag
    seconds = time.perf_counter() - t0
    shutil.rmtree(out, ignore_errors=True)
    return {'seconds': seconds, 'cpu': _cpu() - c0, 'state_messages': n_state,
            'maxrss_mb': _maxrss_mb()}


def phase_convert(bag: Path, out: Path) -> dict:
    import tqdm  # noqa: F401 - imported before the clock starts, like rosbags for the read
    import zarr  # noqa: F401

    from soft_rom.bags.writer import typestore
    from soft_rom.convert import convert

    typestore()  # built before the clock starts (0.15 s of imports), as for the plain read
    t0, c0 = time.perf_counter(), _cpu()
    ts, reports = convert([bag], out, progress=False, overwrite=True)
    seconds, cpu = time.perf_counter() - t0, _cpu() - c0
    q = ts.q_array(ts.episode_names[0])
    shutil.rmtree(out, ignore_errors=True)
    return {'seconds': seconds, 'cpu': cpu, 'state_messages': reports[0].n_samples,
            'Q_shape': list(q.shape), 'Q_chunks': list(q.chunks), 'maxrss_mb': _maxrss_mb()}


def _child(phase: str, args: argparse.Namespace, bag: Path, out: Path,
           cache: str = 'warm') -> dict:
    os.sync()                              # the previous phase's writes are not ours
    cmd = [sys.executable, __file__, '--phase', phase, '--bag', str(bag), '--out', str(out),
           '--n-dof', str(args.n_dof), '--messages', str(args.messages),
           '--storage', args.storage, '--cache', cache]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--n-dof', type=int, default=231336)
    parser.add_argument('--messages', type=int, default=2000)
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    parser.add_argument('--dir', default=tempfile.gettempdir())
    parser.add_argument('--small', action='store_true', help='300 x 23,136 DOF preset')
    parser.add_argument('--keep', action='store_true', help='keep the bag and training set')
    parser.add_argument('--phase', choices=('write', 'read', 'floor', 'floor-db', 'convert'),
                        help=argparse.SUPPRESS)
    parser.add_argument('--cache', choices=('cold', 'warm'), default='warm',
                        help=argparse.SUPPRESS)
    parser.add_argument('--bag', help=argparse.SUPPRESS)
    parser.add_argument('--out', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.small:
        args.n_dof, args.messages = 23136, 300
    if args.phase:
        bag, out = Path(args.bag), Path(args.out)
        if args.phase != 'write':
            _prepare(bag, args.cache)
        if args.phase == 'write':
            res = phase_write(bag, args.n_dof, args.messages, args.storage)
        elif args.phase == 'read':
            res = phase_read(bag)
        elif args.phase == 'floor':
            res = phase_copy(bag, out)
        elif args.phase == 'floor-db':
            res = phase_copy(bag, out, drop_behind=True)
        else:
            res = phase_convert(bag, out)
        print(json.dumps(res))
        return 0

    work = Path(tempfile.mkdtemp(prefix='soft_rom_bench_convert_', dir=args.dir))
    bag, out = work / 'bench_bag', work / 'bench.zarr'
    try:
        print(f'bag: {args.messages} state messages x {args.n_dof} float64 ({args.storage}) '
              f'under {work}')
        w = _child('write', args, bag, out)
        size = sum(f.stat().st_size for f in bag.iterdir())
        print(f'write   : {w["seconds"]:8.2f} s  {size / 1e9:6.2f} GB  '
              f'{size / 1e6 / w["seconds"]:8.1f} MB/s  peak {w["maxrss_mb"]:7.1f} MB')
        res = {}
        for phase in ('read', 'convert', 'floor', 'floor-db'):
            for cache in ('warm', 'cold'):
                res[phase, cache] = _child(phase, args, bag, out, cache)
        for (phase, cache), r in res.items():
            label = f'{phase} {cache}'
            print(f'{label:14s}: {r["seconds"]:7.2f} s wall {r["cpu"]:7.2f} s cpu  '
                  f'{r["state_messages"] / r["seconds"]:7.1f} state msg/s  '
                  f'{size / 1e6 / r["seconds"]:7.1f} MB/s  peak {r["maxrss_mb"]:7.1f} MB')
        print('  read = plain rosbags read + deserialise of every message; floor = the same '
              'read + writing the state payloads to one flat file (plain writes, no '
              'drop-behind); floor-db = the same in 1 MiB writes with drop-behind, as the '
              'converter writes; warm = bag in the page cache, cold = bag dropped from it '
              '(POSIX_FADV_DONTNEED)')
        c = res['convert', 'cold']
        print(f'  convert: Q {c["Q_shape"]} chunks {c["Q_chunks"]}')
        for cache in ('warm', 'cold'):
            r, c = res['read', cache], res['convert', cache]
            f, g = res['floor', cache], res['floor-db', cache]
            ratio = r['seconds'] / c['seconds']
            print(f'throughput ratio convert / plain read, {cache}: wall {ratio:.2f} '
                  f'(target >= 0.5) -> {"PASS" if ratio >= 0.5 else "FAIL"};  '
                  f'cpu {r["cpu"] / c["cpu"]:.2f};  convert / floor: wall '
                  f'{f["seconds"] / c["seconds"]:.2f}, cpu {f["cpu"] / c["cpu"]:.2f};  '
                  f'convert / floor-db: wall {g["seconds"] / c["seconds"]:.2f}, '
                  f'cpu {g["cpu"] / c["cpu"]:.2f};  floor-db / plain read: wall '
                  f'{r["seconds"] / g["seconds"]:.2f}')
        peak = max(res['convert', cache]['maxrss_mb'] for cache in ('warm', 'cold'))
        print(f'conversion peak memory: {peak:.0f} MB (target <= 1024 MB) -> '
              f'{"PASS" if peak <= 1024 else "FAIL"}')
        print(f'machine load average during the run: {os.getloadavg()[0]:.1f} '
              f'on {os.cpu_count()} cores')
    finally:
        if args.keep:
            print(f'kept {work}')
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
