"""Markdown as a reader's viewer renders it: tables found by markdown-it-py, cells counted.

markdown-it-py (GitHub-flavoured tables) pads a short row and drops the cells of a long
one, so a row with an unescaped ``|`` in a cell renders without complaint but loses its
value. :func:`table_problems` finds every table the parser finds and counts each row's
cells in the source the way the parser splits them (on ``|`` not preceded by ``\\``).
"""

from __future__ import annotations

from markdown_it import MarkdownIt

__all__ = ['cells', 'table_problems', 'tables']


def cells(line: str) -> list[str]:
    """The cells of one table row, split as GFM does (escaped pipes stay in the cell)."""
    text = line.strip()
    if text.startswith('|'):
        text = text[1:]
    if text.endswith('|') and not text.endswith('\\|'):
        text = text[:-1]
    out, cur, escaped = [], '', False
    for ch in text:
        if ch == '|' and not escaped:
            out.append(cur.strip())
            cur = ''
        else:
            cur += ch
        escaped = ch == '\\' and not escaped
    out.append(cur.strip())
    return out


def tables(text: str) -> list[list[tuple[int, list[str]]]]:
    """Each table the parser finds: ``[(1-based line, cells)]``, header row first.

    The delimiter row (``|---|``) is left out.
    """
    md = MarkdownIt('commonmark').enable('table')
    lines = text.splitlines()
    found = []
    for tok in md.parse(text):
        if tok.type == 'table_open' and tok.map is not None:
            start, end = tok.map
            rows = [(i + 1, cells(lines[i])) for i in range(start, end) if i != start + 1]
            found.append(rows)
    return found


def table_problems(text: str) -> list[str]:
    """Rows whose number of cells differs from their header's (empty when all render)."""
    problems = []
    for rows in tables(text):
        (_first, header), body = rows[0], rows[1:]
        for line, row in body:
            if len(row) != len(header):
                problems.append(f'line {line}: {len(row)} cells, header has {len(header)}: '
                                f'{" | ".join(row)}')
    return problems
