"""The README's results, made from a study's ``summary.json`` (never typed by hand).

The README holds a block between :data:`BEGIN` and :data:`END`: the results table of both
studies (each method's best-on-training ROM in time extrapolation, and the mean over the
unseen-input episodes), the paper's conclusions as the study found them, and how long the
study took on which machine. :func:`results_block` writes that block from the summary;
``tools/update_study_docs.py`` puts it into the README (with the summary and the report
under ``docs/``), and ``tests/test_readme.py`` checks that the README holds exactly it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from soft_rom.study.figures import LABELS

__all__ = ['BEGIN', 'END', 'FIGURES', 'read_block', 'replace_block', 'results_block']

BEGIN = '<!-- study-results:begin (made by tools/update_study_docs.py; do not edit) -->'
END = '<!-- study-results:end -->'
#: Where the README finds the study's figures (``tools/update_study_docs.py`` copies them).
FIGURES = 'docs/figures/study/'

_METHODS = ('lopinf', 'dmdc', 'era', 'lopinf_cubic')


def _cells(entries: Mapping[str, tuple[float, float, str]]) -> list[str]:
    """``error (deviation error), label`` per method, the lowest error in bold."""
    best = min((v[0] for v in entries.values()), default=None)
    out = []
    for method in _METHODS:
        if method not in entries:
            out.append('–')
            continue
        err, dev, label = entries[method]
        num = f'{err:.4f}'
        out.append(f'{"**" + num + "**" if err == best else num} ({dev:.3f}), {label}')
    return out


def _r_label(entry: Mapping[str, Any]) -> str:
    text = f'r = {entry["r"]}'
    if entry.get('episode'):
        text += f' (fit on {entry["episode"]})'
    return text


def results_block(summary: Mapping[str, Any]) -> str:
    """The README's results block (markers included) from a study summary."""
    s1, s2 = summary.get('study1', {}), summary.get('study2', {})
    lines = [BEGIN, '']
    if s1:
        lines += [f'![relative output error against r, study 1]({FIGURES}errors_vs_r.png)', '']
    if s2.get('shapes_png'):
        lines += [f'![centerline shapes, study 2, test episode {s2["shape_episode"]}]'
                  f'({FIGURES}{s2["shapes_png"]})', '']
    lines += ["On our FOM (relative output error, the paper's metric; on deviations from `y_ref` "
             'in brackets), from `soft-rom study` ([`docs/study_report.md`]'
             '(docs/study_report.md)):', '',
             '| study | ' + ' | '.join(LABELS[m] for m in _METHODS) + ' |',
             '|---|' + '---|' * len(_METHODS)]
    if s1.get('best'):
        t0, t1 = s1['t_train'], s1['t_end']
        cells = _cells({m: (b['test'], b['test_dev'], _r_label(b))
                        for m, b in s1['best'].items()})
        lines.append(f'| time extrapolation, test {t0:g}–{t1:g} s (best-on-training r) | '
                     + ' | '.join(cells) + ' |')
    if s2.get('test'):
        eps = list(next(iter(s2['test'].values())).keys())
        span = (f'{eps[0]}–{eps[-1]}' if len(eps) > 1 else eps[0]).replace('ep', 'Ep ')
        means = {m: (sum(v.values()) / len(v), sum(s2['test_dev'][m].values()) / len(v),
                     _r_label(s2['chosen'][m])) for m, v in s2['test'].items()}
        lines.append(f'| unseen inputs, mean over {span} | ' + ' | '.join(_cells(means))
                     + ' |')
    lines.append('')
    conclusions = summary.get('conclusions', [])
    if conclusions:
        lines += ["What the study finds of the paper's conclusions:", '']
        lines += [f'- {c}' for c in conclusions]
        lines.append('')
    long = s2.get('long_inputs')
    if long:
        lines += ['Inputs 10 × longer than a training episode (the test inputs chained): '
                  + '; '.join(f'{LABELS.get(m, m)}: {v}' for m, v in long.items()) + '.', '']
    timings, machine = summary.get('timings', {}), summary.get('machine', {})
    if timings:
        total = sum(timings.values())
        stages = ', '.join(f'{k} {v:.0f} s' for k, v in timings.items())
        where = f' on {machine["description"]}' if machine.get('description') else ''
        lines += [f'The study took {total / 60:.1f} min ({stages}){where}.', '']
    lines.append(END)
    return '\n'.join(lines)


def read_block(text: str) -> str:
    """The results block of a README text (markers included).

    Raises
    ------
    ValueError
        The markers are missing or out of order.
    """
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ValueError('the README has no study results block (markers missing)')
    return text[start:end + len(END)]


def replace_block(text: str, block: str) -> str:
    """``text`` with its results block replaced by ``block``."""
    old = read_block(text)
    return text.replace(old, block, 1)
