"""What the control API says of an untrusted model, a too fast reference, a target out of reach.

An untrusted model, a reference too fast for the control step, a static target out of the
model's reach within the input bounds.

Before, a ``Controller``/``MPC`` built in Python on an unstable model said nothing (only the
ROS node logged it); ``wave:f=200`` at a 10 ms step ran, tracking the static shape that the
200 Hz wave is when sampled every 10 ms; a static bend 4 x the training pressures ran with
its commands at the bounds, 56 % short of the target, without a word.
"""

from __future__ import annotations

import re
import warnings

from _eel_rom import eel, modal_rom
import numpy as np
import pytest

from soft_rom.control import (
    Controller,
    MPC,
    MPCConfig,
    parse_reference,
    Reference,
    ROMPlant,
    run_closed_loop,
)
from soft_rom.control.reference import reach_miss, step_reference, training_band
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, ReferenceReachWarning, UntrustedModelWarning
from soft_rom.models import SecondOrderModel


def _untrusted() -> SecondOrderModel:
    """The modal ROM with one negative stiffness: an unstable mode (a new object each call)."""
    m = modal_rom(4)
    K = m.K.copy()
    K[0, 0] = -1.0
    return SecondOrderModel(K, m.C, m.B, m.E, dt=m.dt, y_ref=m.y_ref,
                            output_names=m.output_names, input_units=['Pa'] * 6,
                            output_units=['m'] * 40, metadata=m.metadata)


def _said(record: list[warnings.WarningMessage], category: type[Warning]) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, category)]


def test_an_untrusted_model_warns_once_naming_why_at_the_callers_line() -> None:
    bad = _untrusted()
    issues = bad.trust_issues()
    assert issues
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter('always')
        Controller(bad)
        Controller(bad, MPCConfig(horizon=0.1))        # the same model again: said once
        MPC(bad)
        Controller(modal_rom(4))                       # a trusted one: nothing
    said = [w for w in record if issubclass(w.category, UntrustedModelWarning)]
    assert len(said) == 1, [str(w.message) for w in said]
    assert all(issue in str(said[0].message) for issue in issues)
    assert said[0].filename == __file__               # the user's line, not soft_rom's
    with pytest.warns(UntrustedModelWarning, match='not trusted: '):
        MPC(_untrusted())                             # the MPC alone says it too


def test_a_reference_above_the_control_steps_nyquist_rate_is_refused() -> None:
    m = modal_rom(4)
    fast = parse_reference('wave:f=200', m, duration=0.3)
    # what the old code tracked: sampled every 10 ms (after the 0.2 s fade-in), a 200 Hz
    # wave is one static shape
    ticks = np.arange(21, 30) * 0.01
    assert np.ptp(fast.at(ticks), axis=1).max() < 1e-9 < np.ptp(fast.Y, axis=1).max()
    with pytest.raises(ConfigError, match=r'200 Hz, at or above the Nyquist rate \(50 Hz\) of '
                                          r'the 10 ms control step.*a static shape'):
        run_closed_loop(m, fast, plant=ROMPlant(m), duration=0.3)
    ctl = Controller(m)
    why = ctl.set_reference(fast)
    assert 'Nyquist' in why and ctl.reference is None
    assert ctl.counters.references_refused == 1
    assert 'a 20 Hz motion' in ctl.set_reference(parse_reference('wave:f=80', m, duration=0.3))
    assert ctl.set_reference(parse_reference('wave:f=40', m, duration=0.3)) == ''
    # a shorter control step samples the 200 Hz wave: taken
    assert Controller(m, MPCConfig(step=0.001, horizon=0.02)).set_reference(fast) == ''


def _static(m, dy: np.ndarray, label: str) -> Reference:
    """At rest, then held at ``y_ref + dy`` from 0.05 s."""
    Y = np.repeat(m.y_ref[:, None], 3, axis=1)
    Y[:, 1:] += dy[:, None]
    return Reference(t=np.array([0.0, 0.05, 1.0]), Y=Y, label=label)


