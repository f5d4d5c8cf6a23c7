"""Markdown report of the studies: tables of our numbers with the paper's beside them.

Every figure the study writes is shown, numbered and captioned (what it shows and how to
read it); every table cell is escaped, so that the report renders as written.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from soft_rom.study import paper
from soft_rom.study.figures import LABELS

__all__ = ['FIGURES', 'markdown_table', 'study_report']

#: The figures a full study writes, in the order the report shows them.
FIGURES = ('errors_vs_r.png', 'errors_vs_r_deviation.png', 'traces.png', 'bars.png',
           'bars_deviation.png', 'centerline_<episode>.png')


def _fmt(v: Any) -> str:
    if v is None:                  # summary.json's null: an error that could not be computed
        return 'n/a'
    if isinstance(v, float):
        if v != v or v in (float('inf'), float('-inf')):
            return str(v)
        return f'{v:.4f}' if 1e-3 <= abs(v) < 1e3 or v == 0 else f'{v:.2e}'
    return str(v)


def _cell(text: str) -> str:
    """One table cell: ``|`` escaped (else it splits the cell), line breaks as spaces."""
    return ' '.join(text.replace('\\|', '|').replace('|', '\\|').split())


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table; ``|`` in a cell is escaped."""
    lines = ['| ' + ' | '.join(_cell(str(h)) for h in header) + ' |',
             '|' + '---|' * len(header)]
    lines += ['| ' + ' | '.join(_cell(_fmt(v)) for v in row) + ' |' for row in rows]
    return '\n'.join(lines)


class _Figures:
    """Numbers the figures in the order they are shown."""

    def __init__(self, folder: str) -> None:
        self.folder = folder
        self.n = 0

    def __call__(self, name: str, alt: str, caption: str) -> list[str]:
        self.n += 1
        return [f'![{alt}]({self.folder}{name})', '', f'**Figure {self.n}.** {caption}', '']


def _label(entry: Mapping[str, Any], method: str) -> str:
    return str(entry.get('label') or f'{LABELS.get(method, method)} r={entry["r"]}')


def _extrapolation_section(s1: Mapping[str, Any], fig: _Figures) -> list[str]:
    t0, t1 = s1['t_train'], s1['t_end']
    out = [f'## Study 1: time extrapolation (train on Ep 1, t < {t0:.2f} s; test '
           f'{t0:.2f}–{t1:.2f} s)', '']
    out += fig('errors_vs_r.png', 'errors vs r',
               "Relative output error `‖Y − Ŷ‖_F / ‖Y‖_F` (the paper's metric, absolute "
               f'coordinates) against the reduced dimension r, on the training window (t < '
               f'{t0:g} s, dotted, circles) and the test window (dash-dotted, triangles) of Ep 1, '
               "one panel per method (the cubic LOpInf in the LOpInf panel); the paper's Fig. 2 "
               'in grey. A point above the axis is marked at its top edge (its value is in the '
               'tables). The absolute coordinates (x up to 1.2 m) dominate this metric, so it '
               'is small for every model; Figure 2 shows the same on deviations.')
    out += fig('errors_vs_r_deviation.png', 'errors vs r, deviations',
               'The same errors on deviations from the rest shape `y_ref` '
               '(`‖Y − Ŷ‖_F / ‖Y − y_ref‖_F`): 1 means no better than predicting the rest '
               'shape. This is the metric that tells the models apart.')
    out += ['Per method and r ("dev.": on deviations; stability margin: the distance of the '
            'least stable eigenvalue from the stability boundary, negative when unstable; '
            'paper: the numbers of its Fig. 2 for the same r):', '']
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
    out += ["The ROM of each method with the lowest training error (as in the paper's Fig. 3):",
            '', markdown_table(
                ['model', 'train', 'test', 'train (dev.)', 'test (dev.)', 'paper r'],
                [[_label(b, m), b['train'], b['test'], b['train_dev'], b['test_dev'],
                  paper.EXTRAPOLATION_BEST_R.get(m, '–')] for m, b in best.items()]), '']
    names = s1['trace_names']
    out += fig('traces.png', 'output traces',
               f'Outputs {" and ".join(names)} (height of the mid-body point and of the tail, '
               f'mm) of the FOM (black) and of these ROMs over Ep 1; the magenta line ends '
               "the training window. Where a ROM leaves the axis range (half the FOM's range "
               'beyond it on each side) its curve stops at the edge, marked with a triangle.')
    return out


