"""``soft-rom evaluate``: models x episodes -> both relative errors, plots, JSON.

Examples::

    soft-rom evaluate models/eel_*.npz --data eel.zarr --t-split 1.5 --plots figs/
    soft-rom evaluate models/eel_lopinf_r10.npz --data eel.zarr --episodes ep3,ep4 --json e.json
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
from typing import Any

import numpy as np

from soft_rom.cli._common import (
    a_path,
    add_json,
    add_quiet,
    check_apart,
    check_model_matches_data,
    check_writable_folder,
    finite_float,
    is_summary_json,
)
from soft_rom.cli.fit import open_training_set
from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.evaluation import evaluate
from soft_rom.models import LinearROM, load_model
from soft_rom.models.labels import model_label
from soft_rom.pipeline import select_episodes

__all__ = ['add_parser', 'plot_outputs', 'run']


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``evaluate``."""
    parser = subparsers.add_parser(
        'evaluate', help='errors of model files on a training/test set',
        description='Simulate each model on the inputs of each episode (from the reference '
                    'state) and report the relative output error ||Y - Yhat||/||Y|| and the same '
                    'on deviations from y_ref, per model x episode and pooled; optionally on '
                    't < T_SPLIT and t >= T_SPLIT separately.')
    parser.add_argument('models', nargs='+', metavar='MODEL', help='model files (.npz)')
    parser.add_argument('--data', required=True, metavar='TRAINING_SET',
                        help='training set (.zarr) holding the episodes')
    parser.add_argument('--episodes', default=None,
                        help='comma-separated episode names (default all)')
    parser.add_argument('--t-split', type=finite_float(0.0, lo_open=True), default=None,
                        help='also report errors before/after this time (s from episode start)')
    parser.add_argument('--initial', choices=('reference', 'output'), default='reference',
                        help='initial state: the reference configuration (default) or fitted '
                             'to the first measured output')
    parser.add_argument('--plots', type=a_path, default=None, metavar='DIR',
                        help='write PNG plots of output traces (measured vs predicted)')
    parser.add_argument('--outputs', default=None,
                        help='comma-separated output indices (0-based) or names to plot '
                             '(default: 2 spread over the vector)')
    add_json(parser, help='write all rows as JSON')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace the --json file and --plots folder soft_rom wrote before')
    parser.add_argument('--strict', action='store_true',
                        help='refuse models that cannot be trusted (unstable, indefinite, ...)')
    add_quiet(parser)
    parser.set_defaults(func=run)
    return parser


def _check_layout(model: LinearROM, path: str, ts: Any) -> None:
    check_model_matches_data(model, path, f'the training set {ts.path}',
                             counts=(len(ts.input_names), len(ts.output_names)),
                             input_units=ts.input_units, output_units=ts.output_units,
                             layout=ts.output_layout)


_EVAL_JSON = is_summary_json(('model', 'episode', 'segment'))


def run(args: argparse.Namespace) -> int:
    """Execute ``soft-rom evaluate``."""
    from soft_rom.outputs import atomic_dir, check_output

    if args.json is not None:
        check_writable_folder(args.json.parent, '--json file')
        check_apart(args.json, '--json', [('training set', Path(args.data))]
                    + [('model file', Path(p)) for p in args.models]
                    + ([('plots folder', args.plots)] if args.plots is not None else []))
        check_output(args.json, overwrite=args.overwrite, what='evaluation summary',
                     is_ours=_EVAL_JSON)
    if args.outputs is not None and args.plots is None:
        raise ConfigError('--outputs chooses the outputs of the trace plots; give --plots '
                          'FOLDER too')
    if args.plots is not None:
        check_writable_folder(args.plots.parent, 'plots')
        check_output(args.plots, overwrite=args.overwrite, what='plots folder',
                     kinds=('plots',))
    models = []
    for path in args.models:
        model = load_model(path, strict=args.strict)
        if args.plots is not None:
            _output_indices(args.outputs, model)
        models.append((path, model))
    ts = open_training_set(args.data)             # a bag: refused with its convert command
    episodes = select_episodes(ts, args.episodes)
    for path, model in models:
        _check_layout(model, path, ts)
    rows: list[dict[str, Any]] = []
    predictions: list[tuple[str, LinearROM, dict[str, np.ndarray]]] = []
    labels = _labels(models)
    for path, model in models:
        ev = evaluate(model, episodes, t_split=args.t_split, initial=args.initial,
                      return_predictions=args.plots is not None)
        for row in ev.rows:
            rows.append({'model': labels[path][0], 'method': model.method, 'r': model.r,
                         'label': model_label(model), 'trusted': model.trusted, **row})
        if args.plots is not None:
            predictions.append((path, model, ev.predictions))
    if args.plots is not None:
        with atomic_dir(args.plots, overwrite=args.overwrite, kind='plots',
                        what='plots folder') as stage:
            for path, model, pred in predictions:
                for ep in episodes:
                    plot_outputs(ep, pred[ep.name], model,
                                 stage / f'{labels[path][1]}__{ep.name}.png',
                                 outputs=args.outputs, t_split=args.t_split)
    if args.json is not None:
        from soft_rom.cli._common import dumps_strict, write_text_output
        write_text_output(args.json, dumps_strict(rows, indent=2) + '\n',
                          overwrite=args.overwrite, what='evaluation summary',
                          is_ours=_EVAL_JSON)
    # with one episode the pooled rows ('*') repeat it: the table shows them with two or more
    print(format_table([r for r in rows if len(episodes) > 1 or r['episode'] != '*']))
    for path, model in models:
        if not model.trusted:
            print(f'  {Path(path).name}: NOT TRUSTED: {"; ".join(model.trust_issues())}')
    if args.plots is not None and not args.quiet:
        print(f'plots written to {args.plots}/', file=sys.stderr)
    return 0


