"""Stamps for un-stamped inputs (:class:`SequenceClock`): senders slower than the model.

The outside world's un-stamped arrays come at whatever rate the sender has: a controller at
100 Hz, a pressure board at 120 Hz, a camera pipeline at 30 Hz, on a 1 kHz model, with
transport jitter and executor stalls. Each must be stamped near the time it was sent, not
compressed into one model step per message (which left a 100 Hz sender's whole sequence
72 ms behind) nor rounded to whole steps (which drifted a 120 Hz sender's stamps to 110 ms
before they jumped back).
"""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.models import DiscreteModel
from soft_rom.predictor import Predictor
from soft_rom.predictor.loop import RuntimeLoop
from soft_rom.predictor.seqclock import SequenceClock

H = 1_000_000                                   # a 1 kHz model
T0 = 1_700_000_000 * 1_000_000_000              # an epoch stamp


def _arrivals(hz: float, seconds: float, seed: int, stalls: bool = False):
    """Send times of a sender at ``hz`` and their reception times (jitter, stalls)."""
    rng = np.random.default_rng(seed)
    n = int(seconds * hz)
    sent = T0 + np.round(np.arange(n) * 1e9 / hz).astype(np.int64)
    recv = sent + rng.integers(50_000, 900_000, n)          # 0.05 .. 0.9 ms of transport
    if stalls:                                              # 30-ms executor stalls: bursts
        w = int(0.03 * hz) + 1
        for a in range(200, n - w, 997):
            recv[a:a + w] = recv[a + w]
    return sent, np.maximum.accumulate(recv)


def _stamps(sent, recv, clock):
    return np.array([clock.stamp(int(r)) for r in recv]) - sent


@pytest.mark.parametrize('hz', [500, 250, 100, 50, 10])
def test_a_sender_slower_than_the_model_keeps_its_times_from_the_first_message(hz) -> None:
    sent, recv = _arrivals(hz, 20.0, seed=hz)
    clock = SequenceClock(H, 100 * H)
    err = _stamps(sent, recv, clock)
    assert np.abs(err).max() <= H, (err.min(), err.max())
    assert clock.period == round(1e9 / hz) and clock.resyncs == 0


@pytest.mark.parametrize('hz', [300, 150, 120, 75, 60, 45, 30])
@pytest.mark.parametrize('stalls', [False, True])
def test_a_sender_off_the_models_grid_stays_in_phase(hz, stalls) -> None:
    sent, recv = _arrivals(hz, 30.0, seed=3 * hz, stalls=stalls)
    clock = SequenceClock(H, 100 * H)
    err = _stamps(sent, recv, clock)
    assert abs(clock.period - 1e9 / hz) <= 3e-4 * 1e9 / hz      # the period, in ns
    settled = sent >= T0 + 3 * 10**9
    assert np.abs(err[settled]).max() <= 1.2 * H, (err[settled].min(), err[settled].max())
    assert np.abs(err).max() <= 5 * H and np.abs(err).mean() <= H
    assert clock.resyncs <= 6                 # phase steps at start-up, then none needed


@pytest.mark.parametrize('pause_ms', [0, 60])
def test_a_100_hz_array_sender_is_applied_when_it_was_sent(pause_ms) -> None:
    # a controller at 100 Hz on a 1 kHz model, its arrays un-stamped: each input must act
    # from (within a step of) its send time; D != 0 shows at each step which input acts.
    # A pause of the sender (60 ms after 1 s) leaves the 16 arrays after it early
    rng = np.random.default_rng(4)
    model = DiscreteModel(np.diag([0.99, 0.95, 0.9]), 0.01 * rng.standard_normal((3, 2)),
                          rng.standard_normal((6, 3)), rng.standard_normal((6, 2)), dt=1e-3,
                          y_ref=np.zeros(6))
    sent, recv = _arrivals(100, 2.0, seed=8)
    sent[100:] += pause_ms * H
    recv[100:] += pause_ms * H
    U = rng.standard_normal((2, sent.size))
    loop = RuntimeLoop(Predictor(model))
    x = np.zeros(3)
    acting: dict[int, int] = {}              # input index -> first step it acts on
    j = 0
    for k, r in enumerate(recv):
        for t, y in loop.on_array(U[:, k], 0, int(r)).outputs:
            for cand in range(j, min(j + 3, U.shape[1])):
                if np.max(np.abs(y - model.C @ x - model.D @ U[:, cand])) <= 1e-12:
                    j = cand
                    break
            else:
                raise AssertionError(f'no input explains the output at {(t - T0) / 1e6} ms')
            acting.setdefault(j, t)
            x = model.A @ x + model.B @ U[:, j]
    assert len(acting) >= sent.size - 1
    delay = np.array([acting[i] - sent[i] for i in sorted(acting) if not 100 <= i < 116])
    assert np.abs(delay).max() <= H, delay.max()              # was 72 ms after the 9th


