#!/usr/bin/env python3
"""A/B a benchmark against an older revision of soft_rom, in the same run.

The revision's ``soft_rom`` package is exported with ``git archive`` into a temporary folder;
the benchmark script (of this tree) then runs in subprocesses alternately against that
package (``PYTHONPATH``) and against this tree, ``--rounds`` times each, and writes its
figures to JSON (``--json-out``). The best (smallest) time of each figure per side is printed
with the ratio this tree / baseline (below 1: faster now) and the machine's load average
before and after.

Usage::

    python benchmarks/ab.py [--rev d4907b4] [--rounds 3] -- benchmarks/bench_lopinf.py --repeat 5
    python benchmarks/ab.py -- benchmarks/bench_predictor.py --k 2000
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

REPO = Path(__file__).resolve().parents[1]


def export(rev: str, dest: Path) -> Path:
    """The package of ``rev`` under ``dest`` (``git archive``); returns the tree's root."""
    archive = subprocess.run(['git', '-C', str(REPO), 'archive', rev, 'soft_rom'],
                             capture_output=True, check=True).stdout
    dest.mkdir(parents=True, exist_ok=True)
    subprocess.run(['tar', '-x', '-C', str(dest)], input=archive, check=True)
    return dest


def run(script: str, args: list[str], root: Path, out: Path) -> dict[str, float]:
    """One run of the benchmark against the package under ``root``; its figures."""
    env = dict(os.environ, PYTHONPATH=str(root))
    res = subprocess.run([sys.executable, script, *args, '--json-out', str(out)], env=env,
                         cwd=REPO, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f'{script} against {root} failed:\n{res.stdout[-2000:]}'
                         f'{res.stderr[-2000:]}')
    figures = json.loads(out.read_text())
    out.unlink()
    return {str(k): float(v) for k, v in figures.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--rev', default='d4907b4', help='baseline revision (default d4907b4)')
    ap.add_argument('--rounds', type=int, default=3)
    ap.add_argument('bench', nargs=argparse.REMAINDER,
                    help='-- SCRIPT [ARGS...]: the benchmark and its options')
    args = ap.parse_args(argv)
    bench = [a for a in args.bench if a != '--']
    if not bench:
        ap.error('give the benchmark after --')
    script, bench_args = bench[0], bench[1:]
    load0 = os.getloadavg()
    tmp = Path(tempfile.mkdtemp(prefix='soft_rom_ab_'))
    try:
        base = export(args.rev, tmp / 'base')
        sides = {f'baseline {args.rev}': base, 'this tree': REPO}
        best: dict[str, dict[str, float]] = {name: {} for name in sides}
        for i in range(args.rounds):
            for name, root in sides.items():
                figures = run(script, bench_args, root, tmp / f'{i}.json')
                for key, value in figures.items():
                    best[name][key] = min(best[name].get(key, value), value)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    load1 = os.getloadavg()
    (a_name, a), (b_name, b) = best.items()
    width = max(len(k) for k in a) if a else 10
    print(f'{script} {" ".join(bench_args)}: best of {args.rounds} alternating runs each')
    print(f'{"figure":<{width}} {a_name:>16} {b_name:>12} {"ratio":>7}')
    for key in a:
        if key in b:
            ratio = b[key] / a[key] if a[key] else float('nan')
            print(f'{key:<{width}} {a[key]:>16.4g} {b[key]:>12.4g} {ratio:>7.3f}')
    print(f'load average before {load0[0]:.1f}, after {load1[0]:.1f} '
          f'({os.cpu_count()} cpus)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
