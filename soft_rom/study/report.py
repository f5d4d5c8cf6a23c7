"""Markdown report of the studies: tables of our numbers with the paper's beside them."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from soft_rom.study import paper
from soft_rom.study.figures import LABELS

__all__ = ['markdown_table', 'study_report']


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if v != v or v in (float('inf'), float('-inf')):
            return str(v)
        return f'{v:.4f}' if 1e-3 <= abs(v) < 1e3 or v == 0 else f'{v:.2e}'
    return str(v)


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table."""
    lines = ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(_fmt(v) for v in row) + ' |' for row in rows]
    return '\n'.join(lines)


def _extrapolation_section(s1: Mapping[str, Any]) -> list[str]:
    out = ['## Study 1: time extrapolation (train on Ep 1, t < %.2f s; test %.2f–%.2f s)'
           % (s1['t_train'], s1['t_train'], s1['t_end']), '',
           '![errors vs r](errors_vs_r.png)', '',
           "Relative output error `‖Y − Ŷ‖_F / ‖Y‖_F` (the paper's, absolute coordinates) and "
           'the same on deviations from `y_ref` ("dev."), for each reduced dimension. Paper: the '
           'numbers of its Fig. 2 for the same r.', '']
    for method in ('lopinf', 'dmdc', 'era', 'lopinf_cubic'):
        if method not in s1['curves']:
            continue
        c = s1['curves'][method]
        pp = paper.TIME_EXTRAPOLATION.get(method, {})
        pr = dict(zip(pp.get('r', []), zip(pp.get('train', []), pp.get('test', []))))
        rows = []
        for i, r in enumerate(c['r']):
            p_train, p_test = pr.get(r, ('–', '–'))
            rows.append([r, c['train'][i], c['test'][i], c['train_dev'][i], c['test_dev'][i],
                         c['stability_margin'][i], p_train, p_test])
        out += [f'### {LABELS[method]}', '', markdown_table(
            ['r', 'train', 'test', 'train (dev.)', 'test (dev.)', 'stability margin',
             'paper train', 'paper test'], rows), '']
    best = s1['best']
    out += ["Best ROM of each method on the training data (plotted below, as in the paper's "
            'Fig. 3):', '', markdown_table(
                ['method', 'r', 'train', 'test', 'train (dev.)', 'test (dev.)', 'paper r'],
                [[LABELS[m], b['r'], b['train'], b['test'], b['train_dev'], b['test_dev'],
                  paper.EXTRAPOLATION_BEST_R.get(m, '–')] for m, b in best.items()]), '',
            '![output traces](traces.png)', '',
            f'Outputs shown: {", ".join(s1["trace_names"])} (the magenta line ends training).', '']
    return out


def _unseen_section(s2: Mapping[str, Any]) -> list[str]:
    out = ['## Study 2: robustness to unseen inputs (train on Ep 1 + Ep 2; test Ep 3–6)', '',
           'ROMs chosen by their training error, as in the paper: '
           + ', '.join(f'{LABELS[m]} r = {s2["chosen"][m]["r"]}' for m in s2['chosen'])
           + f'. ERA/OKID fits one episode; it was fitted on Ep 1 and on Ep 2 separately and the '
           f'one that does better on the test episodes kept ({s2["era_episode"]}), as the paper '
           f'does.', '', '![test errors](bars.png)', '']
    eps = list(next(iter(s2['test'].values())).keys())
    rows = []
    for m, per_ep in s2['test'].items():
        rows.append([LABELS[m], s2['chosen'][m]['r']] + [per_ep[e] for e in eps]
                    + [paper.UNSEEN_INPUTS.get(m, {}).get(e, '–') for e in eps])
    out += [markdown_table(['method', 'r'] + [f'{e} (ours)' for e in eps]
                           + [f'{e} (paper)' for e in eps], rows), '']
    rows = [[LABELS[m], s2['chosen'][m]['r']] + [per_ep[e] for e in eps]
            for m, per_ep in s2['test_dev'].items()]
    out += ['On deviations from `y_ref`:', '',
            markdown_table(['method', 'r'] + eps, rows), '',
            f'![centerline shapes]({s2["shapes_png"]})', '',
            f'Centerline shapes (x–z, mm) of the FOM and the ROMs for {s2["shape_episode"]} '
            f'at t = {", ".join(f"{t:g}" for t in s2["shape_times"])} s.', '']
    cub = s2.get('cubic_vs_linear')
    if cub:
        out += [f'Cubic vs linear LOpInf at the same r = {cub["r"]} (deviation errors; target: '
                f'cubic <= 0.5 x linear on at least 3 of {len(cub["ratio"])} episodes, met on '
                f'{cub["wins"]}):', '', markdown_table(
                    ['episode', 'linear', 'cubic', 'cubic / linear'],
                    [[e, cub['linear'][e], cub['cubic'][e], cub['ratio'][e]]
                     for e in cub['ratio']]), '']
    long = s2.get('long_inputs')
    if long:
        out += ['Inputs 10x longer than a training episode (test inputs chained): '
                + '; '.join(f'{LABELS.get(m, m)}: {v}' for m, v in long.items()), '']
    return out


def study_report(summary: Mapping[str, Any]) -> str:
    """The whole Markdown report from the study summary dictionary."""
    lines = ['# soft_rom study report', '',
             'Reproduction of the two studies of Sharma et al., *Data-driven Model Reduction for '
             'Soft Robots via Lagrangian Operator Inference* (section 3) on the embedded eel FOM, '
             'through ROS 2 bags and the converter.', '']
    fom = summary.get('fom', {})
    if fom:
        lines += ['## Full-order model and data', '', markdown_table(
            ['quantity', 'value'], [[k, v] for k, v in fom.items()]), '']
    if 'study1' in summary:
        lines += _extrapolation_section(summary['study1'])
    if 'study2' in summary:
        lines += _unseen_section(summary['study2'])
    if summary.get('replay'):
        lines += ['## Replay through the predictor core', '', markdown_table(
            ['quantity', 'value'], [[k, v] for k, v in summary['replay'].items()]), '']
    if summary.get('conclusions'):
        lines += ["## Which of the paper's conclusions hold here", '']
        lines += [f'- {c}' for c in summary['conclusions']] + ['']
    if summary.get('timings'):
        lines += ['## Timings', '', markdown_table(
            ['step', 'seconds'], [[k, v] for k, v in summary['timings'].items()]), '']
    return '\n'.join(lines)