def test_a_burst_at_start_up_takes_one_step_per_message_across_a_gap() -> None:
    # 60 arrays sent as fast as the sender can (the node test's burst), received 0.1 ms
    # apart, the sender descheduled for 5 ms after the third: still one step each
    recv = T0 + np.arange(60) * 100_000
    recv[3:] += 5 * H
    clock = SequenceClock(H, 100 * H)
    stamps = np.array([clock.stamp(int(r)) for r in recv])
    assert np.all(np.diff(stamps) == H) and clock.resyncs == 0


def test_a_lagging_reception_clock_at_start_up_does_not_shift_the_sequence() -> None:
    # sim time in lock-step: the controller's 100 Hz arrays are sent at exact multiples of
    # 10 ms, but the node has not always taken the newest /clock when one arrives (1-3 ms
    # behind, 40 % of the arrays at start-up, 10 % later). The arrivals' lower envelope is
    # the send times, and from the first phase check (the 17th array) the stamps are exact.
    rng = np.random.default_rng(2)
    sent = T0 + np.arange(300) * 10 * H
    late = np.where(rng.random(300) < np.r_[np.full(10, 0.4), np.full(290, 0.1)],
                    rng.integers(1, 4, 300), 0) * H
    clock = SequenceClock(H, 100 * H)
    err = _stamps(sent, sent + late, clock)
    assert late[:9].any() and np.all(err[17:] == 0), np.flatnonzero(err)
    assert clock.period == 10 * H


@pytest.mark.parametrize('seed', range(4))
def test_a_9th_array_taken_a_step_early_does_not_put_the_sequence_early(seed) -> None:
    # sim time, a CI loop's failure (predictor state 1.2e-2 off): the 9th array, the last
    # of the start-up, was taken before the /clock of its step, and the sequence went on
    # from its reception, a step early, until a phase check moved it (the 17th array). Its
    # stamp is now the whole step nearest the sequence fitted to the 9 arrivals: in step
    # from the 9th on; 10 % of the later arrays are taken a step early too.
    rng = np.random.default_rng(seed)
    sent = T0 + np.arange(300) * 10 * H
    early = np.where(rng.random(300) < 0.1, H, 0)
    early[:8], early[8] = 0, H
    clock = SequenceClock(H, 100 * H)
    err = _stamps(sent, sent - early, clock)
    assert np.all(err[8:] == 0), np.flatnonzero(err)
    assert clock.period == 10 * H


@pytest.mark.parametrize('steps_off', [{0: 2}, {0: 1, 8: -1}, {0: -1, 8: 1}, {8: -2}, {0: 5}])
def test_start_up_arrays_taken_steps_off_keep_the_period_on_the_grid(steps_off) -> None:
    # sim time, the closed-loop test's intermittent failure in CI (predictor state 0.27 and
    # 0.35 off): the controller's 100 Hz arrays in lock-step, each taken at its send time
    # but the first or the 9th, taken a few steps off (before the /clock of its step, or
    # after later ones). The start-up period was the mean of the 8 intervals, the first
    # and the 9th arrival's alone: 2 steps between them made it 9.75 ms (10.25, 10.5 ms),
    # off the model's grid, which no early check corrects, and the stamps drifted 4-37 ms
    # off until a window's votes, after 1.4 s (the model's state 0.1 to 0.4 off)
    sent = T0 + np.arange(300) * 10 * H
    off = np.zeros(300, dtype=np.int64)
    for k, steps in steps_off.items():
        off[k] = steps * H
    clock = SequenceClock(H, 100 * H)
    err = _stamps(sent, sent + off, clock)
    assert np.all(err[8:] == 0), (np.flatnonzero(err), err[8:].min(), err[8:].max())
    assert clock.period == 10 * H and clock.resyncs == 0


