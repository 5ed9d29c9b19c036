"""The virtual youBot and the driver over a virtual CAN bus: units, signs, TMCL, watchdogs, faults."""
import time

import can
import numpy as np
import pytest

from tmcm_rig import forward_command, make_rig
from youbot_fdi.errors import ConfigError
from youbot_fdi.faults import FaultKind
from youbot_fdi.tmcm.driver import CLOCK_TRACKING, Level
from youbot_fdi.tmcm.parameters import AxisParameter, ErrorFlag
from youbot_fdi.tmcm.tmcl import decode_reply_can, TmclCommand, TmclRequest, TmclStatus

@pytest.fixture()
def rig():
    rig = make_rig()
    yield rig
    rig.close()


def tmcl(rig, request, with_checksum=False):
    """Talk to a module like a Trinamic tool: a third bus on the same channel."""
    with can.Bus(interface='virtual', channel=rig.channel,
                 can_filters=[{'can_id': 0x02, 'can_mask': 0x7FF, 'extended': False}]) as tool:
        can_id, payload = request.to_can(with_checksum=with_checksum)
        tool.send(can.Message(arbitration_id=can_id, data=payload, is_extended_id=False))
        message = tool.recv(timeout=2.0)
    assert message is not None, 'no TMCL reply'
    return message if len(message.data) != 7 else decode_reply_can(message.arbitration_id, message.data)


def test_velocity_mode_units_and_signs(rig):
    command = forward_command(rig.model, 0.3)
    sample = rig.run(1.5, 'velocity', command)
    assert command[0] < 0 < command[1]  # left wheels negative in the driver convention
    np.testing.assert_allclose(sample.velocity, command, atol=0.01)  # 1 rpm = 0.004 rad/s
    # Effort: the current that holds the speed against viscous friction, D * w.
    np.testing.assert_allclose(sample.effort, 0.035 * command, rtol=0.05, atol=0.005)
    # Position in rad, consistent with the true wheel angle, driver convention.
    true_angle, _ = rig.base.wheel_state()
    np.testing.assert_allclose(sample.position, true_angle, atol=2e-3)
    twist = rig.model.kinematics.forward(rig.model.kinematics.from_driver(sample.velocity))
    assert twist[0] == pytest.approx(0.3, abs=2e-3) and abs(twist[1]) < 1e-3


def test_a_starved_simulation_still_answers_with_the_state_of_the_moment(rig):
    """Real modules sample their encoders on their own clock. Following the wall clock with no
    CPU for its thread (here: no thread at all), the virtual base still answers each cycle with
    the state of the moment its command was on the bus (it catches up first): the wheels have turned by their
    speed times the time that passed, never the same position twice (which the FDI would read as
    every encoder frozen at once)."""
    command = forward_command(rig.model, 0.3)
    before = rig.run(1.0, 'velocity', command)  # at speed, in lockstep
    rig.base.follow_wall_clock()
    started = time.monotonic()
    time.sleep(0.1)
    rig.driver.cycle()
    rig.settle()
    elapsed = time.monotonic() - started
    rig.driver.close_cycles()
    after = rig.driver.sample()
    turned = after.position - before.position
    assert np.all(np.abs(turned) > 0.5 * np.abs(command) * 0.1)
    assert np.all(np.abs(turned) <= np.abs(command) * (elapsed + 0.01) + 0.01)
    # The driver's clock here is the simulation's, which stood still while the modules' went on:
    # its clock tracking pulls the stamp back by CLOCK_TRACKING of that 0.1 s; sample times are
    # whole milliseconds.
    assert after.stamp - before.stamp >= 0.1 - rig.base.period - CLOCK_TRACKING * 0.1 - 1e-3


def test_effort_mode_is_open_loop_torque(rig):
    effort = np.array([-0.05, 0.05, -0.05, 0.05])  # forward in the driver convention
    sample = rig.run(4.0, 'effort', effort)
    np.testing.assert_allclose(sample.effort, effort, atol=0.002)  # 1 mA = 0.00087 N·m
    np.testing.assert_allclose(sample.velocity, effort / 0.035, rtol=0.02)
    assert all(f & ErrorFlag.TORQUE_MODE for f in sample.error_flags)


