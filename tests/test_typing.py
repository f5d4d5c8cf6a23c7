"""Type checking as a test: mypy on the package with the configuration in pyproject.toml.

``[tool.mypy]`` in ``pyproject.toml`` states the configuration (``files = ['soft_rom']``,
``check_untyped_defs``, ``no_implicit_optional``, ``warn_unused_ignores``, ...); this test runs
``python -m mypy`` from the repository root exactly as a developer would, so the command line
and the test can never disagree. mypy is a test extra (``pip install -e '.[test]'``).
"""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]


def test_mypy_is_clean_on_the_package() -> None:
    out = subprocess.run([sys.executable, '-m', 'mypy'], cwd=ROOT, capture_output=True,
                         text=True, check=False)
    report = out.stdout + out.stderr
    assert 'No module named mypy' not in report, (
        'mypy is not installed: it is a test extra, pip install -e ".[test]"')
    assert out.returncode == 0, report
    assert 'Success: no issues found' in out.stdout, report
