"""The driver core (``tmcm/driver.py``): one sample per process-data cycle, every wheel's readings
from that cycle; a module that does not answer gets NaN, never its previous reading (issue 33)."""
import can
import numpy as np
import pytest

from tmcm_rig import forward_command, make_rig, new_channel
from youbot_fdi.model import load_model
from youbot_fdi.tmcm.driver import BaseDriver, CLOCK_TRACKING, DriverSettings, MailboxOutcome
from youbot_fdi.tmcm.parameters import AxisParameter
from youbot_fdi.model.firmware import ControlMode
from youbot_fdi.tmcm.process_data import MotorCommand, MotorStatus, ProcessDataIds
from youbot_fdi.tmcm.tmcl import TmclCommand, TmclReply, TmclStatus
from youbot_fdi.timing import CycleTiming, parse_cores


class Clock:
    """A settable driver clock [s]."""

    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture()
def driver():
    """A driver on a bus of its own, fed status frames by hand (no modules)."""
    model = load_model('youbot')
    clock, samples = Clock(), []
    bus = can.Bus(interface='virtual', channel=new_channel())
    made = BaseDriver(model, bus, DriverSettings(), clock=clock, owns_bus=True,
                      on_sample=samples.append)
    made.test_clock, made.test_samples = clock, samples
    yield made
    made.close()


def answer(driver, wheel, cycle, ticks=1000, rpm=500, milliamps=300, sample_time=0):
    """Wheel ``wheel``'s module answers ``cycle`` (its three status frames, as the receive thread
    hands them to the driver)."""
    module = driver.settings.module_ids[wheel]
    status = MotorStatus(ticks, rpm, milliamps, 0, rpm, 2, cycle, sample_time)
    for can_id, payload in zip(ProcessDataIds().status_ids(module), status.encode()):
        driver._on_frame(can_id, payload, 0.0)


def test_a_cycle_is_one_sample_once_every_module_answered(driver):
    driver.cycle()
    cycle = driver.cycle_count
    for wheel in range(3):
        answer(driver, wheel, cycle, ticks=1000 + wheel)
    assert driver.test_samples == []  # not before the last module has answered
    answer(driver, 3, cycle, ticks=1003)
    (sample,) = driver.test_samples
    assert sample.cycle == cycle and sample.answered.all()
    np.testing.assert_allclose(sample.position,
                               driver.drive.ticks_to_wheel_angle(np.arange(1000, 1004)))


def test_a_module_that_does_not_answer_its_cycle_gets_nan_not_its_previous_reading(driver):
    driver.cycle()
    first = driver.cycle_count
    for wheel in range(4):
        answer(driver, wheel, first, ticks=1000)
    driver.test_clock.now += 0.01
    driver.cycle()
    second = driver.cycle_count
    for wheel in (0, 1, 3):  # wheel 2 stays silent
        answer(driver, wheel, second, ticks=2000)
    driver.test_clock.now += 0.5 * driver.settings.answer_timeout
    driver.cycle()
    assert len(driver.test_samples) == 1  # open until its deadline: answer_timeout after it
    driver.test_clock.now += 0.5 * driver.settings.answer_timeout
    driver.cycle()
    sample = driver.test_samples[1]
    assert list(sample.answered) == [True, True, False, True]
    assert np.isnan([sample.position[2], sample.velocity[2], sample.effort[2]]).all()
    np.testing.assert_allclose(sample.position[[0, 1, 3]], driver.drive.ticks_to_wheel_angle(2000))
    assert list(driver.missed_cycles) == [0, 0, 1, 0]
    bus = {h.name: h for h in driver.health()}
    assert bus['wheel_joint_bl'].values['missed_cycles'] == '1'
    assert bus['bus'].values['incomplete_cycles'] == '1'


def test_a_module_that_answers_a_later_cycle_is_missing_from_the_earlier_one_at_once(driver):
    """A module answers its cycles in order: its answer to a later cycle proves the earlier
    answer will not come, so that cycle closes without waiting for answer_timeout."""
    driver.cycle()
    first = driver.cycle_count
    for wheel in (0, 1, 3):
        answer(driver, wheel, first)
    driver.test_clock.now += 0.01
    driver.cycle()
    second = driver.cycle_count
    answer(driver, 2, second)  # wheel 2 skipped the first cycle
    (sample,) = driver.test_samples
    assert sample.cycle == first and list(sample.answered) == [True, True, False, True]
    for wheel in (0, 1, 3):
        answer(driver, wheel, second)
    assert [s.cycle for s in driver.test_samples] == [first, second]
    assert driver.test_samples[1].answered.all() and driver.late_answers == 0


