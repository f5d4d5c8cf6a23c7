"""The benchmarks' entry point: a soft_rom error ends the run with its one line.

A wrong path or a file that is not what the benchmark needs (a training set, a model file)
raises one of :mod:`soft_rom.errors` or an ``OSError``; like the CLI, the benchmark then
prints that line, prefixed with its own name, and exits 1 instead of printing a traceback.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
import sys


def run(main: Callable[[], object]) -> None:
    """Run ``main`` and exit with its return value (a soft_rom error: one line, exit 1)."""
    from soft_rom.errors import SoftRomError
    try:
        code = main()
    except (SoftRomError, OSError) as exc:   # OSError: a missing or unreadable file
        raise SystemExit(f'{Path(sys.argv[0]).name}: {exc}') from None
    sys.exit(code)
