"""`soft-rom fit` and `soft-rom evaluate` end to end on a small synthetic training set."""

from __future__ import annotations

import json

from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.cli import main
from soft_rom.data import Episode
from soft_rom.models import load_model

pytest.importorskip('zarr')
from soft_rom.dataset import TrainingSet  # noqa: E402


def _fom_episodes() -> list[Episode]:
    """A damped spring chain (second-order linear FOM) with full states, two episodes."""
    return spring_chain_episodes(n_dof=12, m=2, p=4, k=500, dt=2e-3, seed=0, stiffness=400.0,
                                 drive_nodes=(4, 8), input_gain=1e-3, amplitude=30e3, hold=25,
                                 q_span=1.0)


@pytest.fixture(scope='module')
def training_set(tmp_path_factory):
    path = tmp_path_factory.mktemp('data') / 'chain.zarr'
    eps = _fom_episodes()
    return TrainingSet.from_episodes(path, eps, input_units=['Pa', 'Pa'],
                                     output_units=['m'] * 4,
                                     q_ref=eps[0].Q[:, 0], y_ref=eps[0].Y[:, 0]).path


def test_fit_all_methods_then_evaluate(training_set, tmp_path, capsys):
    out = tmp_path / 'models'
    rc = main(['fit', str(training_set), '--method', 'lopinf,dmdc,era', '--r', '4,6',
               '--episodes', 'ep1', '--t-max', '0.6', '--decimation', '1', '--n-markov', '60',
               '-o', str(out), '--json', str(tmp_path / 'fit.json'), '--no-progress'])
    assert rc == 0
    table = capsys.readouterr().out
    assert 'chain_lopinf_r4.npz' in table and 'chain_era_r6.npz' in table
    names = sorted(p.name for p in out.glob('*.npz'))
    assert names == sorted(f'chain_{m}_r{r}.npz' for m in ('lopinf', 'dmdc', 'era')
                           for r in (4, 6))
    rows = json.loads((tmp_path / 'fit.json').read_text())
    assert len(rows) == 6
    for row in rows:
        assert np.isfinite(row['train_relative_deviation_error'])
        if row['method'] != 'era':
            # A linear chain whose motion lives in a few POD modes: good fits. (ERA/OKID is
            # not asked to be good here: 0.6 s of data against a 1.3 s slowest period.)
            assert row['train_relative_deviation_error'] < 0.2, row
    model = load_model(out / 'chain_dmdc_r6.npz')
    assert model.method == 'dmdc' and model.r == 6
    assert model.input_units == ['Pa', 'Pa']
    assert model.metadata['training']['episodes'] == ['ep1']
    assert model.metadata['training']['t_max'] == 0.6
    for name in names:         # each method records how fast its training outputs moved
        band = load_model(out / name).metadata['envelope']['y_band_hz']
        assert 0 < band < 0.5 / model.dt, (name, band)

    models = [str(p) for p in sorted(out.glob('*_r6.npz'))]
    rc = main(['evaluate', *models, '--data', str(training_set), '--t-split', '0.6',
               '--json', str(tmp_path / 'ev.json'), '--plots', str(tmp_path / 'plots')])
    assert rc == 0
    rows = json.loads((tmp_path / 'ev.json').read_text())
    # 3 models x (2 episodes + pooled) x (all, train, test)
    assert len(rows) == 3 * 3 * 3
    by = {(r['model'], r['episode'], r['segment']): r for r in rows}
    row = by[('chain_dmdc_r6.npz', 'ep1', 'train')]
    assert row['n_samples'] == 300
    assert by[('chain_dmdc_r6.npz', 'ep1', 'test')]['n_samples'] == 200
    assert len(list((tmp_path / 'plots').glob('*.png'))) == 3 * 2


def test_fit_energy_default_and_prefix(training_set, tmp_path):
    out = tmp_path / 'm'
    rc = main(['fit', str(training_set), '--method', 'dmdc', '--energy', '0.99',
               '--prefix', 'eel', '-o', str(out), '--no-progress'])
    assert rc == 0
    (path,) = list(out.glob('eel_dmdc_r*.npz'))
    model = load_model(path)
    assert model.metadata['energy_captured'] >= 0.99


@pytest.mark.parametrize('argv, message', [
    (['fit', '{missing}', '--method', 'dmdc', '-o', '{out}'], 'does not exist'),
    (['fit', '{ts}', '--method', 'dmdc', '--episodes', 'ep9', '-o', '{out}'], 'ep9'),
    (['fit', '{ts}', '--method', 'era', '--era-episode', 'ep2', '--episodes', 'ep1',
      '-o', '{out}'], 'ep2'),
    (['evaluate', '{model}', '--data', '{ts}', '--episodes', 'nope'], 'nope'),
    (['evaluate', '{other}', '--data', '{ts}'], 'inputs'),
    (['evaluate', '{missing}.npz', '--data', '{ts}'], 'not found'),
])
def test_bad_input_gives_clear_errors(training_set, tmp_path, capsys, argv, message):
    from soft_rom.models import DiscreteModel
    model = DiscreteModel(np.eye(2) * 0.5, np.ones((2, 2)), np.ones((4, 2)), dt=2e-3,
                          method='dmdc').save(tmp_path / 'good.npz')
    other = DiscreteModel(np.eye(2) * 0.5, np.ones((2, 3)), np.ones((4, 2)), dt=2e-3,
                          method='dmdc').save(tmp_path / 'other.npz')
    subs = {'missing': str(tmp_path / 'missing'), 'out': str(tmp_path / 'o'),
            'ts': str(training_set), 'model': str(model), 'other': str(other)}
    rc = main([a.format(**subs) for a in argv])
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err