def test_start_up_arrays_behind_a_loaded_node_are_in_step_after_the_17th() -> None:
    # measured in the closed loop, its predictor niced on a CPU with 3 busy processes: the
    # first arrays were taken up to 30 ms late, and it caught up by the 10th. The mean of the
    # 8 start-up intervals made the period 10.5 ms, more than a refinement (2 %) from the
    # early estimates, and the stamps stayed 2-10 ms late for the 2 s of the test (state 0.7
    # off, with 7 arrays dropped later); fitted again to the first 17, the period is 10 ms
    late_ms = [0, 1, 13, 28, 30, 24, 19, 11, 4] + [0] * 6 + [1, 1, 1, 2] + [0] * 11 + [1] \
        + [0] * 5
    sent = T0 + np.arange(len(late_ms)) * 10 * H
    clock = SequenceClock(H, 100 * H)
    err = _stamps(sent, sent + np.array(late_ms) * H, clock)
    assert np.all(err[17:] == 0), err // H
    assert clock.period == 10 * H


def _taken_behind_a_slow_first_callback(sent, first_ms: float, clock, tell: bool):
    """Stamps when the node's first callback takes ``first_ms`` (the others 0.05 ms).

    A message is taken when it has arrived and the node is free; with ``tell`` the node
    says when it is free again (:meth:`SequenceClock.taken`), as the predictor node does.
    """
    recv = sent + 100_000                          # 0.1 ms of transport
    free, out = None, []
    for k, r in enumerate(recv):
        now = int(r) if free is None else max(int(r), free)
        out.append(clock.stamp(now))
        free = now + int((first_ms if k == 0 else 0.05) * H)
        if tell:
            clock.taken(free)
    return np.array(out)


def test_arrays_queued_behind_a_slow_first_callback_take_one_step_each() -> None:
    # under rclpy the predictor node's first callback took 1.6-2.0 ms (most of it the first
    # publish of the outputs): a 1 kHz sender's next arrays waited and were taken after it
    # (measured: the 2nd to 4th at 2.64, 2.91 and 3.01 ms after the 1st). Each is still one
    # step; before, the 2nd took two and the whole sequence stayed a step late.
    sent = T0 + np.arange(300) * H
    stamps = _taken_behind_a_slow_first_callback(sent, 2.55, SequenceClock(H, 100 * H), True)
    assert np.all(np.diff(stamps) == H)
    assert np.all(stamps - sent == stamps[0] - sent[0])
    # the node's delay read as the sender's period (no `taken`): one step more
    old = _taken_behind_a_slow_first_callback(sent, 2.55, SequenceClock(H, 100 * H), False)
    assert np.diff(old).max() == 2 * H


@pytest.mark.parametrize('hz', [100, 500])
def test_a_slower_sender_behind_a_slow_first_callback_keeps_its_times(hz) -> None:
    # the rule is for messages that waited: a sender slower than the model is not one
    sent = T0 + np.round(np.arange(4 * hz) * 1e9 / hz).astype(np.int64)
    clock = SequenceClock(H, 100 * H)
    stamps = _taken_behind_a_slow_first_callback(sent, 2.55, clock, True)
    assert np.abs(stamps - sent - (stamps[0] - sent[0])).max() <= H
    assert clock.period == round(1e9 / hz)


@pytest.mark.parametrize('hz', [1000, 500, 120, 100, 30])
@pytest.mark.parametrize('pause_ms', [5, 30, 90, 150])
def test_a_sender_back_from_a_pause_is_stamped_at_its_times_again(hz, pause_ms) -> None:
    # a controller's GC pause: it sends nothing for `pause_ms`, then goes on at its rate.
    # Its arrays after the pause must not stay on the sequence from before it (a 1 kHz
    # sender's stayed `pause_ms` behind for ever; a 100 Hz sender's up to 100 ms off for
    # 2.5 s, its period voted wrong from the pause in the window)
    sent, recv = _arrivals(hz, 6.0, seed=hz + pause_ms)
    k0 = int(3.5 * hz)                  # after a window's estimate of the period (30 Hz: 2.1 s)
    sent[k0:] += pause_ms * H
    recv[k0:] += pause_ms * H
    clock = SequenceClock(H, 100 * H)
    err = np.abs(_stamps(sent, recv, clock))
    assert err[3 * hz:k0].max() <= 1.2 * H            # in phase before the pause (settled)
    # 16 arrays late by the pause (a burst after a stall of the node would catch up);
    # beyond max_lag_s (150 ms) it took 32 before
    assert err[k0 + 16:].max() <= 1.2 * H, np.flatnonzero(err > 1.2 * H) - k0
    assert abs(clock.period - 1e9 / hz) <= 1e-3 * 1e9 / hz
    assert clock.resyncs <= 4


