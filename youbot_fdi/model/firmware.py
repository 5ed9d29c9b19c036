"""Emulation of the TMCM motor firmware's control modes on the wheel dynamics.

The youBot's controllers (report Fig. 5.3) cascade position -> velocity -> current loops. The
current loop runs at tens of kHz and is treated as ideal here: the commanded current (clipped to
the limit) is the motor current. What the model emulates:

- current mode (report §5.2.2, open loop): wheel torque = current * torque_constant / gear_ratio;
- velocity mode (report §5.2.3): a PI loop from wheel-speed error to current, sampled every
  ``period`` (1 ms on the youBot, "PID control time"), with integral clipping and the current limit;
- stop: velocity mode with a zero target.

Gains are in wheel units: ``velocity_kp`` [A/(rad/s)], ``velocity_ki`` [A/rad]. A firmware gain in
mA/rpm converts with ``kp_wheel = kp_motor / 1000 * 60 / (2*pi*gear_ratio)``.

``loop: continuous`` runs the PI in continuous time instead (what the report's Simulink model did):
the closed loop is then discretised exactly and is stable for any gain, but it is not what a
sampled controller does. With the report's stiff inertias a *sampled* 1 kHz loop with the report's
gains is unstable: :func:`sampled_loop_spectral_radius` shows it.
"""
from dataclasses import dataclass
import enum

import numpy as np

from youbot_fdi.model.dynamics import zoh_discretize


class ControlMode(enum.IntEnum):
    """TMCM controller modes (youBot driver ``ProtocolDefinitions.hpp`` values)."""

    MOTOR_STOP = 0
    POSITION = 1
    VELOCITY = 2
    NO_MORE_ACTION = 3
    CURRENT = 6


class LoopKind(str, enum.Enum):
    """How the velocity PI is simulated."""

    DISCRETE = 'discrete'
    CONTINUOUS = 'continuous'


@dataclass(frozen=True)
class FirmwareParameters:
    """Velocity-loop settings of the motor firmware."""

    period: float  # PID control time [s]
    velocity_kp: float  # [A/(rad/s)] at the wheel
    velocity_ki: float  # [A/rad] at the wheel
    loop: LoopKind = LoopKind.DISCRETE


def velocity_loop_matrices(dynamics, torque_per_amp, firmware):
    """Continuous closed-loop state space of the velocity PI on every wheel (no saturation).

    State ``[theta (n); theta_dot (n); integral of speed error (n)]``, input the wheel-speed
    targets [rad/s].

    Returns
    -------
    a_matrix : ndarray, shape (3n, 3n)
    b_matrix : ndarray, shape (3n, n)
    """
    n = dynamics.n_wheels
    eye = np.eye(n)
    gain_p = torque_per_amp * firmware.velocity_kp
    gain_i = torque_per_amp * firmware.velocity_ki
    m_inv = dynamics.mass_inverse
    a_matrix = np.zeros((3 * n, 3 * n))
    a_matrix[:n, n:2 * n] = eye
    a_matrix[n:2 * n, n:2 * n] = -m_inv @ (dynamics.friction_matrix + gain_p * eye)
    a_matrix[n:2 * n, 2 * n:] = m_inv * gain_i
    a_matrix[2 * n:, n:2 * n] = -eye
    b_matrix = np.vstack([np.zeros((n, n)), m_inv * gain_p, eye])
    return a_matrix, b_matrix


def slowest_time_constant(dynamics, torque_per_amp, firmware) -> float:
    """The velocity loop's slowest time constant [s] (no saturation): 1 / the smallest decay rate
    of its speed and integral modes (:func:`velocity_loop_matrices`; the angles only integrate).
    How long a wrong guess of the loop's state takes to fade by e. Without an integral gain the
    integral acts on nothing: only the speed modes count. inf: a mode that never decays."""
    n = dynamics.n_wheels
    a_matrix, _ = velocity_loop_matrices(dynamics, torque_per_amp, firmware)
    return _slowest(a_matrix[n:, n:] if firmware.velocity_ki > 0.0 else a_matrix[n:2 * n, n:2 * n])


def response_time_constant(dynamics, torque_per_amp, firmware) -> float:
    """The velocity loop's slowest proportional time constant [s]: 1 / the smallest decay rate of
    its speed modes under the proportional gain and the friction alone
    (:func:`velocity_loop_matrices` without the integral). How long the torque the loop applies
    after a step of its target takes to fade by e: the step's acceleration happens within it (the
    integral's slower mode takes up the friction, not the step). inf: a mode that never decays."""
    n = dynamics.n_wheels
    a_matrix, _ = velocity_loop_matrices(dynamics, torque_per_amp, firmware)
    return _slowest(a_matrix[n:2 * n, n:2 * n])


def _slowest(modes) -> float:
    """1 / the smallest decay rate of the linear modes ``modes`` (square) [s]; inf: one never decays."""
    rate = float(np.min(-np.linalg.eigvals(modes).real))
    return 1.0 / rate if rate > 0.0 else float('inf')


def sampled_loop_spectral_radius(dynamics, torque_per_amp, firmware):
    """Spectral radius of the sampled (discrete) velocity loop, ignoring saturation.

    Below 1 the loop is stable. The loop measures the speed, updates the integral, and holds the
    resulting torque for one ``firmware.period``.
    """
    n = dynamics.n_wheels
    a_matrix, b_matrix = dynamics.state_space()
    a_d, b_d = zoh_discretize(a_matrix, b_matrix, firmware.period)
    phi, gamma = a_d[n:, n:], b_d[n:, :]
    gain_p = torque_per_amp * firmware.velocity_kp
    gain_i = torque_per_amp * firmware.velocity_ki
    period = firmware.period
    closed = np.block([
        [phi - gamma * (gain_p + gain_i * period), gamma * gain_i],
        [-period * np.eye(n), np.eye(n)],
    ])
    return float(np.max(np.abs(np.linalg.eigvals(closed))))


class VelocityController:
    """The firmware's sampled PI velocity loop for every wheel (state: the error integrals)."""

    def __init__(self, firmware, max_current, n_wheels):
        self.firmware = firmware
        self.max_current = float(max_current)
        self.integral = np.zeros(n_wheels)  # [rad]
        # The integral is clipped so that its share of the current alone cannot exceed the limit.
        self._integral_limit = (self.max_current / firmware.velocity_ki
                                if firmware.velocity_ki > 0.0 else np.inf)

    def reset(self, mask=None):
        """Zero the integrals (of the wheels in boolean ``mask``, or all)."""
        if mask is None:
            self.integral[:] = 0.0
        else:
            self.integral[np.asarray(mask, dtype=bool)] = 0.0

    def current(self, target, measured, active):
        """Current command [A] for the wheels in ``active``; the others' integrals are held at 0.

        Parameters
        ----------
        target, measured : ndarray, shape (n,)
            Wheel-speed target and measurement [rad/s].
        active : ndarray of bool, shape (n,)
            Wheels under velocity control this period.
        """
        error = np.where(active, target - measured, 0.0)
        self.integral = np.clip(np.where(active, self.integral + error * self.firmware.period, 0.0),
                                -self._integral_limit, self._integral_limit)
        command = self.firmware.velocity_kp * error + self.firmware.velocity_ki * self.integral
        return np.clip(command, -self.max_current, self.max_current)
