"""Bad input through real rclpy topics (issue 17): NaN, short, unknown-name, empty and
backwards-stamped JointState on /joint_states and /wheel_commands among good ones. The nodes keep
running, say what was wrong on /diagnostics (rate-limited), raise no wheel fault; a silent
/joint_states is the base's comm_loss within comm_timeout."""
import math

import pytest

from ros_harness import harness  # noqa: F401 - the fixture

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from youbot_fdi.fdi.settings import FdiSettings  # noqa: E402
from youbot_fdi.model import load_model  # noqa: E402
from youbot_fdi.nodes.common import LATCHED_QOS, now_seconds, seconds_to_stamp  # noqa: E402
from youbot_fdi.nodes.conversions import event_from_status  # noqa: E402
from youbot_fdi.nodes.decision import DecisionNode  # noqa: E402
from youbot_fdi.nodes.observer import ObserverNode  # noqa: E402
from youbot_fdi.nodes.residual_generator import ResidualGeneratorNode  # noqa: E402

NAMES = load_model('youbot').wheel_names
RATE = 100.0  # [Hz]
BAD_EVERY = 10  # one bad message among this many
SILENCE = 2.0  # [s]
IN_FLIGHT = 0.1  # [s] for messages already published to arrive


def message(stamp, names=NAMES, values=None):
    msg = JointState()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.name = list(names)
    values = [0.0] * len(names) if values is None else values
    msg.position, msg.velocity, msg.effort = list(values), list(values), list(values)
    return msg


def bad_messages(stamp):
    """One of each kind of bad message, in turn."""
    empty = JointState()
    empty.header.stamp = seconds_to_stamp(stamp)
    return [message(stamp, values=[math.nan, 0.0, 0.0, 0.0]),
            message(stamp, values=[0.0, 0.0]),  # shorter than the names
            message(stamp, names=['caster', 'arm_joint_1', 'x', 'y']),
            empty,
            message(stamp - 5.0)]  # stamped 5 s in the past


def fdi_nodes(harness, diagnostics_wanted):
    """The observer, residual generator and decision in ``harness``, and what the probe hears:
    (generator node, decision node, fault events, /diagnostics statuses that
    ``diagnostics_wanted(status)`` accepts, residual messages)."""
    harness.add(ObserverNode(context=harness.context))
    generator = harness.add(ResidualGeneratorNode(context=harness.context))
    decision = harness.add(DecisionNode(context=harness.context))
    faults, statuses, residuals = [], [], []
    probe = harness.probe
    probe.create_subscription(DiagnosticArray, '/youbot_fdi/faults',
                              lambda m: faults.extend(event_from_status(s) for s in m.status), LATCHED_QOS)
    probe.create_subscription(DiagnosticArray, '/diagnostics',
                              lambda m: statuses.extend(filter(diagnostics_wanted, m.status)), 10)
    probe.create_subscription(JointState, '/youbot_fdi/residuals', residuals.append, 10)
    return generator, decision, faults, statuses, residuals


