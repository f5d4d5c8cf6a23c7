#!/usr/bin/env python3
"""Compare two ``soft-rom demo`` summaries: do the models give the same results.

Every number of ``study1``, ``study2`` and ``replay`` in ``summary.json`` is matched between a
baseline and a new run, path by path, and grouped by method (LOpInf, DMDc, ERA/OKID, the
cubic LOpInf, other). Timings (``fit_seconds``, ``wall_seconds``, ``timings``) are left out.
For each group the largest relative difference is printed, with the path where it is; the
linear methods must agree to ``--rtol`` (default 1e-12), the cubic row is reported beside
the baseline (it may change with the held-out choice of its settings).

The replay's Kalman check of a summary written before the report rewrite (issue 28) is
matched under its new key (``replay/kalman/ratio``). The replay's final status and the other
keys of its old check depend on the monitor's settings (thresholds, a second model), not on
the models: they are reported, not checked.

Usage::

    python benchmarks/compare_demo.py BASELINE/summary.json NEW/summary.json [--rtol 1e-12]

Exit status 0 when LOpInf, DMDc and ERA/OKID agree, 1 otherwise.

**Comparing two commits fairly.** Two things move the numbers by more than 1e-12 without
any change to the learners, so hold both fixed:

* *The episodes.* The simulator's fast path (CHOLMOD, numba) gives the same trajectories to
  about 1e-13, not bit for bit; run both commits on the same bags (``--bags``).
* *The BLAS threads.* The study runs its fits on one BLAS thread; an older commit that did
  not must be run with ``OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1``. The pre-pipeline code
  (d4907b4) on two threads differs from itself on one by up to 1.1e-8 (LOpInf) and
  3.7e-11 (DMDc): unstable models amplify the rounding of a threaded SVD.

For example (the pre-pipeline commit in a worktree, the same environment)::

    cp -r BASE/bags bags_a; cp -r BASE/bags bags_b
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 PYTHONPATH=worktree_d4907b4 \\
        python -c "from soft_rom.cli import main; main(['demo', '-o', 'old', '--bags', 'bags_a'])"
    soft-rom demo -o new --bags bags_b
    python benchmarks/compare_demo.py old/summary.json new/summary.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

TIMING_KEYS = ('fit_seconds', 'wall_seconds', 'timings', 'seconds')
GROUPS = ('lopinf_cubic', 'lopinf', 'dmdc', 'era')
#: Keys of an older summary, under their present name.
RENAMED = {('replay', 'Kalman check LOpInf r=4: ratio (target <= 0.5)'):
           ('replay', 'kalman', 'ratio')}


def leaves(obj: Any, path: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    """Every scalar of a JSON document by its path (list items by index)."""
    out: dict[tuple[str, ...], Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(leaves(v, path + (str(k),)))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.update(leaves(v, path + (str(i),)))
    else:
        out[path] = obj
    return out


def group_of(path: tuple[str, ...], doc: dict[str, Any]) -> str:
    """The method a number belongs to (by the path's keys; replay: the LOpInf ROM)."""
    if path[0] == 'replay':
        settings = path[1] == 'final_status' or (path[1].startswith('Kalman check')
                                                 and path not in RENAMED)
        return 'other' if settings else 'lopinf'
    for g in GROUPS:
        if g in path:
            return g
    if path[0] == 'conclusions':
        return 'other'
    return 'other'


def rel(a: Any, b: Any) -> float:
    if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, (int, float)) \
            or not isinstance(b, (int, float)):
        return 0.0 if a == b else math.inf
    if a == b:
        return 0.0
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
        return math.inf
    return abs(a - b) / max(abs(a), abs(b))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('baseline')
    ap.add_argument('new')
    ap.add_argument('--rtol', type=float, default=1e-12)
    args = ap.parse_args(argv)
    with open(args.baseline, encoding='utf-8') as fh:
        base = json.load(fh)
    with open(args.new, encoding='utf-8') as fh:
        new = json.load(fh)
    lb, ln = {}, {}
    for key in ('study1', 'study2', 'replay'):
        lb.update(leaves(base.get(key, {}), (key,)))
        ln.update(leaves(new.get(key, {}), (key,)))
    worst: dict[str, tuple[float, tuple[str, ...]]] = {}
    counts: dict[str, int] = {}
    missing = []
    for path, a in lb.items():
        if any(k in TIMING_KEYS for k in path):
            continue
        g = group_of(path, base)
        counts[g] = counts.get(g, 0) + 1
        if RENAMED.get(path, path) not in ln:
            missing.append(path)
            worst[g] = (math.inf, path)
            continue
        d = rel(a, ln[RENAMED.get(path, path)])
        if d > worst.get(g, (-1.0, ()))[0]:
            worst[g] = (d, path)
    ok = True
    for g in ('lopinf', 'dmdc', 'era', 'lopinf_cubic', 'other'):
        if g not in counts:
            continue
        d, path = worst.get(g, (0.0, ()))
        strict = g in ('lopinf', 'dmdc', 'era')
        verdict = ('OK' if d <= args.rtol else 'DIFFERENT') if strict else 'reported'
        ok &= (d <= args.rtol) or not strict
        print(f'{g:<13} {counts[g]:>4} numbers  max rel. diff {d:.3e}  {verdict}'
              + (f'  (at {"/".join(path)})' if d > 0 else ''))
    if missing:
        print(f'missing in the new summary: {["/".join(p) for p in missing[:10]]}')
    cub_b = base.get('study2', {}).get('cubic_vs_linear', {})
    cub_n = new.get('study2', {}).get('cubic_vs_linear', {})
    for name, doc in (('baseline', base), ('new', new)):
        s1 = doc.get('study1', {}).get('best', {}).get('lopinf_cubic', {})
        s2 = doc.get('study2', {}).get('test_dev', {}).get('lopinf_cubic', {})
        print(f'cubic row, {name:<8}: study 1 test dev. {s1.get("test_dev")}, study 2 test '
              f'dev. {json.dumps(s2)}')
    if cub_b or cub_n:
        print(f'cubic / linear ratio, baseline {json.dumps(cub_b.get("ratio"))}; '
              f'new {json.dumps(cub_n.get("ratio"))}')
    sel = new.get('study2', {}).get('forces_selection')
    if sel:
        print(f'cubic forces selection (new): {json.dumps(sel)}')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
