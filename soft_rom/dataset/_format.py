"""Constants and zarr helpers of the training-set format (shared by its writer and reader)."""

from __future__ import annotations

from collections.abc import Mapping
import json
from pathlib import Path
import shlex
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import DatasetError

FORMAT = 'soft_rom.trainingset'
FORMAT_VERSION = 3
#: Versions this soft_rom reads: 1 (absolute times), 2 (no checksums), 3 (a CRC-32C after
#: every chunk of every array, :mod:`soft_rom.dataset.checksum`).
READ_VERSIONS = (1, 2, 3)
#: First version whose chunks carry checksums.
CHECKSUM_VERSION = 3
#: Marker kind of a training-set folder (:mod:`soft_rom.outputs`).
KIND = 'trainingset'
#: Format version 1 (absolute times) is read when every episode starts before this (s).
V1_MAX_START_S = 1e4
#: Default ``Q`` chunk: rows (at most) and columns.
Q_CHUNK_ROWS = 32768
Q_CHUNK_COLS = 32
#: Root attribute of a set whose writer stored every chunk, zeros too (every set since it
#: was added; before, zarr 3 left out chunks of zeros of ``t``, ``U``, ``Y`` and the
#: references, so that such a missing chunk may be one of zeros in an older set).
ALL_CHUNKS = 'all_chunks_stored'


def _zarr() -> Any:
    try:
        import zarr
    except ImportError as err:  # pragma: no cover - zarr is a hard dependency
        raise DatasetError('the training-set format needs the zarr package: '
                           'pip install zarr') from err
    return zarr


def _open_group(path: Path, mode: str) -> Any:
    from soft_rom.dataset.checksum import register
    register()                     # the crc32c filter, also with numcodecs < 0.14
    zarr = _zarr()
    major = int(str(zarr.__version__).split('.')[0])
    if mode == 'w' and major >= 3:
        return zarr.open_group(str(path), mode=mode, zarr_format=2)
    return zarr.open_group(str(path), mode=mode)


def _create_array(group: Any, name: str, shape: tuple[int, ...], chunks: tuple[int, ...],
                  data: NDArray[Any] | None = None, compress: bool = True,
                  order: str = 'C') -> Any:
    """Create a float64 array under ``group`` with the zarr 3 or the zarr 2 API.

    Every chunk written is stored, also one of zeros (zarr 3 leaves those out by default):
    the reader takes a missing chunk for a damaged set (:data:`ALL_CHUNKS`). Every chunk
    ends with its CRC-32C (the ``crc32c`` filter, :mod:`soft_rom.dataset.checksum`).
    """
    from soft_rom.dataset.checksum import codec
    chunks = tuple(max(int(c), 1) for c in chunks)
    filters = [codec()]
    if hasattr(group, 'create_array'):  # zarr 3
        kw: dict[str, Any] = {} if compress else {'compressors': None}
        arr = group.create_array(name, shape=shape, chunks=chunks, dtype='f8',
                                 fill_value=0.0, order=order, filters=filters,
                                 config={'write_empty_chunks': True}, **kw)
    else:  # zarr 2
        kw = {} if compress else {'compressor': None}
        arr = group.create_dataset(name, shape=shape, chunks=chunks, dtype='f8',
                                   fill_value=0.0, order=order, write_empty_chunks=True,
                                   filters=filters, **kw)
    if data is not None and data.size:
        arr[...] = data
    return arr


def _jsonable(obj: Any, what: str) -> Any:
    """``obj`` converted to plain JSON types (numpy scalars and arrays become lists)."""
    def default(o: Any) -> Any:
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f'{type(o).__name__} is not JSON-serialisable')
    try:
        return json.loads(json.dumps(obj, default=default, allow_nan=True))
    except (TypeError, ValueError) as err:
        raise DatasetError(f'{what} must be JSON-serialisable: {err}') from err


def _check_name(name: str) -> str:
    name = str(name)
    if not name or '/' in name or '\\' in name or name.startswith('.') or name != name.strip():
        raise DatasetError(f'episode name {name!r} is not valid: use a non-empty name without '
                           "'/' that does not start with '.'.")
    return name


def _reconvert(path: Path, attrs: Mapping[str, Any]) -> str:
    """The command that converts the bags of a training set again."""
    prov = attrs.get('provenance') or {}
    bags = prov.get('bags') if isinstance(prov, Mapping) else None
    args = ' '.join(shlex.quote(str(b)) for b in bags) if isinstance(bags, list) and bags \
        else 'BAG...'
    return f'soft-rom convert {args} -o {shlex.quote(str(path))} --overwrite'
