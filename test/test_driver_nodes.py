"""driver_shim + virtual_youbot as rclpy nodes over a virtual CAN bus, through real topics."""
import time

import numpy as np
import pytest

from ros_harness import Harness
from tmcm_rig import forward_command, new_channel, NOISE_FREE
from youbot_fdi.model import load_model

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402  (after importorskip in ros_harness)
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from youbot_fdi.nodes.common import SENSOR_QOS  # noqa: E402
from youbot_fdi.nodes.driver_shim import DriverShimNode  # noqa: E402
from youbot_fdi.nodes.virtual_youbot import VirtualYoubotNode  # noqa: E402

NAMES = ['wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl', 'wheel_joint_br']


@pytest.fixture()
def sim():
    harness = Harness()
    channel = new_channel()
    overrides = [Parameter('can_channel', value=channel)]
    noise_free = [Parameter(name, value=value) for name, value in NOISE_FREE.items()]
    harness.base_node = harness.add(VirtualYoubotNode(context=harness.context,
                                                      parameter_overrides=overrides + noise_free))
    harness.add(DriverShimNode(context=harness.context, parameter_overrides=overrides))
    harness.states, harness.diagnostics = [], []
    harness.probe.create_subscription(JointState, '/joint_states', harness.states.append, SENSOR_QOS)
    harness.probe.create_subscription(DiagnosticArray, '/diagnostics', harness.diagnostics.append, 10)
    harness.commands = harness.probe.create_publisher(JointState, '/wheel_commands', 10)
    yield harness
    harness.close()


SETTLED_STATES = 10  # the last ~0.1 s of /joint_states


def settled(states, field):
    """The median of ``field`` over the last states: a command published late on a loaded machine
    lets the shim's watchdog zero one sample (it should), and a module's answer read too late is
    missing (NaN, the shim's contract); neither must decide the test."""
    return np.nanmedian([getattr(s, field) for s in states[-SETTLED_STATES:]], axis=0)


#: Commanded for at least this long, then for at most this long until the readings settle [s].
COMMANDED_SECONDS, MOST_SECONDS = 2.0, 8.0


def drive_until_settled(harness, action, field, target, atol, seconds=COMMANDED_SECONDS):
    """Call ``action`` every 50 ms for ``seconds``, then on until the settled ``field`` is within
    ``atol`` of ``target`` (at most ``MOST_SECONDS`` in all). A cycle run late on a loaded machine
    lets the modules' controller timeout stop them (the shim's contract, counted on
    /diagnostics), and the base then settles again under the same commands: how long that takes
    is the machine's, what it settles on is the shim's."""
    harness.spin_for(seconds, every=0.05, action=action)
    start = time.monotonic()
    while (time.monotonic() - start < MOST_SECONDS - seconds and harness.states
           and not np.allclose(settled(harness.states, field), target, atol=atol)):
        harness.spin_for(0.5, every=0.05, action=action)


def command(harness, velocity=None, effort=None, names=NAMES):
    msg = JointState()
    msg.name = list(names)
    msg.velocity = [] if velocity is None else [float(v) for v in velocity]
    msg.effort = [] if effort is None else [float(v) for v in effort]
    harness.commands.publish(msg)


def test_shim_drives_the_virtual_base_through_topics(sim):
    target = forward_command(load_model('youbot'), 0.3)
    # Commands in a scrambled joint order: matched by name, not by index.
    order = [2, 0, 3, 1]
    drive_until_settled(
        sim, lambda: command(sim, velocity=target[order], names=[NAMES[i] for i in order]),
        'velocity', target, 0.02)
    assert sim.states, 'no /joint_states'
    last = sim.states[-1]
    assert list(last.name) == NAMES
    np.testing.assert_allclose(settled(sim.states, 'velocity'), target, atol=0.02)
    np.testing.assert_allclose(settled(sim.states, 'effort'), 0.035 * target, atol=0.01)
    stamps = [s.header.stamp.sec + s.header.stamp.nanosec * 1e-9 for s in sim.states[-20:]]
    assert np.all(np.diff(stamps) > 0)
    assert len(sim.states) > 100  # ~100 Hz for 2 s
    assert sim.spin_until(lambda: sim.diagnostics, 2.0)
    names = {status.name for status in sim.diagnostics[-1].status}
    assert names == {f'youbot_fdi/driver_shim: {n}' for n in NAMES + ['bus']}


def test_effort_commands_and_the_watchdog(sim):
    effort = np.array([-0.05, 0.05, -0.05, 0.05])
    drive_until_settled(sim, lambda: command(sim, effort=effort), 'effort', effort, 0.003, 1.5)
    np.testing.assert_allclose(settled(sim.states, 'effort'), effort, atol=0.003)
    sim.spin_for(1.5)  # no more commands: the watchdog commands zero speed
    np.testing.assert_allclose(sim.states[-1].velocity, 0.0, atol=0.02)


def test_bad_commands_are_reported_not_fatal(sim):
    command(sim, velocity=[0.0, float('nan'), 0.0, 0.0])
    command(sim, velocity=[1.0, 1.0, 1.0], names=NAMES[:3])
    command(sim, velocity=[1.0, 1.0, 1.0, 1.0, 1.0], names=NAMES + ['wheel_joint_xx'])
    sim.spin_for(1.5)
    bus = [s for s in sim.diagnostics[-1].status if s.name.endswith(': bus')][0]
    values = {kv.key: kv.value for kv in bus.values}
    assert int(values['rejected_commands']) == 2  # NaN and the missing joint; extra names are fine
    assert bus.level == b'\x01'
    assert sim.states, 'the shim kept publishing'


def test_runtime_fault_injection_shows_in_joint_states(sim):
    target = forward_command(load_model('youbot'), 0.3)
    sim.spin_for(1.0, every=0.05, action=lambda: command(sim, velocity=target))
    result = sim.base_node.set_parameters([Parameter('fault_wheel', value='wheel_joint_fr'),
                                           Parameter('fault', value='runaway')])
    assert all(r.successful for r in result)
    sim.spin_for(1.5, every=0.05, action=lambda: command(sim, velocity=np.zeros(4)))
    last = sim.states[-1]
    assert abs(last.velocity[1]) > 5.0
    assert abs(last.velocity[0]) < 1.0
    refused = sim.base_node.set_parameters([Parameter('fault', value='melted')])
    assert not refused[0].successful


def test_switch_off_service(sim):
    client = sim.probe.create_client(Trigger, '/driver_shim/switch_off_motors')
    assert client.wait_for_service(timeout_sec=2.0)
    future = client.call_async(Trigger.Request())
    assert sim.spin_until(future.done, 2.0)
    assert future.result().success
    sim.spin_for(0.5, every=0.05, action=lambda: command(sim, velocity=np.ones(4)))
    np.testing.assert_allclose(sim.states[-1].effort, 0.0, atol=1e-9)