def test_answers_read_a_cycle_late_are_data_not_silence(driver):
    """A busy host's receive thread reads the answers of a cycle after the next cycle went out:
    they were on the bus in time, and both cycles are published whole, in order."""
    driver.cycle()
    first = driver.cycle_count
    driver.test_clock.now += 0.01
    driver.cycle()
    second = driver.cycle_count
    driver.test_clock.now += 0.01
    driver.cycle()
    for cycle in (first, second):
        for wheel in range(4):
            answer(driver, wheel, cycle)
    assert [s.cycle for s in driver.test_samples] == [first, second]
    assert all(s.answered.all() for s in driver.test_samples)
    assert driver.missed_cycles.sum() == 0 and driver.late_answers == 0


def test_an_answer_after_its_cycle_closed_is_dropped_and_counted(driver):
    driver.cycle()
    late = driver.cycle_count
    for wheel in range(3):
        answer(driver, wheel, late)
    driver.test_clock.now += driver.settings.answer_timeout
    driver.cycle()  # answer_timeout later: closes the first cycle without wheel 3
    answer(driver, 3, late)
    assert driver.late_answers == 1
    assert len(driver.test_samples) == 1 and not driver.test_samples[0].answered[3]


def test_a_cycle_fired_right_after_another_leaves_it_open_for_its_answers(driver):
    """A timer catching up fires two cycles a millisecond apart: the first one's answers are on
    their way, not missing."""
    driver.cycle()
    first = driver.cycle_count
    driver.test_clock.now += 0.001
    driver.cycle()
    second = driver.cycle_count
    for wheel in range(4):
        answer(driver, wheel, first)
    for wheel in range(4):
        answer(driver, wheel, second)
    assert [s.cycle for s in driver.test_samples] == [first, second]
    assert all(s.answered.all() for s in driver.test_samples) and driver.missed_cycles.sum() == 0


def reply(driver, wheel, command, status=TmclStatus.SUCCESS):
    """Wheel ``wheel``'s module answers a TMCL ``command`` (as the receive thread hands it over)."""
    host, payload = TmclReply(driver.settings.host_id, driver.settings.module_ids[wheel], int(status),
                              int(command), 0).to_can()
    driver._on_frame(host, payload, 0.0)


def test_a_motor_off_does_not_wait_for_the_module_and_its_reply_is_reported_later(driver):
    """The reaction's stop: the MST frame goes out and the wheel gets 0 mA from the next cycle,
    without waiting for the module's reply (which would hold the cycle); the reply, or its
    absence after tmcl_timeout, is reported afterwards."""
    sent = []
    driver.transport.send = lambda can_id, payload: sent.append((can_id, bytes(payload))) or True
    driver.motor_off('wheel_joint_fr')  # no module on this bus: a waiting call would get None
    driver.motor_off(3)
    assert [TmclCommand(p[0]) for _, p in sent] == [TmclCommand.MST, TmclCommand.MST]
    assert driver.mailbox_outcomes() == []  # nothing settled yet: no reply, timeout not reached
    reply(driver, 1, TmclCommand.MST)
    assert driver.mailbox_outcomes() == [MailboxOutcome('wheel_joint_fr', TmclCommand.MST, True, True)]
    sent.clear()
    driver.set_command('velocity', [1.0] * 4)
    driver.cycle()  # the cycle goes on, with 0 mA for both wheels switched off
    commands = {can_id: MotorCommand.decode(p) for can_id, p in sent}
    modes = [commands[driver.ids.command_id(m)] for m in driver.settings.module_ids]
    assert [(c.mode, c.value) for c in modes][1] == (int(ControlMode.CURRENT), 0)
    assert [(c.mode, c.value) for c in modes][3] == (int(ControlMode.CURRENT), 0)
    assert modes[0].mode == int(ControlMode.VELOCITY) and modes[0].value != 0
    driver.test_clock.now += driver.settings.tmcl_timeout * 1.01
    # silent: not confirmed
    assert driver.mailbox_outcomes() == [MailboxOutcome('wheel_joint_br', TmclCommand.MST, False, False)]
    assert driver.mailbox_outcomes() == []