def _labels(models: list[tuple[str, LinearROM]]) -> dict[str, tuple[str, str]]:
    """Table label and plot file stem of each model file.

    Its name when the names are distinct; else (models of the same name from different
    folders, e.g. two fits compared) the path as given and a stem made of its folders, so
    that neither the rows nor the plots of one model can pass for the other's.
    """
    paths = [p for p, _ in models]
    names = [Path(p).name for p in paths]
    if len(set(names)) == len(set(paths)):
        return {p: (Path(p).name, Path(p).stem) for p in paths}
    out = {}
    for p in paths:
        parts = [{'..': 'up'}.get(x, x) for x in Path(p).with_suffix('').parts
                 if x not in ('/', '.')]
        out[p] = (str(p), '_'.join(parts))
    return out


def format_table(rows: list[dict[str, Any]]) -> str:
    """Text table of the evaluation rows: each model by its file and what it is."""
    w = max([len(r['model']) for r in rows] + [5])
    wl = max([len(r.get('label', '')) for r in rows] + [4])
    head = (f'{"model":<{w}} {"what":<{wl}} {"episode":<10} {"segment":<7} {"samples":>7} '
            f'{"err":>10} {"dev err":>10}')
    lines = [head, '-' * len(head)]
    for r in rows:
        lines.append(f'{r["model"]:<{w}} {r.get("label", ""):<{wl}} {r["episode"]:<10} '
                     f'{r["segment"]:<7} {r["n_samples"]:>7d} {r["relative_error"]:>10.3e} '
                     f'{r["relative_deviation_error"]:>10.3e}')
    return '\n'.join(lines)


def _output_indices(spec: str | None, model: LinearROM) -> list[int]:
    p = model.n_outputs
    if spec is None:
        return sorted({p // 4, (3 * p) // 4}) if p > 1 else [0]
    out = []
    for item in spec.split(','):
        item = item.strip()
        if item in model.output_names:
            out.append(model.output_names.index(item))
            continue
        try:
            i = int(item)
        except ValueError as err:
            raise DimensionError(f'--outputs: {item!r} is neither an index nor an output '
                                 f'name.') from err
        if not 0 <= i < p:
            raise DimensionError(f'--outputs: index {i} out of range 0..{p - 1}.')
        out.append(i)
    twice = sorted({model.output_names[i] for i in out if out.count(i) > 1})
    if twice:
        raise DimensionError(f'--outputs: {", ".join(twice)} given twice (a panel each).')
    return out


def plot_outputs(ep: Episode, Y_hat: np.ndarray, model: LinearROM, path: str | Path, *,
                 outputs: str | None = None, t_split: float | None = None) -> Path:
    """PNG of measured vs predicted output traces of one episode.

    Titled with the model (method, variant, forces, r), the episode and what the model was
    trained on; lengths in mm when the outputs are in metres; the split line in the legend;
    a prediction that leaves the axis range cut at the edge and marked
    (:func:`soft_rom.study.figures.output_traces`).
    """
    from soft_rom.study.figures import output_traces

    idx = _output_indices(outputs, model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    units = {model.output_units[i] for i in idx}
    scale, unit = (1e3, 'mm') if units == {'m'} else (1.0, units.pop() if len(units) == 1
                                                        else '')
    label = model_label(model, data_dt=ep.dt)
    meta = model.metadata if isinstance(model.metadata, dict) else {}
    prov = meta.get('training') or meta.get('provenance') or {}
    trained = prov.get('episodes') if isinstance(prov, dict) else None
    on = (f'; trained on {", ".join(str(e) for e in trained)}'
          if isinstance(trained, list) and trained else '')
    seg = '' if t_split is None else f'; split at t = {t_split:g} s'
    return output_traces(path, ep.t - ep.t[0], ep.Y, {'model': Y_hat}, idx,
                         [model.output_names[i] for i in idx], t_split=t_split,
                         rom_labels={'model': label}, scale=scale, unit=unit,
                         reference_label=f'measured ({ep.name})',
                         split_label='t-split',
                         title=f'{label}: episode {ep.name}{on}{seg}')
