"""The paper-scale run (soft_rom.study.paper_scale) at resolution 1 with tiny episodes.

Sizing, refusal before any work, resume after an interruption, stage records.
"""

from __future__ import annotations

import json
from pathlib import Path
import time

import pytest

from soft_rom.cli import main
from soft_rom.errors import ResourceError, SolverError
from soft_rom.sim.eel import memory_estimate
from soft_rom.study import paper_scale
from soft_rom.study.paper_scale import check_plan, plan_run, run_paper_scale, STAGES
from soft_rom.study.run import StudyConfig

ERA = {'decimation': 1, 'output_rank': 4, 'observer_order': 6, 'n_markov': 60}


def _cfg(**kw) -> StudyConfig:
    base = dict(n_episodes=3, duration=0.12, t_train=0.09, r_lopinf=(2, 4), r_dmdc=(4,),
                r_era=(6,), r_cubic=(), shape_times=(0.05, 0.1), jobs=2, era_options=ERA)
    return StudyConfig(**{**base, **kw})


def test_the_plan_sizes_what_is_left(tmp_path: Path) -> None:
    cfg = StudyConfig(resolution=4, n_episodes=6)
    plan = plan_run(tmp_path / 'out', cfg, tmp_path / 'bags')
    assert plan.episodes_todo == (1, 2, 3, 4, 5, 6) and plan.stages_done == ()
    # the paper's data volume: 6 x 2,000 snapshots of ~234k DOF ~ 22 GB, bags and set
    assert 21e9 < plan.bag_bytes < 25e9 and 22e9 < plan.set_bytes < 27e9     # padded chunks
    assert plan.sim_memory == 2 * memory_estimate(4)[1]              # two jobs
    assert plan.fit_memory <= 4e9


def test_a_run_that_does_not_fit_is_refused_with_the_figures(tmp_path: Path) -> None:
    plan = plan_run(tmp_path / 'out', StudyConfig(resolution=4), tmp_path / 'bags')
    with pytest.raises(ResourceError, match=r'needs 2\d\.\d GB for the bags of 6 episode\(s\) '
                                            r'and 2\d\.\d GB for the training set: 4\d\.\d GB '
                                            r'in .*, 10\.0 GB free'):
        check_plan(plan, free_disk=lambda p: 10e9, free_memory=64e9)
    with pytest.raises(ResourceError, match=r'memory .* 1\.0 GB available'):
        check_plan(plan, free_disk=lambda p: 1e12, free_memory=1e9)
    check_plan(plan, free_disk=lambda p: 1e12, free_memory=64e9)     # fits: no error