def test_command_watchdog_stops_the_wheels(rig):
    rig.run(1.0, 'velocity', forward_command(rig.model))
    assert not rig.driver.command_is_stale()
    sample = rig.run(2.0)  # no new commands: the watchdog (0.25 s) takes over
    assert rig.driver.command_is_stale()
    np.testing.assert_allclose(sample.velocity, 0.0, atol=0.01)
    health = {h.name: h for h in rig.driver.health()}
    assert health['bus'].values['command_watchdog'] == 'tripped'


def test_controller_timeout_stops_a_module_until_cleared(rig):
    """With recover_controller_timeout off, as the original driver: stopped until cleared."""
    from dataclasses import replace
    rig.driver.settings = replace(rig.driver.settings, recover_controller_timeout=False)
    command = forward_command(rig.model)
    rig.run(1.0, 'velocity', command)
    rig.base.advance(0.5)  # no process data for 0.5 s > 0.1 s controller timeout
    sample = rig.run(0.05, 'velocity', command)
    assert all(f & ErrorFlag.TIMEOUT for f in sample.error_flags)
    sample = rig.run(1.5, 'velocity', command)  # commands again, but the flag holds them stopped
    np.testing.assert_allclose(sample.velocity, 0.0, atol=0.01)
    assert {h.name: h.level for h in rig.driver.health()}['wheel_joint_fl'] == Level.ERROR
    assert rig.driver.clear_flags() == []
    sample = rig.run(1.5, 'velocity', command)
    np.testing.assert_allclose(sample.velocity, command, atol=0.01)
    assert not any(f & ErrorFlag.TIMEOUT for f in sample.error_flags)


def test_a_late_cycle_that_trips_the_controller_timeout_is_recovered(rig):
    """A host cycle late by more than GP 90 stops the modules (their timeout flag); once the
    commands flow again the driver clears the flag (SAP 158) and the wheels follow again, counted
    in the bus diagnostics. A stale command (the host's own watchdog) is not recovered from."""
    command = forward_command(rig.model)
    rig.run(1.0, 'velocity', command)
    rig.base.advance(0.5)  # the host stalled for 0.5 s
    sample = rig.step('velocity', command)  # the modules answer its first cycle with the flag
    assert all(f & ErrorFlag.TIMEOUT for f in sample.error_flags)
    assert rig.driver.timeout_recoveries == 0
    sample = rig.run(1.5, 'velocity', command)
    np.testing.assert_allclose(sample.velocity, command, atol=0.01)
    assert not any(f & ErrorFlag.TIMEOUT for f in sample.error_flags)
    assert rig.driver.timeout_recoveries == 4
    bus = {h.name: h for h in rig.driver.health()}['bus']
    assert bus.values['controller_timeouts_cleared'] == '4'
    rig.base.advance(0.5)
    sample = rig.run(1.0)  # no fresh command: the flag stays, nothing is cleared
    assert all(f & ErrorFlag.TIMEOUT for f in sample.error_flags)
    assert rig.driver.timeout_recoveries == 4


def test_motors_off_coasts_with_zero_current(rig):
    rig.run(1.0, 'velocity', forward_command(rig.model))
    rig.driver.motors_off()
    sample = rig.run(0.5, 'velocity', forward_command(rig.model))
    np.testing.assert_allclose(sample.effort, 0.0, atol=1e-9)
    assert np.all(np.abs(sample.velocity) > 0.1)  # still rolling, decelerating by friction


