"""Hand-made hostile model files (shared by the model, fuzz and CLI misuse tests).

Each builder writes one file at ``path`` and returns it. The bytes are written by hand
(zip members, ``.npy`` headers, metadata JSON) so that they can be anything at all.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
import struct
from typing import Any
import zipfile

import numpy as np

from soft_rom.models import DiscreteModel, SecondOrderModel


def second_order(seed: int = 0, r: int = 3, m: int = 2, p: int = 4) -> SecondOrderModel:
    """A small, stable, trusted LOpInf model."""
    rng = np.random.default_rng(seed)
    Qk, _ = np.linalg.qr(rng.normal(size=(r, r)))
    K = (Qk * rng.uniform(10.0, 400.0, r)) @ Qk.T
    C = (Qk * rng.uniform(0.5, 5.0, r)) @ Qk.T
    return SecondOrderModel(0.5 * (K + K.T), 0.5 * (C + C.T), rng.normal(size=(r, m)),
                            rng.normal(size=(p, r)), dt=1e-3, y_ref=rng.normal(size=p),
                            metadata={'provenance': {'bags': ['ep1']}, 'note': 'ok'})


def discrete(seed: int = 1, r: int = 4, m: int = 2, p: int = 3,
             radius: float = 0.9) -> DiscreteModel:
    """A small discrete model with spectral radius ``radius``."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(r, r))
    A *= radius / np.max(np.abs(np.linalg.eigvals(A)))
    return DiscreteModel(A, rng.normal(size=(r, m)), rng.normal(size=(p, r)),
                         rng.normal(size=(p, m)), dt=2e-3, method='era', y_ref=np.ones(p))


def npy_bytes(arr: np.ndarray) -> bytes:
    """The ``.npy`` serialisation of a numeric array."""
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def npy_raw(header: str, payload: bytes = b'', version: int = 1) -> bytes:
    """A ``.npy`` member with a hand-written header text."""
    text = header.encode('latin1')
    if version == 1:
        return b'\x93NUMPY\x01\x00' + struct.pack('<H', len(text)) + text + payload
    return b'\x93NUMPY' + bytes([version, 0]) + struct.pack('<I', len(text)) + text + payload


def members_of(model: Any) -> dict[str, bytes]:
    """The archive members (name -> bytes) :meth:`save` would write for ``model``."""
    arrays = dict(model.matrices())
    arrays['y_ref'] = model.y_ref
    out = {f'{k}.npy': npy_bytes(v) for k, v in arrays.items()}
    out['__metadata__.npy'] = npy_bytes(meta_array(model.header()))
    return out


def meta_array(header: Any) -> np.ndarray:
    text = header if isinstance(header, (str, bytes)) else json.dumps(header)
    data = text.encode('utf-8', 'surrogatepass') if isinstance(text, str) else text
    return np.frombuffer(data, dtype=np.uint8)


def write_zip(path: str | Path, members: dict[str, bytes], *,
              compression: int = zipfile.ZIP_STORED) -> Path:
    """Write ``members`` as a zip archive."""
    path = Path(path)
    with zipfile.ZipFile(path, 'w', compression=compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def with_header(model: Any, path: str | Path, **changes: Any) -> Path:
    """``model``'s file with metadata fields replaced."""
    header = model.header()
    header.update(changes)
    members = members_of(model)
    members['__metadata__.npy'] = npy_bytes(meta_array(header))
    return write_zip(path, members)


def with_metadata_text(model: Any, path: str | Path, text: str | bytes) -> Path:
    """``model``'s file with the metadata document replaced by ``text``."""
    members = members_of(model)
    members['__metadata__.npy'] = npy_bytes(meta_array(text))
    return write_zip(path, members)


def with_arrays(model: Any, path: str | Path, **arrays: Any) -> Path:
    members = members_of(model)
    for k, v in arrays.items():
        members[f'{k}.npy'] = v if isinstance(v, bytes) else npy_bytes(np.asarray(v))
    return write_zip(path, members)


def patch_zip_fields(path: str | Path, *, method: int | None = None,
                     flags: int | None = None) -> Path:
    """Patch the compression method / flag bits of every local and central header."""
    path = Path(path)
    data = bytearray(path.read_bytes())
    for sig, off_flags, off_method in ((b'PK\x03\x04', 6, 8), (b'PK\x01\x02', 8, 10)):
        start = 0
        while (i := data.find(sig, start)) >= 0:
            if flags is not None:
                data[i + off_flags:i + off_flags + 2] = struct.pack('<H', flags)
            if method is not None:
                data[i + off_method:i + off_method + 2] = struct.pack('<H', method)
            start = i + 4
    path.write_bytes(bytes(data))
    return path


def corrupt_deflate(model: Any, path: str | Path) -> Path:
    """A deflated archive whose ``K`` stream is corrupt (CRC and sizes left as they were)."""
    path = write_zip(path, members_of(model), compression=zipfile.ZIP_DEFLATED)
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo('K.npy')
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    for j in range(start + 2, start + min(info.compress_size, 40)):
        data[j] = 0xFF
    path.write_bytes(bytes(data))
    return path


def multi_disk_zip64(path: str | Path) -> Path:
    """An end-of-central-directory with a ZIP64 locator that claims several disks."""
    locator = b'PK\x06\x07' + struct.pack('<LQL', 0, 0, 2)
    eocd = b'PK\x05\x06' + struct.pack('<HHHHLLH', 0, 0, 0, 0, 0, 0, 0)
    path = Path(path)
    path.write_bytes(locator + eocd)
    return path


def declare_size(path: str | Path, name: str, size: int) -> Path:
    """Patch the declared uncompressed size of member ``name`` (local and central header)."""
    path = Path(path)
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(name)
    data = bytearray(path.read_bytes())
    local = info.header_offset
    data[local + 22:local + 26] = struct.pack('<L', size)
    i = data.find(b'PK\x01\x02')
    while i >= 0:
        n = struct.unpack('<H', data[i + 28:i + 30])[0]
        if data[i + 46:i + 46 + n] == name.encode():
            data[i + 24:i + 28] = struct.pack('<L', size)
            break
        i = data.find(b'PK\x01\x02', i + 4)
    path.write_bytes(bytes(data))
    return path


__all__ = ['corrupt_deflate', 'declare_size', 'discrete', 'members_of', 'meta_array',
           'multi_disk_zip64', 'npy_bytes', 'npy_raw', 'patch_zip_fields', 'second_order',
           'with_arrays', 'with_header', 'with_metadata_text', 'write_zip']
