"""Trust checks of every model the study (or the demo) fits: a false alarm is a failure.

Run: ``.venv/bin/python benchmarks/check_study_trust.py --bags BAGS [--demo] [-o OUT]``

Runs ``soft-rom study`` (or ``soft-rom demo``) on the episode bags in ``BAGS`` (written by an
earlier run, e.g. ``soft-rom demo -o D`` leaves them in ``D/bags``; simulated there if
missing) with every fit of the sweep intercepted: for each model it prints the method, ``r``,
the steady-state gain ratio (largest output move for inputs held within the training range,
over the largest training deviation; the trust check flags above
:data:`soft_rom.gain.GAIN_FACTOR`) and the trust issues. Exits 1 if the gain check flags any
model the study fits (a false alarm); the other trust issues are listed.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import tempfile
from typing import Any

import numpy as np


def gain_ratio(model: Any) -> float:
    """Largest steady-state output move over the training input box / training deviation."""
    from soft_rom.gain import peak_response
    env = model.metadata.get('envelope') or {}
    if not env.get('u_min') or not env.get('y_dev_max'):
        return float('nan')
    peak = peak_response(model, np.asarray(env['u_min'], dtype=float),
                         np.asarray(env['u_max'], dtype=float), env.get('samples'))
    return float(np.max(peak)) / float(env['y_dev_max'])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--bags', required=True, help='episode bags (reused, or written there)')
    ap.add_argument('--demo', action='store_true', help='the demo instead of the full study')
    ap.add_argument('-o', '--output', default=None, help='report folder (default: temporary)')
    args = ap.parse_args(argv)

    from soft_rom.cli import main as cli
    import soft_rom.study.studies as run

    original = run.sweep
    rows: list[tuple[str, int, float, list[str]]] = []

    def sweep(method: str, rs: Any, episodes: Any, ts: Any, **kw: Any) -> Any:
        models = original(method, rs, episodes, ts, **kw)
        for r, model in models.items():
            rows.append((method, int(r), gain_ratio(model), model.trust_issues()))
        return models

    run.sweep = sweep
    with tempfile.TemporaryDirectory() as tmp:
        out = args.output or os.path.join(tmp, 'report')
        verb = 'demo' if args.demo else 'study'
        code = cli([verb, '--bags', args.bags, '-o', out, '--quiet'])
    print(f'{verb} exit code {code}; {len(rows)} models fitted')
    print(f'{"method":<13} {"r":>3} {"gain ratio":>11}  trust')
    worst: dict[str, float] = {}
    for method, r, ratio, issues in rows:
        worst[method] = max(worst.get(method, 0.0), ratio if np.isfinite(ratio) else 0.0)
        print(f'{method:<13} {r:>3d} {ratio:>11.3g}  ' + ('ok' if not issues
                                                          else '; '.join(issues)))
    from soft_rom.gain import GAIN_FACTOR
    print('largest gain ratio per method (flagged above '
          f'{GAIN_FACTOR:g}): ' + ', '.join(f'{m} {v:.3g}' for m, v in worst.items()))
    flagged = [row for row in rows if row[3]]
    gain = [row for row in rows if any(i.startswith('absurd gain') for i in row[3])]
    print(f'not trusted: {len(flagged)} of {len(rows)}; for an absurd gain: {len(gain)}')
    return 1 if gain or code != 0 else 0


if __name__ == '__main__':
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.exit(main())
