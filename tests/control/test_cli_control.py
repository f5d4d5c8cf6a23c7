"""``soft-rom control`` end to end on the FOM, and ``simulate --inputs`` reproducing its record."""

from __future__ import annotations

import json
import os
from pathlib import Path

from _eel_rom import modal_rom
import numpy as np
import pytest

from soft_rom.bags import EpisodeBagWriter
from soft_rom.cli import main
from soft_rom.models import SecondOrderModel


@pytest.fixture(scope='module')
def model_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp('model') / 'eel_modal_r6.npz'
    modal_rom(6).save(path)
    return path


@pytest.fixture(scope='module')
def reference(tmp_path_factory) -> Path:
    model = modal_rom(6)
    Y = np.repeat(model.y_ref[:, None], 3, axis=1)
    Y[20:, 1:] += 0.004 * np.linspace(0, 1, 20)[:, None] ** 2     # bend the tail 4 mm
    path = tmp_path_factory.mktemp('ref') / 'bend.npz'
    np.savez(path, t=np.array([0.0, 0.05, 1.0]), Y=Y)
    return path


@pytest.fixture(scope='module')
def run_dir(tmp_path_factory, model_file, reference) -> Path:
    out = tmp_path_factory.mktemp('control') / 'out'
    code = main(['control', str(model_file), '--reference', str(reference), '-o', str(out),
                 '--duration', '0.12', '--quiet'])
    assert code == 0
    return out


def test_control_writes_the_record_summary_and_figure(run_dir: Path) -> None:
    with np.load(run_dir / 'closed_loop.npz', allow_pickle=False) as z:
        t, U, Y, Yr, Ym = z['t'], z['U'], z['Y'], z['Y_ref'], z['Y_meas']
        assert U.shape == (6, t.size) and Y.shape == Yr.shape == (40, t.size)
        assert Ym.shape == (40, z['t_meas'].size) and 13 <= z['t_meas'].size <= 15  # 120 Hz
        assert np.all(U >= z['u_min'][:, None]) and np.all(U <= z['u_max'][:, None])
        assert z['solve_s'].size == 12
    summary = json.loads((run_dir / 'summary.json').read_text())
    assert summary['status_counts'] == {'ok': 12}
    assert summary['solve']['p99_ms'] > 0 and summary['qp_solver'] == 'daqp'
    assert 0 < summary['tracking_deviation_error'] < 1.5
    assert (run_dir / 'closed_loop.png').stat().st_size > 10_000


def test_simulate_inputs_reproduces_the_plant_outputs(run_dir: Path, tmp_path: Path) -> None:
    from soft_rom.convert.api import read_episode
    code = main(['simulate', '--inputs', str(run_dir / 'closed_loop.npz'), '-o',
                 str(tmp_path / 'bags'), '--no-state', '--quiet'])
    assert code == 0
    ep, _ = read_episode(tmp_path / 'bags' / 'closed_loop')
    with np.load(run_dir / 'closed_loop.npz', allow_pickle=False) as z:
        Y, U, t = z['Y'], z['U'], z['t']
    np.testing.assert_allclose(ep.t, t, atol=1e-12)
    np.testing.assert_array_equal(ep.U, U)
    assert ep.metadata['output_names'][:2] == ['x1', 'x2']
    rel = np.linalg.norm(ep.Y - Y) / np.linalg.norm(Y)
    assert rel <= 1e-9, rel


def test_control_refuses_bad_input_in_one_line(run_dir, model_file, reference, tmp_path,
                                               capsys) -> None:
    cases = [
        (['--reference', str(reference), '-o', str(run_dir)], 'exists already'),
        (['--reference', 'wave:speed=3', '-o', str(tmp_path / 'a')], 'unknown option'),
        (['--reference', 'nowhere.npz', '-o', str(tmp_path / 'b')], 'nowhere.npz'),
        (['--reference', 'step:u=1/2', '-o', str(tmp_path / 'c')], '6 finite pressures'),
        (['--reference', str(reference), '-o', str(tmp_path / 'd'), '--step', '0.0015'],
         'whole multiple'),
    ]
    bad = tmp_path / 'bad.npz'
    np.savez(bad, t=np.array([0.0, 1.0]), Y=np.zeros((39, 2)))
    cases.append((['--reference', str(bad), '-o', str(tmp_path / 'e')], '39 outputs'))
    for args, why in cases:
        code = main(['control', str(model_file), *args, '--quiet'])
        err = capsys.readouterr().err
        assert code == 2, (args, err)
        assert why in err and err.count('\n') == 1 and 'Traceback' not in err, err
        assert not (tmp_path / 'a').exists()


