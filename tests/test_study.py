"""The studies end to end on a short, small run of the embedded eel (bags, converter, fits)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from soft_rom.errors import ConfigError
from soft_rom.models import load_model
from soft_rom.study.report import markdown_table
from soft_rom.study.run import run_study, StudyConfig


@pytest.fixture(scope='module')
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp('study')
    cfg = StudyConfig(n_episodes=3, duration=0.4, t_train=0.3, r_lopinf=(2, 4), r_dmdc=(4,),
                      r_era=(6, 8), shape_times=(0.1, 0.2, 0.39), jobs=1,
                      era_options={'decimation': 1, 'output_rank': 4, 'observer_order': 8,
                                   'n_markov': 100})
    summary = run_study(out, cfg, progress=False, replay=True)
    return out, summary


def test_study_writes_report_figures_models(study) -> None:
    out, summary = study
    for name in ('report.md', 'summary.json', 'errors_vs_r.png', 'traces.png', 'bars.png',
                 'centerline_ep3.png'):
        assert (out / name).is_file(), name
    assert json.loads((out / 'summary.json').read_text())['study1']['best']
    report = (out / 'report.md').read_text()
    assert '## Study 1' in report and '## Study 2' in report and 'paper' in report
    chosen = summary['study2']['chosen']
    model = load_model(out / 'models' / f'eel_lopinf_r{chosen["lopinf"]["r"]}.npz')
    assert model.method == 'lopinf' and model.input_units == ['Pa'] * 6


def test_study_numbers_are_sane(study) -> None:
    _out, summary = study
    c = summary['study1']['curves']['lopinf']
    assert c['r'] == [2, 4]
    assert all(np.isfinite(c['train'])) and all(np.isfinite(c['test']))
    # LOpInf ROMs are stable by construction and fit their training window.
    assert min(c['stability_margin']) > 0
    assert min(c['train_dev']) < 0.5
    # The absolute metric is dominated by the body's x coordinates: far below the deviation one.
    assert max(c['train']) < 0.1 * min(c['train_dev'])
    assert set(summary['study2']['test']['lopinf']) == {'ep3'}
    assert summary['replay']['samples'] == 400
    assert summary['conclusions']


def test_rerun_reuses_bags_and_reconverts_when_they_change(study, tmp_path) -> None:
    out, _summary = study
    cfg = StudyConfig(n_episodes=2, duration=0.4, t_train=0.3, r_lopinf=(2,), r_dmdc=(2,),
                      r_era=(4,), jobs=1, era_options={'decimation': 1, 'output_rank': 4,
                                                       'observer_order': 8, 'n_markov': 100})
    # Same folder: the bags are reused, the 3-episode training set is replaced by a 2-episode one.
    stamp = (out / 'bags' / 'ep1.json').stat().st_mtime_ns
    summary = run_study(out, cfg, progress=False, studies=(1,))
    assert summary['fom']['episodes'] == 2
    assert (out / 'bags' / 'ep1.json').stat().st_mtime_ns == stamp
    with pytest.raises(ConfigError, match='other settings'):
        run_study(tmp_path / 'other', StudyConfig(n_episodes=2, duration=0.4, t_train=0.3,
                                                  seed=7, jobs=1),
                  progress=False, studies=(1,), bag_dir=out / 'bags')


def test_failed_fits_are_said_and_a_study_with_none_is_an_error(tmp_path, caplog) -> None:
    """Found by an audit: methods that failed at every r left empty tables, exit 0, no reason.

    10-ms episodes are too short for LOpInf's 8th-order differences and for ERA's preset
    Markov horizon; DMDc fits. With only LOpInf asked for, nothing fits: an error.
    """
    from soft_rom.errors import SolverError
    cfg = StudyConfig(n_episodes=2, duration=0.01, t_train=0.005, r_lopinf=(2,), r_dmdc=(2,),
                      r_era=(4,), r_cubic=(), jobs=1)
    summary = run_study(tmp_path / 'a', cfg, progress=False, studies=(1,))
    failed = summary['failures']
    assert [f.split(' failed: ')[0] for f in failed] == ['study 1: lopinf', 'study 1: era']
    assert 'too short for the derivative estimator' in failed[0]
    report = (tmp_path / 'a' / 'report.md').read_text()
    assert '## Warnings' in report and failed[1] in report
    assert list(summary['study1']['best']) == ['dmdc']
    none = StudyConfig(n_episodes=2, duration=0.01, t_train=0.005, r_lopinf=(2,), r_dmdc=(),
                       r_era=(), r_cubic=(), jobs=1)
    with pytest.raises(SolverError, match='no method fitted a model: study 1: lopinf failed'):
        run_study(tmp_path / 'a', none, progress=False, studies=(1,))


def test_report_renders_and_shows_every_figure(study) -> None:
    """Every table row has its header's cells (markdown-it-py); every figure is captioned."""
    from _markdown import table_problems

    from soft_rom.study.report import study_report

    out, summary = study
    # The folder's report is the report of its summary.json (the module's other tests run
    # the study again into the folder, so the full run's report is made from its summary).
    on_disk = json.loads((out / 'summary.json').read_text())
    assert (out / 'report.md').read_text() == study_report(on_disk)
    report = study_report(json.loads(json.dumps(summary, default=str)))
    assert table_problems(report) == []
    assert '\\|output deviation\\|' in report          # the | of the name is escaped
    shown = re.findall(r'!\[[^\]]*\]\(([^)]+)\)', report)
    assert sorted(shown) == sorted(p.name for p in out.glob('*.png'))
    assert len(re.findall(r'\*\*Figure \d+\.\*\* \S', report)) == len(shown)
    rep = summary['replay']
    assert rep['kalman']['kalman'] == pytest.approx(
        json.loads((out / 'replay_ep3.json').read_text())['kalman']['kalman'])
    assert f'{rep["kalman"]["kalman"]:.4f}' in report       # one Kalman figure, in both
    from soft_rom.cli.demo import replay_lines
    k = rep['kalman']
    assert f'{k["open_loop"]:.3f} -> {k["kalman"]:.3f}' in replay_lines(rep)
    assert rep['final_status'] in report and 'thresholds from' in report
    assert summary['machine']['cpus'] >= 1 and 'Measured on' in report


