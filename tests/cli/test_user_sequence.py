"""A new user's first session, from the README only: simulate, convert, fit, evaluate.

The sequence of issue 23, on ``soft-rom simulate --episodes 4 --seed 11`` data:

* ``fit`` on a bag says to convert it, ``--r 8:4`` says the range is empty;
* ``convert`` takes the folder ``simulate`` wrote; a sidecar caught by a glob is refused
  with the advice to give that folder;
* ERA/OKID with ``--r 10,20,30`` and with ``--r 4:12:4`` (the README's shape) exits 0, every
  model at one time step;
* ``--forces cubic`` with its defaults (train ep1, ep2) predicts ep3 and ep4 with a deviation
  error at most 1.25 x that of the linear LOpInf at the same r;
* ``--dmdc-variant stable`` is named apart (``..._dmdc-stable_r8.npz``), with a training error
  at most 2 x the paper variant's;
* no message names a Python keyword (``name=value``): options are CLI flags.
"""

from __future__ import annotations

import json
import re

import pytest

from soft_rom.cli import main

pytest.importorskip('zarr')

#: A Python keyword argument as a message would write it: ``decimation=1``, ``n_markov=500``.
KEYWORD = re.compile(r'\b(?!r=|dt=)[a-z][a-z0-9_]*=(?!=)\S')


@pytest.fixture(scope='module')
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp('user')
    assert main(['simulate', '--episodes', '4', '--seed', '11', '-o', str(root / 'sim'),
                 '--jobs', '2', '--quiet']) == 0
    return root


def _run(capsys, argv):
    code = main(argv)
    out = capsys.readouterr()
    text = out.out + out.err
    assert not KEYWORD.search(text), text
    return code, text


@pytest.mark.slow
def test_a_new_users_sequence(session, capsys):
    root = session
    sim, data = root / 'sim', root / 'eel.zarr'
    code, text = _run(capsys, ['fit', str(sim / 'ep1'), '-o', str(root / 'm0')])
    assert code == 2 and 'soft-rom convert' in text and 'not a training set' in text
    code, text = _run(capsys, ['convert', str(sim / 'ep1'), str(sim / 'ep1.json'),
                               '-o', str(data), '--quiet'])     # what `sim/ep1*` expands to
    assert code == 2 and 'give that folder' in text and not data.exists(), text
    code, text = _run(capsys, ['convert', str(sim), '-o', str(data), '--quiet'])
    assert code == 0, text
    code, text = _run(capsys, ['fit', str(data), '--r', '8:4', '-o', str(root / 'm0')])
    assert code == 2 and 'range 8:4 is empty: start must be below stop' in text

    for name, rs in (('era1', '10,20,30'), ('era2', '4:12:4')):
        code, text = _run(capsys, ['fit', str(data), '--method', 'era', '--episodes', 'ep1',
                                   '--r', rs, '-o', str(root / name),
                                   '--json', str(root / f'{name}.json'), '--quiet'])
        assert code == 0, text
        rows = json.loads((root / f'{name}.json').read_text())
        assert {row['dt'] for row in rows} == {0.001}, rows

    fits = {}
    for name, extra in (('linear', []), ('cubic', ['--forces', 'cubic'])):
        code, text = _run(capsys, ['fit', str(data), '--method', 'lopinf', '--r', '4',
                                   '--episodes', 'ep1,ep2', *extra, '-o', str(root / name),
                                   '--json', str(root / f'{name}.json'), '--quiet'])
        assert code == 0, text
        fits[name] = json.loads((root / f'{name}.json').read_text())[0]['path']
    errors = {}
    for name, path in fits.items():
        code, text = _run(capsys, ['evaluate', path, '--data', str(data), '--episodes',
                                   'ep3,ep4', '--json', str(root / f'ev_{name}.json'),
                                   '--quiet'])
        assert code == 0, text
        rows = json.loads((root / f'ev_{name}.json').read_text())
        errors[name] = {r['episode']: r['relative_deviation_error'] for r in rows
                        if r['segment'] == 'all'}
    for ep in ('ep3', 'ep4'):
        assert errors['cubic'][ep] <= 1.25 * errors['linear'][ep], errors

    code, text = _run(capsys, ['fit', str(data), '--method', 'dmdc', '--dmdc-variant',
                               'stable', '--episodes', 'ep1,ep2', '--r', '8', '-o',
                               str(root / 'dmdc'), '--json', str(root / 'dmdc.json'),
                               '--quiet'])
    assert code == 0, text
    row, = json.loads((root / 'dmdc.json').read_text())
    assert row['path'].endswith('eel_dmdc-stable_r8.npz') and 'DMDc stable r=8' in text
    assert row['train_relative_deviation_error'] <= 2 * row[
        'paper_variant_train_relative_deviation_error'], row
