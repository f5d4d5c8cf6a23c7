"""The cubic LOpInf's held-out selection: the one selection against a former one, A/B.

On a training set (the demo's ``data.zarr``, or ``soft-rom simulate`` + ``convert`` data), the
selection that ``soft-rom fit --forces cubic`` and study 2's cubic slot run is timed in one
process against the selection of an earlier commit (default 6ef4db1, before the selection was
one; its ``soft_rom/pipeline/cubic.py`` is read from git): the held-out selection plus the
final cubic fit at the chosen settings, on the same reduced data, wall and CPU time. Each
chosen cubic model and the linear LOpInf are scored on the test episodes (relative deviation
error), with the verdict. Run from the repository root::

    .venv/bin/python benchmarks/bench_cubic_selection.py DEMO_OUT/data.zarr \\
        [--train ep1,ep2] [--test ep3,ep4,ep5,ep6] [--r 4] [--baseline 6ef4db1]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np

from soft_rom.dataset import TrainingSet
from soft_rom.evaluation import predict
from soft_rom.metrics import relative_deviation_error
from soft_rom.pipeline import (
    FitSettings,
    HeldOutCubicSelection,
    make_learner,
    open_training_data,
    replace_learner,
)
from soft_rom.reduce import InMemoryPOD


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f'load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores'


def _baseline(commit: str) -> Any:
    """The module ``soft_rom/pipeline/cubic.py`` of ``commit``, imported from a temp file."""
    root = Path(__file__).resolve().parents[1]
    text = subprocess.run(['git', 'show', f'{commit}:soft_rom/pipeline/cubic.py'], cwd=root,
                          check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / 'baseline_cubic.py'
    path.write_text(text, encoding='utf-8')
    spec = importlib.util.spec_from_file_location('baseline_cubic', path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules['baseline_cubic'] = module          # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('training_set', type=Path)
    ap.add_argument('--train', default='ep1,ep2')
    ap.add_argument('--test', default='ep3,ep4,ep5,ep6')
    ap.add_argument('--r', type=int, default=4)
    ap.add_argument('--baseline', default='6ef4db1')
    args = ap.parse_args()
    print(_load(), flush=True)
    ts = TrainingSet.open(args.training_set)
    old = _baseline(args.baseline)
    data = open_training_data(ts, episodes=args.train)
    cubic = make_learner('lopinf', FitSettings(forces='cubic'), 'state')
    linear = make_learner('lopinf', FitSettings(), 'state')
    red = InMemoryPOD().reduce(data, basis='pod', r=args.r, what='LOpInf')
    tests = [ts[name] for name in args.test.split(',')]

    def score(model: Any) -> np.ndarray:
        return np.array([relative_deviation_error(ep.Y, predict(model, ep), ts.y_ref)
                         for ep in tests])

    lin = score(replace_learner(linear, r=args.r).fit(red).model_)
    print(f'linear LOpInf r={args.r}, test deviation error {np.round(lin, 3)}', flush=True)
    times = {}
    for name in ('baseline', 'one selection'):
        t0, c0 = time.perf_counter(), time.process_time()
        if name == 'baseline':
            v = old.HeldOutCubicSelection().select(red, cubic, args.r)
            opts, kept = v.options, v.forces
        else:
            v = HeldOutCubicSelection().select(red, cubic, args.r, linear=linear)
            opts, kept = v.cubic_options, v.forces
        model = replace_learner(cubic, r=args.r, cubic_options=opts).fit(red).model_
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        times[name] = (wall, cpu)
        cub = score(model)
        print(f'{name}: selection + final cubic fit {wall:.1f} s wall, {cpu:.1f} s CPU; '
              f'reg {opts["reg"]:g}, eps4 {opts["eps4"]:g}; held out linear '
              f'{v.linear_error:.4g}, cubic {v.cubic_error:.4g}; kept by the rule: {kept}',
              flush=True)
        print('  candidates: ' + ', '.join(f'({c["reg"]:g}, {c["eps4"]:g}) {c["error"]:.4g}'
                                           for c in v.candidates))
        print(f'  cubic test deviation error {np.round(cub, 3)}, / linear '
              f'{np.round(cub / lin, 2)}', flush=True)
    (w0, c0), (w1, c1) = times['baseline'], times['one selection']
    print(f'one selection / baseline: wall {w1 / w0:.2f}x, CPU {c1 / c0:.2f}x; {_load()}')


if __name__ == '__main__':
    from _entry import run
    run(main)
