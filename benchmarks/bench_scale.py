#!/usr/bin/env python3
"""Paper-scale fitting benchmark: streaming POD + LOpInf / DMDc / ERA-OKID from disk.

Generates a synthetic training set on disk (low-rank second-order dynamics plus white noise,
written with :class:`soft_rom.dataset.TrainingSetWriter`, the real on-disk format), then

1. reads the raw ``Q`` chunk files sequentially (the I/O baseline),
2. runs the streaming POD (each pass timed), fused with the projection,
3. fits LOpInf, DMDc and ERA/OKID on the reduced data,

and prints wall time, peak RSS of the fitting process (data generation runs in a child
process so it does not count), and the ratio of POD-pass throughput to raw-read throughput.

Page cache: by default (``--cold``) every ``Q`` chunk file is dropped from the page cache
(``posix_fadvise(DONTNEED)``) before the raw read, before the POD, and right after each
block is read by the POD, so *both* figures are disk reads; ``--warm`` keeps the cache (then
both read from memory when the data fit in RAM).

Presets (n states x episodes x snapshots):
    small   10,000 x 3 x 1,000      ~0.24 GB
    medium  231,336 x 6 x 250       ~2.8 GB
    paper   231,336 x 6 x 2,000     ~22 GB   (the paper's FOM and data volume)

Measured (2 cores, shared machine, load average ~4-6 from other jobs, cold cache)::

    paper   raw read 429 MB/s; randomized POD 3 passes 261 s (291 MB/s of chunk files,
            ratio 0.68), CPU 249 s; LOpInf 0.3 s, DMDc 1.0 s, ERA/OKID 3.0 s;
            total 266 s, peak RSS 1015 MiB
    medium  raw read 811 MB/s; randomized 17.0 s (ratio 0.70), Gram 21.9 s (ratio 0.36,
            CPU-bound); Dask LocalCluster (2 workers) 29.7 s, coordinates equal to the
            local ones to 6.5e-16 relative; ``--pod gram --compare-memory``, streamed
            against in memory (predicted outputs, relative to their deviations): LOpInf
            6.7e-13, learned mass 6.7e-13, cubic r=8 3.1e-13, DMDc 3.2e-12 (small preset:
            6.5e-13, 6.5e-13, 3.8e-13, 9.0e-13)

Checksums (``--checksum-ab``): the POD is run on the set as written (format version 3, a
CRC-32C verified at every chunk read) and on a copy of it without checksums (the chunk files
less their last 4 bytes, the filter removed: what version 2 stored), alternately and twice
each, cold or warm alike; the ratio of the medians is the cost of verifying the checksums.

Usage::

    python benchmarks/bench_scale.py --preset small
    python benchmarks/bench_scale.py --preset medium --pod both
    python benchmarks/bench_scale.py --preset medium --checksum-ab
    python benchmarks/bench_scale.py --preset paper --dir /tmp/soft_rom_scale
"""

from __future__ import annotations

import argparse
import glob
import json
import os
from pathlib import Path
import resource
import shutil
import subprocess
import sys
import time

import numpy as np

PRESETS = {
    'small': dict(n=10_000, episodes=3, k=1_000),
    'medium': dict(n=231_336, episodes=6, k=250),
    'paper': dict(n=231_336, episodes=6, k=2_000),
}
M_IN, P_OUT, R_TRUE, DT = 6, 40, 12, 1e-3


