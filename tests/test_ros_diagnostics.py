"""The predictor node's per-topic statuses, from the figures the core reports."""

from __future__ import annotations

from _ros import require_rclpy

require_rclpy()

from soft_rom.ros.diagnostics import Diagnostics, TopicMonitor  # noqa: E402

OK, WARN, STALE = 0, 1, 3


def _status(received: int, dropped: int, stamp_age: float, age: float = 0.01,
            publishers: int = 1):
    diag = Diagnostics('pred', '/pred', ['/t/pressures'])
    values = {f'input.p{i}.{k}': v for i in (1, 2) for k, v in (
        ('received', str(received)), ('dropped', str(dropped)), ('clipped', '0'),
        ('age_s', f'{age:g}'), ('rate_hz', '100'), ('timed_out', 'false'))}
    st = diag._input_statuses(values, ['p1', 'p2'], [stamp_age, stamp_age], timeout=0.5,
                              publishers=[publishers])[0]
    level = st.level[0] if isinstance(st.level, bytes) else st.level
    return level, st.message, {kv.key: kv.value for kv in st.values}


def test_an_array_topic_counts_a_whole_dropped_array_once() -> None:
    level, message, values = _status(0, 7, float('inf'))
    assert level == WARN and message.startswith('none taken; 7 dropped'), message
    assert values['dropped'] == '7'


def test_stamps_on_another_clock_are_warned() -> None:
    assert _status(50, 0, 0.003)[:2] == (OK, '100 Hz')
    level, message, _ = _status(50, 0, -99.9)             # 100 s in the future
    assert level == WARN and 'stamped 99.9 s ahead of this node' in message
    level, message, _ = _status(50, 0, 1.8e9)             # wall-time stamps, sim-time node
    assert level == WARN and 'behind this node' in message


def test_a_chamber_whose_inputs_are_dropped_as_stamped_ahead_says_so() -> None:
    diag = Diagnostics('pred', '/pred', ['/t/c1', '/t/c2'])
    values = {f'input.p{i}.{k}': v for i in (1, 2) for k, v in (
        ('received', '50' if i == 1 else '0'), ('dropped', '0' if i == 1 else '40'),
        ('clipped', '0'), ('age_s', '0.01' if i == 1 else 'inf'), ('rate_hz', '100'),
        ('timed_out', 'false'), ('ahead', '0' if i == 1 else '40'),
        ('ahead_s', 'nan' if i == 1 else '99.9'))}
    sts = diag._input_statuses(values, ['p1', 'p2'], [0.003, float('inf')], timeout=0.5,
                               publishers=[1, 1])
    levels = [st.level[0] if isinstance(st.level, bytes) else st.level for st in sts]
    assert levels == [OK, WARN], [st.message for st in sts]
    assert sts[1].message == ("stamped 99.9 s ahead of this node's clock (another clock? "
                              'use_sim_time?): dropped, 40 so far')
    assert {kv.key: kv.value for kv in sts[1].values}['ahead'] == '40'


def test_silent_topic_with_drops_says_both() -> None:
    level, message, _ = _status(10, 3, 0.003, age=2.0)
    assert level == STALE and 'nothing taken for 2 s; 3 dropped' in message, message


def test_a_second_publisher_on_an_input_topic_is_warned() -> None:
    level, message, values = _status(50, 0, 0.003, publishers=2)
    assert level == WARN and message == '2 publishers on this topic (a second sender?)'
    assert values['publishers'] == '2'


def test_a_measured_centerline_in_another_frame_is_warned() -> None:
    diag = Diagnostics('pred', '/pred', ['/t/pressures'])
    monitor = TopicMonitor('/t/centerline', 'measured', 'world')
    monitor.seen(10**9)
    st = diag._measured_status(monitor, 10**9 + 10**7, timeout=0.5)
    assert (st.level[0] if isinstance(st.level, bytes) else st.level) == OK
    monitor.frame = 'mocap_optitrack'
    st = diag._measured_status(monitor, 10**9 + 2 * 10**7, timeout=0.5)
    assert (st.level[0] if isinstance(st.level, bytes) else st.level) == WARN
    assert "frame_id 'mocap_optitrack' is not the frame_id of this node ('world')" in st.message
