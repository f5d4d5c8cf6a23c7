"""``soft-rom replay MODEL BAG -o OUT``: run the predictor node's core offline over a bag.

The bag's inputs (and measured centerline, when present) are read with
:func:`soft_rom.convert.read_episode`; the same :class:`~soft_rom.predictor.Predictor` the
node runs is stepped over them, and the node's topics are written to ``OUT``
(:mod:`soft_rom.bags.replay_io`). A summary of the errors is printed.

With ``--stream`` the bag is fed message by message instead (each pressure and measured
centerline with its own stamp, the publish timer emulated on the bag clock), configured by
the node's parameter file: the node's behaviour on multi-rate recordings, offline.

The output bag is written in a staging folder and swapped into place whole; it carries the
soft_rom output marker, so a later ``--overwrite`` may replace it. A bag soft_rom did not
write as a replay -- a recording, a simulated episode -- is never replaced, and the output
may not be the input bag.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from soft_rom.cli._common import (
    a_path,
    add_json,
    add_quiet,
    check_apart,
    check_model_matches_data,
    check_writable_folder,
    dumps_strict,
    finite_float,
    is_summary_json,
    write_text_output,
)
from soft_rom.errors import BagError, ConfigError

__all__ = ['add_parser', 'run']


def _node_name(text: str) -> str:
    """A ROS 2 node name: letters, digits and underscores, not starting with a digit."""
    import re
    if not re.fullmatch(r'[A-Za-z_][A-Za-z0-9_]*', text):
        raise argparse.ArgumentTypeError(f'{text!r} is not a ROS 2 node name (letters, digits '
                                         'and _, not starting with a digit)')
    return text


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``replay`` and its options."""
    parser = subparsers.add_parser(
        'replay', help='model x bag -> bag of predictions (the predictor node, offline)',
        description='Run the predictor node core over the inputs of a bag and write the '
                    'topics the node would publish (/soft_rom_predictor/centerline, '
                    'centerline_marker, output, error, model_info and /diagnostics).')
    parser.add_argument('model', help='model file (.npz)')
    parser.add_argument('bag', help='input bag (sqlite3 or MCAP)')
    parser.add_argument('-o', '--output', type=a_path, required=True, metavar='OUT',
                        help='output bag directory')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='storage of the output bag (default mcap)')
    parser.add_argument('--mapping', default=None,
                        help='topic mapping YAML for reading the bag (see soft-rom convert); '
                             'not with --stream, which reads the topics of --config')
    parser.add_argument('--config', default=None,
                        help='predictor params file (default: none; config/predictor.yaml '
                             'layout); command-line options override it')
    parser.add_argument('--kalman', action='store_true', default=None,
                        help='correct the state with the steady-state Kalman filter')
    parser.add_argument('--process-noise', type=finite_float(0.0, lo_open=True), default=None,
                        help='Kalman process noise variance')
    parser.add_argument('--measurement-noise', type=finite_float(0.0, lo_open=True),
                        default=None,
                        help='Kalman measurement noise variance')
    parser.add_argument('--stepping', choices=('event', 'fixed', 'input'), default=None,
                        help='event time (the newest time every input is known; default of the '
                             'node), a fixed integration rate, or a step to each input stamp')
    parser.add_argument('--publish-rate', type=finite_float(0.0, 1e6), default=None,
                        help='publish rate in Hz, 0 = every step (default: the params file, '
                             'else every step)')
    parser.add_argument('--components', default=None,
                        help='output layout, component-major (default xz)')
    parser.add_argument('--frame-id', default=None, help='frame of the centerline')
    parser.add_argument('--node-name', type=_node_name, default='soft_rom_predictor',
                        help='topics are /<node-name>/... (default soft_rom_predictor)')
    parser.add_argument('--no-measured', action='store_true',
                        help='ignore the measured centerline (open-loop prediction only)')
    parser.add_argument('--stream', action='store_true',
                        help='feed the bag message by message with its own stamps, exactly '
                             'as the node sees it (topics from --config, node defaults '
                             'otherwise), instead of the converted episode')
    parser.add_argument('--compare', action='store_true',
                        help='also report open-loop vs Kalman-corrected errors')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace OUT (and the --json file) if soft-rom replay wrote it')
    parser.add_argument('--strict', action='store_true',
                        help='refuse a model that cannot be trusted (unstable, indefinite, ...)')
    add_json(parser, help='also write the summary as JSON')
    add_quiet(parser)
    parser.set_defaults(func=run)
    return parser


