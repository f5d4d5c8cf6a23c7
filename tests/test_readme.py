"""The README stays true: its tables render, its flags exist, its results are the study's.

* Every Markdown table in the README and in ``docs/`` has, in every row, its header's
  number of cells (markdown-it-py finds the tables; a stray ``|`` loses a value).
* Every ``soft-rom`` command in the README (code blocks and inline code) uses options the
  verb's parser has, with values among their choices; every flag named alone in inline
  code is an option of some verb (or of the outside tool named beside it); every
  ``-p NAME:=`` of a ``ros2 run soft_rom predictor`` is a declared node parameter; the
  deprecated aliases the README says are accepted are accepted by every verb it says.
* The results table between the ``study-results`` markers is exactly what
  ``soft_rom.study.readme.results_block`` makes of ``docs/study_summary.json`` (the
  summary ``soft-rom study`` wrote), and ``docs/study_report.md`` is that study's report:
  a number edited by hand, or a stale study, fails here (``tools/update_study_docs.py``
  regenerates both).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import re
import shlex

from _markdown import table_problems
import pytest

from soft_rom.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'

#: Flags of other programs the README names in inline code, and whose they are.
OTHER_TOOLS = {
    '--ros-args': 'ros2 run / ros2 launch',
    '--compression-mode': 'ros2 bag record',
    '--loop': 'ros2 bag play',
    '--rate': 'ros2 bag play',
    '--clock': 'ros2 bag play',
    '--preset': 'benchmarks/bench_scale.py',
    '-p': 'ros2 run ... --ros-args -p NAME:=VALUE',
    '-pip': "rosdep's -pip keys",
}


def _verbs() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return parser, dict(sub.choices)


def _code_blocks(text: str) -> list[str]:
    return re.findall(r'```[a-z]*\n(.*?)```', text, flags=re.S)


def _inline_code(text: str) -> list[str]:
    prose = re.sub(r'```[a-z]*\n.*?```', '', text, flags=re.S)
    return re.findall(r'`([^`\n]+)`', prose)


def _commands(text: str) -> list[str]:
    """Every ``soft-rom ...`` command line (comments and continuations handled)."""
    lines = []
    for block in _code_blocks(text):
        for line in block.replace('\\\n', ' ').splitlines():
            lines += [part for part in re.split(r'&&|;|\|', line.split(' # ')[0])]
    lines += _inline_code(text)
    out = []
    for line in lines:
        m = re.search(r'(?:^|\s|/)soft-rom\s+(\S.*)$', line.strip())
        if m:
            out.append(m.group(1).split('#')[0].strip())
    return out


def test_markdown_tables_render_whole() -> None:
    files = [README] + sorted((ROOT / 'docs').glob('*.md'))
    problems = {f.name: table_problems(f.read_text(encoding='utf-8')) for f in files}
    assert not any(problems.values()), problems


def test_every_readme_command_uses_existing_options() -> None:
    top, verbs = _verbs()
    commands = _commands(README.read_text(encoding='utf-8'))
    assert len(commands) >= 15, commands
    bad = []
    for command in commands:
        tokens = shlex.split(command.replace('...', 'X'))
        verb = tokens[0]
        if verb.startswith('<') or verb == 'VERB' or verb == 'VERB:':
            continue                 # the grammar, not a command: `soft-rom <verb>`
        if verb not in verbs:
            bad.append(f'{command}: no verb {verb!r}')
            continue
        options = {**top._option_string_actions, **verbs[verb]._option_string_actions}
        for i, tok in enumerate(tokens[1:], start=1):
            if not tok.startswith('-') or tok == '-':
                continue
            flag = tok.split('=', 1)[0]
            action = options.get(flag)
            if action is None:
                bad.append(f'{command}: soft-rom {verb} has no {flag}')
                continue
            value = tok.split('=', 1)[1] if '=' in tok else (
                tokens[i + 1] if i + 1 < len(tokens) else None)
            if action.choices is not None and value is not None and callable(action.type):
                try:
                    value = action.type(value)      # e.g. type=int with choices=range(...)
                except (TypeError, ValueError):
                    pass
            if action.choices is not None and value is not None and value not in action.choices:
                bad.append(f'{command}: {flag} {value!r} is not one of {list(action.choices)}')
    assert not bad, '\n'.join(bad)


def test_every_flag_named_in_the_readme_exists() -> None:
    top, verbs = _verbs()
    known = set(top._option_string_actions)
    for parser in verbs.values():
        known |= set(parser._option_string_actions)
    bad = []
    for span in _inline_code(README.read_text(encoding='utf-8')):
        first = span.split()[0] if span.split() else ''
        if not first.startswith('-'):
            continue                 # a command (checked above), a path, a value
        for flag in re.findall(r'(?:^|\s|/)(--?[a-zA-Z][\w-]*)', span):
            if flag not in known and flag not in OTHER_TOOLS:
                bad.append(f'`{span}`: {flag} is no option of any soft-rom verb')
    assert not bad, '\n'.join(bad)


def test_node_parameters_in_the_readme_are_declared() -> None:
    from soft_rom.predictor.params import NODE_PARAMS, PARAMS

    names = {p.name for p in PARAMS + NODE_PARAMS}
    text = README.read_text(encoding='utf-8')
    used = set(re.findall(r'-p\s+([a-z_]+):=', text))
    used |= set(re.findall(r'ros2 param set \S+ ([a-z_]+) ', text))
    assert used, 'no node parameter found in the README'
    assert used <= names, sorted(used - names)


@pytest.mark.parametrize('alias, real, verbs', [
    ('--no-progress', '--quiet', None),                 # every verb that has --quiet
    ('--summary-json', '--json', ('fit', 'evaluate', 'replay')),
    ('--out', '--output', ('simulate', 'study', 'demo')),
])
def test_deprecated_aliases_are_accepted_where_the_readme_says(alias, real, verbs) -> None:
    _top, parsers = _verbs()
    wanted = verbs or [v for v, p in parsers.items() if real in p._option_string_actions]
    assert wanted
    for verb in wanted:
        actions = parsers[verb]._option_string_actions
        assert real in actions and alias in actions, (verb, alias)
        assert actions[alias].dest == actions[real].dest, (verb, alias)
    text = README.read_text(encoding='utf-8')
    assert alias in text


def test_readme_results_are_the_committed_study() -> None:
    from soft_rom.study.readme import read_block, results_block

    summary = json.loads((ROOT / 'docs' / 'study_summary.json').read_text(encoding='utf-8'))
    text = README.read_text(encoding='utf-8')
    assert read_block(text) == results_block(summary), (
        'the README results differ from docs/study_summary.json: regenerate them with '
        'tools/update_study_docs.py, never by hand')


def test_study_report_in_docs_is_the_committed_study() -> None:
    from soft_rom.study.report import study_report

    summary = json.loads((ROOT / 'docs' / 'study_summary.json').read_text(encoding='utf-8'))
    report = (ROOT / 'docs' / 'study_report.md').read_text(encoding='utf-8')
    assert report == study_report(summary, figures='figures/study/')
    for name in re.findall(r'\]\((figures/study/[^)]+)\)', report):
        assert (ROOT / 'docs' / name).is_file(), name


def test_a_hand_edit_of_the_results_table_fails(tmp_path) -> None:
    """The check above is not vacuous: one digit changed in the table is caught."""
    from soft_rom.study.readme import read_block, results_block

    summary = json.loads((ROOT / 'docs' / 'study_summary.json').read_text(encoding='utf-8'))
    block = read_block(README.read_text(encoding='utf-8'))
    table_row = next(line for line in block.splitlines() if line.startswith('| time'))
    digit = re.search(r'\d(?=\))', table_row)
    assert digit is not None
    edited_row = (table_row[:digit.start()] + str((int(digit.group()) + 1) % 10)
                  + table_row[digit.end():])
    assert block.replace(table_row, edited_row) != results_block(summary)