def test_bad_messages_are_named_on_diagnostics_and_raise_no_fault(harness):
    _, decision, faults, warnings, residuals = fdi_nodes(
        harness, lambda s: s.level == DiagnosticStatus.WARN and s.name.endswith(': input'))
    probe = harness.probe
    joints = probe.create_publisher(JointState, '/joint_states', 10)
    commands = probe.create_publisher(JointState, '/wheel_commands', 10)
    count = [0]
    newest = [0.0]  # the newest stamp sent on /joint_states [s]

    def publish():
        stamp = now_seconds(decision)
        k = count[0]
        count[0] += 1
        if k % BAD_EVERY == BAD_EVERY - 1:
            bad = bad_messages(stamp)[(k // BAD_EVERY) % 5]
            (joints if (k // BAD_EVERY) % 2 else commands).publish(bad)
            joints.publish(bad)
            newest[0] = max(newest[0], bad.header.stamp.sec + bad.header.stamp.nanosec * 1e-9)
        else:
            commands.publish(message(stamp))
            joints.publish(message(stamp))
            newest[0] = stamp

    harness.spin_for(6.0, every=1.0 / RATE, action=publish)
    assert residuals, 'the observer stopped'
    harness.spin_for(IN_FLIGHT)  # residuals of the last samples may still be on their way
    late = len(residuals)
    for node in ('observer', 'residual_generator'):
        text = ' '.join(w.message for w in warnings if w.name.endswith(f'/{node}: input'))
        problems = ('NaN', 'shorter', 'joint missing', 'no values')
        for problem in problems + (('backwards',) if node == 'observer' else ()):
            assert problem in text, f'{node}: {problem!r} not named on /diagnostics: {text}'
        assert sum(w.name.endswith(f'/{node}: input') for w in warnings) <= 8  # one a second (6 s)
    assert [e for e in faults if e.level == 'ERROR'] == []

    # /joint_states falls silent: comm_loss of the base within comm_timeout, stamped that long
    # after the newest sample the base sent (a bad one too: the base was not silent then).
    silent_from = now_seconds(decision)
    harness.spin_for(SILENCE)
    lost = [e for e in faults if e.level == 'ERROR']
    assert [(e.wheel, e.fault) for e in lost] == [(None, 'comm_loss')]
    settings = FdiSettings()
    assert lost[0].stamp - newest[0] == pytest.approx(settings.data_timeout, abs=1e-6)
    assert len(residuals) == late
    assert silent_from < lost[0].stamp + 0.5  # raised while silent, not before


def test_fdi_nodes_behind_a_flowing_base_are_a_pipeline_warn_not_a_base_comm_loss(harness):
    """Residuals stop while /joint_states flow (an FDI node starved of CPU, or down): the
    decision says so as a WARN ``pipeline`` status on /diagnostics and raises no fault; when the
    base itself then falls silent, that is its comm_loss, stamped ``data_timeout`` after the
    newest sample it sent."""
    generator, decision, faults, pipeline, residuals = fdi_nodes(
        harness, lambda s: s.name.endswith('decision: pipeline'))
    probe = harness.probe
    joints = probe.create_publisher(JointState, '/joint_states', 10)
    commands = probe.create_publisher(JointState, '/wheel_commands', 10)
    newest = [0.0]

    def publish():
        newest[0] = now_seconds(decision)
        commands.publish(message(newest[0]))
        joints.publish(message(newest[0]))

    harness.spin_for(2.0, every=1.0 / RATE, action=publish)
    assert residuals, 'no residuals before the stall'
    assert pipeline and all(s.level == DiagnosticStatus.OK for s in pipeline)
    harness.executor.remove_node(generator)  # the residual generator stops; the base drives on
    # residuals it published before it stopped may still be on their way: let them arrive
    harness.spin_for(IN_FLIGHT, every=1.0 / RATE, action=publish)
    stopped = len(residuals)
    harness.spin_for(1.0, every=1.0 / RATE, action=publish)
    assert len(residuals) == stopped
    assert [e for e in faults if e.level == 'ERROR'] == []
    assert pipeline[-1].level == DiagnosticStatus.WARN and 'behind or down' in pipeline[-1].message
    harness.spin_for(SILENCE)  # now the base falls silent too
    lost = [e for e in faults if e.level == 'ERROR']
    assert [(e.wheel, e.fault) for e in lost] == [(None, 'comm_loss')]
    assert lost[0].stamp - newest[0] == pytest.approx(FdiSettings().data_timeout, abs=1e-6)


def test_a_stall_check_soon_after_one_that_saw_the_base_raises_no_comm_loss(harness, monkeypatch):
    """A busy host holds the stall timer up; the timer keeps its grid, so an on-time firing can
    follow a late one within milliseconds. Its take finds no new /joint_states sample (none came in
    those milliseconds): that is not data_timeout of silence. Only once the base has been silent
    for data_timeout on the node's clock is it comm_loss, stamped from the newest sample."""
    import youbot_fdi.nodes.decision as decision_node
    decision = harness.add(DecisionNode(context=harness.context))
    timeout = FdiSettings().data_timeout
    clock = [100.0]
    monkeypatch.setattr(decision_node, 'now_seconds', lambda _node: clock[0])
    waiting = [message(99.99)]  # the base's newest sample, not yet taken
    monkeypatch.setattr(decision.base_watch, 'take', lambda: waiting.pop() if waiting else None)
    decision._last_stamp = 100.0 - 1.5 * timeout  # the residuals stopped (the FDI nodes behind)
    decision.check_stall()  # held up: the base flowed meanwhile
    assert decision._behind_since is not None and decision.events == []
    clock[0] += 0.01  # the next slot of the timer's grid
    decision.check_stall()
    assert decision.events == []
    clock[0] += timeout  # a period later, still no sample: the base is silent
    decision.check_stall()
    assert [(e.wheel, e.fault, e.stamp) for e in decision.events] == [
        (None, 'comm_loss', pytest.approx(99.99 + timeout))]


def test_a_wheel_without_readings_is_its_comm_loss_never_a_frozen_encoder(harness):
    """The driver shim gives NaN for a module that did not answer its cycle (issue 33): single
    missing readings are missing data; a wheel silent for the data timeout is that wheel's
    comm_loss (not the base's, not encoder_freeze), and OK once it has answered for heal_time."""
    harness.add(ObserverNode(context=harness.context))
    harness.add(ResidualGeneratorNode(context=harness.context))
    decision = harness.add(DecisionNode(context=harness.context))
    faults = []
    harness.probe.create_subscription(DiagnosticArray, '/youbot_fdi/faults',
                                      lambda m: faults.extend(event_from_status(s) for s in m.status),
                                      LATCHED_QOS)
    joints = harness.probe.create_publisher(JointState, '/joint_states', 10)
    count = [0]
    silent_between = (300, 360)  # samples: 0.6 s without wheel bl

    def publish():
        k = count[0]
        count[0] += 1
        values = [0.0] * 4
        if k % 7 == 3 or silent_between[0] <= k < silent_between[1]:  # one missing now and then
            values[2] = math.nan
        joints.publish(message(now_seconds(decision), values=values))

    harness.spin_for(3.6 + FdiSettings().heal_time + 1.0, every=1.0 / RATE, action=publish)
    changes = [(e.level, e.wheel, e.fault) for e in faults if e.level in ('ERROR', 'OK')]
    assert changes[:2] == [('ERROR', 'wheel_joint_bl', 'comm_loss'), ('OK', 'wheel_joint_bl', 'comm_loss')]
    assert all(wheel == 'wheel_joint_bl' for _, wheel, _ in changes)