def test_the_cli_refuses_before_writing_anything(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(paper_scale.shutil, 'disk_usage',
                        lambda p: type('U', (), {'free': 1e6})())
    out = tmp_path / 'study'
    code = main(['study', '--staged', '--duration', '0.1', '--episodes', '3', '-o', str(out),
                 '--quiet'])
    err = capsys.readouterr().err
    assert code == 1
    assert err.count('\n') == 1 and 'GB free' in err and 'error:' in err
    assert not out.exists()


def _fake(name: str, out: Path, fail: bool = False) -> dict:
    """A stage that only counts its runs (in a file: stages run in their own processes)."""
    with (out / f'{name}.calls').open('a') as fh:
        fh.write('x')
    if fail:
        raise RuntimeError(f'{name} interrupted')
    return {'stage': name}


# module-level, so that the stage processes (spawned) import them by name
def _fake_study1(out, cfg, bag_dir, progress):
    return _fake('study1', out)


def _fail_study1(out, cfg, bag_dir, progress):
    return _fake('study1', out, fail=True)


def _fake_study2(out, cfg, bag_dir, progress):
    return _fake('study2', out)


def _fail_study2(out, cfg, bag_dir, progress):
    return _fake('study2', out, fail=True)


def _fake_cold_read(out, cfg, bag_dir, progress):
    return _fake('cold_read', out)


def _fake_report(out, cfg, bag_dir, progress):
    return _fake('report', out)


FAKES = {'study1': _fake_study1, 'study2': _fake_study2, 'cold_read': _fake_cold_read,
         'report': _fake_report}


def _calls(out: Path, name: str) -> int:
    path = out / f'{name}.calls'
    return len(path.read_text()) if path.exists() else 0


_SIMULATE = paper_scale._simulate_group


def _simulate_but_not_ep2(task):
    """The worker of ep2 is interrupted (two jobs: ep1 and ep3 side by side, ep2)."""
    if 2 in task[2]:
        raise RuntimeError('interrupted')
    return _SIMULATE(task)


def test_an_interrupted_run_resumes_without_redoing_episodes_or_stages(
        tmp_path: Path, monkeypatch) -> None:
    out, bags = tmp_path / 'study', tmp_path / 'bags'
    cfg = _cfg()
    for name, fake in FAKES.items():
        monkeypatch.setitem(paper_scale._STAGE_FUNCS, name, fake)
    # 1) interrupted while simulating ep2: ep1 and ep3 are kept, ep2 left no bag
    monkeypatch.setattr(paper_scale, '_simulate_group', _simulate_but_not_ep2)
    with pytest.raises(SolverError, match='simulating ep2 failed .* run the same command'):
        run_paper_scale(out, cfg, bag_dir=bags, progress=False, echo=lambda s: None)
    for _ in range(100):           # the other worker finishes after the failure is seen
        if (bags / 'ep3.json').exists():
            break
        time.sleep(0.2)
    assert sorted(p.name for p in bags.iterdir()) == ['ep1', 'ep1.json', 'ep3', 'ep3.json']
    kept = {e: (bags / f'ep{e}' / f'ep{e}.mcap').stat().st_mtime_ns for e in (1, 3)}
    # 2) resumed: only ep2 is simulated (a killed run's half-written bag is removed); then a
    #    stage dies, the stages before it are kept
    (bags / '.ep2.tmp-0123abcd' / 'ep2').mkdir(parents=True)
    monkeypatch.setattr(paper_scale, '_simulate_group', _SIMULATE)
    monkeypatch.setitem(paper_scale._STAGE_FUNCS, 'study2', _fail_study2)
    lines: list[str] = []
    with pytest.raises(SolverError, match='stage study2 failed .* run the same command again'):
        run_paper_scale(out, cfg, bag_dir=bags, progress=False, echo=lines.append)
    assert 'to simulate: ep2 ' in lines[0]
    assert not (bags / '.ep2.tmp-0123abcd').exists()
    assert {e: (bags / f'ep{e}' / f'ep{e}.mcap').stat().st_mtime_ns for e in (1, 3)} == kept
    records = {s for s in STAGES if (out / 'stages' / f'{s}.json').is_file()}
    assert records == {'simulate', 'convert', 'study1'}
    sim = json.loads((out / 'stages' / 'simulate.json').read_text())
    assert sim['result']['episodes'] == [2] and sim['peak_rss_gb'] > 0
    assert sim['result']['linear_solver'] in ('cholmod', 'banded-cholesky')
    assert json.loads((out / 'stages' / 'convert.json').read_text())['result'][
        'training_set_bytes'] > 0
    # 3) resumed at study2
    monkeypatch.setitem(paper_scale._STAGE_FUNCS, 'study2', _fake_study2)
    lines.clear()
    run_paper_scale(out, cfg, bag_dir=bags, progress=False, echo=lines.append)
    assert 'to simulate: none' in lines[0]
    assert sum('skipped' in line for line in lines) == 3          # simulate, convert, study1
    assert _calls(out, 'study1') == 1 and _calls(out, 'study2') == 2
    assert all((out / 'stages' / f'{s}.json').is_file() for s in STAGES)
    # 4) everything done: nothing runs again
    lines.clear()
    run_paper_scale(out, cfg, bag_dir=bags, progress=False, echo=lines.append)
    assert sum('skipped' in line for line in lines) == len(STAGES)
    assert _calls(out, 'study1') == 1 and _calls(out, 'report') == 1


def test_the_cli_resumes_in_its_own_folder(tmp_path: Path, monkeypatch, capsys) -> None:
    out = tmp_path / 'study'
    for name, fake in FAKES.items():
        monkeypatch.setitem(paper_scale._STAGE_FUNCS, name, fake)
    monkeypatch.setitem(paper_scale._STAGE_FUNCS, 'study1', _fail_study1)
    argv = ['study', '--staged', '--duration', '0.06', '--episodes', '3', '--jobs', '1',
            '-o', str(out), '--quiet']
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'stage study1 failed' in err
    monkeypatch.setitem(paper_scale._STAGE_FUNCS, 'study1', _fake_study1)
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert 'simulate: done before' in printed and 'convert: done before' in printed
    assert _calls(out, 'study1') == 2 and _calls(out, 'report') == 1


def test_the_staged_run_end_to_end(tmp_path: Path) -> None:
    """Real stages: bags, training set, streaming fits, the cold read, the report."""
    out = tmp_path / 'study'
    summary = run_paper_scale(out, _cfg(jobs=1), progress=False, echo=lambda s: None)
    scale = summary['paper_scale']
    assert set(scale['stages']) == set(STAGES) - {'report'}
    assert all(v['wall_s'] > 0 and v['peak_rss_gb'] > 0 for v in scale['stages'].values())
    assert scale['disk']['bag_bytes'] > 0 and scale['disk']['training_set_bytes'] > 0
    fit = scale['streaming_fit_vs_cold_read']
    assert fit['bytes'] > 0 and fit['ratio'] > 0
    assert fit['passes'] >= 1 and 0 < fit['pod_s'] <= fit['lopinf_fit_s']     # per pass too
    per_pass = fit['pod_s'] / fit['passes']
    assert fit['per_pass_ratio'] == pytest.approx(per_pass / fit['cold_read_s'])
    assert summary['study1']['best']['lopinf']['test'] < 0.01
    assert set(summary['study2']['test']) >= {'lopinf', 'dmdc'}
    assert (out / 'report.md').is_file() and (out / 'bars.png').is_file()