def test_what_a_hostile_input_audit_found_is_one_line(run_dir, model_file, reference,
                                                     tmp_path, capsys) -> None:
    """Each case of a hostile-input audit, now one line with exit 2.

    Before, each crashed (exit 1, 'a bug'), printed a meaningless figure with exit 0, warned
    over many lines first, or named the wrong cause.
    """
    model = modal_rom(6)
    t = np.array([0.0, 0.05, 1.0])
    files = {
        'rest.npz': dict(t=t, Y=np.repeat(model.y_ref[:, None], 3, axis=1)),   # 9.7e12 once
        'huge.npz': dict(t=t, Y=np.load(reference)['Y'] * 1e300),
        'complex.npz': dict(t=t, Y=np.load(reference)['Y'] + 0j),
    }
    for name, arrays in files.items():
        np.savez(tmp_path / name, **arrays)
    with open(reference, 'rb') as fh:
        (tmp_path / 'trunc.npz').write_bytes(fh.read()[:200])
    np.save(tmp_path / 'plain.npy', np.zeros(3))
    os.rename(tmp_path / 'plain.npy', tmp_path / 'plain.npz')
    (tmp_path / 'text.npz').write_text('my notes\n')
    np.savez(tmp_path / 'objects.npz', t=t, Y=np.array([{'a': 1}] * 3, dtype=object))
    kpa = SecondOrderModel(model.K, model.C, model.B * 1e3, model.E, dt=model.dt,
                           y_ref=model.y_ref, output_names=model.output_names,
                           input_units=['kPa'] * 6, output_units=['m'] * 40)
    kpa.save(tmp_path / 'kpa.npz')
    for name in ('ep1', 'ep2'):                       # a folder of two recordings
        with EpisodeBagWriter(tmp_path / 'bags' / name, storage='mcap', n_nodes=2) as w:
            for j in range(11):
                w.write(0.01 * j, np.zeros(6), np.zeros((20, 3)), np.zeros((2, 3)))
    short = ['--duration', '0.05']
    cases = [
        (['--reference', f'episode:{tmp_path / "bags"}'], 'a folder of 2 bags'),
        (['--reference', 'step:u=1000/0/0/0/0/0,at=99', *short], 'does not leave'),
        (['--reference', 'step:u=-2e4/0/0/0/0/0', *short], 'does not leave'),
        (['--reference', str(tmp_path / 'rest.npz')], 'does not leave'),
        (['--reference', str(tmp_path / 'huge.npz')], 'too large'),
        (['--reference', str(tmp_path / 'complex.npz')], 'complex128 data'),
        (['--reference', str(tmp_path / 'trunc.npz')], 'not an .npz file'),
        (['--reference', str(tmp_path / 'plain.npz')], 'not an .npz file'),
        (['--reference', str(tmp_path / 'text.npz')], 'not an .npz file'),
        (['--reference', str(tmp_path / 'objects.npz')], 'never loads'),
        (['--reference', 'wave:f=2,f=3'], 'f= given twice'),
        (['--reference', 'wave:f=2', '--seed', '-1'], '--seed'),
        (['--reference', 'step:u=1e12/0/0/0/0/0'], 'at most'),
        (['--reference', 'wave:f=200'], 'at or above the Nyquist rate (50 Hz)'),
        (['--reference', 'wave:f=2', '--step', '0.5', '--horizon', '1'], 'Nyquist rate (1 Hz)'),
    ]
    for i, (args, why) in enumerate(cases):
        code = main(['control', str(model_file), *args, '-o', str(tmp_path / f'o{i}'),
                     '--quiet'])
        err = capsys.readouterr().err
        assert code == 2, (args, err)
        assert why in err and err.count('\n') == 1 and 'Traceback' not in err, (args, err)
        assert not (tmp_path / f'o{i}').exists()
    assert main(['control', str(tmp_path / 'kpa.npz'), '--reference', str(reference), '-o',
                 str(tmp_path / 'k'), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'inputs are in kPa; the embedded eel plant works in Pa' in err, err
    # negative values as written: no '=' needed
    assert main(['control', str(model_file), '--reference', str(reference), '-o',
                 str(tmp_path / 'neg'), '--u-min', '-2e4', '--u-max', '2e4', '--duration',
                 '0.02', '--quiet']) == 0
    with np.load(tmp_path / 'neg' / 'closed_loop.npz') as z:
        assert z['U'].min() >= -2e4 and z['U'].max() <= 2e4


def test_a_run_where_no_control_step_succeeded_is_an_error(tmp_path, capsys) -> None:
    """A model the QP cannot use (a hand-edited unstable one): exit 1, the record kept."""
    m = modal_rom(6)
    bad = SecondOrderModel(-1e3 * m.K, m.C, m.B, m.E, dt=m.dt, y_ref=m.y_ref,
                           output_names=m.output_names, input_units=['Pa'] * 6,
                           output_units=['m'] * 40)
    bad.save(tmp_path / 'unstable.npz')
    code = main(['control', str(tmp_path / 'unstable.npz'), '--reference',
                 'wave:f=2,amplitude=0.003', '--u-min', '-5e4', '--u-max', '5e4', '--duration',
                 '0.05', '-o', str(tmp_path / 'out'), '--quiet'])
    err = capsys.readouterr().err
    # the last line (an old matplotlib may log its style's deprecations while drawing the
    # record's figure, before it)
    last = err.strip().splitlines()[-1]
    assert code == 1 and 'Traceback' not in err, err
    assert last.startswith('soft-rom control: error: no control step succeeded ('), err
    # the model is not trusted: said once, on one line, before the run
    assert err.count('not trusted') == 1 and err.startswith(
        f'soft-rom control: warning: {bad.method} r=6 model is not trusted: unstable'), err
    with open(tmp_path / 'out' / 'summary.json') as fh:
        summary = json.load(fh)
    counts = summary['status_counts']
    assert summary['model_trust'] == bad.trust_issues() != []
    assert sum(counts.values()) == 5 and 'ok' not in counts, counts
    assert set(counts) <= {'failed', 'infeasible'}, counts


def test_a_static_target_out_of_reach_is_said_once_before_the_run(model_file, reference,
                                                                   tmp_path, capsys) -> None:
    """The run goes on (exit 0); the warning is one line, not repeated after the run."""
    m = modal_rom(6)
    gain = m.discretize(0.01)
    G = gain.C @ np.linalg.solve(np.eye(gain.A.shape[0]) - gain.A, gain.B) + gain.D
    Y = np.repeat(m.y_ref[:, None], 3, axis=1)
    Y[:, 1:] += (G @ (200e3 * np.array([1.0, -1.0] * 3)))[:, None]   # 4 x the +-50 kPa
    np.savez(tmp_path / 'far.npz', t=np.array([0.0, 0.05, 1.0]), Y=Y)
    short = ['--duration', '0.02', '--quiet']
    assert main(['control', str(model_file), '--reference', str(reference), '-o',
                 str(tmp_path / 'near'), *short]) == 0
    err = capsys.readouterr().err
    assert 'warning' not in err.lower(), err          # the 4 mm bend is within reach
    assert main(['control', str(model_file), '--reference', str(tmp_path / 'far.npz'), '-o',
                 str(tmp_path / 'far'), *short]) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if 'out of reach' in line]
    assert len(lines) == 1 and lines[0].startswith(
        "soft-rom control: warning: the reference 'far.npz' is out of reach within the input "
        'bounds'), err
    with open(tmp_path / 'far' / 'summary.json') as fh:
        assert json.load(fh)['warnings'] == [lines[0].split('warning: ', 1)[1]]


def test_simulate_inputs_refuses_what_is_not_pressures_over_time(tmp_path, capsys) -> None:
    t = np.arange(5) * 1e-3
    np.savez(tmp_path / 'huge.npz', t=t, U=np.full((6, 5), 1e303))
    np.savez(tmp_path / 'tiny_dt.npz', t=np.arange(5) * 1e-12, U=np.zeros((6, 5)))
    np.savez(tmp_path / 'bools.npz', t=t, U=np.zeros((6, 5), dtype=bool))
    (tmp_path / 'folder').mkdir()
    cases = [(tmp_path / 'huge.npz', 'at most 1e+07 Pa'), (tmp_path / 'tiny_dt.npz', 'step of t'),
             (tmp_path / 'bools.npz', 'bool data'), (tmp_path / 'folder', 'is a folder')]
    for path, why in cases:
        code = main(['simulate', '--inputs', str(path), '-o', str(tmp_path / 'out'),
                     '--quiet'])
        err = capsys.readouterr().err
        assert code == 2 and why in err and err.count('\n') == 1, (path, err)
    assert main(['simulate', '--episodes', '1', '--steps', '3', '--dt', '1e-9', '-o',
                 str(tmp_path / 'out'), '--quiet']) == 2
    assert '--dt' in capsys.readouterr().err
    assert not (tmp_path / 'out').exists()


def test_the_rate_weight_default_is_the_library_default() -> None:
    """`soft-rom control` and the controller node (which reads MPCConfig) use one weight."""
    import argparse

    from soft_rom.cli.control import add_parser
    from soft_rom.control import MPCConfig
    parser = add_parser(argparse.ArgumentParser().add_subparsers())
    assert parser.get_default('rate_weight') == MPCConfig().rate_weight == 1e-4
