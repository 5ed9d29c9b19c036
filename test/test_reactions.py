"""Fault reactions (issue 15): the wheel allocation without lost wheels and the reaction policy."""
from dataclasses import replace
import math

import numpy as np
import pytest

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.fdi.decision import FaultEvent
from youbot_fdi.fdi.reactions import ReactionSettings, Reactor
from youbot_fdi.model.allocation import Allocation, AllocationError, substitute_readings
from youbot_fdi.model.kinematics import tracking_rms
from youbot_fdi.model.profile import load_model
from youbot_fdi.settings import load_settings

TWIST = np.array([0.3, -0.2, 0.5])  # [m/s, m/s, rad/s]
#: The policy acting on every alarm at once (the confirmation has tests of its own).
IMMEDIATE = ReactionSettings(react=True, confirmation_time=0.0)


def omni_ring(count, radius=0.2, wheel=0.05):
    """The Jacobian of ``count`` omni wheels evenly on a ring (any N)."""
    rows = []
    for k in range(count):
        angle = 2 * math.pi * k / count
        rows.append((-math.sin(angle) / wheel, math.cos(angle) / wheel, radius / wheel))
    return np.array(rows)


@pytest.mark.parametrize('lost', range(4))
def test_youbot_drives_on_three_wheels_with_any_one_lost(lost):
    kinematics = load_model('youbot').kinematics
    allocation = Allocation.for_lost(kinematics.jacobian, [lost])
    rolling = kinematics.inverse(TWIST)
    free = allocation.wheel_speeds(TWIST)  # the lost wheel rolls freely: nothing to make up
    np.testing.assert_allclose(free, rolling, atol=1e-12)
    dragging = rolling[lost] * 0.4  # it drags: the others make up for it
    speeds = allocation.wheel_speeds(TWIST, [dragging])
    measured = speeds.copy()
    measured[lost] = dragging
    np.testing.assert_allclose(kinematics.forward(measured), TWIST, atol=1e-12)
    assert not np.allclose(np.delete(speeds, lost), np.delete(rolling, lost))


def test_n_wheels_and_layouts_that_lose_rank():
    ring = omni_ring(6)
    allocation = Allocation.for_lost(ring, [1, 4])
    speeds = allocation.wheel_speeds(TWIST, [0.0, 0.0])
    measured = speeds.copy()
    measured[[1, 4]] = 0.0
    np.testing.assert_allclose(np.linalg.pinv(ring) @ measured, TWIST, atol=1e-12)
    with pytest.raises(AllocationError, match='rank'):
        Allocation.for_lost(ring, [0, 1, 2, 3])  # two wheels left for three degrees of freedom
    robotino = load_model('robotino').kinematics
    with pytest.raises(AllocationError, match='do not determine'):
        Allocation.for_lost(robotino.jacobian, [0], list(robotino.platform.names))


def test_a_frozen_reading_is_replaced_by_its_kinematic_estimate():
    kinematics = load_model('youbot').kinematics
    true = kinematics.inverse(TWIST)
    frozen = true.copy()
    frozen[2] = 1.234
    np.testing.assert_allclose(substitute_readings(kinematics.jacobian, frozen, [2]), true, atol=1e-12)


def event(level, wheel, fault, stamp=1.0):
    return FaultEvent(stamp, level, wheel, fault)


