"""The predictor node with one chamber on another clock: it neither drives nor stops the model.

A chamber whose FluidPressure messages are stamped 100 s ahead of the node's clock (its
sensor on another clock) made the event time follow it: the model jumped 100 s ahead
(``clock_jump``), the healthy chambers were reported "timed out ... behind the other
inputs" and their values were applied late. Inputs stamped more than 10 s ahead of the
node's clock are now dropped (counted ``input_ahead`` and in the chamber's ``dropped``;
WARN "stamped ... ahead" on its topic); the healthy chambers keep driving the model.
"""

from __future__ import annotations

import signal

from _ros import client_fixture, no_noise, NodeProcess, require_rclpy

require_rclpy()

from test_ros_node import _publishers, model, MS, Outputs, params, pressure, TOPICS  # noqa: E402

client = client_fixture('clock_apart_client')


def test_a_chamber_stamped_ahead_does_not_drag_the_model(client, tmp_path) -> None:
    m = model()
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), publish_rate_hz=50.0))
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        assert client.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                                 and bool(out.infos), 20.0), node.log()
        ahead = 100_000 * MS                        # the last chamber: 100 s in the future
        sent_last = 0
        for _ in range(400):                        # about 2 s at 200 Hz, stamped when sent
            t = client.node.get_clock().now().nanoseconds
            for i, pub in enumerate(pubs):
                pub.publish(pressure(1000.0 * (i + 1), t + (ahead if i == 2 else 0)))
            sent_last = t
            client.spin_for(0.005)
        client.spin_for(0.25)             # the next diagnostics (5 Hz; input_timeout_s 0.5)
        assert out.times, node.log()
        # the model time follows the healthy chambers' stamps, never the bad one's
        assert max(out.times) <= sent_last + 10 * MS, (max(out.times) - sent_last) * 1e-9
        assert max(out.times) >= sent_last - 300 * MS, (sent_last - max(out.times)) * 1e-9
        for tp in TOPICS[:2]:
            st = out.status(f': input {tp}')
            assert st['level'] == 0 and st['timed_out'] == 'false' and st['late'] == '0', st
        bad = out.status(f': input {TOPICS[2]}')
        assert bad['level'] == 1 and 'stamped 100 s ahead' in bad['message'], bad
        assert int(bad['dropped']) >= 300 and bad['received'] == '0', bad
        pred = out.status(': prediction')
        assert int(pred['input_ahead']) == int(bad['dropped']), pred
        assert pred['clock_jump'] == '0' and pred['late'] == '0', pred
        assert node.stop(signal.SIGINT) == 0
        assert not no_noise(node.log()), node.log()
    finally:
        node.kill()
