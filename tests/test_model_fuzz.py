"""Seeded mutation fuzzer of model files: each mutant ends in ModelFileError or a usable model.

The suite runs 2,000 mutants (seeded, about 10 s). A longer run::

    .venv/bin/python tests/test_model_fuzz.py --n 20000 --seed 1

prints the count of mutants per outcome and exits 1 if any raised anything else.
"""

from __future__ import annotations

import argparse
from collections import Counter
import io
import json
from pathlib import Path
import random
import struct
import sys
import tempfile
import time
import traceback
import zipfile

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _hostile as h  # noqa: E402

from soft_rom.errors import ModelFileError  # noqa: E402
from soft_rom.models import load_model  # noqa: E402

_VALUES = ['1e300', '-1', '0', '-0.0', '1e-300', 'NaN', 'Infinity', '7' * 50, 'null', 'true',
           '"\\ud800"', '"' + 'x' * 300 + '"', '[' * 40 + ']' * 40, '{}', '[]', '"a\\u0000"',
           '2.5', '1e5', '3', '"SecondOrderModel"', '"DiscreteModel"', '"lopinf"']
_INTS = [0, 1, 0x7F, 0x80, 0xFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 0x10000]


def _corpus() -> list[bytes]:
    out = []
    for model in (h.second_order(), h.discrete(), h.discrete(radius=1.4)):
        for comp in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            buf = io.BytesIO()
            with zipfile.ZipFile(buf, 'w', compression=comp) as zf:
                for name, data in h.members_of(model).items():
                    zf.writestr(name, data)
            out.append(buf.getvalue())
    return out


def _members(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return {n: zf.read(n) for n in zf.namelist()}


def _rezip(members: dict[str, bytes], comp: int) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, 'w', compression=comp) as zf:
        for name, d in members.items():
            zf.writestr(name, d)
    return buf.getvalue()


def _mutate_json(rng: random.Random, members: dict[str, bytes]) -> None:
    meta = np.load(io.BytesIO(members['__metadata__.npy']), allow_pickle=False)
    text = meta.tobytes().decode()
    header = json.loads(text)
    key = rng.choice(sorted(header))
    raw = json.dumps(header)
    token = json.dumps(header[key])
    raw = raw.replace(f'"{key}": {token}', f'"{key}": {rng.choice(_VALUES)}', 1)
    if rng.random() < 0.2:
        raw = raw[:rng.randrange(len(raw) + 1)]
    members['__metadata__.npy'] = h.npy_bytes(np.frombuffer(
        raw.encode('utf-8', 'surrogatepass'), dtype=np.uint8))


def _mutate_array(rng: random.Random, members: dict[str, bytes]) -> None:
    name = rng.choice([n for n in members if n != '__metadata__.npy'])
    arr = np.load(io.BytesIO(members[name]), allow_pickle=False)
    choice = rng.randrange(6)
    if choice == 0 and arr.size:
        arr = arr.copy()
        arr.flat[rng.randrange(arr.size)] = rng.choice(
            [np.nan, np.inf, 1e300, -1e300, 1e140, -5.0, 0.0])
    elif choice == 1:
        arr = np.zeros(tuple(rng.randrange(0, 6) for _ in range(rng.randrange(0, 4))))
    elif choice == 2:
        arr = -arr
    elif choice == 3:
        arr = arr.astype(rng.choice([np.int64, np.float32, np.complex128, np.bool_, '>f8']))
    elif choice == 4:
        arr = arr * 10.0 ** rng.randrange(1, 200)
    else:
        arr = arr.T.copy() if arr.ndim == 2 else arr[..., None]
    members[name] = h.npy_bytes(arr)


def _mutate_npy_header(rng: random.Random, members: dict[str, bytes]) -> None:
    name = rng.choice(sorted(members))
    data = bytearray(members[name])
    hlen = struct.unpack('<H', data[8:10])[0]
    text = data[10:10 + hlen].decode('latin1')
    repl = rng.choice(['(1000000, 1000000)', '(3, 3, 3, 3)', '()', '(-1,)', '(2**64,)',
                       "'O'", "'<i8'", 'True', '(((((', "'''", '1e999', 'None'])
    spans = [("'descr': '", "'"), ("'shape': (", ')'), ("'fortran_order': ", ',')]
    a, b = rng.choice(spans)
    i = text.find(a)
    if i >= 0:
        j = text.find(b, i + len(a))
        text = text[:i + len(a) - 1] + repl + text[j + 1:]
    enc = text.encode('latin1')
    members[name] = bytes(data[:8]) + struct.pack('<H', len(enc)) + enc + bytes(data[10 + hlen:])


