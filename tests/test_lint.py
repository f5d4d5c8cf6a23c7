"""Lint as a test, like ament_flake8/ament_pep257: ruff with the project's configuration."""

from __future__ import annotations

from pathlib import Path
import shutil
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _ruff() -> str | None:
    local = Path(sys.executable).parent / 'ruff'
    return str(local) if local.exists() else shutil.which('ruff')


@pytest.mark.skipif(_ruff() is None, reason='ruff is installed with the test extras')
def test_ruff_is_clean() -> None:
    out = subprocess.run([_ruff(), 'check', 'soft_rom', 'tests', 'benchmarks', 'launch',
                          'setup.py'], cwd=ROOT, capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