def test_reactor_follows_the_policy_and_reset_ends_it(tmp_path):
    kinematics = load_model('youbot').kinematics
    settings = load_settings(ReactionSettings, 'kinematics_bridge', _reactions_yaml(tmp_path, react=True))
    assert settings.confirmation_time > 0.0  # shipped: reactions wait for a confirmed alarm
    reactor = Reactor(kinematics, replace(settings, confirmation_time=0.0))
    started = reactor.on_event(event('ERROR', 'wheel_joint_fl', 'torque_loss'))
    assert [(r.level, r.action, r.wheel) for r in started] == [('INFO', 'degrade', 'wheel_joint_fl')]
    assert reactor.degraded == ['wheel_joint_fl'] and not reactor.stopped and reactor.driving_degraded
    slow = 0.3 * TWIST  # within the degraded wheel-speed cap: followed exactly
    np.testing.assert_allclose(kinematics.forward(reactor.wheel_speeds(slow)), slow, atol=1e-12)
    fast = reactor.wheel_speeds(10 * TWIST)  # capped as a whole: same direction, slower
    assert np.max(np.abs(fast)) == pytest.approx(reactor.settings.degraded_max_wheel_speed)
    np.testing.assert_allclose(kinematics.forward(fast) / np.linalg.norm(kinematics.forward(fast)),
                               TWIST / np.linalg.norm(TWIST), atol=1e-12)
    ended = reactor.on_event(event('OK', 'wheel_joint_fl', 'torque_loss', 2.0))
    assert [(r.action, r.wheel) for r in ended] == [('end_degrade', 'wheel_joint_fl')]
    np.testing.assert_allclose(reactor.wheel_speeds(TWIST), kinematics.inverse(TWIST))
    reactor.on_event(event('ERROR', 'wheel_joint_br', 'encoder_freeze', 2.5))
    assert reactor.substituted == ['wheel_joint_br']
    # its module's loop runs on the frozen reading: motor off, driven around like a lost wheel
    assert reactor.degraded == ['wheel_joint_br'] and reactor.driving_degraded
    assert reactor.motors_to_switch_off() == ['wheel_joint_br']
    runaway = reactor.on_event(event('ERROR', 'wheel_joint_bl', 'runaway', 3.0))
    assert runaway[0].action == 'motor_off' and reactor.stopped and not reactor.driving_degraded
    assert sorted(reactor.motors_to_switch_off()) == ['wheel_joint_bl', 'wheel_joint_br']
    np.testing.assert_array_equal(reactor.wheel_speeds(TWIST), np.zeros(4))
    assert reactor.on_event(event('ERROR', None, 'comm_loss'))[0].action == 'stop'
    assert runaway[0].to_dict()['level'] == 'INFO' and 'action' in runaway[0].to_dict()



@pytest.mark.parametrize('condition', ['load_change', 'unseen_operating_point'])
def test_a_base_condition_neither_starts_nor_ends_a_reaction(condition):
    """The base's WARN/OK conditions share the base's component (wheel null) with comm_loss:
    their OK must not end the stop a comm_loss started."""
    reactor = Reactor(load_model('youbot').kinematics, IMMEDIATE)
    assert reactor.on_event(event('ERROR', None, 'comm_loss'))[0].action == 'stop'
    assert reactor.on_event(event('WARN', None, condition, 1.5)) == []
    assert reactor.on_event(event('OK', None, condition, 2.0)) == [] and reactor.stopped
    assert [r.action for r in reactor.on_event(event('OK', None, 'comm_loss', 3.0))] == ['end_stop']
    assert not reactor.stopped


def test_degrading_a_base_that_would_lose_rank_stops_it_instead():
    robotino = load_model('robotino').kinematics
    reactor = Reactor(robotino, IMMEDIATE)
    reactions = reactor.on_event(event('ERROR', robotino.platform.names[0], 'friction'))
    assert [r.action for r in reactions] == ['degrade', 'stop'] and 'rank' in reactions[-1].detail
    assert reactor.stopped
    youbot = Reactor(load_model('youbot').kinematics, IMMEDIATE)
    youbot.on_event(event('ERROR', 'wheel_joint_fl', 'torque_loss'))
    second = youbot.on_event(event('ERROR', 'wheel_joint_br', 'encoder_freeze'))  # two wheels lost
    assert [r.action for r in second] == ['substitute', 'stop', 'stop'] and youbot.stopped


def test_a_reaction_waits_until_its_alarm_has_stood_the_confirmation_time():
    reactor = Reactor(load_model('youbot').kinematics, ReactionSettings(react=True))
    wait = reactor.settings.confirmation_time
    assert reactor.on_event(event('ERROR', 'wheel_joint_fl', 'stuck', 1.0)) == []
    assert reactor.confirm(1.0 + 0.5 * wait) == [] and not reactor.stopped
    assert [r.action for r in reactor.confirm(1.0 + wait)] == ['stop'] and reactor.stopped
    assert reactor.confirm(5.0) == []  # once


def test_an_alarm_cleared_before_its_confirmation_starts_nothing():
    reactor = Reactor(load_model('youbot').kinematics, ReactionSettings(react=True))
    wait = reactor.settings.confirmation_time
    assert reactor.on_event(event('ERROR', 'wheel_joint_fr', 'runaway', 1.0)) == []
    assert reactor.on_event(event('OK', 'wheel_joint_fr', 'runaway', 1.0 + 0.5 * wait)) == []
    assert reactor.confirm(1.0 + 2 * wait) == []
    assert not reactor.stopped and reactor.motors_to_switch_off() == []