def _read(bag: str, mapping_path: str | None, model: Any,
          model_path: str) -> tuple[Any, Any, str | None]:
    """Episode, conversion report and output components of ``bag`` replayed by ``model``.

    The components are the output layout stored in the model file, else the one the
    converter stored with the episode (:func:`soft_rom.layout.replay_components`).
    """
    from soft_rom.convert import load_mapping, read_episode
    from soft_rom.layout import layout_of, replay_components

    # outputs slower than the model: read on its step, or the inputs between two are lost
    episode, report = read_episode(bag, load_mapping(mapping_path), finest=model.dt)
    meta = episode.metadata
    check_model_matches_data(model, str(model_path), f'the bag {bag}',
                             counts=(episode.U.shape[0], episode.Y.shape[0]),
                             input_units=meta.get('input_units'),
                             output_units=meta.get('output_units'), layout=None)
    return episode, report, replay_components(layout_of(model.metadata),
                                              layout_of(episode.metadata))


_REPLAY_JSON = is_summary_json(('output_bag',))


def _check_paths(args: argparse.Namespace) -> None:
    """Usage errors found before any work: output is the input, bad folders, files exist."""
    from soft_rom.outputs import check_output

    bag, out = Path(args.bag).resolve(), Path(args.output).resolve()
    if out == bag or bag in out.parents or out in bag.parents:
        raise ConfigError(f'the output {args.output} would replace or sit inside the input bag '
                          f'{args.bag}; choose another -o')
    if args.mapping is not None and not Path(args.mapping).is_file():
        raise ConfigError(f'--mapping {args.mapping} is not a file')
    if args.config is not None and not Path(args.config).is_file():
        raise ConfigError(f'--config {args.config} is not a file')
    check_writable_folder(Path(args.output).parent, 'output bag')
    if args.json is not None:
        check_writable_folder(args.json.parent, '--json file')
        check_apart(args.json, '--json', [('output bag', Path(args.output)),
                                          ('input bag', Path(args.bag)),
                                          ('model file', Path(args.model))])
        check_output(args.json, overwrite=args.overwrite, what='replay summary',
                     is_ours=_REPLAY_JSON)
    check_output(args.output, overwrite=args.overwrite, what='replay bag', kinds=('replay',))


def _settings(args: argparse.Namespace) -> tuple[dict[str, Any], Any]:
    """The node's parameters (``--config``, then the options given) and its config."""
    from soft_rom.predictor.params import load_params_file, predictor_config

    values: dict[str, Any] = load_params_file(args.config) if args.config else {}
    overrides = {'kalman': args.kalman, 'process_noise': args.process_noise,
                 'measurement_noise': args.measurement_noise, 'stepping': args.stepping,
                 'publish_rate_hz': args.publish_rate, 'output_components': args.components,
                 'frame_id': args.frame_id}
    values.update({k: v for k, v in overrides.items() if v is not None})
    config = predictor_config(values)
    _check_filter_options(args, config.kalman)
    return values, config


def _check_filter_options(args: argparse.Namespace, kalman: bool) -> None:
    """Refuse the Kalman options that would do nothing (``kalman``: the filter is on)."""
    if args.no_measured and (args.kalman or args.compare):
        flag = '--kalman' if args.kalman else '--compare'
        raise ConfigError(f'{flag} corrects the prediction with the measured centerline, which '
                          f'--no-measured ignores; drop one of them')
    if args.stream and args.compare:
        raise ConfigError('--compare replays the converted episode twice (open loop and '
                          'Kalman); it does not run with --stream')
    noise = [f for f, v in (('--process-noise', args.process_noise),
                            ('--measurement-noise', args.measurement_noise)) if v is not None]
    if noise and not (kalman or args.compare):
        raise ConfigError(f'{" and ".join(noise)} set{"s" if len(noise) == 1 else ""} the '
                          'Kalman filter, which is off; add --kalman (or --compare)')


