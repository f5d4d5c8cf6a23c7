"""Benchmarks given a wrong path: one line naming it, exit 1, no traceback (as the CLI)."""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]

# (script, arguments): each opens the file before any timing starts
CASES = [
    ('bench_dmdc.py', ['--training-set', '{missing}']),
    ('bench_dmdc.py', ['--training-set', '{not_zarr}']),
    ('bench_curve_cost.py', ['{missing}']),
    ('bench_cubic_selection.py', ['{missing}']),
    ('bench_mpc.py', ['--model', '{missing}']),
]


@pytest.mark.parametrize(('script', 'args'), CASES)
def test_a_wrong_path_gets_one_line_and_exit_1(tmp_path: Path, script: str,
                                               args: list[str]) -> None:
    not_zarr = tmp_path / 'notes.txt'
    not_zarr.write_text('not a training set\n')
    paths = {'missing': str(tmp_path / 'typo.zarr'), 'not_zarr': str(not_zarr)}
    argv = [a.format(**paths) for a in args]
    out = subprocess.run([sys.executable, str(ROOT / 'benchmarks' / script), *argv],
                         capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and 'Traceback' not in out.stderr, out.stderr
    assert lines[0].startswith(f'{script}: ')
    assert str(tmp_path) in lines[0]          # it names the path that was wrong
    assert not_zarr.read_text() == 'not a training set\n'
