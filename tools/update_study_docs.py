"""Regenerate the study results the docs show, from one ``soft-rom study`` run.

Writes, from the study's ``summary.json`` and figures:

* the README's results block (between its ``study-results`` markers: the results table,
  the conclusions, the study's timings with the machine and load, two figures);
* ``docs/study_summary.json`` (the summary; ``tests/test_readme.py`` checks the README
  and the report against it);
* ``docs/study_report.md`` (the study's report) and its figures in
  ``docs/figures/study/``.

Run from the repository root::

    python tools/update_study_docs.py              # runs `soft-rom study` first (< 1 min idle)
    python tools/update_study_docs.py STUDY_DIR    # a folder `soft-rom study -o` wrote

Nothing is written unless the study is complete (both studies, every figure).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import re
import shutil
import sys
import tempfile

ROOT = Path(__file__).resolve().parents[1]


def update(study: Path) -> None:
    """Copy ``study``'s results into the README and ``docs/``."""
    from soft_rom.study.readme import FIGURES, replace_block, results_block
    from soft_rom.study.report import study_report

    summary = json.loads((study / 'summary.json').read_text(encoding='utf-8'))
    if 'study1' not in summary or 'study2' not in summary:
        raise SystemExit(f'{study}: not a complete study (both studies are needed)')
    report = study_report(summary, figures='figures/study/')
    names = re.findall(r'\]\(figures/study/([^)]+)\)', report)
    missing = [n for n in names if not (study / n).is_file()]
    if missing:
        raise SystemExit(f'{study}: figures missing: {", ".join(missing)}')
    figures = ROOT / FIGURES
    shutil.rmtree(figures, ignore_errors=True)
    figures.mkdir(parents=True)
    for name in names:
        shutil.copyfile(study / name, figures / name)
    (ROOT / 'docs' / 'study_summary.json').write_text(
        json.dumps(summary, indent=2, allow_nan=False) + '\n', encoding='utf-8')
    (ROOT / 'docs' / 'study_report.md').write_text(report, encoding='utf-8')
    readme = ROOT / 'README.md'
    readme.write_text(replace_block(readme.read_text(encoding='utf-8'),
                                    results_block(summary)), encoding='utf-8')
    print(f'updated README.md, docs/study_summary.json, docs/study_report.md and '
          f'{FIGURES} ({len(names)} figures) from {study}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('study', nargs='?', type=Path,
                        help='folder written by soft-rom study (default: run it now)')
    args = parser.parse_args()
    if args.study is not None:
        update(args.study)
        return 0
    with tempfile.TemporaryDirectory(prefix='soft_rom_study_') as tmp:
        out = Path(tmp) / 'study'
        from soft_rom.cli import main as soft_rom
        code = soft_rom(['study', '-o', str(out)])
        if code:
            return code
        update(out)
    return 0


if __name__ == '__main__':
    sys.exit(main())
