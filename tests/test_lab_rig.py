"""The user's sequence on bags recorded like a lab rig (epoch stamps, own clocks, no state).

See :mod:`tests._rig`: a known spring chain, six chamber sensors at 500 Hz on independent
jittered clocks, a 120 Hz motion-capture centerline with jitter, lost frames and 0.5 mm
noise. The bags go through ``convert``, ``fit`` (LOpInf, DMDc, ERA) and ``evaluate`` as a
user would run them; the LOpInf errors on the held-out bag are compared with an
unconstrained least-squares second-order fit on the same training episodes and the same
coordinates (with eighth-order differences and with the same Savitzky-Golay derivatives as
LOpInf), computed here in the same run, and with the identity-mass LOpInf (``--mass
identity``), which pays a bias in output coordinates (non-symmetric stiffness ``T M⁻¹ K T⁻¹``).
"""

from __future__ import annotations

import json
from pathlib import Path

from _rig import N_POINTS, record, Robot, T0_NS
import numpy as np
import pytest

from soft_rom.basis import POD, project
from soft_rom.cli import main
from soft_rom.dataset import TrainingSet
from soft_rom.ddt import DerivativeEstimator, FiniteDifference, SavitzkyGolay
from soft_rom.metrics import relative_deviation_error
from soft_rom.models import load_model, SecondOrderModel

DURATION = 10.0


def unconstrained_fit(train: list, test, y_ref: np.ndarray, r: int,
                      est: DerivativeEstimator) -> float:
    """Deviation error on ``test`` of ``q'' = -K q - C q' + B u`` fitted by plain least squares."""
    pod = POD(r=r).fit([e.Y for e in train], y_ref)
    V = pod.basis_
    dt = train[0].dt
    Qs, Qd, Qdd, (Us,) = est.episodes([project(e.Y, V, y_ref) for e in train], dt,
                                      [[e.U for e in train]])
    X, *_ = np.linalg.lstsq(np.vstack([Qs, Qd, Us]).T, Qdd.T, rcond=None)
    X = X.T
    model = SecondOrderModel(-X[:, :r], -X[:, r:2 * r], X[:, 2 * r:], V, dt=dt, y_ref=y_ref)
    with np.errstate(all='ignore'):
        Yh = model.simulate(test.U)
    err = relative_deviation_error(test.Y, Yh, y_ref)
    return err if np.isfinite(err) else float('inf')


@pytest.fixture(scope='module')
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp('lab')
    robot = Robot.make()
    recs = [record(robot, root / f'lab{i}', duration=DURATION, seed=i,
                   t0_ns=T0_NS + (i - 1) * 60_000_000_000) for i in (1, 2, 3)]
    return root, recs


def test_convert_real_clocks_to_a_uniform_grid(lab, monkeypatch):
    root, recs = lab
    monkeypatch.chdir(root)
    assert main(['convert', 'lab1', 'lab2', 'lab3', '-o', 'lab.zarr', '--quiet']) == 0
    ts = TrainingSet.open('lab.zarr')
    assert ts.episode_names == ['lab1', 'lab2', 'lab3'] and ts.n_states is None
    assert len(ts.input_names) == 6 and len(ts.output_names) == 2 * N_POINTS
    for name, rec in zip(ts.episode_names, recs):
        ep = ts[name]
        assert ep.t[0] == 0.0 and ep.is_uniform(rtol=1e-12)
        assert abs(ep.dt - 1 / 120) < 1e-6                 # the camera's period
        assert ts.t0_ns(name) == int(rec.cam_ns[0])        # first frame, exact integer ns
        rep = ts.metadata(name)['conversion_report']['topics']
        cam = rep['/soft_robot/centerline']
        assert cam['read'] == rec.cam_ns.size == cam['used'] and not cam['dropped']
        assert cam['splits'] == 0
        # each lost frame leaves a stretch of two periods: its grid points are interpolated
        # across it (counted apart from the ordinary interpolation between jittered frames)
        assert rec.lost <= cam['grid_gap_interpolated'] <= 3 * rec.lost
        for i in range(1, 7):
            chamber = rep[f'/soft_robot/pressure/chamber_{i}']
            assert not chamber['dropped'] and chamber['max_hold_s'] < 2.5e-3
    info = ts.describe()['episodes']['lab1']
    assert info['t0_ns'] == int(recs[0].cam_ns[0]) > T0_NS     # the epoch stamp, exact