def rss_peak_mb() -> float:
    """Peak resident set size of this process (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# -- data generation --------------------------------------------------------------------
def generate(path: Path, n: int, episodes: int, k: int, noise: float, seed: int) -> None:
    """Write the synthetic training set (called in a child process)."""
    from scipy.linalg import expm

    from soft_rom.dataset import TrainingSetWriter

    rng = np.random.default_rng(seed)
    # Modal second-order system: r_true modes, 0.5-8 Hz, 2-5 % damping.
    w = 2 * np.pi * np.linspace(0.5, 8.0, R_TRUE)
    z = np.linspace(0.02, 0.05, R_TRUE)
    Ac = np.zeros((2 * R_TRUE, 2 * R_TRUE))
    Ac[:R_TRUE, R_TRUE:] = np.eye(R_TRUE)
    Ac[R_TRUE:, :R_TRUE] = -np.diag(w ** 2)
    Ac[R_TRUE:, R_TRUE:] = -np.diag(2 * z * w)
    Bc = np.zeros((2 * R_TRUE, M_IN))
    Bc[R_TRUE:] = rng.standard_normal((R_TRUE, M_IN)) * (w[:, None] ** 2) * 1e-6
    F = expm(np.block([[Ac, Bc], [np.zeros((M_IN, 2 * R_TRUE + M_IN))]]) * DT)
    Ad, Bd = F[:2 * R_TRUE, :2 * R_TRUE], F[:2 * R_TRUE, 2 * R_TRUE:]
    Phi = rng.standard_normal((n, R_TRUE)) / np.sqrt(n) * np.linspace(1.0, 0.05, R_TRUE)
    E = rng.standard_normal((P_OUT, R_TRUE))
    q_ref = np.linspace(0.0, 1.2, n)
    y_ref = np.linspace(0.0, 1.2, P_OUT)
    step = 32  # the training set's chunk width: one chunk column per append
    # White noise without drawing n*K normals (CPU-bound at 22 GB): each snapshot's noise is
    # a window at a random offset of one long Gaussian sequence -- distinct shifts of white
    # noise, so the noise still has full rank.
    bank = rng.standard_normal(n + 2 ** 22)
    with TrainingSetWriter(path, input_names=[f'p{i + 1}' for i in range(M_IN)],
                           input_units=['Pa'] * M_IN,
                           output_names=[f'y{i + 1}' for i in range(P_OUT)],
                           output_units=['m'] * P_OUT, overwrite=True) as wtr:
        for e in range(episodes):
            # Random piecewise-constant pressures (new level every 50-200 ms), in Pa.
            U = np.empty((M_IN, k))
            j = 0
            while j < k:
                hold = int(rng.integers(50, 200))
                U[:, j:j + hold] = rng.uniform(0, 3e4, size=(M_IN, 1))
                j += hold
            x = np.zeros(2 * R_TRUE)
            Xm = np.empty((R_TRUE, k))
            for j in range(k):
                Xm[:, j] = x[:R_TRUE]
                x = Ad @ x + Bd @ U[:, j]
            Y = E @ Xm + y_ref[:, None]
            t = np.arange(k) * DT
            ep = wtr.begin_episode(f'ep{e + 1}', n_states=n)
            for a in range(0, k, step):
                b = min(a + step, k)
                Q = q_ref[:, None] + Phi @ Xm[:, a:b]
                for c, off in enumerate(rng.integers(0, 2 ** 22, size=b - a)):
                    Q[:, c] += noise * bank[off:off + n]
                ep.append(t[a:b], U[:, a:b], Y[:, a:b], Q)
        wtr.set_reference(q_ref=q_ref, y_ref=y_ref)


# -- page cache and raw reads -----------------------------------------------------------
def chunk_files(ts_path: Path) -> list[str]:
    """All chunk files of every episode's Q array, in (episode, column, row) order."""
    files = []
    for qdir in sorted(glob.glob(str(ts_path / 'episodes' / '*' / 'Q'))):
        names = [f for f in os.listdir(qdir) if not f.startswith('.') and f[0].isdigit()]
        key = []
        for f in names:
            parts = f.replace('/', '.').split('.')
            key.append((int(parts[1]), int(parts[0]), f))
        files += [os.path.join(qdir, f) for _, _, f in sorted(key)]
    return files


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (all threads) so far."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def drop_cache(files: list[str], sync: bool = False) -> None:
    """Evict the files' pages from the page cache (no root needed; dirty pages need sync)."""
    if sync:
        os.sync()
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def raw_read(files: list[str]) -> tuple[float, int]:
    """Sequentially read every file into one reused buffer: (seconds, bytes)."""
    buf = bytearray(16 * 2 ** 20)
    view = memoryview(buf)
    total = 0
    t0 = time.perf_counter()
    for f in files:
        with open(f, 'rb', buffering=0) as fh:
            while True:
                got = fh.readinto(view)
                if not got:
                    break
                total += got
    return time.perf_counter() - t0, total


