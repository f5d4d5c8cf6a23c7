"""``lifecycle: true``: the predictor as a managed node, driven by lifecycle_msgs services.

configure loads and validates the model (a bad one: FAILURE, stays unconfigured), activate
creates the topics, deactivate removes them keeping the state, cleanup unloads.
"""

from __future__ import annotations

import signal

from _ros import Client, client_fixture, no_noise, NodeProcess, require_rclpy
import numpy as np

require_rclpy()

from lifecycle_msgs.msg import State, Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from sensor_msgs.msg import FluidPressure  # noqa: E402
from test_ros_node import model, MS, Outputs, params, pressure, RELIABLE, T0_NS, TOPICS  # noqa: E402

client = client_fixture('lifecycle_client')


def _state(client: Client, fqn: str) -> int:
    return client.call(GetState, f'{fqn}/get_state', GetState.Request(),
                       idempotent=True).current_state.id


def _transition(client: Client, fqn: str, tid: int) -> bool:
    req = ChangeState.Request(transition=Transition(id=tid))
    return client.call(ChangeState, f'{fqn}/change_state', req).success


def test_lifecycle_configure_activate_deactivate_cleanup(client, tmp_path) -> None:
    m = model()
    good = m.save(tmp_path / 'm.npz')
    node = NodeProcess(tmp_path, params(tmp_path / 'missing.npz', lifecycle=True),
                       name='managed')
    try:
        fqn = node.fqn
        out = Outputs(client, fqn)
        pubs = [client.node.create_publisher(FluidPressure, tp, RELIABLE) for tp in TOPICS]
        assert _state(client, fqn) == State.PRIMARY_STATE_UNCONFIGURED
        assert node.proc.poll() is None                   # a missing model does not exit
        # configure with a missing model: FAILURE, still unconfigured, reason logged
        assert not _transition(client, fqn, Transition.TRANSITION_CONFIGURE)
        assert _state(client, fqn) == State.PRIMARY_STATE_UNCONFIGURED
        assert 'missing.npz' in node.log()
        assert client.set_parameters(fqn, model_path=str(good))[0].successful
        assert _transition(client, fqn, Transition.TRANSITION_CONFIGURE)
        assert _state(client, fqn) == State.PRIMARY_STATE_INACTIVE
        client.spin_for(0.3)
        assert all(p.get_subscription_count() == 0 for p in pubs)     # inactive: no topics
        assert _transition(client, fqn, Transition.TRANSITION_ACTIVATE)
        assert client.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs),
                                 timeout=10.0)
        for j in range(10):
            for pub in pubs:
                pub.publish(pressure(1.0, T0_NS + j * MS))
        assert client.spin_until(lambda: T0_NS + 9 * MS in out.stamped, timeout=10.0)
        before = out.stamped[T0_NS + 9 * MS]
        # deactivate: topics gone, state kept (the next step continues from step 9)
        assert _transition(client, fqn, Transition.TRANSITION_DEACTIVATE)
        assert client.spin_until(lambda: all(p.get_subscription_count() == 0 for p in pubs),
                                 timeout=10.0)
        assert _transition(client, fqn, Transition.TRANSITION_ACTIVATE)
        assert client.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs),
                                 timeout=10.0)
        for pub in pubs:
            pub.publish(pressure(1.0, T0_NS + 10 * MS))
        assert client.spin_until(lambda: T0_NS + 10 * MS in out.stamped, timeout=10.0)
        fresh = m.simulate(np.ones((3, 11)))
        np.testing.assert_allclose(out.stamped[T0_NS + 10 * MS], fresh[:, 10], atol=1e-12)
        np.testing.assert_allclose(before, fresh[:, 9], atol=1e-12)
        # cleanup unloads; configure again works
        assert _transition(client, fqn, Transition.TRANSITION_DEACTIVATE)
        assert _transition(client, fqn, Transition.TRANSITION_CLEANUP)
        assert _state(client, fqn) == State.PRIMARY_STATE_UNCONFIGURED
        assert _transition(client, fqn, Transition.TRANSITION_CONFIGURE)
        assert node.stop(signal.SIGINT) == 0
        assert not no_noise(node.log()), node.log()
    finally:
        node.kill()
