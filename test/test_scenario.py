"""Scripted drives: steps, and ramps under an acceleration limit (a velocity smoother)."""
import numpy as np
import pytest

from youbot_fdi.errors import ConfigError
from youbot_fdi.model.scenario import AccelerationLimit, DriveScript, load_script

RAW = [{'name': 'forward', 'vx': 0.3, 'duration': 2.0},
       {'name': 'spin', 'wz': 0.8, 'duration': 2.0},
       {'name': 'blip', 'vy': 1.0, 'duration': 0.1},  # too short for its ramp
       {'name': 'diagonal', 'vx': 0.2, 'vy': -0.2, 'duration': 2.0}]
LIMIT = {'linear': 2.5, 'angular': 3.2}
DT = 1e-3  # [s]


def rates(script, duration):
    """(times, twists, rate of change (k-1, 3)) sampled every DT over ``duration`` [s]."""
    times = np.arange(0.0, duration, DT)
    twists = script.twists(times)
    return times, twists, np.diff(twists, axis=0) / DT


def test_without_a_limit_each_segment_is_a_step_held_for_its_duration():
    script = DriveScript.from_config(RAW)
    assert script.max_acceleration is None
    np.testing.assert_array_equal(script.twists([0.0, 1.999, 2.0, 4.05, 4.1, 6.09, 6.1]),
                                  [[0.3, 0, 0], [0.3, 0, 0], [0, 0, 0.8], [0, 1.0, 0],
                                   [0.2, -0.2, 0], [0.2, -0.2, 0], [0, 0, 0]])


def test_ramps_keep_to_both_limits_and_move_every_axis_together():
    script = DriveScript.from_config(RAW, max_acceleration=LIMIT)
    _, twists, rate = rates(script, script.duration + 1.0)
    assert np.hypot(rate[:, 0], rate[:, 1]).max() <= LIMIT['linear'] * (1 + 1e-6)
    assert np.abs(rate[:, 2]).max() <= LIMIT['angular'] * (1 + 1e-6)
    # forward -> spin: 0.3 m/s at 2.5 m/s^2 is 0.12 s, 0.8 rad/s at 3.2 rad/s^2 is 0.25 s;
    # both axes take the longer time, on one straight line
    mid = script.twists([2.0 + 0.125])[0]
    np.testing.assert_allclose(mid, [0.15, 0.0, 0.4], atol=1e-9)
    np.testing.assert_allclose(script.twists([1.0, 2.25, 3.9])[[0, 2]], [[0.3, 0, 0], [0, 0, 0.8]])
    np.testing.assert_allclose(script.twists([2.25])[0], [0, 0, 0.8], atol=1e-9)
    # continuous everywhere: no step left in the command
    assert np.abs(np.diff(twists, axis=0)).max() <= max(LIMIT.values()) * DT * (1 + 1e-6)
    # it starts from rest and ends at rest
    np.testing.assert_array_equal(twists[0], [0, 0, 0])
    np.testing.assert_allclose(twists[-1], [0, 0, 0], atol=1e-12)


def test_a_segment_too_short_for_its_ramp_ends_part_way_and_the_next_ramp_starts_there():
    script = DriveScript.from_config(RAW, max_acceleration=LIMIT)
    end_of_blip = script.twists([4.1])[0]
    # 0.1 s of a ramp from (0, 0, 0.8) to (0, 1, 0): limited by the linear 2.5 m/s^2 (0.4 s) -> 1/4
    np.testing.assert_allclose(end_of_blip, [0.0, 0.25, 0.6], atol=1e-9)
    np.testing.assert_allclose(script.twists([4.1 + 1e-6])[0], end_of_blip, atol=1e-5)
    np.testing.assert_allclose(script.twists([5.0])[0], [0.2, -0.2, 0.0], atol=1e-9)


def test_stretching_a_script_keeps_its_acceleration_limit():
    script = DriveScript.from_config(RAW, max_acceleration=LIMIT)
    stretched = script.scaled_to(2 * script.duration)
    assert stretched.max_acceleration == script.max_acceleration
    _, _, rate = rates(stretched, stretched.duration)
    assert np.hypot(rate[:, 0], rate[:, 1]).max() == pytest.approx(LIMIT['linear'], rel=1e-6)


@pytest.mark.parametrize('raw', [{'linear': 2.5}, {'linear': 2.5, 'angular': 0.0},
                                 {'linear': -1.0, 'angular': 3.2}, {'linear': True, 'angular': 3.2},
                                 {'linear': float('nan'), 'angular': 3.2}, [2.5, 3.2],
                                 {'linear': 2.5, 'angular': 3.2, 'jerk': 1.0}])
def test_a_bad_acceleration_limit_is_a_config_error_that_names_it(raw):
    with pytest.raises(ConfigError, match='max_acceleration'):
        DriveScript.from_config(RAW, 'drive.yaml', max_acceleration=raw)


def test_the_demo_drive_is_smoothed_and_a_script_file_may_leave_the_limit_out(tmp_path):
    _, demo = load_script()
    assert isinstance(demo.max_acceleration, AccelerationLimit)
    path = tmp_path / 'steps.yaml'
    path.write_text('segments:\n  - {vx: 0.3, duration: 1.0}\n')
    _, steps = load_script(path)
    assert steps.max_acceleration is None
    np.testing.assert_array_equal(steps.twists([0.0]), [[0.3, 0, 0]])


def test_as_steps_drops_the_limit_and_keeps_the_segments():
    script = DriveScript.from_config(RAW, max_acceleration=LIMIT)
    steps = script.as_steps()
    assert steps.segments == script.segments and steps.max_acceleration is None
    np.testing.assert_array_equal(steps.twists([2.0]), [[0, 0, 0.8]])
