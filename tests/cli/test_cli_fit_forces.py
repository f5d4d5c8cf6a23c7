"""`soft-rom fit --forces cubic|auto` on simulated eel episodes: one held-out selection.

The CLI (both flags) and the learning-curve study run the pipeline's one
``HeldOutCubicSelection``: the same candidates, errors and verdict on the same episodes.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from soft_rom.cli import main
from soft_rom.data import Episode
from soft_rom.models import load_model

pytest.importorskip('zarr')
from soft_rom.dataset import TrainingSet  # noqa: E402
from soft_rom.sim import EelModel  # noqa: E402
from soft_rom.sim.inputs import random_pressures  # noqa: E402
from soft_rom.study.curve import CurveConfig, CurveData, learning_curve  # noqa: E402

N_STEPS = 250


def _eel_episodes(amplitude: float, seed: int, n: int) -> list[Episode]:
    """``n`` episodes of the embedded eel FOM (resolution 1, 0.25 s) with their states."""
    model = EelModel()
    P = [random_pressures(N_STEPS, 1e-3, seed=seed, episode=i, amplitude=amplitude,
                          hold=(0.03, 0.1)) for i in range(1, n + 1)]
    states = [np.empty((model.n_nodes * 3, N_STEPS)) for _ in P]

    def keep(i: int):
        def cb(j: int, t: float, u: np.ndarray, centerline: np.ndarray,
               positions: np.ndarray) -> None:
            states[i][:, j] = positions.reshape(-1)
        return cb

    res = model.simulate_lockstep(P, N_STEPS, 1e-3, callbacks=[keep(i) for i in range(n)])
    return [Episode(t=r.t, U=r.pressures, Y=r.outputs(), Q=Q, name=f'ep{i + 1}')
            for i, (r, Q) in enumerate(zip(res, states))]


@pytest.fixture(scope='module')
def eel_sets(tmp_path_factory):
    """Training sets at 50 kPa (strongly nonlinear) and 0.5 kPa (linear to 1e-3)."""
    out = {}
    for tag, amplitude in (('a50', 50e3), ('a05', 0.5e3)):
        eps = _eel_episodes(amplitude, seed=7, n=3)
        path = tmp_path_factory.mktemp(tag) / 'eel.zarr'
        TrainingSet.from_episodes(path, eps, input_units=['Pa'] * 6, output_units=['m'] * 40,
                                  q_ref=eps[0].Q[:, 0], y_ref=eps[0].Y[:, 0])
        out[tag] = (path, eps)
    return out


def _fit(path, out, forces: str, capsys, *extra: str) -> tuple[list[dict], str]:
    rc = main(['fit', str(path), '--r', '4', '--forces', forces, '-o', str(out),
               '--json', str(out.parent / f'{out.name}.json'), '--no-progress', *extra])
    assert rc == 0
    text = capsys.readouterr().out
    return json.loads((out.parent / f'{out.name}.json').read_text()), text


def test_auto_reports_the_held_out_comparison_the_study_makes(eel_sets, tmp_path, capsys):
    path, eps = eel_sets['a50']
    rows, text = _fit(path, tmp_path / 'auto50', 'auto', capsys)
    (row,) = rows
    sel = row['forces_selection']
    kept = sel['kept']
    assert sel['asked'] == 'auto' and kept in ('linear', 'cubic')
    assert row['path'].endswith('_cubic_r4.npz' if kept == 'cubic' else 'eel_lopinf_r4.npz')
    assert sel['episodes'] == 3 and sorted(sum(sel['folds'], [])) == [0, 1, 2]
    assert math.isfinite(sel['linear_error']) and math.isfinite(sel['choice']['error'])
    assert sel['ratio'] == pytest.approx(sel['choice']['error'] / sel['linear_error'])
    # The console says both errors and what was kept.
    assert f'linear {sel["linear_error"]:.3g}' in text
    assert f'cubic {sel["choice"]["error"]:.3g}' in text
    assert f'--forces auto keeps {kept}' in text
    # The model file is the model kept, the verdict recorded in it.
    name = 'eel_lopinf_cubic_r4.npz' if kept == 'cubic' else 'eel_lopinf_r4.npz'
    model = load_model(tmp_path / 'auto50' / name)
    assert model.metadata['forces_selection']['choice'] == sel['choice']
    # The learning-curve study makes the same choice on the same training episodes.
    cfg = CurveConfig(sizes=(3,), n_test=1, amplitudes=(50e3,),
                      methods=('lopinf', 'lopinf_cubic'), r_lopinf=(4,))
    ts = TrainingSet.open(path)
    train = [ts[e.name] for e in eps]
    test = [Episode(t=e.t, U=e.U, Y=e.Y, name='test') for e in eps[:1]]
    curve = learning_curve(CurveData(train=train, test=test, q_ref=np.asarray(ts.q_ref),
                                     y_ref=np.asarray(ts.y_ref)), cfg)
    point = curve['points'][0]['lopinf_cubic']
    # Same folds, candidates and rule; the errors agree to the cubic solver's tolerance (the
    # study projects on a 40-mode basis, the CLI on 4 modes: round-off apart).
    assert point['choice']['reg'] == sel['choice']['reg']
    assert point['choice']['eps4'] == sel['choice']['eps4']
    assert point['choice']['error'] == pytest.approx(sel['choice']['error'], rel=1e-3)
    assert point['held_out_linear'] == pytest.approx(sel['linear_error'], rel=1e-3)
    assert point['forces_auto'] == kept

    # auto keeps what the rule says: cubic only from 4 folds on and when at least 10 % better
    # held out; 3 episodes make 3 folds, so linear, and the console says why.
    assert len(sel['folds']) == 3 and sel['min_folds'] == 4 and kept == 'linear'
    assert 'on 3 folds only; a cubic model is kept from 4 folds on' in text

    # --forces cubic: the same selection (same verdict), the best cubic candidate fitted.
    rows, text = _fit(path, tmp_path / 'cubic50', 'cubic', capsys)
    (row,) = rows
    cub = row['forces_selection']
    assert row['path'].endswith('eel_lopinf_cubic_r4.npz') and 'cubic' in row['model']
    assert cub['asked'] == 'cubic' and cub['kept'] == 'cubic'
    assert {k: v for k, v in cub.items() if k not in ('asked', 'kept')} == \
        {k: v for k, v in sel.items() if k not in ('asked', 'kept')}
    model = load_model(tmp_path / 'cubic50' / 'eel_lopinf_cubic_r4.npz')
    info = model.metadata['diagnostics']['solver_info']
    assert (info['reg'], info['eps4']) == (cub['choice']['reg'], cub['choice']['eps4'])
    said = ('the linear model held out better' if cub['ratio'] > 1 else
            'cubic as asked; --forces auto would keep linear')
    assert said in text


def test_auto_keeps_the_linear_model_on_a_nearly_linear_eel(eel_sets, tmp_path, capsys):
    path, _ = eel_sets['a05']
    rows, text = _fit(path, tmp_path / 'auto', 'auto', capsys)
    (row,) = rows
    sel = row['forces_selection']
    assert row['method'] == 'lopinf' and sel['kept'] == 'linear'
    # Not for lack of a cubic model: it fitted and scored, and was not clearly better.
    assert sel['choice'] is not None and math.isfinite(sel['choice']['error'])
    assert sel['ratio'] > 0.9
    assert '--forces auto keeps linear: the cubic held-out error is' in text
    assert [p.name for p in (tmp_path / 'auto').glob('*.npz')] == ['eel_lopinf_r4.npz']
    assert 'forces_selection' in load_model(tmp_path / 'auto' / 'eel_lopinf_r4.npz').metadata


def test_auto_on_one_episode_and_streamed(eel_sets, tmp_path, capsys):
    path, _ = eel_sets['a05']
    # One episode: its tail is held out (one fold), so auto keeps linear and says why.
    rows, text = _fit(path, tmp_path / 'one', 'auto', capsys, '--episodes', 'ep1')
    (row,) = rows
    sel = row['forces_selection']
    assert sel['scheme'] == 'tails' and sel['kept'] == 'linear' and row['method'] == 'lopinf'
    assert 'the last 20% of 1 training episode' in text and 'on 1 fold only' in text
    # Streamed (the exact Gram POD at this size): the same verdict as in memory.
    rows, _ = _fit(path, tmp_path / 'mem', 'auto', capsys)
    streamed, _ = _fit(path, tmp_path / 'str', 'auto', capsys, '--streaming')
    a, b = rows[0]['forces_selection'], streamed[0]['forces_selection']
    assert a['kept'] == b['kept'] == 'linear' and a['choice']['reg'] == b['choice']['reg']
    assert b['linear_error'] == pytest.approx(a['linear_error'], rel=1e-6)
