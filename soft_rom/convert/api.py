""":func:`convert` (bags to a training set) and :func:`read_episode` (one bag to memory)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
import logging
from pathlib import Path
import re
from typing import Any

import numpy as np

from soft_rom import outputs
from soft_rom.bags.reader import is_bag
from soft_rom.convert.mapping import BagMapping
from soft_rom.convert.probe import clocks_apart
from soft_rom.convert.report import ConversionReport
from soft_rom.convert.stream import (
    Array,
    BagConverter,
    BagPlan,
    input_names,
    probe_bag,
    SegmentSink,
)
from soft_rom.data import Episode
from soft_rom.dataset import adopt_legacy, EpisodeWriter, KIND, TrainingSet, TrainingSetWriter
from soft_rom.errors import BagError, ConfigError, ResourceError

__all__ = ['choose_dt_ns', 'convert', 'read_episode']

LOG = logging.getLogger(__name__)

#: ``--dt`` may be at most this many times finer than the fastest topic's median period.
MAX_UPSAMPLING = 10
#: Memory the in-memory signals (t, U, Y) of one conversion may take.
MEMORY_LIMIT = 4 << 30
#: Free disk checked again every this many state columns (the metadata may lie).
DISK_CHECK_EVERY = 4096


def _natural(p: Path) -> list[Any]:
    """Sort key: ``ep2`` before ``ep10``."""
    return [int(t) if t.isdigit() else t for t in re.split(r'(\d+)', p.name)]


def _paths(bags: Iterable[str | Path]) -> list[Path]:
    """The bags given, each checked to exist and given once.

    A folder that is no bag but holds bags (``soft-rom simulate -o``'s) stands for its bags,
    in natural order (``ep2`` before ``ep10``).
    """
    given = [Path(b) for b in bags]
    if not given:
        raise BagError('no bag given.')
    out: list[Path] = []
    for p in given:
        if not p.exists():
            raise FileNotFoundError(f'bag {p} does not exist.')
        if p.is_file() and not is_bag(p):       # most often a sidecar caught by a glob
            beside = any(c.is_dir() and is_bag(c) for c in p.parent.iterdir())
            raise BagError(f'{p} is not a ROS 2 bag (no .mcap or .db3 file)' + (
                f'; to convert every bag in {p.parent}, give that folder.' if beside else '.'))
        inner = [] if not p.is_dir() or is_bag(p) else sorted(
            (c for c in p.iterdir() if c.is_dir() and is_bag(c)), key=_natural)
        out.extend(inner or [p])
    seen: dict[Path, Path] = {}
    for p in out:
        first = seen.setdefault(p.resolve(), p)
        if first is not p:
            raise BagError(f'bag {p} is given twice (also as {first}); it would become two '
                           'identical episodes (one in training, one held out, say): give '
                           'each recording once.')
    return out


def _note_clocks(plan: BagPlan, report: ConversionReport) -> None:
    """Warn (and note in the report) when the topics' clocks are seconds apart."""
    note = clocks_apart(plan)
    if note is not None:
        LOG.warning('bag %s: %s', plan.path, note)
        report.notes.append(note)


def choose_dt_ns(plans: Sequence[BagPlan], mapping: BagMapping) -> int:
    """The grid step: ``mapping.dt`` within bounds, else the outputs' median period.

    Raises
    ------
    ConfigError
        ``dt`` is finer than :data:`MAX_UPSAMPLING` times the fastest topic's period.
    """
    periods = [p.output.period_ns for p in plans if p.output.period_ns]
    if not periods:
        raise BagError(f'output topic {mapping.output.topic}: fewer than two messages with '
                       'increasing stamps; its period (the default time step) is unknown.')
    default = int(np.median(periods))
    if mapping.dt is None:
        return default
    dt_ns = int(round(mapping.dt * 1e9))
    fastest = min((x for x in (p.min_period() for p in plans) if x is not None),
                  key=lambda x: x[1])
    floor = max(1, fastest[1] // MAX_UPSAMPLING)
    if dt_ns < floor:
        raise ConfigError(
            f'--dt {mapping.dt:g} s is finer than the recording supports: its fastest topic '
            f'{fastest[0]} has a median period of {fastest[1] * 1e-6:.4g} ms; choose '
            f'--dt >= {floor * 1e-9:.3g} s ({MAX_UPSAMPLING}x finer at most), or leave it '
            f'out for the output period ({default * 1e-6:.4g} ms).')
    return dt_ns


def _check_grid(plans: Sequence[BagPlan], dt_ns: int, values: int, out: Path) -> None:
    """Refuse a grid that would not fit on disk or in memory (estimated from the log span)."""
    points = sum(max(0, p.log_end_ns - p.first_log_ns) // dt_ns + 1 for p in plans)
    outputs.check_free_space(out.parent, points * values * 8.0,
                             f'a {dt_ns * 1e-9:g} s grid ({points} points)')
    m, pp = plans[0].n_inputs, plans[0].output.size or 0
    need = points * ((m + pp + 1) * 8.0 + 120.0)       # arrays + one small object per point
    if need > MEMORY_LIMIT:
        raise ResourceError(f'a {dt_ns * 1e-9:g} s grid ({points} points) needs about '
                            f'{need / 1e9:.3g} GB of memory for its inputs and outputs (limit '
                            f'{MEMORY_LIMIT / 1e9:.3g} GB); choose a larger --dt.')


class _WriterSegment:
    """One episode going into the training-set writer."""

    def __init__(self, writer: EpisodeWriter, stage: Path, n_values: int) -> None:
        self.writer = writer
        self.stage = stage
        self.bytes_per_column = 8.0 * n_values
        self.count = 0

    def append_state(self, q: Array) -> None:
        if self.count % DISK_CHECK_EVERY == 0:
            outputs.check_free_space(self.stage, DISK_CHECK_EVERY * self.bytes_per_column
                                     + (64 << 20), 'the next state columns')
        self.writer.append_states(q.reshape(-1, 1), check_finite=False, copy=False)
        self.count += 1

    def finish(self, t: Array, U: Array, Y: Array, metadata: dict[str, Any]) -> None:
        self.writer.metadata.update(metadata)
        self.writer.append_signals(t, U, Y)


class _TrainingSetSink:
    def __init__(self, writer: TrainingSetWriter) -> None:
        self.writer = writer

    def begin(self, name: str, n_states: int | None, t0_ns: int) -> SegmentSink:
        ep = self.writer.begin_episode(name, n_states=n_states, t0_ns=t0_ns)
        return _WriterSegment(ep, self.writer.store_path, n_states or 0)


class _MemorySegment:
    def __init__(self, sink: _MemorySink, name: str, t0_ns: int) -> None:
        self.sink = sink
        self.name = name
        self.t0_ns = t0_ns
        self.Q: list[Array] = []

    def append_state(self, q: Array) -> None:
        self.Q.append(q)

    def finish(self, t: Array, U: Array, Y: Array, metadata: dict[str, Any]) -> None:
        Q = np.stack(self.Q, axis=1) if self.Q else None
        self.sink.episodes.append(Episode(t=t, U=U, Y=Y, Q=Q, name=self.name,
                                          metadata=dict(metadata)))


class _MemorySink:
    def __init__(self) -> None:
        self.episodes: list[Episode] = []

    def begin(self, name: str, n_states: int | None, t0_ns: int) -> SegmentSink:
        return _MemorySegment(self, name, t0_ns)


def _consistent(plans: Sequence[BagPlan], mapping: BagMapping) -> None:
    first = plans[0]
    names = input_names(mapping, first)
    outs = mapping.output.names(first.output.size or 0)
    n = None if first.state is None else first.state.size
    for plan in plans[1:]:
        got = input_names(mapping, plan)
        got_out = mapping.output.names(plan.output.size or 0)
        if got != names or len(got_out) != len(outs):
            raise BagError(f'bag {plan.path} gives inputs {got[0]} / {len(got_out)} outputs '
                           f'that differ from the first bag ({names[0]} / {len(outs)}).')
        got_n = None if plan.state is None else plan.state.size
        if got_n != n:
            raise BagError(f'bag {plan.path} has {got_n} state values; the first bag has {n}.')


def convert(bags: Sequence[str | Path], out: str | Path, mapping: BagMapping | None = None, *,
            storage: str = 'auto', include_state: bool | None = None,
            overwrite: bool = False, progress: bool = True,
            echo: Callable[[ConversionReport], Any] | None = None
            ) -> tuple[TrainingSet, list[ConversionReport]]:
    """Convert bags (one episode each, more where long gaps split them) to a training set.

    Parameters
    ----------
    bags : sequence of path
        rosbag2 directories (or ``.mcap`` / ``.db3`` files), in episode order. A folder
        that is no bag but holds bag directories (``soft-rom simulate -o``'s) gives its
        bags in natural order (``ep2`` before ``ep10``); other files in it are left out.
    out : path
        Training set to write (``*.zarr``); written atomically.
    mapping : BagMapping, optional
        Topic mapping and time options (defaults: the bag contract).
    storage : {'auto', 'mcap', 'sqlite3'}
        Require a storage format, or accept either.
    include_state : bool, optional
        Store ``Q``; default: when the bags have the state topic.
    overwrite : bool
        Replace ``out`` if soft_rom wrote it (a training set); anything else is refused.
    progress : bool
        Show tqdm progress bars.
    echo : callable, optional
        Called with each bag's :class:`ConversionReport` as soon as it is converted (the
        CLI prints it).

    Returns
    -------
    training_set : TrainingSet
    reports : list of ConversionReport

    Raises
    ------
    OutputExistsError
        ``out`` exists and may not be replaced (checked before any bag is read).
    ConfigError, ResourceError
        ``dt`` too fine for the recording, or a grid too large for the disk or memory.
    BagError
        A bag is missing, corrupt, or has nothing usable.
    """
    m = mapping or BagMapping()
    paths = _paths(bags)
    out = Path(out)
    if overwrite:
        adopt_legacy(out)
    outputs.check_output(out, overwrite=overwrite, what='training set', kinds=(KIND,))
    plans = [probe_bag(p, m, include_state=include_state, storage=storage) for p in paths]
    _consistent(plans, m)
    dt_ns = choose_dt_ns(plans, m)
    first = plans[0]
    n = 0 if first.state is None else int(first.state.size or 0)
    _check_grid(plans, dt_ns, 1 + first.n_inputs + (first.output.size or 0) * 3 + n, out)
    names, units = input_names(m, first)
    layout = m.output.layout(first.output.size or 0)
    outs = layout.names()
    provenance = {'bags': [str(p.resolve()) for p in paths], 'mapping': m.to_dict(),
                  'tool': 'soft-rom convert', 'dt_ns': dt_ns}
    reports: list[ConversionReport] = []
    names_taken: set[str] = set()
    with TrainingSetWriter(out, input_names=names, input_units=units, output_names=outs,
                           output_units=[m.output.units] * len(outs), overwrite=overwrite,
                           attrs={'provenance': provenance,
                                  'output_layout': layout.to_dict()}) as writer:
        sink = _TrainingSetSink(writer)
        for plan in plans:
            report = BagConverter(plan, m, dt_ns, sink, names_taken, progress).run()
            _note_clocks(plan, report)
            for ep in report.episodes:
                writer.update_metadata(ep['name'], {'conversion_report': report.to_dict()})
            reports.append(report)
            if echo is not None:
                echo(report)
    return TrainingSet.open(out), reports


def read_episode(bag_path: str | Path, mapping: BagMapping | None = None, *,
                 include_state: bool = False, storage: str = 'auto',
                 progress: bool = False, finest: float | None = None
                 ) -> tuple[Episode, ConversionReport]:
    """Read one bag into an in-memory :class:`~soft_rom.data.Episode` on the uniform grid.

    ``finest`` (s): without a grid step in the mapping, the grid is at most this coarse
    (a model's step: on a slower camera's grid the inputs between two frames would be lost).

    Where long gaps split the bag, the longest piece is returned (said in the report's
    notes). ``Q`` is held in memory, so ``include_state=True`` is for small models only;
    use :func:`convert` for large ones.

    Returns
    -------
    episode : Episode
        ``metadata`` holds ``t0_ns``, source bag, topics, names and units, and the report.
    report : ConversionReport
    """
    m = mapping or BagMapping()
    paths = _paths([bag_path])
    if len(paths) > 1:
        raise BagError(f'{bag_path} is a folder of {len(paths)} bags ({paths[0].name}, '
                       f'{paths[1].name}, ...); give one of them.')
    path = paths[0]
    plan = probe_bag(path, m, include_state=include_state, storage=storage)
    dt_ns = choose_dt_ns([plan], m)
    if finest is not None and m.dt is None and dt_ns > 1.5 * finest * 1e9:
        dt_ns = int(round(finest * 1e9))
    sink = _MemorySink()
    conv = BagConverter(plan, m, dt_ns, sink, set(), progress)
    report = conv.run()
    _note_clocks(plan, report)
    ep = max(sink.episodes, key=lambda e: e.n_samples)
    if len(sink.episodes) > 1:
        report.notes.append(f'{len(sink.episodes)} pieces between long gaps; returned the '
                            f'longest, {ep.name!r}.')
    in_names, in_units = conv.input_names()
    meta = dict(ep.metadata)
    meta.update({'input_names': in_names, 'input_units': in_units,
                 'output_names': conv.output_names(),
                 'output_layout': conv.output_layout().to_dict(),
                 'output_units': [m.output.units] * ep.Y.shape[0],
                 'conversion_report': report.to_dict()})
    return Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=ep.Q, name=ep.name, metadata=meta), report
