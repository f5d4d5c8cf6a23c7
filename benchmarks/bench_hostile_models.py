"""Cost of refusing (or loading) hostile model files of at most 2 MB.

Run: ``.venv/bin/python benchmarks/bench_hostile_models.py``

Each file is loaded by ``load_model`` (then ``trust_issues()`` and ``soft-rom info``'s
``describe`` when it loads) in a fresh process that reports its wall time and peak RSS;
the baseline is the same process importing soft_rom and numpy/scipy only. Targets: at
most 1 s and 200 MB peak RSS per file. BLAS runs single-threaded in the probes (as in the
other benchmarks): on a loaded 2-core machine a multi-threaded BLAS thrashes (measured
13.8 s instead of 0.26 s for an r = 256 LOpInf file when that was the limit, 3.1 s with the
limit lowered to 512 states); set ``--threads 0`` to keep the library's default.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import zipfile

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))

import _hostile as h  # noqa: E402

_PROBE = r"""
import resource, sys, time
import numpy, scipy.linalg
from soft_rom.errors import ModelFileError
from soft_rom.models import load_model
from soft_rom.cli.info import describe, format_text
t0 = time.perf_counter()
outcome = 'baseline'
if sys.argv[1] != '-':
    try:
        m = load_model(sys.argv[1])
        m.trust_issues()
        format_text(describe(sys.argv[1]))
        outcome = 'loaded' + ('' if m.trusted else ' (not trusted)')
    except ModelFileError as err:
        outcome = 'ModelFileError'
wall = time.perf_counter() - t0
print(wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, outcome)
"""


def _big_model(path: Path, r: int, kind: str) -> Path:
    if kind == 'lopinf':
        arrays = {'K': np.eye(r) * 100.0, 'C': np.eye(r), 'B': np.ones((r, 2)),
                  'E': np.ones((4, r))}
        cls, n = 'SecondOrderModel', 2 * r
    else:
        arrays = {'A': np.eye(r) * 0.5, 'B': np.ones((r, 2)), 'C': np.ones((4, r)),
                  'D': np.zeros((4, 2))}
        cls, n = 'DiscreteModel', r
    header = {**h.second_order().header(), 'class': cls, 'r': r, 'n_states': n,
              'method': 'lopinf' if kind == 'lopinf' else 'dmdc', 'input_names': None,
              'output_names': None, 'input_units': None, 'output_units': None}
    members = {f'{k}.npy': h.npy_bytes(v) for k, v in arrays.items()}
    members['y_ref.npy'] = h.npy_bytes(np.zeros(4))
    members['__metadata__.npy'] = h.npy_bytes(h.meta_array(header))
    return h.write_zip(path, members, compression=zipfile.ZIP_DEFLATED)


def build(d: Path) -> dict[str, Path]:
    model = h.second_order()
    files: dict[str, Path] = {}
    files['valid (r=3)'] = model.save(d / 'valid.npz')
    files['largest accepted LOpInf (r=128)'] = _big_model(d / 'lop128.npz', 128, 'lopinf')
    files['largest accepted DMDc (r=256)'] = _big_model(d / 'dmd256.npz', 256, 'dmdc')
    files['r = 129 LOpInf'] = _big_model(d / 'lop129.npz', 129, 'lopinf')
    files['r = 1500 LOpInf'] = _big_model(d / 'lop1500.npz', 1500, 'lopinf')
    members = h.members_of(model)
    members['evil.npy'] = h.npy_bytes(np.zeros(10))
    p = h.write_zip(d / 'unknown.npz', members, compression=zipfile.ZIP_DEFLATED)
    files['unknown entry declaring 2 GB'] = h.declare_size(p, 'evil.npy', 2_000_000_000)
    p = h.write_zip(d / 'k12500.npz', h.members_of(model), compression=zipfile.ZIP_DEFLATED)
    files['K declared 12,500 x 12,500'] = h.declare_size(p, 'K.npy', 12_500 ** 2 * 8)
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    files['npy shape of 7.28 TiB'] = h.with_arrays(
        model, d / 'tib.npz', K=h.npy_raw(header + '    \n', bytes(72)))
    files['JSON nested 1,000,000 deep'] = h.with_metadata_text(model, d / 'deep.npz',
                                                              '[' * 1_000_000)
    files['JSON 5,000-digit integer'] = h.with_metadata_text(
        model, d / 'int.npz', json.dumps(model.header()).replace('"r": 3', '"r": ' + '7' * 5000))
    files['metadata 1.9 MB of list'] = h.with_metadata_text(
        model, d / 'longlist.npz', json.dumps({**model.header(), 'metadata': {
            'x': [0] * 600_000}}))
    files['corrupt deflate'] = h.corrupt_deflate(model, d / 'deflate.npz')
    files['multi-disk ZIP64'] = h.multi_disk_zip64(d / 'zip64.npz')
    files['dt = 1e300'] = h.with_header(model, d / 'dt.npz', dt=1e300)
    files['K = 1e140 (overflows over a step)'] = h.with_arrays(
        model, d / 'stiff.npz', K=-np.eye(3) * 1e140, C=np.zeros((3, 3)))
    files['spectral radius 1.5'] = h.discrete(radius=1.5).save(d / 'unstable.npz')
    return files


def _probe(path: str, threads: int) -> tuple[float, float, str]:
    env = dict(os.environ)
    if threads:
        for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
            env[var] = str(threads)
    out = subprocess.run([sys.executable, '-c', _PROBE, path], capture_output=True, text=True,
                         check=True, env=env).stdout.split(maxsplit=2)
    return float(out[0]), float(out[1]), out[2].strip()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--threads', type=int, default=1,
                        help='BLAS threads in the probes (0: library default)')
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        files = build(Path(tmp))
        _, base_rss, _ = _probe('-', args.threads)
        print(f'baseline (imports only): peak RSS {base_rss:.0f} MB')
        print(f'{"file":38s} {"size":>9s} {"time [s]":>9s} {"RSS [MB]":>9s} {"+base":>6s}  '
              'outcome')
        worst_t = worst_m = 0.0
        for name, path in files.items():
            size = path.stat().st_size
            assert size <= 2 * 2**20, (name, size)
            wall, rss, outcome = _probe(str(path), args.threads)
            worst_t, worst_m = max(worst_t, wall), max(worst_m, rss)
            print(f'{name:38s} {size:>9,d} {wall:>9.3f} {rss:>9.0f} {rss - base_rss:>+6.0f}  '
                  f'{outcome}')
    ok = worst_t <= 1.0 and worst_m <= 200
    print(f'worst: {worst_t:.3f} s, {worst_m:.0f} MB peak RSS -> '
          f'{"within" if ok else "OVER"} the 1 s / 200 MB targets')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
