"""Kinematics against the report's equations 3.8 and 3.11-3.14, the driver convention, odometry."""
import math

import numpy as np
import pytest

from youbot_fdi.errors import ModelError
from youbot_fdi.model import integrate_pose, Kinematics, load_model, mecanum4, Odometry, Platform, Wheel

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute

R = 0.0475
K = 0.385  # l + L [m]


@pytest.fixture(scope='module')
def youbot():
    return load_model('youbot').kinematics


def report_inverse(vx, vy, wz):
    """Eq. 3.7 written out."""
    return np.array([vx - vy - K * wz, vx + vy + K * wz, vx + vy - K * wz, vx - vy + K * wz]) / R


def driver_inverse(vx, vy, wz):
    """youbot_driver FourSwedishWheelOmniBaseKinematic (motor frames)."""
    return np.array([-vx + vy + K * wz, vx + vy + K * wz, -vx - vy + K * wz, vx - vy + K * wz]) / R


TWISTS = [(0.3, 0.0, 0.0), (0.0, 0.25, 0.0), (0.0, 0.0, 0.8), (0.2, -0.1, 0.5), (-0.4, 0.3, -1.2)]


@pytest.mark.parametrize('twist', TWISTS)
def test_inverse_kinematics_equals_report_eq_3_8(youbot, twist):
    np.testing.assert_allclose(youbot.inverse(twist), report_inverse(*twist), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('twist', TWISTS)
def test_driver_convention_equals_youbot_driver(youbot, twist):
    wheels = youbot.to_driver(youbot.inverse(twist))
    np.testing.assert_allclose(wheels, driver_inverse(*twist), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(youbot.from_driver(wheels), youbot.inverse(twist), atol=1e-12)


def test_forward_kinematics_equals_report_eq_3_11(youbot):
    report_forward = R / 4 * np.array([[1, 1, 1, 1], [-1, 1, 1, -1],
                                       [-1 / K, 1 / K, -1 / K, 1 / K]])
    np.testing.assert_allclose(youbot.forward_matrix, report_forward, rtol=1e-12, atol=1e-15)
    speeds = np.array([1.0, -2.0, 3.5, 0.25])
    vx = R / 4 * speeds.sum()
    vy = R / 4 * (-speeds[0] + speeds[1] + speeds[2] - speeds[3])
    wz = R / (4 * K) * (-speeds[0] + speeds[1] - speeds[2] + speeds[3])
    np.testing.assert_allclose(youbot.forward(speeds), [vx, vy, wz], rtol=1e-12)


def test_forward_after_inverse_is_identity_and_batches(youbot):
    twists = np.array(TWISTS)
    np.testing.assert_allclose(youbot.forward(youbot.inverse(twists)), twists, atol=1e-12)
    assert youbot.inverse(twists).shape == (len(TWISTS), 4)


def test_forward_drive_turns_left_wheels_negative_in_driver_convention(youbot):
    wheels = youbot.to_driver(youbot.inverse((0.3, 0.0, 0.0)))
    assert wheels[0] < 0 and wheels[2] < 0 and wheels[1] > 0 and wheels[3] > 0


def test_slip_residual_is_zero_for_rigid_motion_only(youbot):
    consistent = youbot.inverse((0.1, 0.2, 0.3))
    np.testing.assert_allclose(youbot.slip_residual(consistent), 0.0, atol=1e-12)
    assert np.linalg.norm(youbot.slip_residual(consistent + [1.0, 0, 0, 0])) > 0.4


def test_mecanum4_builder_matches_the_profile(youbot):
    built = Kinematics(mecanum4(('a', 'b', 'c', 'd'), 0.235, 0.15, R))
    np.testing.assert_allclose(built.jacobian, youbot.jacobian, atol=1e-12)


def test_three_wheel_omni_base_from_configuration_alone():
    kin = load_model('omni3_example').kinematics
    radius, centre_distance = 0.05, 0.2
    # Pure rotation: each tangential wheel turns at w * d / r.
    np.testing.assert_allclose(kin.inverse((0, 0, 1.0)), [centre_distance / radius] * 3, rtol=1e-6)
    # Forward is the exact inverse for three wheels.
    for twist in TWISTS:
        np.testing.assert_allclose(kin.forward(kin.inverse(twist)), twist, atol=1e-9)
    # The front wheel (at +y, heading 180 deg) rolls along -x: forward motion turns it at -v / r.
    np.testing.assert_allclose(kin.inverse((0.5, 0, 0))[0], -0.5 / radius, rtol=1e-9)


def test_degenerate_layouts_are_refused():
    with pytest.raises(ModelError, match='rank'):
        Kinematics(Platform(tuple(Wheel(f'w{i}', 0.1 * i, 0.0, 0.0, math.pi / 2, 0.05)
                                  for i in range(3))))
    with pytest.raises(ModelError, match='roller_angle'):
        Wheel('w', 0.0, 0.0, 0.0, 0.0, 0.05)
    with pytest.raises(ModelError, match='radius'):
        Wheel('w', 0.0, 0.0, 0.0, 1.0, 0.0)
    with pytest.raises(ValueError, match='shape'):
        load_model('youbot').kinematics.inverse([1.0, 2.0])


def test_integrate_pose_straight_and_arc():
    np.testing.assert_allclose(integrate_pose((1.0, 2.0, math.pi / 2), (0.5, 0, 0), 2.0),
                               (1.0, 3.0, math.pi / 2), atol=1e-12)
    # A quarter circle of radius 1 m: v = 1 m/s, w = 1 rad/s for pi/2 s ends at (1, 1, pi/2).
    np.testing.assert_allclose(integrate_pose((0, 0, 0), (1.0, 0, 1.0), math.pi / 2),
                               (1.0, 1.0, math.pi / 2), atol=1e-12)
    with pytest.raises(ValueError):
        integrate_pose((0, 0, 0), (1, 0, 0), -0.1)


def test_odometry_from_wheel_angles_closes_a_circle(youbot):
    odometry = Odometry(youbot)
    twist = np.array([0.2, 0.0, 0.4])  # circle of radius 0.5 m, period 2*pi/0.4 s
    dt, steps = 0.01, int(round(2 * math.pi / 0.4 / 0.01))
    wheel_speed = youbot.inverse(twist)
    odometry.update(np.zeros(4), dt)
    for k in range(1, steps + 1):
        pose = odometry.update(wheel_speed * k * dt, dt)
    np.testing.assert_allclose(pose[:2], 0.0, atol=2e-3)  # back at the start (step rounding)
    np.testing.assert_allclose(odometry.twist, twist, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError):
        odometry.update([0.0, 0.0, float('nan'), 0.0], dt)
