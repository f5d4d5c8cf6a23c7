"""Test helpers (``_rig``, ``_bags``, ``_source``, ...) importable from every test folder."""

from __future__ import annotations

from pathlib import Path
import sys

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