@pytest.mark.parametrize('confirmation_time', [0.0, 0.1])
def test_several_wheels_frozen_at_once_are_neither_substituted_nor_stopped(confirmation_time):
    """Two wheels' readings frozen within one confirmation: the data path repeats old readings
    (a base-level data problem); substituting them would stop the base on a false alarm."""
    reactor = Reactor(load_model('youbot').kinematics,
                      ReactionSettings(react=True, confirmation_time=confirmation_time))
    reactions = (reactor.on_event(event('ERROR', 'wheel_joint_fl', 'encoder_freeze', 1.0))
                 + reactor.on_event(event('ERROR', 'wheel_joint_fr', 'encoder_freeze', 1.01))
                 + reactor.confirm(1.01 + confirmation_time))
    if confirmation_time:  # both waited: neither is substituted
        assert [r.action for r in reactions] == ['none', 'none']
        assert reactor.substituted == []
    else:  # the first stood alone when it came; the second is not added to it
        assert [r.action for r in reactions] == ['substitute', 'none']
        assert reactor.substituted == ['wheel_joint_fl']
    assert 'base-level data problem' in reactions[-1].detail
    assert not reactor.stopped


def test_policy_is_validated_and_off_by_default():
    with pytest.raises(ConfigError, match='on_stuck'):
        ReactionSettings(on_stuck='explode').validate()
    with pytest.raises(ConfigError, match='confirmation_time'):
        ReactionSettings(confirmation_time=-1.0).validate()
    reactor = Reactor(load_model('youbot').kinematics)
    assert reactor.on_event(event('ERROR', 'wheel_joint_fl', 'stuck')) == []
    assert not reactor.stopped


def _reactions_yaml(folder, react):
    """config/reactions.yaml with ``react`` set (the shipped file, parsed as a node would)."""
    text = (config_dir() / 'reactions.yaml').read_text().replace('react: false', f'react: {str(react).lower()}')
    path = folder / 'reactions.yaml'
    path.write_text(text)
    return path


def _degraded_drive(kinematics_model, fault, react, cap, **magnitudes):
    """A drive in lockstep with ``fault`` on fl at 0.5 s, its reaction (if any) at 0.6 s; the RMS
    linear tracking error [m/s] from the fault on, against the simulator's true velocity."""
    from youbot_fdi.model.scenario import DriveScript
    from youbot_fdi.tmcm.lockstep import LockstepBase
    kinematics = kinematics_model.kinematics
    script = DriveScript.from_config([{'name': 'forward', 'vx': 0.3, 'duration': 2.5}])
    reactor = Reactor(kinematics, replace(IMMEDIATE, degraded_max_wheel_speed=cap))
    cycle, commanded, actual, measured = 0.01, [], [], None
    with LockstepBase(kinematics_model, cycle, **magnitudes) as rig:
        for k in range(int(script.duration / cycle)):
            t = k * cycle
            if k == 50:
                rig.base.inject(fault, 'wheel_joint_fl')
            if react and k == 60:
                reactor.on_event(event('ERROR', 'wheel_joint_fl', fault, t))
            twist = script.twists([t])[0]
            sample = rig.step('velocity', kinematics.to_driver(reactor.wheel_speeds(twist, measured)))
            measured = reactor.readings(kinematics.from_driver(sample.velocity))
            if k >= 50:
                commanded.append(twist)
                actual.append(kinematics.forward(kinematics.from_driver(rig.base.wheel_state()[1])))
    return tracking_rms(commanded, actual)[0]


@pytest.mark.parametrize('fault, magnitudes', [('torque_loss', {'torque_loss_gain': 0.0}),
                                               ('friction', {'friction_factor': 30.0})])
def test_degraded_driving_halves_the_tracking_error_of_a_wheel_that_cannot_follow(fault, magnitudes):
    """A dead motor or a dragging wheel in velocity mode: the other three wheels, solved given its
    measured speed, carry the base; at least half the tracking error goes under the configured
    degraded cap (config/reactions.yaml). In this model (the body twist is the least-squares twist
    of all wheels) they run up to twice their rolling speed, so the cap matters: at the nominal
    10 rad/s the base is slowed down (docs/nodes.md)."""
    model = load_model('youbot')
    cap = load_settings(ReactionSettings, 'kinematics_bridge',
                        config_dir() / 'reactions.yaml').degraded_max_wheel_speed
    without = _degraded_drive(model, fault, False, cap, **magnitudes)
    with_reaction = _degraded_drive(model, fault, True, cap, **magnitudes)
    assert with_reaction <= 0.5 * without
    capped = _degraded_drive(model, fault, True, 10.0, **magnitudes)
    assert capped > with_reaction
