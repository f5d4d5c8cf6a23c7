"""``soft-rom control`` end to end on the FOM, and ``simulate --inputs`` reproducing its record."""

from __future__ import annotations

import json
from pathlib import Path

from _eel_rom import modal_rom
import numpy as np
import pytest

from soft_rom.cli import main


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


def test_the_rate_weight_default_is_the_library_default() -> None:
    """`soft-rom control` and the controller node (which reads MPCConfig) use one weight."""
    import argparse

    from soft_rom.cli.control import add_parser
    from soft_rom.control import MPCConfig
    parser = add_parser(argparse.ArgumentParser().add_subparsers())
    assert parser.get_default('rate_weight') == MPCConfig().rate_weight == 1e-4