def _write_json(args: argparse.Namespace, summary: dict[str, Any]) -> None:
    if args.json is not None:
        write_text_output(args.json, dumps_strict(summary, indent=2, default=str),
                          overwrite=args.overwrite, what='replay summary', is_ours=_REPLAY_JSON)


def run(args: argparse.Namespace) -> int:
    """Execute ``soft-rom replay``; returns the exit code."""
    from tqdm import tqdm

    from soft_rom.bags.replay_io import replay_to_bag
    from soft_rom.models import load_model
    from soft_rom.outputs import atomic_new_dir
    from soft_rom.predictor import kalman_vs_open_loop, Predictor

    _check_paths(args)
    if not Path(args.bag).exists():
        raise FileNotFoundError(f'bag {args.bag} does not exist')
    checked = load_model(args.model, strict=args.strict)
    values, config = _settings(args)
    predictor = Predictor(args.model, config)
    model = predictor.model
    if args.stream:
        return _run_stream(args, values, predictor)
    try:
        episode, _report, components = _read(args.bag, args.mapping, model, args.model)
    except BagError as err:
        if args.no_measured and str(err).startswith('output topic'):
            # the grid of a converted episode is the measured output's: without one, the bag
            # can only be fed message by message
            raise ConfigError(f'{err} Without a measured centerline, replay it with --stream '
                              '--no-measured (the inputs message by message, as the node '
                              'takes them).') from None
        raise
    if components is not None:
        values.setdefault('output_components', components)
    publish_rate = float(values.get('publish_rate_hz', 0.0) or 0.0)
    every = 1 if publish_rate <= 0 else max(1, int(round(1.0 / (publish_rate * model.dt))))
    measured = not args.no_measured and episode.Y.shape[0] > 0
    with atomic_new_dir(args.output, overwrite=args.overwrite, kind='replay',
                        what='replay bag') as stage:
        with tqdm(total=episode.n_samples, desc='replay', unit='step', leave=False,
                  disable=args.quiet) as bar:
            result = replay_to_bag(
                predictor, episode, stage, storage=args.storage, publish_every=every,
                centerline_rate_hz=float(values.get('centerline_rate_hz', 30.0)),
                measured=measured, node_name=args.node_name,
                frame_id=str(values.get('frame_id', 'world')),
                components=str(values.get('output_components', 'xz')), overwrite=False,
                progress=lambda j: bar.update(100) if j % 100 == 0 and j else None)
    summary = dict(result.summary)
    summary['output_bag'] = str(Path(args.output))
    health = predictor.health()
    summary['final_status'] = health.level.name
    summary['final_message'] = health.message
    summary['trust'] = checked.trust_issues()
    if args.compare and measured:
        summary['compare'] = kalman_vs_open_loop(model, episode, config=config)
    print(f'replayed {summary["samples"]} samples of {args.bag} through '
          f'{model.method} r={model.r} ({"Kalman" if config.kalman else "open loop"}) '
          f'-> {args.output}')
    if not checked.trusted:
        print(f'  model NOT TRUSTED: {"; ".join(checked.trust_issues())}')
    if measured and not math.isnan(summary['relative_error']):
        print(f'  relative error            {summary["relative_error"]:.4e}')
        print(f'  relative deviation error  {summary["relative_deviation_error"]:.4e}')
    else:
        print('  no measured outputs: errors not computed')
    if 'compare' in summary:
        c = summary['compare']
        print(f'  open loop (deviation)     {c["open_loop"]:.4e}')
        print(f'  Kalman    (deviation)     {c["kalman"]:.4e}   ratio {c["ratio"]:.3f}')
    dropped = {k: v for k, v in summary['counters'].items()
               if k in ('wrong_length', 'nonfinite', 'backwards', 'measured_dropped',
                        'diverged') and v}
    print(f'  final status {health.level.name}: {health.message}'
          + (f'; dropped {dropped}' if dropped else ''))
    _write_json(args, summary)
    return 0


_ARRAY_TYPES = ('std_msgs/msg/Float64MultiArray', 'std_msgs/msg/Float32MultiArray')