def _taken_by_a_node_sharing_its_cpu(sent, work_ms: float, slices: float, seed: int,
                                     stops: dict[int, float] | None = None,
                                     between: bool = False):
    """Stamps of a node that works ``work_ms`` a message, and the clock.

    It loses the CPU for 4 ms (another process's scheduler slice) after a fraction
    ``slices`` of them from the 50th on (past the start-up, which has rules of its own):
    within its work, or ``between`` messages (after it said it was free). ``stops``:
    index -> ms that it is stopped for (``SIGSTOP``) from that array's send time.
    """
    rng = np.random.default_rng(seed)
    clock, free, out = SequenceClock(H, 100 * H), None, []
    stopped = [(int(sent[j]), int(sent[j] + ms * H)) for j, ms in (stops or {}).items()]
    for j, s in enumerate(sent + 100_000):          # 0.1 ms of transport
        now = int(s) if free is None else max(int(s), free)
        for a, b in stopped:
            now = b if a <= now < b else now
        out.append(clock.stamp(now))
        lost = 4 * H if rng.random() < slices and j >= 50 else 0
        free = now + int(work_ms * H) + (0 if between else lost)
        clock.taken(free)
        free += lost if between else 0
    return np.array(out), clock


@pytest.mark.parametrize('seed', range(4))
@pytest.mark.parametrize('slices', [0.05, 0.1])
@pytest.mark.parametrize('between', [False, True])
def test_a_backlog_taken_between_another_processs_slices_keeps_one_step_per_array(
        seed, slices, between) -> None:
    # The node stopped for 60 ms and 150 ms (as the node test's pauses) takes its backlog
    # while another process takes the CPU from it now and then: its arrivals catch up
    # unevenly, and the first 16 after a slice trailed without catching up by 2 steps.
    # That read as a sender that paused: on the node under one CPU hog, 4 of 22 runs of
    # the node test had 36-50 resyncs and as many arrays late; here 2-56 resyncs in each
    # case before. An array taken at once after the previous one, and less
    # than a step after its arrival, waited in the queue and is no evidence of the sender's
    # pace. With slices after 10 % of the arrays, a run of 16 can still form from the
    # arrays taken right after a slice (seeds 1 and 3: one resync).
    sent = T0 + np.arange(1200) * H
    stamps, clock = _taken_by_a_node_sharing_its_cpu(sent, 0.3, slices, seed,
                                                     {300: 60.0, 800: 150.0}, between)
    if slices <= 0.05:
        assert clock.resyncs == 0
        assert np.all(np.diff(stamps) == H)
    else:
        assert clock.resyncs <= 1


@pytest.mark.parametrize('work_ms', [0.05, 0.3, 0.6, 0.85, 0.95])
@pytest.mark.parametrize('pause_ms', [5, 30, 150])
def test_a_sender_back_from_a_pause_to_a_working_node_is_stamped_at_its_times(
        work_ms, pause_ms) -> None:
    # the rule above must not hide a sender's own pause from a node that says when it is
    # free: its live arrays come a step less its work apart (at 0.85 and 0.95 ms of work,
    # within 0.25 ms: taken at once, but a step after the previous one), and 16 arrays
    # after the pause it is followed again, as without `taken`
    sent = T0 + np.arange(3000) * H
    k0 = 2000
    sent[k0:] += pause_ms * H
    stamps, clock = _taken_by_a_node_sharing_its_cpu(sent, work_ms, 0.0, 0)
    err = np.abs(stamps - sent - (stamps[0] - sent[0]))
    assert err[:k0].max() == 0 and err[k0 + 16:].max() == 0, np.flatnonzero(err) - k0
    assert clock.resyncs == 1


@pytest.mark.parametrize('steps', [2, 3, 4, 10])
def test_a_1_khz_sender_that_slows_down_is_followed(steps) -> None:
    # a sender that goes from 1 kHz to 1 / `steps` of it falls behind the sequence by
    # steps - 1 a message, steadily: it is not queued behind the node (a rule tried for the
    # backlog above, a run started again at every arrival 2 steps further behind, kept the
    # sequence trailing for ever from 3 steps on)
    recv = [T0 + j * H for j in range(2000)] + [T0 + 2000 * H + j * steps * H
                                                for j in range(1, 1500)]
    clock = SequenceClock(H, 100 * H, 1_000_000_000)
    stamps = np.array([clock.stamp(t) for t in recv])
    assert clock.period == steps * H
    assert abs(recv[-1] - stamps[-1]) <= H