def test_bad_commands_are_rejected_and_counted(rig):
    rig.run(0.2, 'velocity', forward_command(rig.model))
    with pytest.raises(ValueError, match='finite'):
        rig.driver.set_command('velocity', [0.0, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError):
        rig.driver.set_command('velocity', [0.0, 1.0])
    assert rig.driver.rejected_commands == 2
    bus = {h.name: h for h in rig.driver.health()}['bus']
    assert bus.level == Level.WARN and bus.values['rejected_commands'] == '2'


def test_malformed_frames_are_counted_never_fatal(rig):
    with can.Bus(interface='virtual', channel=rig.channel) as rogue:
        for can_id, data in ((0x211, b'\x01'), (0x191, b'\x00' * 3), (0x02, b'\xff' * 2),
                             (0x11, b'\x05\x00'), (0x12, bytes(8))):
            rogue.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        rogue.send(can.Message(arbitration_id=0x211, data=b'x', is_extended_id=True))
    sample = rig.run(0.5, 'velocity', forward_command(rig.model))
    assert sample is not None  # still running
    base_counters, _ = rig.base.transport.snapshot()
    driver_counters, _ = rig.driver.transport.snapshot()
    assert base_counters['malformed'] >= 2 and driver_counters['malformed'] >= 1
    assert base_counters['ignored'] + driver_counters['ignored'] >= 1


def test_tmcl_parameters_like_a_trinamic_tool(rig):
    rig.run(1.0, 'velocity', forward_command(rig.model))
    reply = tmcl(rig, TmclRequest(0x12, TmclCommand.GAP, AxisParameter.ACTUAL_VELOCITY, 0, 0))
    assert reply.status == TmclStatus.SUCCESS and reply.module == 0x12
    expected_rpm = rig.model.drive.wheel_speed_to_rpm(forward_command(rig.model)[1])
    assert reply.value == pytest.approx(expected_rpm, abs=2)
    # PyTrinamic's 8-byte frames, a write, EEPROM store/restore.
    reply = tmcl(rig, TmclRequest(0x13, TmclCommand.SAP, AxisParameter.MAX_CURRENT, 0, 2000), True)
    assert reply.ok and reply.value == 2000
    assert tmcl(rig, TmclRequest(0x13, TmclCommand.GAP, AxisParameter.MAX_CURRENT, 0, 0)).value == 2000
    assert tmcl(rig, TmclRequest(0x13, TmclCommand.RSAP, AxisParameter.MAX_CURRENT, 0, 0)).ok
    assert tmcl(rig, TmclRequest(0x13, TmclCommand.GAP, AxisParameter.MAX_CURRENT, 0, 0)).value == 3564
    # Errors come back as status codes.
    assert tmcl(rig, TmclRequest(0x11, 99, 0, 0, 0)).status == TmclStatus.INVALID_COMMAND
    assert tmcl(rig, TmclRequest(0x11, TmclCommand.GAP, 222, 0, 0)).status == TmclStatus.WRONG_TYPE
    assert tmcl(rig, TmclRequest(0x11, TmclCommand.GAP, 3, 1, 0)).status == TmclStatus.INVALID_VALUE
    assert tmcl(rig, TmclRequest(0x11, TmclCommand.SAP, AxisParameter.ACTUAL_VELOCITY, 0, 5)).status \
        == TmclStatus.WRONG_TYPE
    can_id, payload = TmclRequest(0x11, TmclCommand.GAP, 3, 0, 0).to_can(with_checksum=True)
    with can.Bus(interface='virtual', channel=rig.channel,
                 can_filters=[{'can_id': 0x02, 'can_mask': 0x7FF, 'extended': False}]) as tool:
        tool.send(can.Message(arbitration_id=can_id, data=payload[:7] + bytes([payload[7] ^ 0xFF]),
                              is_extended_id=False))
        answer = tool.recv(timeout=2.0)
    assert decode_reply_can(answer.arbitration_id, answer.data).status == TmclStatus.WRONG_CHECKSUM
    version = tmcl(rig, TmclRequest(0x11, TmclCommand.FIRMWARE_VERSION, 0, 0, 0))
    assert bytes(version.data) == b'1632V200'


MODULES = {0x11: 'wheel_joint_fl', 0x12: 'wheel_joint_fr', 0x13: 'wheel_joint_bl',
           0x14: 'wheel_joint_br'}  # TMCL module address -> wheel (both drive signs)


@pytest.mark.parametrize('address', sorted(MODULES))
def test_tmcl_motion_commands_drive_every_module(rig, address):
    """ROR/ROL/MST and a relative MVP on each module, whatever its drive sign: the module's own
    velocity and position (driver convention) do what TMCL asked."""
    wheel = MODULES[address]
    assert tmcl(rig, TmclRequest(address, TmclCommand.ROR, 0, 0, 1000)).ok
    rig.base.advance(1.0)
    assert rig.base.status(wheel).velocity == pytest.approx(1000, abs=3)
    assert tmcl(rig, TmclRequest(address, TmclCommand.ROL, 0, 0, 500)).ok
    rig.base.advance(1.0)
    assert rig.base.status(wheel).velocity == pytest.approx(-500, abs=3)
    assert tmcl(rig, TmclRequest(address, TmclCommand.MST, 0, 0, 0)).ok
    rig.base.advance(1.0)
    assert abs(rig.base.status(wheel).velocity) <= 2
    start = rig.base.status(wheel).position
    assert tmcl(rig, TmclRequest(address, TmclCommand.MVP, 1, 0, 20000)).ok  # relative move
    rig.base.advance(3.0)
    assert rig.base.status(wheel).position == pytest.approx(start + 20000, abs=50)
    assert abs(rig.base.status(wheel).velocity) <= 20
    assert tmcl(rig, TmclRequest(address, TmclCommand.MVP, 0, 0, start - 5000)).ok  # absolute move
    rig.base.advance(3.0)
    assert rig.base.status(wheel).position == pytest.approx(start - 5000, abs=50)


# ---- faults: each shows in the driver's samples as it would on a robot ----

def nominal_and_faulty(kind, wheel, seconds, command_kind, command, before=1.0):
    results = []
    for inject in (False, True):
        rig = make_rig()
        try:
            rig.run(before, command_kind, command)
            if inject:
                rig.base.inject(kind, wheel)
            results.append((rig.run(seconds, command_kind, command), rig.driver.health(),
                            rig.base.wheel_state()))
        finally:
            rig.close()
    return results


def forward(model_speed=0.3):
    from youbot_fdi.model import load_model
    return forward_command(load_model('youbot'), model_speed)


def test_torque_loss_lowers_speed_at_the_same_current():
    effort = np.array([-0.05, 0.05, -0.05, 0.05])
    (nominal, _, _), (faulty, _, _) = nominal_and_faulty(FaultKind.TORQUE_LOSS, 'wheel_joint_fr',
                                                         3.0, 'effort', effort)
    np.testing.assert_allclose(faulty.effort, nominal.effort, atol=0.002)  # current looks normal
    assert abs(faulty.velocity[1]) < 0.8 * abs(nominal.velocity[1])


def test_stuck_wheel_stops_while_the_loop_pushes_current():
    (nominal, _, _), (faulty, _, _) = nominal_and_faulty(FaultKind.STUCK, 'wheel_joint_bl', 1.0,
                                                         'velocity', forward())
    assert abs(faulty.velocity[2]) < 0.05 and abs(nominal.velocity[2]) > 6.0
    assert abs(faulty.effort[2]) > 5 * abs(nominal.effort[2])


def test_friction_needs_more_current_for_the_same_speed():
    (nominal, _, _), (faulty, _, _) = nominal_and_faulty(FaultKind.FRICTION, 'wheel_joint_br', 2.0,
                                                         'velocity', forward())
    assert faulty.velocity[3] == pytest.approx(nominal.velocity[3], abs=0.05)
    assert abs(faulty.effort[3]) > 3 * abs(nominal.effort[3])


def test_runaway_wheel_keeps_driving_after_the_command_stops():
    rig = make_rig()
    try:
        rig.run(1.0, 'velocity', forward())
        rig.base.inject(FaultKind.RUNAWAY, 'wheel_joint_fr')
        sample = rig.run(1.5, 'velocity', np.zeros(4))
    finally:
        rig.close()
    assert abs(sample.velocity[1]) > 6.0
    np.testing.assert_allclose(sample.velocity[[0, 2, 3]], 0.0, atol=0.6)  # coupled, but braked


def test_encoder_freeze_freezes_the_reading_not_the_wheel():
    rig = make_rig()
    try:
        rig.run(1.0, 'velocity', forward())
        rig.base.inject(FaultKind.ENCODER_FREEZE, 'wheel_joint_fl')
        first = rig.run(0.2, 'velocity', forward())
        second = rig.run(1.0, 'velocity', forward())
        true_angle, _ = rig.base.wheel_state()
    finally:
        rig.close()
    assert second.position[0] == first.position[0] and second.velocity[0] == first.velocity[0]
    assert abs(true_angle[0] - second.position[0]) > 1.0  # the wheel itself kept turning


def test_comm_loss_is_reported_and_the_module_times_out():
    rig = make_rig()
    try:
        rig.run(1.0, 'velocity', forward())
        rig.base.inject(FaultKind.COMM_LOSS, 'wheel_joint_bl')
        sample = rig.run(1.0, 'velocity', forward())
        health = {h.name: h for h in rig.driver.health()}
        _, true_speed = rig.base.wheel_state()
    finally:
        rig.close()
    assert sample.age[2] > 0.9 and np.all(sample.age[[0, 1, 3]] < 0.05)
    assert health['wheel_joint_bl'].level == Level.ERROR and 'comm_loss' in health['wheel_joint_bl'].message
    assert abs(true_speed[2]) < 0.7  # its controller timed out and stopped the motor


def test_fault_injection_is_validated(rig):
    with pytest.raises(ConfigError, match='unknown wheel'):
        rig.base.inject(FaultKind.STUCK, 'wheel_joint_xx')
    with pytest.raises(ValueError):
        rig.base.inject('melted', 'wheel_joint_fl')
    rig.base.inject('stuck', 0)
    assert rig.base.faults == {'wheel_joint_fl': FaultKind.STUCK}
    rig.base.clear_faults()
    assert rig.base.faults == {}



def test_lockstep_waits_for_each_frame_to_be_handled_not_only_received():
    """A handler slower than the receive thread's count (the frame counted as received, its
    set-point not yet applied, its reply not yet sent) changes nothing: the lockstep rig steps
    only once every frame's handler has returned, so a slow module gives the same drive."""
    import time
    samples = []
    for delay in (0.0, 0.003):
        rig = make_rig()
        handle = rig.base.transport.handler

        def slow(*frame, handle=handle, delay=delay):
            time.sleep(delay)
            return handle(*frame)

        rig.base.transport.handler = slow
        try:
            command = forward_command(rig.model)
            steps = [rig.step('velocity', command) for _ in range(15)]
            assert None not in steps, 'a step returned before the module had replied'
            samples.append([sample.velocity for sample in steps])
            counters, _ = rig.base.transport.snapshot()
            assert counters['handled'] == counters['received'] > 0
        finally:
            rig.close()
    np.testing.assert_array_equal(samples[1], samples[0])


def test_a_fault_injected_while_the_simulation_lags_the_wall_clock_acts_from_the_wall_clocks_now(rig):
    """Following the wall clock, the simulation may be behind it (waiting for frames not read
    yet): a fault injected now must not act on the simulated past, where samples stamped before
    the injection would already show it."""
    rig.base.follow_wall_clock()
    time.sleep(0.05)  # no thread steps it here: the simulation is 50 ms behind
    rig.base.inject('stuck', 'wheel_joint_fl')
    assert rig.base.faults == {}
    rig.base.advance(0.02)
    assert rig.base.faults == {}
    rig.base.advance(0.04)
    assert rig.base.faults == {'wheel_joint_fl': FaultKind.STUCK}