def test_replay_is_ok_for_the_study_model_and_warns_for_a_mismatched_one(study, tmp_path):
    """Thresholds from the held-out error: the study's model ends OK, one of 10 kPa does not."""
    from soft_rom.convert import convert, read_episode
    from soft_rom.predictor import Level, Predictor, replay_episode
    from soft_rom.study.run import _in_memory, _record_held_out, simulate_bags, sweep

    out, summary = study
    rep = summary['replay']
    assert rep['final_status'] == 'OK', rep
    r = summary['study2']['chosen']['lopinf']['r']
    good = load_model(out / 'models' / f'eel_lopinf_r{r}.npz')
    held = good.metadata['held_out']
    assert held['deviation_error'] > 0 and 'left out in turn' in held['data']
    assert rep['warn_threshold'] == pytest.approx(2 * held['deviation_error'])
    # The same fit on episodes of a tenth of the pressure: the same eel, another regime.
    cfg = StudyConfig(n_episodes=2, duration=0.4, t_train=0.3, jobs=1,
                      sim_options={'amplitude': 5e3})
    bags = simulate_bags(tmp_path / 'small', cfg, progress=False)
    ts, _ = convert(bags, tmp_path / 'small.zarr', progress=False)
    train = [_in_memory(ts['ep1']), _in_memory(ts['ep2'])]
    small = sweep('lopinf', [r], train, ts)[r]
    _record_held_out('lopinf', small, {'r': r}, train, ts, cfg)
    episode, _ = read_episode(out / 'bags' / 'ep3')
    pred = Predictor(small)
    replay_episode(pred, episode)
    health = pred.health()
    assert health.level in (Level.WARN, Level.ERROR), health.message
    assert 'x the held-out error' in health.message


def test_markdown_table_escapes_pipes() -> None:
    from _markdown import table_problems

    table = markdown_table(['quantity', 'value'], [['max |y - y_ref| [mm]', 1.0], ['a\\|b', 2]])
    assert table_problems(table) == []
    assert '| max \\|y - y_ref\\| [mm] | 1.0000 |' in table


def test_markdown_table_formats_numbers() -> None:
    table = markdown_table(['a', 'b'], [[1, 0.12345], [2, 1.5e12], [3, 2e-5]])
    assert '| 1 | 0.1235 |' in table and '1.50e+12' in table and '2.00e-05' in table