@pytest.mark.slow
def test_user_sequence_lopinf_beats_unconstrained_fit(lab, monkeypatch, capsys):
    root, _ = lab
    monkeypatch.chdir(root)
    if not Path('lab.zarr').exists():
        assert main(['convert', 'lab1', 'lab2', 'lab3', '-o', 'lab.zarr', '--quiet']) == 0
    assert main(['fit', 'lab.zarr', '--method', 'lopinf,dmdc', '--r', '2:8:2', '--episodes',
                 'lab1,lab2', '-o', 'm', '--no-progress']) == 0
    err = capsys.readouterr().err
    assert 'lopinf uses the measured outputs' in err and 'savgol' in err
    assert 'learned mass' in err and 'refined by output error' in err
    assert main(['fit', 'lab.zarr', '--method', 'lopinf', '--r', '2:8:2', '--episodes',
                 'lab1,lab2', '-o', 'mid', '--mass', 'identity', '--refine', 'none',
                 '--no-progress']) == 0
    assert 'identity mass' in capsys.readouterr().err
    assert main(['fit', 'lab.zarr', '--method', 'era', '--r', '4:12:4', '--episodes', 'lab1',
                 '-o', 'm', '--no-progress']) == 0
    models = sorted(str(p) for p in Path('m').glob('*.npz'))
    assert len(models) == 11
    ident = sorted(str(p) for p in Path('mid').glob('*.npz'))
    got = {}
    for prefix, paths in (('', models), ('identity_', ident)):
        assert main(['evaluate', *paths, '--data', 'lab.zarr', '--episodes', 'lab3',
                     '--json', f'{prefix}eval.json']) == 0
        for row in json.loads(Path(f'{prefix}eval.json').read_text()):
            if row.get('episode') == 'lab3':
                got[prefix + Path(row['model'] if 'model' in row else row['path']).name] = row
    ts = TrainingSet.open('lab.zarr')
    train, test = [ts['lab1'], ts['lab2']], ts['lab3']
    lines = ['r   lopinf(identity, no refine)  lopinf(default)  unconstrained(fd8)  '
             'unconstrained(savgol)  dmdc']
    for r in (2, 4, 6, 8):
        lop = got[f'lab_lopinf_r{r}.npz']['relative_deviation_error']
        lop_id = got[f'identity_lab_lopinf_r{r}.npz']['relative_deviation_error']
        dmdc = got[f'lab_dmdc_r{r}.npz']['relative_deviation_error']
        base_fd8 = unconstrained_fit(train, test, ts.y_ref, r, FiniteDifference(8))
        base_sg = unconstrained_fit(train, test, ts.y_ref, r, SavitzkyGolay())
        lines.append(f'{r}   {lop_id:.4f}                       {lop:.4f}           '
                     f'{base_fd8:.4f}              {base_sg:.4f}                 {dmdc:.4f}')
        assert lop < 0.15                      # noise floor of the true model: ~0.05
        assert lop < base_fd8 / 3
        assert lop < base_sg                   # the acceptance: beats the unconstrained fit
        assert lop < lop_id
        model = load_model(f'm/lab_lopinf_r{r}.npz')
        assert model.metadata['coordinates'] == 'outputs'
        assert model.metadata['mass'] == 'learned'
        assert model.metadata['refine'] == 'output-error'
        ref = model.metadata['diagnostics']['refinement']
        assert ref['criterion'] == 'output-error' and ref['improvement'] > 0
        assert load_model(f'mid/lab_lopinf_r{r}.npz').metadata['mass'] == 'identity'
        assert model.stability_margin() > 0
        assert model.metadata['training']['t0_ns']['lab1'] == ts.t0_ns('lab1')
    for r in (4, 8, 12):
        lines.append(f'era r={r}: {got[f"lab_era_r{r}.npz"]["relative_deviation_error"]:.4f}')
        assert got[f'lab_era_r{r}.npz']['relative_deviation_error'] < 0.3
    # the refinement is said by info; asked for with cubic forces it is refused, nothing written
    capsys.readouterr()
    assert main(['info', 'm/lab_lopinf_r4.npz']) == 0
    shown = capsys.readouterr().out
    assert 'refined by output error' in shown
    held = load_model('m/lab_lopinf_r4.npz').metadata['held_out']    # the monitor's reference
    assert f"held-out deviation error {held['deviation_error']:.4g} (" in shown
    assert main(['fit', 'lab.zarr', '--method', 'lopinf', '--r', '2', '--episodes', 'lab1',
                 '-o', 'mc', '--forces', 'cubic', '--refine', 'output-error',
                 '--no-progress']) == 2
    assert "--refine must be 'none' or 'output-error'" in capsys.readouterr().err
    assert not list(Path('mc').glob('*.npz')) if Path('mc').exists() else True
    # a model on output coordinates replays a recording unchanged
    assert main(['replay', 'm/lab_lopinf_r4.npz', 'lab3', '-o', 'pred']) == 0
    with capsys.disabled():
        print('\n' + '\n'.join(lines))
