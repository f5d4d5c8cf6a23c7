"""Bags to training sets: topic mapping, time alignment on a uniform grid, reports.

``soft-rom convert BAG... -o OUT.zarr`` (and :func:`convert`) turns ROS 2 bags (sqlite3 or
MCAP) into the chunked training set of :mod:`soft_rom.dataset`; :func:`read_episode` reads
one bag into an in-memory :class:`~soft_rom.data.Episode` (the replay tool uses it).

Modules: :mod:`~soft_rom.convert.mapping` (the mapping and its validation),
:mod:`~soft_rom.convert.report` (report dataclasses), :mod:`~soft_rom.convert.stream` (probe
and streaming converter of one bag; :mod:`~soft_rom.convert.hold` holds the inputs on the
grid), :mod:`~soft_rom.convert.api` (the two entry points).

Mapping
-------
:class:`BagMapping` says which topics are the inputs, the output and the state. The defaults
(the bag contract) need no file; ``config/bag_mapping.yaml`` documents every key. Inputs are
a list of *sources*, each one ``FluidPressure`` topic (one input) or one
``Float64/Float32MultiArray`` topic with ``indices`` or ``slice`` (several inputs); every
input is mapped as ``u = scale * raw + offset`` (e.g. ``offset: -101325`` turns absolute
into gauge pressure). With ``topics: auto`` (default) the per-chamber topics
``/soft_robot/pressure/chamber_<i>`` found in the bag are used in chamber order, else
``/soft_robot/pressures``.

The output ``y`` is built from a ``PoseArray`` (or ``PoseStamped``): the selected points
(default all, 0-based ``points`` indices) and components (default ``[x, z]``), ordered
**component-major** by default, ``y = [x_1 .. x_N, z_1 .. z_N]`` with names ``x1 .. xN,
z1 .. zN``; ``order: point_major`` gives ``[x_1, z_1, x_2, z_2, ...]`` instead.

The state is a ``Float64/Float32MultiArray`` (layout ``[nodes, 3]``) or a ``PointCloud2``
with ``x, y, z`` fields; ``Q`` rows are node-major, ``Q[3 i + c]`` = coordinate ``c`` of
node ``i``, stored as float64. A recording of a real robot usually has no state topic: the
set then has no ``Q`` and LOpInf/DMDc use the outputs as coordinates.

Time
----
Every message is timed by its ``header.stamp`` (integer nanoseconds, usually epoch time), or
by the bag log time when the type has no header (multi-arrays) or ``time.stamps: log`` is
set. Stamps stay integers until an episode is written: its times are ``t = j * dt`` seconds
from its first grid point, whose absolute stamp is kept as the integer ``t0_ns``.

Sizes (input widths, number of points, state size) come from the mapping or from the
majority of the first 256 messages of each topic, never from the first message alone; other
sizes are dropped and reported. The grid step is ``time.dt`` (``--dt``) or, by default, the
median output period (the same for every bag of one set); ``--dt`` finer than a tenth of
the fastest topic's period, or a grid that would not fit on the disk or in 4 GB of memory,
is refused before anything is written.

Samples are the output messages; with a state topic each output is paired with the state
message within 0.45 of the output's median period (``match_tolerance`` to choose) and
unpaired ones are dropped. Grid points between two consecutive samples are interpolated
linearly (outputs and states) as long as the samples are at most ``1 + max_gap`` output
periods apart (default ``max_gap = 1.5``: one lost camera frame in a row is bridged); a
longer stretch without samples splits the episode (pieces named ``BAG``, ``BAG_2``, ...;
``split_gap`` seconds overrides the bound; pieces shorter than ``min_samples``, default 32,
are dropped, so that every learner can fit every episode).
Inputs, each on its own clock, are zero-order held: ``U[:, j]`` is the last input value with
stamp ``<= t_j``.

Bad input: what stops and what continues
----------------------------------------
===================================================== =======================================
case                                                  behaviour
===================================================== =======================================
bag missing, truncated, corrupt, unreadable           **stop** (BagError, bag named)
no message on the mapped topics / on the output       **stop**
configured topic missing                              **stop** (topic named, topics listed)
wrong message type on a configured topic              **stop** (topic, found and expected type)
header stamps of a topic mostly going backwards       **stop** (use ``time.stamps: log``)
a topic's own stamps jumping for good (clock reset)   **stop** (topic and jump named)
a topic's clock set back under 1 s (8 stamps in a     **stop** (topic and step named)
row before its last two)
``--dt`` too fine, grid too large for disk or memory  **stop** before writing (ConfigError /
                                                      ResourceError)
output exists and is not a soft_rom training set      **stop** before reading (even with
                                                      ``--overwrite``)
no usable sample left after dropping                  **stop**
NaN/Inf in a message                                  continue: message dropped (inputs keep
                                                      their held value), reported with stamp
size differs from the mapping / the majority          continue: message dropped, reported
centerline frame_id other than the majority's        continue: message dropped, reported
stamp more than 1 s from its log time (after the      continue: message dropped, reported
topic's median offset)
stamp duplicated or going backwards on a topic (a     continue: message dropped, reported
few out of order, or after one stamp glitched ahead)
output sample without a state (or state w/o output)   continue: dropped, reported
output sample before the first message of an input    continue: dropped, reported
one lost output frame (up to ``max_gap`` periods)     continue: interpolated, counted
longer stretch without output                         continue: episode split, counted
===================================================== =======================================

Every report lists, per topic, messages read and used, dropped counts by reason with the
first stamps, grid points taken at a sample / interpolated / interpolated across lost
samples, splits, inputs held over a gap and the longest hold, and stamp period and jitter.
A stop never leaves anything that reads as a training set: the set is written in a hidden
staging folder (:mod:`soft_rom.outputs`) and swapped in only when complete.
"""

from soft_rom.convert.api import choose_dt_ns, convert, read_episode
from soft_rom.convert.mapping import (
                                      BagMapping,
                                      InputSource,
                                      load_mapping,
                                      OutputMapping,
                                      StateMapping,
)
from soft_rom.convert.report import ConversionReport, TopicReport

__all__ = ['BagMapping', 'ConversionReport', 'InputSource', 'OutputMapping', 'StateMapping',
           'TopicReport', 'choose_dt_ns', 'convert', 'load_mapping', 'read_episode']
