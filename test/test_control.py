"""The host-side model-based controller (issue 15) and the controller comparison."""
import numpy as np
import pytest

from youbot_fdi.bench.controllers import (CONTROLLERS, FIRMWARE_PI, MODEL_BASED, format_table,
                                          load_controller_settings, run_drive)
from youbot_fdi.errors import ConfigError
from youbot_fdi.model.control import ModelBasedController, ModelBasedSettings
from youbot_fdi.model.firmware import ControlMode
from youbot_fdi.model.profile import load_model
from youbot_fdi.model.scenario import DriveScript
from youbot_fdi.model.simulation import BaseSimulator

CYCLE = 0.01
SHORT = DriveScript.from_config([{'name': 'forward', 'vx': 0.3, 'duration': 1.0},
                                 {'name': 'spin', 'wz': 0.8, 'duration': 1.0}])


def host_loop(model, controller, target, seconds, torque_gain=None):
    """The controller at CYCLE on the exact dynamics (1 ms steps, current mode); speeds over time."""
    simulator = BaseSimulator(model)
    per_cycle = int(round(CYCLE / simulator.step_size))
    speeds = []
    for _ in range(int(round(seconds / CYCLE))):
        current = model.drive.torque_to_current(controller.torque(target, simulator.velocity))
        for _ in range(per_cycle):
            simulator.step(current, ControlMode.CURRENT, torque_gain=torque_gain)
        speeds.append(simulator.velocity.copy())
    return np.array(speeds)


def test_model_based_controller_follows_a_set_point_on_the_model():
    model = load_model('youbot')
    target = model.kinematics.inverse([0.3, 0.0, 0.5])
    controller = ModelBasedController(model, CYCLE, ModelBasedSettings())
    speeds = host_loop(model, controller, target, 1.5)
    np.testing.assert_allclose(speeds[-1], target, atol=0.02 * np.max(np.abs(target)))
    reference = model.drive.max_torque
    assert np.all(np.abs(controller.torque(target, speeds[-1])) < reference)  # no longer clipped


def test_feedback_makes_up_for_a_weak_motor_and_the_integral_does_not_wind_up():
    model = load_model('youbot')
    target = model.kinematics.inverse([0.2, 0.0, 0.0])
    weak = np.array([0.5, 1.0, 1.0, 1.0])  # half the torque on fl: only feedback can tell
    controller = ModelBasedController(model, CYCLE)
    speeds = host_loop(model, controller, target, 2.0, torque_gain=weak)
    np.testing.assert_allclose(speeds[-1], target, atol=0.02 * np.max(np.abs(target)))
    stalled = ModelBasedController(model, CYCLE)  # a blocked wheel: pushed to the limit, no windup
    for _ in range(200):
        torque = stalled.torque(target, np.zeros(4))
    assert np.all(np.abs(torque) <= model.drive.max_torque + 1e-12)
    saturated = np.isclose(np.abs(torque), model.drive.max_torque)
    assert saturated.any()
    assert np.all(stalled.integral[saturated] < 0.1 * 200 * CYCLE * np.abs(target[saturated]))


def test_settings_are_checked_and_read_from_config():
    with pytest.raises(ConfigError, match='bandwidth'):
        ModelBasedSettings(bandwidth=0.0).validate()
    with pytest.raises(ConfigError, match='integral_ratio'):
        ModelBasedSettings(integral_ratio=-1.0).validate()
    assert isinstance(load_controller_settings(), ModelBasedSettings)
    controller = ModelBasedController(load_model('youbot'), CYCLE)
    with pytest.raises(ValueError, match='4 values'):
        controller.torque(np.zeros(3), np.zeros(4))


def test_both_controllers_drive_the_virtual_base_and_compare():
    model = load_model('youbot')
    runs = [run_drive(model, SHORT, c, profile='youbot', drive='short') for c in CONTROLLERS]
    for run in runs:
        assert run.ran and len(run.time) == 200
        linear, angular = run.tracking_error()
        assert linear < 0.05 and angular < 0.15  # steps: most of the error is the first 0.1 s
        assert 0.0 < run.rms_current() <= run.peak_current() <= model.drive.max_current + 0.01
    # a runaway in current mode holds its last current: the wheel speeds up, tracking is lost
    runaway = run_drive(model, SHORT, MODEL_BASED, 'runaway', fault_at=0.5)
    assert runaway.tracking_error()[0] > 2 * runs[1].tracking_error()[0]
    table = format_table(runs + [runaway])
    assert table.count('\n') == 4 and '| youbot | short | none | firmware_pi |' in table
    assert '| runaway | model_based |' in table


def test_the_report_loop_cannot_mix_modes_and_says_so():
    """The seed profile's continuous (report) loop runs all wheels in one mode: a fault that stops
    one wheel under current mode is reported as not simulated, not raised."""
    seed = load_model('seed')
    run = run_drive(seed, SHORT, MODEL_BASED, 'comm_loss', fault_at=0.5, profile='seed')
    assert not run.ran and 'mix' in run.note
    assert 'not simulated' in format_table([run])
    nominal = run_drive(seed, SHORT, FIRMWARE_PI, profile='seed')  # one mode throughout: runs
    assert nominal.ran and nominal.tracking_error()[0] < 0.05
    unseen = run_drive(seed, SHORT, FIRMWARE_PI, 'friction', fault_at=0.5)  # no friction in that loop
    assert not unseen.ran and 'does not model friction' in unseen.note


def test_tracking_rms_is_planar_speed_error_and_yaw_error():
    from youbot_fdi.model.kinematics import tracking_rms
    commanded = [[0.3, 0.0, 0.0], [0.0, 0.0, 1.0]]
    actual = [[0.0, 0.4, 0.0], [0.0, 0.0, 0.0]]  # 0.5 m/s off, then 1 rad/s off
    linear, angular = tracking_rms(commanded, actual)
    assert linear == pytest.approx(np.sqrt(0.25 / 2)) and angular == pytest.approx(np.sqrt(0.5))
