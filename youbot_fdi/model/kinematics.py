"""Omnidirectional wheel kinematics and odometry (plain numpy, no ROS).

Inverse and forward kinematics share one Jacobian, built from the platform geometry. For a wheel at
``(x, y)`` with heading beta, roller angle gamma and radius r, the contact point moves with
``v_c = (v_x - w*y, v_y + w*x)``; the rollers let it slide freely along ``s = (cos(beta+gamma),
sin(beta+gamma))``, so only the component along ``n = (sin(beta+gamma), -cos(beta+gamma))`` is
driven, and ``r*theta_dot*sin(gamma) = n . v_c``. For the youBot this is exactly the report's
eq. 3.8; the forward kinematics is the least-squares (pseudo-inverse) solution, eq. 3.10-3.14.

Two sign conventions exist (see ../shared CONTRACT): the kinematic one of the report and the driver
one of the motor controllers and topics. Methods here work in the kinematic convention;
:meth:`Kinematics.to_driver` and :meth:`Kinematics.from_driver` convert with the per-wheel
``drive_sign`` from configuration.
"""
from dataclasses import dataclass
import math

import numpy as np

from youbot_fdi.errors import ModelError

#: Rank tolerance relative to the largest singular value of the Jacobian [-].
RANK_TOLERANCE = 1e-9
#: Below this |yaw increment| [rad] the pose update uses the series form of sin(x)/x.
SMALL_ANGLE = 1e-6


def determines_twist(jacobian):
    """True when wheel-speed rows ``jacobian`` (m, 3) determine the base twist: rank 3, within
    :data:`RANK_TOLERANCE` of the largest singular value."""
    jacobian = np.asarray(jacobian, dtype=float)
    if len(jacobian) < 3:
        return False
    singular = np.linalg.svd(jacobian, compute_uv=False)
    return bool(singular[-1] > RANK_TOLERANCE * singular[0])


def limit_wheel_speeds(speeds, limit):
    """Wheel speeds (n,) scaled down as a whole so that none exceeds ``limit`` [rad/s] (the base
    keeps its direction)."""
    fastest = float(np.max(np.abs(speeds)))
    return speeds * (limit / fastest) if fastest > limit else speeds


def tracking_rms(commanded, actual):
    """RMS body-velocity tracking error of twists (k, 3) (vx, vy, wz): (linear [m/s], the RMS
    of the planar speed error; angular [rad/s])."""
    error = np.asarray(actual, dtype=float) - np.asarray(commanded, dtype=float)
    return (float(np.sqrt(np.mean(np.sum(error[:, :2] ** 2, axis=1)))),
            float(np.sqrt(np.mean(error[:, 2] ** 2))))


def _as_rows(values, width, name):
    """Return ``values`` as a float64 array of shape (k, width) and whether it was 1-D."""
    array = np.asarray(values, dtype=float)
    single = array.ndim == 1
    array = np.atleast_2d(array)
    if array.ndim != 2 or array.shape[1] != width:
        msg = f'{name} must have shape ({width},) or (k, {width}), got {np.shape(values)}'
        raise ValueError(msg)
    return array, single