def _check_stream_topics(args: argparse.Namespace, v: dict[str, Any]) -> None:
    """Refuse a ``--stream`` replay whose input topics the bag lacks or has as another type.

    ``--stream`` takes its topics from ``--config`` (the node's parameters), never from a
    ``--mapping``; a missing input topic would otherwise replay nothing (or every message
    of the bag, as the wrong type). A missing measured topic only leaves the errors out
    (said in the summary), as on the node.
    """
    from soft_rom.bags import BagReader

    where = ('--config' if args.config else "the node's defaults; set them with --config")
    if args.mapping is not None:
        raise ConfigError(f'--stream reads the bag as the node does, with the topics, scale '
                          f'and offset of {where}, not --mapping {args.mapping}; set '
                          'input_topics (or array_topic), input_scale, input_offset and '
                          'measured_topic there, or replay without --stream')
    with BagReader(args.bag) as reader:
        have = reader.topics
    wanted: dict[str, tuple[str, ...]]
    if str(v['input_mode']) == 'array':
        key, wanted = 'array_topic', {str(v['array_topic']): _ARRAY_TYPES}
    else:
        key = 'input_topics'
        wanted = {str(tp): ('sensor_msgs/msg/FluidPressure',) for tp in v['input_topics']}
    missing = [tp for tp in wanted if tp not in have]
    if missing:
        raise ConfigError(f'the bag {args.bag} has no input topic {", ".join(missing)} '
                          f'({key}: {where}); it has {sorted(have)}')
    measured = str(v['measured_topic']) if not args.no_measured else ''
    if measured in have:
        wanted[measured] = ('geometry_msgs/msg/PoseArray',)
    wrong = [f'{tp} is {have[tp][0]}, not {" or ".join(types)}'
             for tp, types in wanted.items() if have[tp][0] not in types]
    if wrong:
        raise ConfigError(f'the bag {args.bag}: {"; ".join(wrong)} (input_mode '
                          f'{v["input_mode"]!r}, {key} and measured_topic: {where})')


def _run_stream(args: argparse.Namespace, values: dict[str, Any], predictor: Any) -> int:
    """``replay --stream``: message by message, with the node's parameters."""
    from soft_rom.bags.replay_io import replay_stream_to_bag
    from soft_rom.layout import layout_of, replay_components
    from soft_rom.outputs import atomic_new_dir
    from soft_rom.predictor.params import PARAMS

    v = {p.name: p.default for p in PARAMS}
    components = replay_components(layout_of(predictor.model.metadata), None)
    if components is not None:
        v['output_components'] = components
    v.update(values)
    measured_topic = '' if args.no_measured else str(v['measured_topic'])
    _check_stream_topics(args, v)
    with atomic_new_dir(args.output, overwrite=args.overwrite, kind='replay',
                        what='replay bag') as stage:
        summary = replay_stream_to_bag(
            predictor, args.bag, stage, input_mode=str(v['input_mode']),
            input_topics=list(v['input_topics']), array_topic=str(v['array_topic']),
            input_scale=float(v['input_scale']), input_offset=float(v['input_offset']),
            measured_topic=measured_topic,
            components=str(v['output_components']),
            publish_rate_hz=float(v['publish_rate_hz']),
            centerline_rate_hz=float(v['centerline_rate_hz']), storage=args.storage,
            node_name=args.node_name, frame_id=str(v['frame_id']), overwrite=False)
    model = predictor.model
    health = predictor.health()
    summary.update(output_bag=str(Path(args.output)), final_status=health.level.name,
                   final_message=health.message, trust=model.trust_issues())
    n = summary['messages']
    print(f'replayed {n["inputs"]} input and {n["measured"]} measured messages of {args.bag} '
          f'through {model.method} r={model.r} '
          f'({"Kalman" if predictor.config.kalman else "open loop"}) -> {args.output} '
          f'({n["published"]} published steps)')
    if n['measured']:
        print(f'  relative error            {summary["relative_error"]:.4e}')
        print(f'  relative deviation error  {summary["relative_deviation_error"]:.4e}')
    else:
        print('  no measured outputs: errors not computed')
    print(f'  final status {health.level.name}: {health.message}')
    _write_json(args, summary)
    return 0