def test_a_static_target_out_of_reach_warns_once_with_the_figure() -> None:
    m = modal_rom(4)
    ctl = Controller(m)                                # bounds: the envelope's +-50 kPa
    G = ctl.mpc.steady_gain()
    bend = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    near, far = _static(m, G @ (40e3 * bend), 'near'), _static(m, G @ (160e3 * bend), 'far')
    with warnings.catch_warnings():
        warnings.simplefilter('error', ReferenceReachWarning)
        assert ctl.set_reference(near) == ''          # within the bounds: silent
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter('always')
        assert ctl.set_reference(far) == ''           # taken, not refused
        ctl.set_reference(far)                        # the same target again: said once
        run_closed_loop(m, _static(m, G @ (-160e3 * bend), 'mirror'), plant=ROMPlant(m),
                        duration=0.02)
    said = _said(record, ReferenceReachWarning)
    assert len(said) == 2 and "'far'" in said[0] and "'mirror'" in said[1], said
    assert ctl.reference is far
    figure = int(re.search(r'misses its static target by (\d+) %', said[0]).group(1))
    # 50 kPa of the 160 kPa pattern is in the bounds: at most 1 - 50/160 of it is missed;
    # a model-made target is in its steady shapes: 0 % with unbounded inputs
    assert 40 <= figure <= 69 and '(0 % with unbounded inputs)' in said[0], said[0]
    bounded, free, cut = reach_miss(far, G, ctl.mpc.lo, ctl.mpc.hi, m.y_ref)
    assert figure == round(100 * bounded) and free < 1e-9 and abs(cut - bounded) < 1e-9
    # a moving reference has no static target: nothing to say
    assert reach_miss(parse_reference('wave:f=2', m, duration=1.0), G, ctl.mpc.lo,
                      ctl.mpc.hi, m.y_ref) is None


def test_the_fom_bends_the_study_bend_silently_and_4x_the_training_pressures_not() -> None:
    m = modal_rom(4)
    ctl = Controller(m)                                # bounds: +-50 kPa
    study = step_reference(m, np.array([20e3, -20e3, 15e3, -15e3, 10e3, -10e3]), 0.5,
                           at=0.05, settle=1.0, plant=eel())
    far = step_reference(m, np.array([200e3, -200e3] * 3), 0.5, at=0.05, settle=1.0,
                         plant=eel())
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter('always')
        assert ctl.set_reference(study) == ''
        assert not _said(record, ReferenceReachWarning), _said(record, ReferenceReachWarning)
        assert ctl.set_reference(far) == ''
    said = _said(record, ReferenceReachWarning)
    assert len(said) == 1 and 'static bend u=[200, -200' in said[0], said
    assert int(re.search(r'by (\d+) %', said[0]).group(1)) > 10


def test_an_unstable_model_has_no_steady_state_to_reach() -> None:
    """No reach figure from an unstable model: its steady-state gain is no state it settles in."""
    bad = _untrusted()
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter('always')
        ctl = Controller(bad)
        G = ctl.mpc.steady_gain()
        far = _static(bad, G @ (160e3 * np.array([1.0, -1.0] * 3)), 'far')
        assert ctl.set_reference(far) == ''
    assert _said(record, UntrustedModelWarning) and not _said(record, ReferenceReachWarning)
    # the figure itself would have been large: the skip is what kept it silent
    assert reach_miss(far, G, ctl.mpc.lo, ctl.mpc.hi, bad.y_ref)[2] > 0.1


def test_a_reference_faster_than_the_training_outputs_warns_once() -> None:
    m = modal_rom(4)
    # training outputs that moved at 1.5 Hz (and 0.5 Hz): their band is 1.5 Hz
    t = np.arange(4000) * m.dt
    Y = m.y_ref[:, None] + 1e-3 * np.outer(np.linspace(0, 1, 40), np.sin(2 * np.pi * 1.5 * t)
                                           + np.sin(2 * np.pi * 0.5 * t))
    env = training_envelope([(np.zeros((6, t.size)), Y)], m.y_ref, m.dt)
    assert env['y_band_hz'] == pytest.approx(1.5, abs=0.25)
    band = SecondOrderModel(m.K, m.C, m.B, m.E, dt=m.dt, y_ref=m.y_ref,
                            output_names=m.output_names,
                            metadata={**m.metadata, 'envelope': {**m.metadata['envelope'],
                                                                 'y_band_hz': 1.5}})
    assert training_band(band) == 1.5 and training_band(m) is None
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter('always')
        ctl = Controller(band)
        assert ctl.set_reference(parse_reference('wave:f=1', band, duration=0.5)) == ''
        assert ctl.set_reference(parse_reference('wave:f=4', band, duration=0.5)) == ''
        assert ctl.set_reference(parse_reference('wave:f=4', band, duration=0.6)) == ''
        Controller(m).set_reference(parse_reference('wave:f=4', m, duration=0.5))   # no band
    said = _said(record, ReferenceReachWarning)
    assert len(said) == 1 and "moves at 4 Hz, faster than the model's training data: 99 % " \
        'of their output motion lies below 1.5 Hz' in said[0], said
    assert training_envelope([(np.zeros((6, 40)), np.ones((40, 40)))], dt=m.dt)[
        'y_band_hz'] is None                           # outputs that never move: no band
