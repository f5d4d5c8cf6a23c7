"""Benchmark: the demo's wall time, idle and beside a CPU-bound process, by BLAS thread policy.

Each run is the demo exactly (:func:`soft_rom.study.run.run_study` with the demo's r grids,
the replay and the report) in a fresh child process writing to a fresh folder, with

- ``1``: one BLAS thread for the run and for each simulation worker (what ``soft-rom demo``
  does, :attr:`StudyConfig.blas_threads`), or
- ``default``: the BLAS library's default (one thread per core; the behaviour before), and
- ``idle``: nothing else started, or ``busy``: one ``while True: pass`` process beside it.

Runs are interleaved (policy and load alternate run by run), so the A/B ratios compare runs
under the same conditions on a shared machine. It prints each run's wall time, stage times,
peak memory and the machine's 1-minute load average before and after, then per policy the
median ``busy / idle`` ratio (target <= 2.5) and per load the median ``1 / default`` ratio.

Run (about 3 min per run idle on 2 cores; 12 runs by default)::

    .venv/bin/python benchmarks/bench_demo.py             # 3 x {1, default} x {idle, busy}
    .venv/bin/python benchmarks/bench_demo.py --policies 1   # the demo as shipped only

On an idle machine the ``idle`` runs of policy ``1`` are the figure to quote for ``soft-rom
demo``; the same as one command: ``/usr/bin/time -v .venv/bin/soft-rom demo -o D``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import shutil
import statistics
import subprocess
import sys
import tempfile

_CHILD = """
import json, resource, sys, time
from soft_rom.cli.demo import DEMO_R_DMDC, DEMO_R_ERA, DEMO_R_LOPINF
from soft_rom.study.run import run_study, StudyConfig
threads = None if sys.argv[2] == 'default' else int(sys.argv[2])
cfg = StudyConfig(r_lopinf=DEMO_R_LOPINF, r_dmdc=DEMO_R_DMDC, r_era=DEMO_R_ERA, jobs=2,
                  blas_threads=threads)
t0 = time.perf_counter()
summary = run_study(sys.argv[1], cfg, progress=False, replay=True)
wall = time.perf_counter() - t0
rss = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
          resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
print(json.dumps({'wall': wall, 'timings': summary['timings'], 'rss_mb': rss / 1024,
                  'status': summary.get('replay', {}).get('final_status')}))
"""


def _run(folder: Path, policy: str, busy: bool) -> dict:
    burner = None
    if busy:
        burner = subprocess.Popen([sys.executable, '-c', 'while True: pass'])
    load0 = os.getloadavg()[0]
    try:
        out = subprocess.run([sys.executable, '-c', _CHILD, str(folder), policy],
                             capture_output=True, text=True, check=False)
    finally:
        if burner is not None:
            burner.kill()
            burner.wait()
    shutil.rmtree(folder, ignore_errors=True)
    if out.returncode != 0:
        raise SystemExit(f'demo run failed:\n{out.stderr[-3000:]}')
    result = json.loads(out.stdout.strip().splitlines()[-1])
    result.update(policy=policy, load='busy' if busy else 'idle', load_before=load0,
                  load_after=os.getloadavg()[0])
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=3, help='runs per policy and load')
    parser.add_argument('--policies', nargs='+', default=['1', 'default'],
                        help="BLAS threads: '1' (the demo) and/or 'default'")
    parser.add_argument('--loads', nargs='+', default=['idle', 'busy'],
                        choices=('idle', 'busy'))
    parser.add_argument('--dir', type=Path, default=None, help='scratch folder')
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix='bench_demo_', dir=args.dir))
    print(f'{os.cpu_count()} CPUs; load average at the start {os.getloadavg()[0]:.2f}')
    results = []
    try:
        for i in range(args.runs):
            for load in args.loads:
                for policy in args.policies:
                    r = _run(root / f'demo_{i}_{policy}_{load}', policy, load == 'busy')
                    results.append(r)
                    stages = ', '.join(f'{k} {v:.0f}' for k, v in r['timings'].items())
                    print(f'run {i + 1} threads={policy:<7s} {load}: {r["wall"]:6.1f} s '
                          f'({stages}); peak RSS {r["rss_mb"]:.0f} MB; load '
                          f'{r["load_before"]:.2f} -> {r["load_after"]:.2f}; replay '
                          f'{r["status"]}', flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)

    def median(policy: str, load: str) -> float | None:
        walls = [r['wall'] for r in results if r['policy'] == policy and r['load'] == load]
        return statistics.median(walls) if walls else None

    print('\nmedian wall time [s]:')
    for policy in args.policies:
        idle, busy = median(policy, 'idle'), median(policy, 'busy')
        line = f'  threads={policy:<7s} idle {idle or float("nan"):6.1f}  busy ' \
               f'{busy or float("nan"):6.1f}'
        if idle and busy:
            line += f'  busy/idle {busy / idle:.2f} (target <= 2.5)'
        print(line)
    if '1' in args.policies and 'default' in args.policies:
        for load in args.loads:
            a, b = median('1', load), median('default', load)
            if a and b:
                print(f'  {load}: threads=1 / default {a / b:.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
