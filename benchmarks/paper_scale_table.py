#!/usr/bin/env python3
"""The README's paper-scale section, written from a staged study's ``summary.json``.

Prints (or, with ``--readme``, writes between the markers ``<!-- paper-scale:begin -->`` and
``<!-- paper-scale:end -->`` of the README) the cost of each stage (wall time, peak RSS), the
disk used, the streaming fit against one cold read of the training set, and the results
beside the paper's Fig. 2 and Fig. 4 values with the orderings checked.

Usage::

    python benchmarks/paper_scale_table.py STUDY/summary.json
    python benchmarks/paper_scale_table.py STUDY/summary.json --readme README.md
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
from typing import Any

from soft_rom.study import paper

BEGIN, END = '<!-- paper-scale:begin -->', '<!-- paper-scale:end -->'
LABELS = {'lopinf': 'LOpInf', 'dmdc': 'DMDc', 'era': 'ERA/OKID'}


def _fmt_s(seconds: float | None) -> str:
    if seconds is None:
        return '-'
    m, s = divmod(int(round(seconds)), 60)
    return f'{m} min {s:02d} s' if m else f'{s} s'


def _num(v: Any, spec: str = '.4f') -> str:
    return '-' if v is None else format(v, spec)


def section(summary: dict[str, Any], *, machine: str = '') -> str:
    """The Markdown section for ``summary`` (a staged run's ``summary.json``)."""
    scale = summary.get('paper_scale', {})
    stages = scale.get('stages', {})
    fom = summary.get('fom', {})
    cfg = summary.get('config', {})
    lines = [f'Measured with `soft-rom study --resolution {cfg.get("resolution")} --jobs '
             f'{cfg.get("jobs")}`: {fom.get("state DOF n", 0):,} DOF, '
             f'{fom.get("episodes")} episodes of {fom.get("samples per episode")} samples'
             + (f', {machine}' if machine else '') + '.', '',
             '| stage | wall time | peak RSS |', '|---|---|---|']
    total = 0.0
    for name, rec in stages.items():
        total += rec.get('wall_s') or 0.0
        lines.append(f'| {name} | {_fmt_s(rec.get("wall_s"))} | '
                     f'{_num(rec.get("peak_rss_gb"), ".2f")} GB |')
    lines.append(f'| **total** | **{_fmt_s(total)}** | |')
    disk = scale.get('disk', {})
    lines += ['', f'Disk: bags {disk.get("bag_bytes", 0) / 1e9:.1f} GB, training set '
              f'{disk.get("training_set_bytes", 0) / 1e9:.1f} GB.']
    fit = scale.get('streaming_fit_vs_cold_read', {})
    if fit.get('ratio') is not None:
        read = (f'one cold sequential read of the same {fit["bytes"] / 1e9:.1f} GB takes '
                f'{_fmt_s(fit["cold_read_s"])}')
        if fit.get('per_pass_ratio') is not None:
            lines.append(
                f'Streaming fit (study 2, LOpInf, every r, Ep 1 + Ep 2): {read}; the '
                f'{fit["pod_method"]} POD reads the data {fit["passes"]} times in '
                f'{_fmt_s(fit["pod_s"])}, **{fit["per_pass_ratio"]:.2f} x a read per pass** '
                f'(goal <= 2 x, compared per pass as `bench_scale.py` does). The whole sweep '
                f'(every pass and the fits of every r) takes {_fmt_s(fit["lopinf_fit_s"])}, '
                f'{fit["ratio"]:.2f} x one read.')
        else:
            lines.append(f'Streaming fit (study 2, LOpInf, every r, Ep 1 + Ep 2): '
                         f'{_fmt_s(fit["lopinf_fit_s"])}; {read}: {fit["ratio"]:.2f} x.')
    s1, s2 = summary.get('study1', {}), summary.get('study2', {})
    lines += ['', '| | ours | paper |', '|---|---|---|']
    for m in ('lopinf', 'dmdc', 'era'):
        b = s1.get('best', {}).get(m)
        p = paper.TIME_EXTRAPOLATION[m]
        r_p = paper.EXTRAPOLATION_BEST_R[m]
        ours = f'{_num(b["test"])} (r = {b["r"]})' if b else 'failed'
        lines.append(f'| time extrapolation, {LABELS[m]} test error | {ours} | '
                     f'{p["test"][p["r"].index(r_p)]:.4f} (r = {r_p}) |')
    for m in ('lopinf', 'dmdc', 'era'):
        errs = s2.get('test', {}).get(m, {})
        r = s2.get('chosen', {}).get(m, {}).get('r')
        ours = (f'{min(errs.values()):.4f}-{max(errs.values()):.4f} (r = {r})' if errs
                else 'failed')
        pv = paper.UNSEEN_INPUTS[m].values()
        lines.append(f'| unseen inputs, {LABELS[m]} test errors | {ours} | '
                     f'{min(pv):.4f}-{max(pv):.4f} (r = {paper.UNSEEN_INPUTS_R[m]}) |')
    lines += ['', 'Orderings (the paper: LOpInf < DMDc in both studies, LOpInf < ERA/OKID on '
              'unseen inputs):', '']
    best = s1.get('best', {})
    if {'lopinf', 'dmdc'} <= set(best):
        ok = best['lopinf']['test'] < best['dmdc']['test']
        lines.append(f'- time extrapolation, LOpInf < DMDc: {"yes" if ok else "**no**"}')
    test = s2.get('test', {})
    for other in ('dmdc', 'era'):
        if {'lopinf', other} <= set(test):
            eps = list(test['lopinf'])
            wins = sum(test['lopinf'][e] < test[other][e] for e in eps)
            lines.append(f'- unseen inputs, LOpInf < {LABELS[other]}: {wins} of {len(eps)} '
                         'test episodes')
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('summary', type=Path, help="the staged run's summary.json")
    parser.add_argument('--readme', type=Path, default=None,
                        help='write the section between the markers of this README')
    parser.add_argument('--machine', default='', help='e.g. "idle 2-core machine, 24 GB"')
    args = parser.parse_args(argv)
    text = section(json.loads(args.summary.read_text(encoding='utf-8')), machine=args.machine)
    if args.readme is None:
        print(text, end='')
        return 0
    readme = args.readme.read_text(encoding='utf-8')
    if BEGIN not in readme or END not in readme:
        print(f'{args.readme}: no {BEGIN} ... {END} markers', file=sys.stderr)
        return 2
    head, rest = readme.split(BEGIN, 1)
    _old, tail = rest.split(END, 1)
    args.readme.write_text(f'{head}{BEGIN}\n{text}{END}{tail}', encoding='utf-8')
    print(f'wrote the paper-scale section of {args.readme}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
