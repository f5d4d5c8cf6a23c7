"""The architecture, checked: import-linter's contracts, no import cycle, modules of a size.

The contracts are in ``pyproject.toml`` (``[tool.importlinter]``): the layers from the CLI
down to the core, rclpy and the ROS messages imported by ``soft_rom.ros`` only, rosbags by
``soft_rom.bags`` only, and no cycle among the modules of any package. grimp (the graph
import-linter builds on) lists every import cycle, type-checking imports included.
"""

from __future__ import annotations

import ast
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

#: Modules allowed over the limit, each with the length it may not exceed (none since the
#: splits of issue 23); none may grow, and no other may pass the limit.
LONG_MODULES: dict[str, int] = {}
#: Functions allowed over the limit (module:function), each with the length it may not exceed
#: (none since issue 23); at most MAX_LONG_FUNCTIONS of them.
LONG_FUNCTIONS: dict[str, int] = {}


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


def _sizes() -> tuple[dict[str, int], dict[str, int]]:
    """Lines of every module of the package, and of every function over the limit."""
    modules, functions = {}, {}
    for path in sorted(PACKAGE.rglob('*.py')):
        name = path.relative_to(PACKAGE).as_posix()
        text = path.read_text(encoding='utf-8')
        modules[name] = len(text.splitlines())
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = int(node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    functions[f'{name}:{node.name}'] = lines
    return modules, functions


def test_modules_and_functions_do_not_grow_past_the_limits():
    modules, functions = _sizes()
    long_modules = {m: n for m, n in modules.items() if n > MAX_MODULE_LINES}
    grown = {m: (n, LONG_MODULES.get(m)) for m, n in long_modules.items()
             if n > LONG_MODULES.get(m, MAX_MODULE_LINES)}
    assert not grown, f'modules over {MAX_MODULE_LINES} lines (now, allowed): {grown}'
    grown = {f: (n, LONG_FUNCTIONS.get(f)) for f, n in functions.items()
             if n > LONG_FUNCTIONS.get(f, MAX_FUNCTION_LINES)}
    assert not grown, f'functions over {MAX_FUNCTION_LINES} lines (now, allowed): {grown}'
    assert len(LONG_FUNCTIONS) <= MAX_LONG_FUNCTIONS
    # the lists only shrink: an entry that is short now is taken off
    gone = sorted(set(LONG_MODULES) - set(long_modules)) + sorted(set(LONG_FUNCTIONS)
                                                                  - set(functions))
    assert not gone, f'now within the limits, remove from the lists: {gone}'