def test_switching_on_clears_every_module_without_waiting_and_names_a_silent_one(driver):
    """The motors on again: both sticky flags' clearing sent to every module at once; a module
    that answers with an error or not at all is reported, and the others are not."""
    sent = []
    driver.transport.send = lambda can_id, payload: sent.append((can_id, bytes(payload))) or True
    driver.motor_off(0)
    driver.motors_on()
    assert driver.motors_enabled and driver.motors_off_wheels == set()
    clears = [(can_id, p[1]) for can_id, p in sent if TmclCommand(p[0]) is TmclCommand.SAP]
    assert sorted(clears) == sorted((m, int(parameter)) for m in driver.settings.module_ids
                                    for parameter in (AxisParameter.CLEAR_TIMEOUT_FLAG,
                                                      AxisParameter.CLEAR_I2T_FLAG))
    reply(driver, 0, TmclCommand.MST)
    for wheel in (0, 1):
        reply(driver, wheel, TmclCommand.SAP)
    reply(driver, 2, TmclCommand.SAP, TmclStatus.INVALID_VALUE)
    assert driver.mailbox_outcomes() == [MailboxOutcome('wheel_joint_fl', TmclCommand.MST, True, True),
                                         MailboxOutcome('wheel_joint_fl', TmclCommand.SAP, True, True),
                                         MailboxOutcome('wheel_joint_fr', TmclCommand.SAP, True, True),
                                         MailboxOutcome('wheel_joint_bl', TmclCommand.SAP, True, False)]
    driver.test_clock.now += driver.settings.tmcl_timeout * 1.01
    assert driver.mailbox_outcomes() == [MailboxOutcome('wheel_joint_br', TmclCommand.SAP, False, False)]


def test_samples_come_in_cycle_order_one_per_cycle_in_lockstep():
    rig = make_rig()
    delivered = []
    rig.driver.on_sample = delivered.append
    try:
        for _ in range(20):
            rig.step('velocity', forward_command(rig.model))
    finally:
        rig.close()
    assert len(delivered) == 20
    assert all(s.answered.all() for s in delivered)
    stamps = np.array([s.stamp for s in delivered])
    np.testing.assert_allclose(np.diff(stamps), 0.01, atol=1.5e-3)  # the module clock is in ms


def test_a_silent_module_in_lockstep_reads_nan_from_its_first_missed_cycle():
    from youbot_fdi.faults import FaultKind
    rig = make_rig()
    try:
        rig.run(0.5, 'velocity', forward_command(rig.model))
        rig.base.inject(FaultKind.COMM_LOSS, 'wheel_joint_bl')
        sample = rig.step('velocity', forward_command(rig.model))
    finally:
        rig.close()
    assert list(sample.answered) == [True, True, False, True]


def test_cycle_timing_reports_period_lateness_and_late_cycles():
    timing = CycleTiming(0.01, late_after=0.05)
    for now in (0.0, 0.01, 0.02, 0.035, 0.045, 0.145):
        timing.tick(now)
    summary = timing.summary()
    assert summary.cycles == 6 and summary.late_cycles == 1  # the 0.1 s period: 0.09 s late
    assert summary.period_max == pytest.approx(0.1)
    assert summary.lateness_max == pytest.approx(0.09)
    assert summary.period_p50 == pytest.approx(0.01)
    assert summary.values()['period_p50_ms'] == '10.00'


def test_cpu_cores_are_parsed_or_refused_with_the_text():
    assert parse_cores('') == () and parse_cores('1') == (1,) and parse_cores('1, 0') == (0, 1)
    with pytest.raises(ValueError, match='two'):
        parse_cores('two')


def test_unpermitted_scheduling_is_reported_not_fatal():
    from youbot_fdi.timing import apply_scheduling
    lines = apply_scheduling(priority=0, cores=(10_000,))  # no such core
    assert len(lines) == 1 and 'not applied' in lines[0]