class Kinematics:
    """Wheel-speed <-> base-twist mapping of a :class:`~youbot_fdi.model.geometry.Platform`.

    Attributes
    ----------
    jacobian : ndarray, shape (n, 3)
        Wheel speeds [rad/s] (kinematic convention) per base twist ``(v_x [m/s], v_y [m/s],
        w_z [rad/s])``.
    forward_matrix : ndarray, shape (3, n)
        Least-squares inverse of ``jacobian`` (report eq. 3.11 for the youBot).
    roller_jacobian : ndarray, shape (n, 3)
        Speed at which each wheel's contact point slides along its rollers, per base twist, in
        wheel radians per second (the slide speed [m/s] over the wheel radius).
    drive_signs : ndarray, shape (n,)
        Kinematic-to-driver sign per wheel.
    """

    def __init__(self, platform):
        self.platform = platform
        rows, roller_rows = [], []
        for wheel in platform.wheels:
            direction = wheel.heading + wheel.roller_angle
            sin_d, cos_d = math.sin(direction), math.cos(direction)
            scale = wheel.radius * math.sin(wheel.roller_angle)
            driven = np.array([sin_d, -cos_d, -wheel.y * sin_d - wheel.x * cos_d]) / scale
            rows.append(driven)
            # v_c = r theta_dot h + u s (h the heading, s the roller direction): the roller-borne
            # part is u = s . v_c - r theta_dot cos(gamma); per twist, over r.
            slide = np.array([cos_d, sin_d, wheel.x * sin_d - wheel.y * cos_d]) / wheel.radius
            roller_rows.append(slide - math.cos(wheel.roller_angle) * driven)
        self.jacobian = np.array(rows)
        self.roller_jacobian = np.array(roller_rows)
        if not determines_twist(self.jacobian):
            singular = np.linalg.svd(self.jacobian, compute_uv=False)
            msg = (f'the wheel layout of {platform.names} does not determine the base twist '
                   f'(Jacobian rank < 3, singular values {singular})')
            raise ModelError(msg)
        self.forward_matrix = np.linalg.pinv(self.jacobian)
        self._slide_matrix = self.roller_jacobian @ self.forward_matrix  # wheel speeds -> slides
        #: wheel speeds -> their part no rigid base motion explains (n, n) (zero for three wheels)
        self.slip_matrix = np.eye(len(rows)) - self.jacobian @ self.forward_matrix
        #: the parity relations of the wheel torques: an orthonormal basis (n, n - 3) of the wheel
        #: torques no force or torque on the base makes, the null space of the Jacobian's
        #: transpose (rank 3, checked above; empty for three wheels)
        self.parity_basis = np.linalg.svd(self.jacobian.T)[2][3:].T
        self.drive_signs = np.array(platform.drive_signs)

    @property
    def n_wheels(self):
        """Number of wheels."""
        return self.jacobian.shape[0]

    def inverse(self, twist):
        """Wheel speeds [rad/s] (kinematic convention) for a base twist.

        Parameters
        ----------
        twist : array_like, shape (3,) or (k, 3)
            ``(v_x [m/s], v_y [m/s], w_z [rad/s])`` in the base frame.

        Returns
        -------
        ndarray, shape (n,) or (k, n)
        """
        rows, single = _as_rows(twist, 3, 'twist')
        speeds = rows @ self.jacobian.T
        return speeds[0] if single else speeds

    def forward(self, wheel_speeds):
        """Least-squares base twist for wheel speeds (kinematic convention).

        Parameters
        ----------
        wheel_speeds : array_like, shape (n,) or (k, n)
            Wheel speeds [rad/s] (or wheel angle increments [rad], giving a pose increment).

        Returns
        -------
        ndarray, shape (3,) or (k, 3)
            ``(v_x [m/s], v_y [m/s], w_z [rad/s])``.
        """
        rows, single = _as_rows(wheel_speeds, self.n_wheels, 'wheel_speeds')
        twist = rows @ self.forward_matrix.T
        return twist[0] if single else twist

    def to_driver(self, wheel_values):
        """Convert per-wheel values from the kinematic to the driver convention (same shape)."""
        return np.asarray(wheel_values, dtype=float) * self.drive_signs

    def from_driver(self, wheel_values):
        """Convert per-wheel values from the driver to the kinematic convention (same shape)."""
        return np.asarray(wheel_values, dtype=float) * self.drive_signs

    def roller_slide(self, wheel_speeds):
        """How fast each contact point slides along its rollers [wheel rad/s] (the slide speed
        [m/s] over the radius) while the base moves as the wheel speeds say (least squares), shape
        as the input. Zero for a wheel whose contact only rolls; equal to the wheel speed in size
        for an omni wheel whose contact moves at 45° to its rolling direction."""
        return np.asarray(wheel_speeds, dtype=float) @ self._slide_matrix.T

    def slip_residual(self, wheel_speeds):
        """Part of the wheel speeds no rigid base motion explains [rad/s], shape as the input.

        Zero for consistent wheels; for N > 3 wheels a non-zero value means slip or a bad reading.
        """
        return np.asarray(wheel_speeds, dtype=float) @ self.slip_matrix.T

    def slip_speed(self, wheel_speeds):
        """The largest wheel's :meth:`slip_residual` in size [rad/s], shape as the input without
        its last axis."""
        return np.abs(self.slip_residual(wheel_speeds)).max(axis=-1)


