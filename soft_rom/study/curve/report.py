"""The learning curve's figure and Markdown report."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import math
from pathlib import Path
from typing import Any

import numpy as np

from soft_rom.study.report import markdown_table

__all__ = ['CURVE_LABELS', 'curve_figure', 'curve_report', 'curve_section']

CURVE_LABELS = {'lopinf': 'LOpInf', 'lopinf_cubic': 'LOpInf cubic', 'dmdc': 'DMDc',
                'dmdc_stable': 'DMDc stable', 'era': 'ERA/OKID (one episode)'}
_STYLE = {'lopinf': ('tab:red', '-', 'o'), 'lopinf_cubic': ('tab:purple', '-', 's'),
          'dmdc': ('tab:green', '--', 'v'), 'dmdc_stable': ('tab:olive', ':', '^'),
          'era': ('tab:blue', '-.', 'D')}
#: Errors above this are drawn at the top edge of the figure (blow-ups included).
_Y_MAX = 3.0


def _finite(v: Any) -> float:
    return float(v) if v is not None and math.isfinite(float(v)) else math.inf


def _stats(values: Sequence[Any]) -> tuple[float, float, float]:
    """Median, min and max of test errors (``inf`` counts as the largest)."""
    a = np.array([_finite(v) for v in values])
    return float(np.median(a)), float(np.min(a)), float(np.max(a))


def _test(point: Mapping[str, Any], method: str) -> list[Any] | None:
    entry = point.get(method)
    return None if not entry else entry.get('test')


def curve_figure(path: Path, summary: Mapping[str, Any]) -> Path:
    """Deviation error on the test episodes against training size, one panel per amplitude.

    The line is the median over the test episodes, the band their range; errors above
    the top of the axis (blow-ups included) are drawn on its edge with an open marker.
    """
    from soft_rom.study.figures import _plt
    plt = _plt()
    curves = summary['curves']
    # Each amplitude on its own scale: near-linear errors are 10-100 x smaller.
    fig, axes = plt.subplots(1, len(curves), figsize=(5.2 * len(curves), 4.2), squeeze=False)
    duration = float(summary['config']['duration'])
    for ax, (tag, curve) in zip(axes[0], curves.items()):
        ns = [p['n'] for p in curve['points']]
        for method, (color, ls, marker) in _STYLE.items():
            rows = [_test(p, method) for p in curve['points']]
            if all(r is None for r in rows):
                continue
            x = [n for n, r in zip(ns, rows) if r is not None]
            med, lo, hi = zip(*[_stats(r) for r in rows if r is not None])
            shown = np.minimum(med, _Y_MAX)
            ax.plot(x, shown, ls=ls, marker=marker, color=color, label=CURVE_LABELS[method])
            ax.fill_between(x, np.minimum(lo, _Y_MAX), np.minimum(hi, _Y_MAX), color=color,
                            alpha=0.12, lw=0)
            over = [(xi, _Y_MAX) for xi, m in zip(x, med) if m > _Y_MAX]
            if over:
                ax.plot(*zip(*over), ls='none', marker=marker, mfc='white', color=color)
        dist = curve.get('fom_vs_linearization')
        if dist:
            ax.axhline(float(np.median(dist)), color='0.4', ls=(0, (4, 3)), lw=1,
                       label='FOM vs its linearization')
        ax.set_xscale('log', base=2)
        ax.set_yscale('log')
        ax.set_xticks(ns)
        ax.set_xticklabels([f'{n}\n{n * duration:g} s' for n in ns])
        ax.set_ylim(top=_Y_MAX * 1.15)
        ax.set_xlabel('training episodes (data)')
        ax.set_title(f'{tag}: {len(curve["test_names"])} test episodes')
        ax.grid(True, which='both', alpha=0.3)
    for ax in axes[0]:
        ax.set_ylabel('relative deviation error (test)')
    axes[0][-1].legend(fontsize=7, loc='best')
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _fmt_err(values: Sequence[Any] | None) -> str:
    if not values:
        return '–'
    med, lo, hi = _stats(values)
    return f'{med:.3g} [{lo:.3g}–{hi:.3g}]' if math.isfinite(hi) else \
        f'{med:.3g} [{lo:.3g}–blow-up]'


def _cubic_rows(curve: Mapping[str, Any]) -> list[list[Any]]:
    rows = []
    for p in curve['points']:
        c = p.get('lopinf_cubic')
        if not c:
            continue
        choice = c.get('choice') or {}
        held = (f'{_finite(choice.get("error")):.3g} vs {_finite(c["held_out_linear"]):.3g}'
                if choice else '–')
        wins = sum(1 for x in c['ratio'] if x <= 0.5)
        long = c.get('long_inputs') or {}
        rows.append([p['n'], c['r'],
                     f'{choice.get("reg", "–"):g} / {choice.get("eps4", "–"):g}' if choice
                     else '–', held, c['forces_auto'],
                     ' / '.join(f'{x:.2f}' for x in c['ratio']), f'{wins} of {len(c["ratio"])}',
                     max(c['ratio_auto']),
                     ('bounded' if long.get('bounded') else 'NOT bounded')
                     + (f' ({long["peak_ratio"]:.2g}×)' if long.get('peak_ratio') else '')
                     if long else '–'])
    return rows


def curve_section(summary: Mapping[str, Any]) -> list[str]:
    """The report section of the learning curve (Markdown lines)."""
    cfg = summary['config']
    curves = summary['curves']
    out = ['## Learning curve: how much data before the cubic LOpInf pays off', '',
           f'Training sets of {", ".join(str(n) for n in cfg["sizes"])} episodes of '
           f'{cfg["duration"]:g} s (seed {cfg["seed"]}, each set the first episodes of the '
           f'next); {cfg["n_test"]} test episodes of seed {cfg["seed"] + 1}, never seen by a fit '
           "or a choice. Every setting (r; the cubic model's reg and eps4; whether the cubic "
           f'model is kept) is chosen on held-out training episodes ({cfg["folds"]} folds at '
           'most). ERA/OKID fits one episode: it gets one episode as long as the whole '
           f'training set (seed {cfg["seed"] + 2}). Errors: relative deviation error on the '
           'test episodes, median [range].', '', '![learning curve](learning_curve.png)', '']
    for tag, curve in curves.items():
        dist = curve.get('fom_vs_linearization') or []
        out += [f'### {tag}', '',
                'FOM against its linearization at rest on the test episodes: '
                + ', '.join(f'{d:.3g}' for d in dist) + '.', '']
        methods = [m for m in CURVE_LABELS if any(p.get(m) for p in curve['points'])]
        rows = []
        for p in curve['points']:
            row: list[Any] = [p['n'], f'{p["n"] * cfg["duration"]:g}']
            for m in methods:
                e = p.get(m)
                row.append('–' if not e else f'r={e.get("r")}: {_fmt_err(e.get("test"))}')
            rows.append(row)
        out += [markdown_table(['n', 'data [s]'] + [CURVE_LABELS[m] for m in methods], rows),
                '']
        cub = _cubic_rows(curve)
        if cub:
            out += ['Cubic against linear LOpInf at the same r (test ratios per episode; '
                    '`auto` is what `--forces auto` keeps; 10× inputs: the cubic model on '
                    'chained test inputs ten times longer than a training episode, peak '
                    'deviation in training maxima):', '',
                    markdown_table(['n', 'r', 'reg / eps4', 'held-out cubic vs linear',
                                    'auto keeps', 'cubic / linear (test)', '≤ 0.5 ×',
                                    'auto / linear, worst', '10× inputs'], cub), '']
    if summary.get('timings'):
        out += ['Run time and peak memory:', '', markdown_table(
            ['stage', 'seconds'], [[k, f'{v:,.0f}'] for k, v in summary['timings'].items()]),
            '']
        out += [markdown_table(['peak memory', 'MB'],
                               [[k, f'{v:,.0f}']
                                for k, v in summary.get('peak_memory_mb', {}).items()]),
                '']
    return out


def curve_report(summary: Mapping[str, Any]) -> str:
    """The whole Markdown report of a learning-curve run."""
    return '\n'.join(['# soft_rom learning-curve report', ''] + curve_section(summary))