@pytest.mark.parametrize('data, words', [
    (b'{x\n', 'is not valid JSON'),
    (b'[]\n', 'must hold a JSON object; got an array'),
    (b'"ep1"\n', 'must hold a JSON object; got a string'),
    (b'\xff\xfe{}\n', 'is not UTF-8 text'),
])
def test_corrupt_bag_sidecar_is_refused_naming_it(tmp_path, capsys, data, words) -> None:
    from soft_rom.cli import main
    from soft_rom.errors import BagError
    from soft_rom.study.run import simulate_bags

    bags = tmp_path / 'sb'
    (bags / 'ep1').mkdir(parents=True)
    sidecar = bags / 'ep1.json'
    sidecar.write_bytes(data)
    cfg = StudyConfig(n_episodes=2, duration=0.4, t_train=0.3, jobs=1)
    with pytest.raises(BagError, match=words):
        simulate_bags(bags, cfg, progress=False)
    assert not (bags / 'ep2').exists()          # refused before any simulation
    for verb in ('study', 'demo'):
        capsys.readouterr()
        rc = main([verb, '-o', str(tmp_path / verb), '--bags', str(bags), '--episodes', '2',
                   '--quiet', '--jobs', '1'])
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if line.strip()]
        assert rc == 2, err
        assert len(lines) == 1 and 'Traceback' not in err, err
        assert lines[0].startswith(f'soft-rom {verb}: error: bag sidecar {sidecar}'), err
        assert words in lines[0]
    assert sidecar.read_bytes() == data and not (bags / 'ep2').exists()


def test_a_method_with_no_fitted_r_draws_no_curve(tmp_path) -> None:
    """A method that failed at every r (an empty curve) leaves the panel empty, not a crash."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from soft_rom.study.figures import _plot_in_range, ABOVE
    fig, ax = plt.subplots()
    assert _plot_in_range(ax, [], [], 1e-3, 1.0, log=True) == 0
    assert not ax.lines
    assert _plot_in_range(ax, [2, 4], [0.5, 5.0], 1e-3, 1.0, log=True) == ABOVE
    plt.close(fig)


def test_points_off_the_scale_are_marked_at_their_own_r() -> None:
    """An order's point off the axis is marked at its own r, a sampled curve where it leaves.

    errors_vs_r's points above the axis (two in a row included) are marked at their r, not
    where the line crosses the edge.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from soft_rom.study.figures import _plot_in_range, ABOVE, BELOW

    def marks(ax):
        return sorted((float(ln.get_xdata()[0]), ln.get_marker()) for ln in ax.lines
                      if ln.get_marker() in ('^', 'v') and ln.get_zorder() == 5)

    fig, ax = plt.subplots()
    sides = _plot_in_range(ax, [4, 8, 12, 16], [0.1, 22.3, 30.0, 1e-5], 1e-3, 1.0, log=True,
                           points=True, marker='o')
    assert sides == ABOVE | BELOW
    assert marks(ax) == [(8.0, '^'), (12.0, '^'), (16.0, 'v')]
    ax.clear()
    assert _plot_in_range(ax, [0.0, 1.0], [0.0, 2.0], -1.0, 1.0) == ABOVE
    assert marks(ax) == [(0.5, '^')]              # where the curve leaves the range
    plt.close(fig)


def test_dmdc_in_a_second_process_gives_the_same_study_2(study, tmp_path) -> None:
    """``jobs`` 2 runs study 2's DMDc in a spawned process: the same numbers, bit for bit."""
    from dataclasses import replace

    from soft_rom.convert import convert
    from soft_rom.study.run import blas_threads
    from soft_rom.study.studies import study_unseen_inputs

    out, _summary = study
    ts, _ = convert([out / 'bags' / f'ep{i}' for i in (1, 2, 3)], tmp_path / 'data.zarr',
                    progress=False)
    cfg = StudyConfig(n_episodes=3, duration=0.4, t_train=0.3, r_lopinf=(4,),
                      r_dmdc=(2, 4), r_era=(6,), shape_times=(0.1, 0.2, 0.39), jobs=1,
                      era_options={'decimation': 1, 'output_rank': 4, 'observer_order': 8,
                                   'n_markov': 100})
    for name in ('one', 'two'):
        (tmp_path / name).mkdir()
    with blas_threads(cfg.blas_threads):              # as run_study: the worker's count
        one = study_unseen_inputs(ts, cfg, tmp_path / 'one')
        two = study_unseen_inputs(ts, replace(cfg, jobs=2), tmp_path / 'two')
    assert list(two['chosen']) == list(one['chosen']) == ['lopinf', 'dmdc', 'lopinf_cubic',
                                                         'era']
    assert two['chosen'] == one['chosen']
    assert two['test'] == one['test'] and two['test_dev'] == one['test_dev']
    r = one['chosen']['dmdc']['r']
    a = load_model(tmp_path / 'two' / 'models' / f'eel_dmdc_r{r}.npz')
    b = load_model(tmp_path / 'one' / 'models' / f'eel_dmdc_r{r}.npz')
    assert a.metadata['held_out'] == b.metadata['held_out']
    assert np.array_equal(a.A, b.A) and np.array_equal(a.B, b.B)
    assert two['fit_seconds']['dmdc'] > 0