class ColdArray:
    """Wrap a zarr array: after each read, drop the chunk files just read from the cache."""

    def __init__(self, array, qdir: str) -> None:
        self.array = array
        self.shape = array.shape
        self.chunks = array.chunks
        self.dtype = array.dtype
        self.qdir = qdir

    def __getitem__(self, key):
        out = self.array[key]
        rows, cols = key
        r0, r1, _ = rows.indices(self.shape[0])
        c0, c1, _ = cols.indices(self.shape[1])
        cr, cc = self.chunks
        files = [os.path.join(self.qdir, f'{i}.{j}') for i in range(r0 // cr, (r1 - 1) // cr + 1)
                 for j in range(c0 // cc, (c1 - 1) // cc + 1)]
        drop_cache([f for f in files if os.path.exists(f)])
        return out


# -- fits on reduced data ---------------------------------------------------------------
def reduced_data(td, pod, seconds):
    """The ReducedData of a fitted StreamingPOD (what StreamingReducer.reduce builds)."""
    from soft_rom.reduce import ReducedData
    last = 0.0
    for ep in td.episodes:
        kk = ep.Q.shape[1]
        x = np.asarray(ep.Q[:, kk - 1:kk], dtype=np.float64)[:, 0] - pod.q_ref_
        last += float(x @ x)
    eps = td.episodes
    return ReducedData(coordinates=tuple(pod.coords_), U=tuple(ep.U for ep in eps),
                       Y=tuple(ep.Y for ep in eps), t=tuple(ep.t for ep in eps),
                       y_ref=td.y_ref, names=tuple(ep.name for ep in eps), basis='pod',
                       energy=pod.energy_, singular_values=pod.singular_values_,
                       n_states=int(pod.q_ref_.size), pairs_sq_norm=pod.total_energy_ - last,
                       q_ref=pod.q_ref_, channels=dict(td.names),
                       metadata={'scale': {'pod_method': pod.method, 'seconds': seconds}})


def fit_one(method, red, r, k):
    """One model of ``method`` on reduced data (ERA/OKID: its first episode)."""
    from soft_rom.learners import DMDc, ERAOKID, LOpInf
    if method == 'lopinf':
        return LOpInf(r=r).fit(red).model_
    if method == 'dmdc':
        return DMDc(r=r).fit(red).model_
    # OKID needs ~104 samples for m=6, p=40 after decimation
    return ERAOKID(decimation=int(max(1, min(5, k // 120)))).fit(red).model_


def compare_memory(ts, red, r, r_cubic):
    """The streamed models against the in-memory ones (same learners, exact SVD in memory).

    Prints, for LOpInf (linear, learned mass, cubic at ``r_cubic``) and DMDc, the largest
    difference of the two models' predicted outputs over the first episode, relative to its
    output deviations; DMDc in memory on every POD coordinate (equivalent to the centred
    snapshots, which at this size would need some 20 GB).
    """
    from soft_rom.evaluation import predict
    from soft_rom.learners import DMDc, LOpInf
    from soft_rom.pipeline import open_training_data
    from soft_rom.reduce import InMemoryPOD
    t0, c0 = time.perf_counter(), cpu_seconds()
    td = open_training_data(ts)
    mem = InMemoryPOD().reduce(td, basis='pod', r=sum(ep.n_samples for ep in td.episodes))
    print(f'in-memory POD (all {mem.n_coordinates} modes): {time.perf_counter() - t0:.1f} s, '
          f'CPU {cpu_seconds() - c0:.1f} s, peak RSS {rss_peak_mb():.0f} MiB')
    ep = td.episodes[0]
    dev = float(np.linalg.norm(ep.Y - td.y_ref[:, None]))
    out = {}
    cubic = {'reg': 1e-3, 'eps4': 1e-2}
    for name, make in (('lopinf linear', lambda: LOpInf(r=r)),
                       ('lopinf learned mass', lambda: LOpInf(r=r, mass='learned')),
                       (f'lopinf cubic r={r_cubic}',
                        lambda: LOpInf(r=r_cubic, forces='cubic', cubic_options=cubic)),
                       ('dmdc', lambda: DMDc(r=r))):
        t1 = time.perf_counter()
        a, b = make().fit(mem).model_, make().fit(red).model_
        diff = float(np.linalg.norm(predict(a, ep) - predict(b, ep))) / dev
        print(f'  {name:<22} streamed vs in memory: {diff:.2e} (relative to the output '
              f'deviations; {time.perf_counter() - t1:.1f} s)')
        out[name] = diff
    return out


def strip_checksums(src: Path, dst: Path) -> None:
    """Copy the training set ``src`` to ``dst`` as format version 2 stored it: no checksums.

    Every chunk file loses its last 4 bytes (the CRC-32C) and every ``.zarray`` its filter;
    the compressed arrays (``t``, ``U``, ``Y``) are decoded and written again.
    """
    import zarr

    from soft_rom.dataset.checksum import register
    register()
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns('[0-9]*'))
    kw: dict = {'zarr_format': 2, 'config': {'write_empty_chunks': True}} \
        if int(zarr.__version__.split('.')[0]) >= 3 else {'write_empty_chunks': True}
    for meta_path in sorted(src.rglob('.zarray')):
        rel = meta_path.parent.relative_to(src)
        meta = json.loads(meta_path.read_text())
        if meta.get('compressor') is None:
            meta['filters'] = None
            (dst / rel / '.zarray').write_text(json.dumps(meta, indent=2))
            for f in meta_path.parent.iterdir():
                if not f.name.startswith('.'):
                    data = f.read_bytes()
                    (dst / rel / f.name).write_bytes(data[:-4])
        else:
            arr = np.asarray(zarr.open_array(str(meta_path.parent), mode='r')[...])
            shutil.rmtree(dst / rel)
            new = zarr.open_array(str(dst / rel), mode='w', shape=arr.shape,
                                  chunks=tuple(meta['chunks']), dtype='f8',
                                  order=meta['order'], fill_value=0.0, **kw)
            new[...] = arr
            attrs = meta_path.parent / '.zattrs'
            if attrs.exists():
                shutil.copy(attrs, dst / rel / '.zattrs')
    attrs = json.loads((dst / '.zattrs').read_text())
    attrs['format_version'] = 2
    (dst / '.zattrs').write_text(json.dumps(attrs))


def checksum_ab(path: Path, args: argparse.Namespace) -> dict:
    """POD with and without checksums, alternately (A B A B); returns the figures."""
    from soft_rom.dataset import TrainingSet
    from soft_rom.pipeline import open_training_data
    from soft_rom.scale.blocks import LocalExecutor, SnapshotSet
    from soft_rom.scale.pod import StreamingPOD

    plain = path.with_name(path.stem + '_nocrc.zarr')
    t0 = time.perf_counter()
    strip_checksums(path, plain)
    print(f'copy without checksums written in {time.perf_counter() - t0:.1f} s')
    times: dict[str, list[float]] = {'crc32c': [], 'none': []}
    ref = None
    for rep in range(2):
        for label, p in (('crc32c', path), ('none', plain)):
            ts = TrainingSet.open(p)
            assert ts.checksummed == (label == 'crc32c')
            td = open_training_data(ts)
            files = chunk_files(p)
            if not args.warm:
                drop_cache(files, sync=rep == 0)
                for ep in td.episodes:
                    object.__setattr__(ep, 'Q', ColdArray(ep.Q, str(p / 'episodes' / ep.name
                                                                    / 'Q')))
            snaps = SnapshotSet([ep.Q for ep in td.episodes], td.q_ref)
            pod = StreamingPOD(r=args.r, method='randomized',
                               n_coords=max(2 * args.r, args.r + 20),
                               power_iters=args.power_iters, executor=LocalExecutor(),
                               seed=args.seed)
            t0 = time.perf_counter()
            pod.fit(snaps)
            dt = time.perf_counter() - t0
            times[label].append(dt)
            sv = pod.singular_values_[:args.r]
            ref = sv if ref is None else ref
            print(f'  POD {label:6s} (run {rep + 1}): {dt:.2f} s, {pod.n_passes_} passes; '
                  f'singular values equal: {bool(np.array_equal(sv, ref))}; load '
                  f'{os.getloadavg()[0]:.1f}')
    shutil.rmtree(plain, ignore_errors=True)
    med = {k: float(np.median(v)) for k, v in times.items()}
    ratio = med['crc32c'] / med['none']
    print(f'checksum A/B ({"warm" if args.warm else "cold"} cache): POD with CRC-32C '
          f'{med["crc32c"]:.2f} s, without {med["none"]:.2f} s (medians of 2): ratio '
          f'{ratio:.3f} (target <= 1.05); load average {os.getloadavg()} on '
          f'{os.cpu_count()} cpus')
    return {'seconds': times, 'ratio': ratio, 'load_average': os.getloadavg()}


# -- main -------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--preset', choices=sorted(PRESETS), default='small')
    ap.add_argument('--dir', default='/tmp/soft_rom_scale_bench')
    ap.add_argument('--reuse', action='store_true', help='reuse an existing data set')
    ap.add_argument('--keep', action='store_true', help='keep the data set afterwards')
    ap.add_argument('--pod', choices=['randomized', 'gram', 'both'], default='randomized')
    ap.add_argument('--power-iters', type=int, default=1)
    ap.add_argument('--r', type=int, default=12, help='LOpInf and DMDc reduced dimension')
    ap.add_argument('--noise', type=float, default=1e-5, help='noise std (m)')
    ap.add_argument('--warm', action='store_true', help='keep the page cache (see docstring)')
    ap.add_argument('--dask', type=int, default=0, metavar='WORKERS',
                    help='also run the POD on a LocalCluster with this many workers and '
                         'compare with the local result')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--compare-memory', action='store_true',
                    help='also fit in memory (the snapshots loaded, an exact SVD) and print '
                         'how far each streamed model is from it (use --pod gram: exact)')
    ap.add_argument('--cubic-r', type=int, default=8,
                    help='reduced dimension of the cubic LOpInf of --compare-memory')
    ap.add_argument('--checksum-ab', action='store_true',
                    help='only time the POD with and without chunk checksums (A/B)')
    args = ap.parse_args(argv)

    cfg = PRESETS[args.preset]
    n, E, k = cfg['n'], cfg['episodes'], cfg['k']
    nbytes = 8 * n * E * k
    root = Path(args.dir)
    path = root / f'{args.preset}.zarr'
    root.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(root).free
    print(f'preset {args.preset}: n={n:,} x {E} episodes x {k:,} snapshots = '
          f'{nbytes / 1e9:.2f} GB of Q; free disk {free / 1e9:.1f} GB; cpus {os.cpu_count()}')
    if not (args.reuse and path.exists()):
        if free < 1.1 * nbytes:
            print('not enough free disk for this preset', file=sys.stderr)
            return 2
        t0 = time.perf_counter()
        code = ('import sys; sys.path.insert(0, %r); import bench_scale as b; '
                'b.generate(b.Path(%r), %d, %d, %d, %r, %d)'
                % (str(Path(__file__).parent), str(path), n, E, k, args.noise, args.seed))
        subprocess.run([sys.executable, '-c', code], check=True)
        print(f'generated in {time.perf_counter() - t0:.1f} s '
              f'({nbytes / 1e6 / (time.perf_counter() - t0):.0f} MB/s)')

    if args.checksum_ab:
        result = checksum_ab(path, args)
        print('JSON ' + json.dumps({'preset': args.preset, 'checksum_ab': result}))
        if not args.keep:
            shutil.rmtree(path, ignore_errors=True)
        return 0

    from soft_rom.dataset import TrainingSet
    from soft_rom.pipeline import open_training_data
    from soft_rom.scale.blocks import LocalExecutor, SnapshotSet
    from soft_rom.scale.pod import StreamingPOD

    files = chunk_files(path)
    if not args.warm:
        drop_cache(files, sync=True)
    t_raw, b_raw = raw_read(files)
    raw_tp = b_raw / t_raw
    print(f'raw sequential read ({"cold" if not args.warm else "warm"}): {b_raw / 1e9:.2f} GB '
          f'in {t_raw:.1f} s = {raw_tp / 1e6:.0f} MB/s')

    ts = TrainingSet.open(path)
    td = open_training_data(ts)
    if not args.warm:
        for ep in td.episodes:
            qdir = str(path / 'episodes' / ep.name / 'Q')
            object.__setattr__(ep, 'Q', ColdArray(ep.Q, qdir))
    results: dict = {'preset': args.preset, 'n': n, 'episodes': E, 'k': k,
                     'bytes': nbytes, 'raw_MBps': raw_tp / 1e6}
    methods = ['randomized', 'gram'] if args.pod == 'both' else [args.pod]
    red = None
    for method in methods:
        if not args.warm:
            drop_cache(files)
        ex = LocalExecutor()
        snaps = SnapshotSet([ep.Q for ep in td.episodes], td.q_ref,
                            [ep.name for ep in td.episodes])
        # 'gram' keeps every coordinate (as soft_rom.reduce.StreamingReducer does): exact.
        n_coords = E * k if method == 'gram' else max(2 * args.r, args.r + 20)
        pod = StreamingPOD(r=args.r, method=method, n_coords=n_coords,
                           power_iters=args.power_iters, executor=ex, seed=args.seed,
                           compute_basis=method != 'gram')
        t0, c0 = time.perf_counter(), cpu_seconds()
        try:
            pod.fit(snaps)
        except Exception as err:  # noqa: BLE001 - report and go on with the other method
            print(f'POD {method}: {type(err).__name__}: {err}')
            continue
        t_pod, c_pod = time.perf_counter() - t0, cpu_seconds() - c0
        tp = ex.bytes_read / t_pod
        tp_disk = pod.n_passes_ * b_raw / t_pod  # on-disk bytes (chunks are padded)
        print(f'POD {method}: {pod.n_passes_} passes, {ex.bytes_read / 1e9:.2f} GB read in '
              f'{t_pod:.1f} s = {tp / 1e6:.0f} MB/s ({tp_disk / 1e6:.0f} MB/s of chunk files)'
              f' -> ratio to raw read {tp_disk / raw_tp:.2f}; '
              f'energy captured by r={pod.r_}: {pod.energy_[pod.r_ - 1]:.6f}; '
              f'peak RSS so far {rss_peak_mb():.0f} MiB; CPU {c_pod:.1f} s')
        results[f'pod_{method}'] = {'seconds': t_pod, 'cpu_seconds': c_pod,
                                    'passes': pod.n_passes_,
                                    'MBps': tp / 1e6, 'ratio_to_raw': tp_disk / raw_tp,
                                    'sv': pod.singular_values_[:args.r].tolist()}
        if red is None:
            red = reduced_data(td, pod, t_pod)
        else:
            s0 = np.asarray(results[f'pod_{methods[0]}']['sv'])
            print(f'  singular values {methods[0]} vs {method}: max rel diff '
                  f'{np.max(np.abs(pod.singular_values_[:args.r] / s0 - 1)):.2e}')
    if red is None:
        return 1
    t_total = t_pod
    fitted = {}
    for method in ('lopinf', 'dmdc', 'era'):
        t0, c0 = time.perf_counter(), cpu_seconds()
        model = fit_one(method, red, args.r, k)
        fitted[method] = model
        dt_fit, c_fit = time.perf_counter() - t0, cpu_seconds() - c0
        t_total += dt_fit
        ep = td.episodes[0]
        from soft_rom.evaluation import predict
        Yhat = predict(model, ep)
        err = np.linalg.norm(ep.Y - Yhat) / np.linalg.norm(ep.Y - td.y_ref[:, None])
        print(f'fit {method}: r={model.r}, {dt_fit:.1f} s, train rel. deviation error ep1 '
              f'{err:.3e}, stability margin {model.stability_margin():.2e}; CPU {c_fit:.1f} s')
        results[f'fit_{method}'] = {'seconds': dt_fit, 'cpu_seconds': c_fit, 'r': model.r,
                                    'dev_error': float(err)}
    results['total_seconds'] = t_total
    results['load_average'] = os.getloadavg()
    results['peak_rss_MiB'] = rss_peak_mb()
    if args.compare_memory:
        results['memory_vs_streaming'] = compare_memory(ts, red, args.r, args.cubic_r)
    print(f'TOTAL POD + LOpInf + DMDc + ERA/OKID: {t_total:.1f} s; peak RSS '
          f'{rss_peak_mb():.0f} MiB; load average {os.getloadavg()[0]:.1f} on '
          f'{os.cpu_count()} cpus (other jobs inflate wall times; see the CPU seconds)')

    if args.dask:
        from dask.distributed import Client, LocalCluster

        from soft_rom.scale.dask_backend import DaskExecutor
        with LocalCluster(n_workers=args.dask, threads_per_worker=1,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            raw_eps = [ts[name] for name in ts.episode_names]
            snaps = SnapshotSet([ep.Q for ep in raw_eps], ts.q_ref)
            kw = dict(r=args.r, method=methods[0], n_coords=max(2 * args.r, args.r + 20),
                      power_iters=args.power_iters, seed=args.seed)
            t0 = time.perf_counter()
            dpod = StreamingPOD(**kw, executor=DaskExecutor(client)).fit(snaps)
            t_d = time.perf_counter() - t0
            diff = max(float(np.max(np.abs(a - b))) for a, b in
                       zip(dpod.coords_, red.pod.coords_)) / red.pod.singular_values_[0]
            print(f'Dask LocalCluster ({args.dask} workers): POD in {t_d:.1f} s; max rel. '
                  f'difference of coordinates vs local {diff:.2e}')
            results['dask'] = {'seconds': t_d, 'rel_diff': diff}
    print('JSON ' + json.dumps(results))
    if not args.keep:
        shutil.rmtree(path, ignore_errors=True)
    return 0


if __name__ == '__main__':
    from _entry import run
    run(main)