def test_a_module_that_fell_silent_holds_up_only_the_first_cycle_it_missed(driver):
    """Once a module has answered nothing for answer_timeout, cycles close as soon as the others
    have answered (its entries NaN): a dead module does not delay every wheel's readings."""
    driver.cycle()
    for wheel in range(4):
        answer(driver, wheel, driver.cycle_count)
    driver.test_clock.now += 0.01
    driver.cycle()
    missed = driver.cycle_count
    for wheel in range(3):  # wheel 3 falls silent
        answer(driver, wheel, missed)
    assert len(driver.test_samples) == 1  # waits: wheel 3's answer may still be on its way
    driver.test_clock.now += driver.settings.answer_timeout
    driver.cycle()  # its deadline: closed without wheel 3
    assert driver.test_samples[-1].cycle == missed
    later = driver.cycle_count
    for wheel in range(3):
        answer(driver, wheel, later)
    assert driver.test_samples[-1].cycle == later  # at once, no deadline waited
    assert list(driver.test_samples[-1].answered) == [True, True, True, False]
    answer(driver, 3, later)  # it answers again: too late for that cycle, counted
    assert driver.late_answers == 1
    driver.test_clock.now += 0.01
    driver.cycle()  # and the next cycle waits for it again
    for wheel in range(3):
        answer(driver, wheel, driver.cycle_count)
    assert driver.test_samples[-1].cycle == later
    answer(driver, 3, driver.cycle_count)
    assert driver.test_samples[-1].answered.all()


def test_a_host_behind_in_reading_the_bus_waits_that_much_longer(driver):
    """Modules answer at once; when this host reads their answers late (the delay of the latest
    answer read), the answers of later cycles are likely still unread, not missing: a cycle
    waits answer_timeout plus that delay (up to another answer_timeout) before its silent
    modules get NaN."""
    timeout = driver.settings.answer_timeout
    driver.cycle()
    first = driver.cycle_count
    driver.test_clock.now += 0.01
    driver.cycle()
    second = driver.cycle_count
    driver.test_clock.now += 0.5 * timeout - 0.01
    for wheel in range(4):  # read half a timeout after the first cycle went out
        answer(driver, wheel, first)
    driver.test_clock.now += timeout
    driver.cycle()  # the second cycle is past answer_timeout, within the host's delay more
    assert [s.cycle for s in driver.test_samples] == [first]
    for wheel in range(4):
        answer(driver, wheel, second)
    assert [s.cycle for s in driver.test_samples] == [first, second]
    assert driver.missed_cycles.sum() == 0
    driver.test_clock.now += 2.0 * timeout
    driver.cycle()
    driver.test_clock.now += 2.0 * timeout  # nobody answers: waited at most two timeouts
    driver.cycle()
    assert driver.silent_cycles >= 1


def test_modules_that_sampled_at_instants_apart_are_separate_samples(driver):
    """A host preempted between sending a cycle's commands: one module sampled 30 ms before the
    others. One stamp for all would misplace its reading by that much; it is a sample of its
    own (NaN for the others), first, with its own time, and nothing is lost."""
    for millisecond in range(3000, 5000, 10):  # the driver learns the modules' clock offset
        driver.cycle()
        for wheel in range(4):
            answer(driver, wheel, driver.cycle_count, sample_time=millisecond)
        driver.test_clock.now += 0.01
    driver.test_samples.clear()
    driver.cycle()
    cycle = driver.cycle_count
    answer(driver, 0, cycle, ticks=1000, sample_time=5000)
    for wheel in (1, 2, 3):
        answer(driver, wheel, cycle, ticks=2000, sample_time=5030)
    early, late = driver.test_samples
    assert list(early.answered) == [True, False, False, False]
    assert list(late.answered) == [False, True, True, True]
    # (the clock tracking moves by CLOCK_TRACKING of each sample's discrepancy)
    assert late.stamp - early.stamp == pytest.approx(0.030, abs=4 * CLOCK_TRACKING * 0.030)
    assert driver.split_cycles == 1 and driver.missed_cycles.sum() == 0
    np.testing.assert_allclose(late.position[1:], driver.drive.ticks_to_wheel_angle(2000))