def _unseen_section(s2: Mapping[str, Any], fig: _Figures) -> list[str]:
    eps = list(next(iter(s2['test'].values())).keys())
    span = f'{eps[0]}–{eps[-1]}' if len(eps) > 1 else eps[0]
    span = span.replace('ep', 'Ep ')
    chosen = s2['chosen']
    out = [f'## Study 2: robustness to unseen inputs (train on Ep 1 + Ep 2; test {span})', '',
           'ROMs chosen by their training error, as in the paper: '
           + ', '.join(_label(c, m) for m, c in chosen.items())
           + '. ERA/OKID fits one episode; it was fitted on Ep 1 and on Ep 2 separately and '
           f'the one that does better on the test episodes kept ({s2["era_episode"]}), as the '
           'paper does.', '']
    out += fig('bars.png', 'test errors',
               f'Relative output error of each chosen ROM on each test episode ({span}, inputs '
               "it was not trained on); black ticks: the paper's Fig. 4.")
    rows = []
    for m, per_ep in s2['test'].items():
        rows.append([_label(chosen[m], m)] + [per_ep[e] for e in eps]
                    + [paper.UNSEEN_INPUTS.get(m, {}).get(e, '–') for e in eps])
    out += [markdown_table(['model'] + [f'{e} (ours)' for e in eps]
                           + [f'{e} (paper)' for e in eps], rows), '']
    out += fig('bars_deviation.png', 'test errors, deviations',
               'The same on deviations from the rest shape `y_ref` (1: no better than the '
               'rest shape).')
    rows = [[_label(chosen[m], m)] + [per_ep[e] for e in eps]
            for m, per_ep in s2['test_dev'].items()]
    out += [markdown_table(['model'] + eps, rows), '']
    times = ', '.join(f'{t:g}' for t in s2['shape_times'])
    out += fig(s2['shapes_png'], 'centerline shapes',
               f'Centerline shapes (x–z, mm) of the FOM (black) and of the chosen ROMs on test '
               f'episode {s2["shape_episode"].replace("ep", "Ep ")} at t = {times} s. The z '
               "range is twice the FOM's largest deflection; a shape that leaves it stops at "
               'the edge, marked with a triangle.')
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


def _replay_section(rep: Mapping[str, Any]) -> list[str]:
    if 'error' in rep:
        return ['## Replay through the predictor core', '', str(rep['error']), '']
    out = ['## Replay through the predictor core', '',
           f'{rep.get("label", rep["model"])} (`models/{rep["model"]}`) replayed over the bag '
           f'{rep["bag"]} by the predictor node\'s core (`soft-rom replay`, open loop), '
           f'writing the node\'s topics to `{rep["output bag"]}/`:', '',
           markdown_table(['quantity', 'value'], [
               ['samples', rep['samples']],
               ['relative error', rep['relative_error']],
               ['relative error on deviations', rep['relative_deviation_error']],
               ['final status', f'{rep["final_status"]}: {rep.get("final_message", "")}'],
               ['warn / error thresholds', f'{_fmt(rep.get("warn_threshold"))} / '
                                           f'{_fmt(rep.get("error_threshold"))}'],
               ['thresholds from', rep.get('threshold_source', '')]]), '']
    k = rep.get('kalman')
    if k:
        out += [f'With the Kalman correction (the measured centerline with {k["noise_mm"]:g} mm '
                'white noise, the filter designed for that noise), the error on deviations '
                f'against the noise-free FOM goes from {k["open_loop"]:.4f} open loop to '
                f'{k["kalman"]:.4f} (ratio {k["ratio"]:.3f}).', '']
    return out


def study_report(summary: Mapping[str, Any], *, figures: str = '') -> str:
    """The whole Markdown report from the study summary dictionary.

    ``figures`` is prepended to every figure's file name (e.g. ``'figures/'`` for a copy of
    the report whose figures sit in a subfolder).
    """
    fig = _Figures(figures)
    lines = ['# soft_rom study report', '',
             'Reproduction of the two studies of Sharma et al., *Data-driven Model Reduction for '
             'Soft Robots via Lagrangian Operator Inference* (section 3) on the embedded eel FOM, '
             'through ROS 2 bags and the converter.', '']
    fom = summary.get('fom', {})
    if fom:
        lines += ['## Full-order model and data', '', markdown_table(
            ['quantity', 'value'], [[k, v] for k, v in fom.items()]), '']
    if summary.get('failures'):
        lines += ['## Warnings', '',
                  'Fits that failed (missing from the tables and figures below), and figures '
                  'that could not be recorded:', '']
        lines += [f'- {f}' for f in summary['failures']] + ['']
    if 'study1' in summary:
        lines += _extrapolation_section(summary['study1'], fig)
    if 'study2' in summary:
        lines += _unseen_section(summary['study2'], fig)
    if summary.get('replay'):
        lines += _replay_section(summary['replay'])
    if summary.get('conclusions'):
        lines += ["## Which of the paper's conclusions hold here", '']
        lines += [f'- {c}' for c in summary['conclusions']] + ['']
    if summary.get('timings'):
        machine = summary.get('machine', {}).get('description')
        lines += ['## Timings', '']
        if machine:
            lines += [f'Measured on {machine}.', '']
        lines += [markdown_table(['stage', 'seconds'],
                                 [[k, f'{v:.1f}'] for k, v in summary['timings'].items()]), '']
    return '\n'.join(lines)
