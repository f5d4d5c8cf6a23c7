"""The chunked on-disk training set (zarr), written by ``soft-rom convert`` and read by the fits.

Layout (zarr format 2 on disk, so zarr 2.16+ and zarr 3.x both read and write it, and
:func:`dask.array.from_zarr` reads it on a cluster)::

    OUT.zarr/                      attrs: format='soft_rom.trainingset', format_version=3,
                                          input_names, input_units, output_names,
                                          output_units, episode_names, provenance,
                                          all_chunks_stored=true, ...
        q_ref      (n,)            reference configuration (absent without states)
        y_ref      (p,)            reference output
        episodes/<name>/           attrs: metadata (t0_ns, source bag, topics, report)
            t      (k,)            seconds from the episode's start: t[0] = 0, increasing
            U      (m, k)          inputs, absolute
            Y      (p, k)          outputs, absolute
            Q      (n, k)          optional full states, absolute, float64

Arrays follow the package convention ``(n_channels, n_samples)``, float64. ``Q`` is chunked in
blocks of ``(min(n, 32768), 32)`` (8 MiB), uncompressed, Fortran order inside a chunk: a column
block of 32 snapshots reads ``ceil(n / 32768)`` whole chunks (the streaming POD's randomized
range finder) and a row block reads whole chunks too (its Gram pass), so both access patterns
of :mod:`soft_rom.scale` read every stored byte once per pass. Fortran order makes each
snapshot contiguous inside a chunk file, so the writer appends each snapshot to the open
chunk files of its chunk column straight from the buffer it arrived in
(:class:`~soft_rom.dataset.chunks.ChunkFileWriter`); compression is off because it would
cost a CPU pass per snapshot on a 2-core machine for data (float64 positions) that
compresses poorly. The writer holds at most 16 snapshots waiting to be written.

Time: ``t`` is float seconds from the episode's own start (``t[0] = 0``); the absolute start
is the integer ``metadata['t0_ns']`` (nanoseconds, e.g. the epoch stamp of the first sample),
so a recording stamped at 1.7e9 s keeps its sample times exact. Format version 1 stored
absolute seconds; such a set is read with its times shifted to ``t[0] = 0`` when its stamps
are small enough to be exact (below 1e4 s), and refused with the command that converts its
bags again otherwise.

Format version 3 ends every chunk with its CRC-32C (numcodecs' ``crc32c`` filter, which zarr 2
and 3 both read), checked at every read (:mod:`~soft_rom.dataset.checksum`); sets of version 2
(no checksums) are still read.

Every chunk of every array is stored, chunks of zeros too (``all_chunks_stored``; before
that attribute, zarr 3 left chunks of zeros out). The reader therefore takes a missing chunk
for a damaged set: each array it reads is a :class:`~soft_rom.dataset.stored.StoredArray`,
which checks once, before its first read, that every chunk of its grid is stored (one
directory listing) and whole, and raises :class:`~soft_rom.errors.DatasetError` naming the
set, the episode and the array for that and for any error of zarr or its codecs; zarr alone
would read a missing chunk as zeros.

Modules: :mod:`~soft_rom.dataset.writer` (:class:`TrainingSetWriter`), :mod:`~soft_rom.
dataset.reader` (:class:`TrainingSet`), :mod:`~soft_rom.dataset.stored` (:class:`StoredArray`,
the checked reads), :mod:`~soft_rom.dataset.chunks` (the raw ``Q`` chunk writer) and
``_format`` (constants and zarr helpers).

A training set is written atomically through :func:`soft_rom.outputs.atomic_dir`: into a
hidden staging folder next to the target, marked as a soft_rom output and swapped into place
only when :class:`TrainingSetWriter` closes without an exception. ``overwrite`` replaces only
a folder soft_rom wrote as a training set; a training set written before the marker existed
is recognised by its ``format`` attribute (a bag or any other folder is refused).
"""

from soft_rom.dataset._format import (
                                      FORMAT,
                                      FORMAT_VERSION,
                                      KIND,
                                      Q_CHUNK_COLS,
                                      Q_CHUNK_ROWS,
                                      V1_MAX_START_S,
)
from soft_rom.dataset.reader import TrainingSet
from soft_rom.dataset.stored import StoredArray
from soft_rom.dataset.writer import adopt_legacy, EpisodeWriter, TrainingSetWriter

__all__ = ['FORMAT', 'FORMAT_VERSION', 'KIND', 'EpisodeWriter', 'Q_CHUNK_COLS', 'Q_CHUNK_ROWS',
           'StoredArray', 'TrainingSet', 'TrainingSetWriter', 'V1_MAX_START_S',
           'adopt_legacy']