def integrate_pose(pose, twist, dt):
    """Advance a planar pose by a body twist held constant for ``dt`` (exact SE(2) exponential).

    Parameters
    ----------
    pose : array_like, shape (3,)
        ``(x [m], y [m], yaw [rad])`` in the odometry frame.
    twist : array_like, shape (3,)
        ``(v_x [m/s], v_y [m/s], w_z [rad/s])`` in the base frame.
    dt : float
        Duration [s], >= 0.

    Returns
    -------
    ndarray, shape (3,)
        The new pose; yaw wrapped to (-pi, pi].
    """
    if not (dt >= 0.0 and math.isfinite(dt)):
        msg = f'dt must be a finite duration >= 0 s, got {dt!r}'
        raise ValueError(msg)
    x, y, yaw = (float(v) for v in pose)
    vx, vy, wz = (float(v) for v in twist)
    phi = wz * dt
    if abs(phi) < SMALL_ANGLE:
        sin_term, cos_term = 1.0 - phi * phi / 6.0, phi / 2.0
    else:
        sin_term, cos_term = math.sin(phi) / phi, (1.0 - math.cos(phi)) / phi
    dx_body = (sin_term * vx - cos_term * vy) * dt
    dy_body = (cos_term * vx + sin_term * vy) * dt
    cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
    new_yaw = math.atan2(math.sin(yaw + phi), math.cos(yaw + phi))
    return np.array([x + cos_yaw * dx_body - sin_yaw * dy_body,
                     y + sin_yaw * dx_body + cos_yaw * dy_body, new_yaw])


@dataclass
class Odometry:
    """Dead reckoning from wheel positions (kinematic convention), as the youBot driver does.

    The first update only latches the wheel positions; the pose starts at ``(0, 0, 0)``.
    """

    kinematics: Kinematics
    pose: np.ndarray = None
    twist: np.ndarray = None
    _last_positions: np.ndarray = None

    def __post_init__(self):
        self.reset()

    def reset(self, pose=(0.0, 0.0, 0.0)):
        """Forget the latched wheel positions and set the pose [m, m, rad]."""
        self.pose = np.array(pose, dtype=float)
        self.twist = np.zeros(3)
        self._last_positions = None

    def update(self, wheel_positions, dt):
        """Integrate the wheel angle increments since the last call.

        Parameters
        ----------
        wheel_positions : array_like, shape (n,)
            Wheel angles [rad], kinematic convention.
        dt : float
            Time since the last call [s]; the twist estimate is the increment over ``dt``.

        Returns
        -------
        ndarray, shape (3,)
            The pose ``(x [m], y [m], yaw [rad])``.
        """
        positions = np.asarray(wheel_positions, dtype=float)
        if positions.shape != (self.kinematics.n_wheels,) or not np.all(np.isfinite(positions)):
            msg = (f'wheel_positions must be {self.kinematics.n_wheels} finite angles, '
                   f'got {wheel_positions!r}')
            raise ValueError(msg)
        if self._last_positions is None:
            self._last_positions = positions
            return self.pose
        if not dt > 0.0:
            msg = f'dt must be > 0 s between odometry updates, got {dt!r}'
            raise ValueError(msg)
        increment = self.kinematics.forward(positions - self._last_positions)
        self._last_positions = positions
        self.twist = increment / dt
        self.pose = integrate_pose(self.pose, self.twist, dt)
        return self.pose