@pytest.mark.parametrize('backend', ['streaming', 'dask'])
def test_fit_streaming_and_dask_equal_in_memory(training_set, tmp_path, backend):
    """``--streaming`` / ``--dask ADDRESS`` give the in-memory models (streamed POD)."""
    args = ['fit', str(training_set), '--method', 'lopinf,dmdc', '--r', '4',
            '--episodes', 'ep1,ep2', '--no-progress']
    assert main(args + ['-o', str(tmp_path / 'mem')]) == 0
    extra = ['--streaming']
    cluster = client = None
    if backend == 'dask':
        distributed = pytest.importorskip('distributed')
        cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                           dashboard_address=None)
        client = distributed.Client(cluster)
        extra = ['--dask', cluster.scheduler_address]
    try:
        assert main(args + extra + ['-o', str(tmp_path / 'str')]) == 0
    finally:
        if client is not None:
            client.close()
            cluster.close()
    for name in ('chain_lopinf_r4.npz', 'chain_dmdc_r4.npz'):
        a = load_model(tmp_path / 'mem' / name)
        b = load_model(tmp_path / 'str' / name)
        U = np.random.default_rng(0).normal(size=(a.n_inputs, 300))
        Ya, Yb = a.simulate(U), b.simulate(U)
        dev = np.linalg.norm(Ya - a.y_ref[:, None])
        assert np.linalg.norm(Ya - Yb) <= 1e-6 * dev, name


@pytest.mark.parametrize('argv, words', [
    (['--n-markov', '100000'], '--n-markov 100000 exceeds'),
    (['--n-markov', '5000'], '--n-markov 5000 exceeds'),
    (['--n-markov', '500'], 'at most 499'),          # 500 samples per episode
    (['--n-markov', '100', '--decimation', '5'], 'at most 99'),
    (['--observer-order', '100000'], '--observer-order 100000 is too large'),
    (['--observer-order', '100000', '--era-preset', 'eel', '--n-markov', '100'],
     '--observer-order 100000'),
])
def test_era_options_beyond_the_episode_exit_2_before_any_work(training_set, tmp_path,
                                                                capsys, argv, words):
    capsys.readouterr()
    rc = main(['fit', str(training_set), '--method', 'era', '--r', '3', '--era-episode', 'ep1',
               *argv, '-o', str(tmp_path / 'o'), '--quiet'])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and 'Traceback' not in err and 'Warning' not in err, err
    assert lines[0].startswith('soft-rom fit: error: ') and words in lines[0], err
    assert not (tmp_path / 'o').exists()


def test_fit_records_the_held_out_error_the_monitor_uses(training_set, tmp_path):
    """Each episode left out in turn, predicted by the same fit on the other: pooled error."""
    from soft_rom.evaluation import predict
    from soft_rom.predictor.thresholds import held_out_error
    out = tmp_path / 'both'
    assert main(['fit', str(training_set), '--method', 'lopinf,era', '--r', '4',
                 '--decimation', '1', '--n-markov', '60', '-o', str(out), '--quiet']) == 0
    model = load_model(out / 'chain_lopinf_r4.npz')
    held = model.metadata['held_out']
    assert 'ep1' in held['data'] and 'ep2' in held['data'] and held['samples'] == 1000
    ts = TrainingSet.open(training_set)
    se = sd = 0.0
    for train, test in (('ep2', 'ep1'), ('ep1', 'ep2')):
        assert main(['fit', str(training_set), '--method', 'lopinf', '--r', '4', '--episodes',
                     train, '-o', str(tmp_path / train), '--quiet']) == 0
        part = load_model(tmp_path / train / 'chain_lopinf_r4.npz')
        ep = ts[test]
        se += float(np.sum((ep.Y - predict(part, ep)) ** 2))
        sd += float(np.sum((ep.Y - ts.y_ref[:, None]) ** 2))
    assert held['deviation_error'] == pytest.approx(np.sqrt(se / sd), rel=1e-9)
    assert held_out_error(model) == pytest.approx(held['deviation_error'], rel=1e-15)
    # ERA/OKID fits one episode: its last fifth is held out
    era = load_model(out / 'chain_era_r4.npz').metadata['held_out']
    assert era['samples'] == 100 and 'last 20% of ep1' in era['data']
    assert np.isfinite(era['deviation_error']) and era['deviation_error'] > 0