def mutate(rng: random.Random, base: bytes) -> bytes:
    """One mutant of ``base``: raw byte damage or a structured edit of one member."""
    kind = rng.randrange(9)
    data = bytearray(base)
    if kind == 0:
        for _ in range(rng.randint(1, 8)):
            data[rng.randrange(len(data))] = rng.randrange(256)
    elif kind == 1:
        del data[rng.randrange(len(data)):]
    elif kind == 2:
        i = rng.randrange(len(data))
        data[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
    elif kind == 3:
        i = rng.randrange(len(data))
        del data[i:i + rng.randint(1, 256)]
    elif kind == 4:
        i = rng.randrange(max(len(data) - 4, 1))
        data[i:i + 4] = struct.pack('<L', rng.choice(_INTS))
    else:
        comp = zipfile.ZIP_DEFLATED if b'\x08\x00' in base[8:10] else zipfile.ZIP_STORED
        members = _members(base)
        if kind == 5:
            _mutate_json(rng, members)
        elif kind == 6:
            _mutate_array(rng, members)
        elif kind == 7:
            _mutate_npy_header(rng, members)
        else:
            name = rng.choice(sorted(members))
            if rng.random() < 0.5:
                del members[name]
            else:
                members[rng.choice(['x.npy', 'K.npy', 'A.npy', 'y_ref', '../K.npy'])] = \
                    members[name]
        data = bytearray(_rezip(members, comp))
    return bytes(data)


def run(n: int, seed: int, workdir: Path) -> tuple[Counter[str], list[str]]:
    """Load ``n`` mutants; returns outcome counts and reports of unexpected exceptions."""
    from soft_rom.cli.info import describe, format_text

    rng = random.Random(seed)
    corpus = _corpus()
    counts: Counter[str] = Counter()
    bad: list[str] = []
    path = workdir / 'mutant.npz'
    slowest = 0.0
    for i in range(n):
        path.write_bytes(mutate(rng, rng.choice(corpus)))
        t0 = time.perf_counter()
        try:
            model = load_model(path)
            trusted = model.trusted if hasattr(model, 'trusted') else True  # (old API)
            with np.errstate(all='ignore'):    # untrusted models may overflow: that is fine
                model.simulate(np.ones((model.n_inputs, 5)))
            text = format_text(describe(path))
            text.encode('utf-8')
            counts['valid' if trusted else 'valid, not trusted'] += 1
        except ModelFileError:
            counts['ModelFileError'] += 1
        except Exception as err:  # noqa: BLE001 -- this is what the fuzzer looks for
            counts[type(err).__name__] += 1
            bad.append(f'mutant {i}: {type(err).__name__}: {err}\n{traceback.format_exc()}')
            (workdir / f'bad_{i}.npz').write_bytes(path.read_bytes())
        slowest = max(slowest, time.perf_counter() - t0)
    counts['slowest mutant, ms'] = round(1e3 * slowest)
    return counts, bad


def test_fuzz_model_files(tmp_path) -> None:
    t0 = time.perf_counter()
    counts, bad = run(2000, seed=12, workdir=tmp_path)
    assert not bad, bad[0]
    assert counts['ModelFileError'] > 500 and counts['valid'] > 50, counts
    assert time.perf_counter() - t0 < 60


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--n', type=int, default=20000)
    parser.add_argument('--seed', type=int, default=1)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        counts, bad = run(args.n, args.seed, Path(tmp))
        wall = time.perf_counter() - t0
    print(f'{args.n} mutants (seed {args.seed}) in {wall:.1f} s: {dict(counts)}')
    for report in bad[:5]:
        print(report)
    print(f'{len(bad)} exception(s) other than ModelFileError')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
