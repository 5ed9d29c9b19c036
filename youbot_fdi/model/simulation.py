"""Step a platform model under the firmware's control modes (plain numpy, no ROS, no CAN).

:class:`BaseSimulator` is the one place where the dynamic model, the drive train and the firmware
loop meet. It predicts wheel speeds from wheel-speed setpoints (velocity mode, report §5.2.3) or
from motor currents (current mode, §5.2.2), one firmware period at a time. The virtual youBot and
the FDI observer build on it.

Values here are in the kinematic convention and SI units at the wheel; currents in A.
"""
from dataclasses import dataclass, replace

import numpy as np

from youbot_fdi.errors import ModelError
from youbot_fdi.model.dynamics import WheelDynamics, zoh_discretize
from youbot_fdi.model.firmware import (ControlMode, LoopKind, VelocityController,
                                       velocity_loop_matrices)


@dataclass(frozen=True)
class SimulationStep:
    """The state at the end of one step; arrays of shape (n,)."""

    time: float  # [s]
    position: np.ndarray  # [rad]
    velocity: np.ndarray  # [rad/s]
    current: np.ndarray  # motor current over the step [A]
    torque: np.ndarray  # wheel torque over the step [N·m]


class BaseSimulator:
    """Wheel dynamics plus firmware, advanced by a fixed step (the firmware period by default).

    Parameters
    ----------
    model : PlatformModel
    step : float, optional
        Step [s]. With a discrete (sampled) velocity loop it must equal the firmware period.
    """

    def __init__(self, model, step=None):
        self.model = model
        firmware = model.firmware
        self.step_size = float(firmware.period if step is None else step)
        self.continuous_loop = firmware.loop == LoopKind.CONTINUOUS
        if not self.continuous_loop and abs(self.step_size - firmware.period) > 1e-12:
            msg = (f'a sampled velocity loop runs at its firmware period {firmware.period:g} s; '
                   f'got step {self.step_size:g} s')
            raise ModelError(msg)
        n = model.kinematics.n_wheels
        self.n_wheels = n
        self.plant = model.dynamics.discretize(self.step_size)
        self.controller = VelocityController(firmware, model.drive.max_current, n)
        if self.continuous_loop:
            a_matrix, b_matrix = velocity_loop_matrices(model.dynamics, model.drive.torque_per_amp,
                                                        firmware)
            self._loop_a, self._loop_b = zoh_discretize(a_matrix, b_matrix, self.step_size)
        self.reset()

    def reset(self, position=None, velocity=None):
        """Set the wheel state [rad], [rad/s] (zero by default) and clear the controller."""
        n = self.n_wheels
        self.time = 0.0
        self.position = np.zeros(n) if position is None else np.array(position, dtype=float)
        self.velocity = np.zeros(n) if velocity is None else np.array(velocity, dtype=float)
        self.controller.reset()

    def set_viscous_friction(self, friction):
        """Change the per-wheel viscous friction D [N·m·s/rad] (fault injection); re-discretises.

        The sampled loop only: the continuous (report) loop keeps its precomputed closed loop.
        """
        friction = tuple(float(v) for v in np.broadcast_to(friction, (self.n_wheels,)))
        parameters = replace(self.model.dynamics.parameters, viscous_friction=friction)
        self.plant = WheelDynamics(self.model.kinematics, parameters).discretize(self.step_size)

    def step(self, setpoint, mode, torque_gain=None, external_torque=None, measured_velocity=None):
        """Advance one step.

        Parameters
        ----------
        setpoint : array_like, shape (n,)
            Per wheel: speed target [rad/s] in velocity mode, current [A] in current mode,
            ignored in stop mode.
        mode : ControlMode or array_like of ControlMode, shape (n,)
            Per-wheel mode (``MOTOR_STOP`` and ``NO_MORE_ACTION`` hold zero speed).
        torque_gain : array_like, shape (n,), optional
            Delivered over commanded torque (1 nominal; fault injection).
        external_torque : array_like, shape (n,), optional
            Extra torque on each wheel [N·m] (fault injection, disturbances).
        measured_velocity : array_like, shape (n,), optional
            What the firmware's velocity loop measures [rad/s] (default: the true speeds;
            fault injection of a frozen encoder).

        Returns
        -------
        SimulationStep
        """
        n = self.n_wheels
        modes = np.broadcast_to(np.asarray(mode, dtype=int), (n,))
        setpoint = np.asarray(setpoint, dtype=float)
        if setpoint.shape != (n,) or not np.all(np.isfinite(setpoint)):
            msg = f'setpoint must be {n} finite values, got {setpoint!r}'
            raise ValueError(msg)
        current_mode = modes == ControlMode.CURRENT
        target = np.where(current_mode, 0.0, np.where(modes == ControlMode.VELOCITY, setpoint, 0.0))
        gain = np.ones(n) if torque_gain is None else np.asarray(torque_gain, dtype=float)
        extra = np.zeros(n) if external_torque is None else np.asarray(external_torque, dtype=float)
        per_amp = self.model.drive.torque_per_amp
        max_current = self.model.drive.max_current

        if self.continuous_loop:
            if np.any(current_mode) and not np.all(current_mode):
                msg = 'the continuous (report) velocity loop cannot mix current and velocity modes'
                raise ModelError(msg)
            if not np.any(current_mode):
                return self._step_continuous(target)

        feedback = self.velocity if measured_velocity is None else np.asarray(measured_velocity)
        current = np.where(current_mode, np.clip(setpoint, -max_current, max_current),
                           self.controller.current(target, feedback, ~current_mode))
        torque = gain * current * per_amp
        self.position, self.velocity = self.plant.step(self.position, self.velocity, torque + extra)
        self.time += self.step_size
        return SimulationStep(self.time, self.position.copy(), self.velocity.copy(), current, torque)

    def _step_continuous(self, target):
        """The report's continuous-time PI on every wheel, discretised exactly (no saturation)."""
        n = self.n_wheels
        firmware = self.model.firmware
        integral = self.controller.integral
        current = firmware.velocity_kp * (target - self.velocity) + firmware.velocity_ki * integral
        state = self._loop_a @ np.concatenate([self.position, self.velocity, integral])
        state += self._loop_b @ target
        self.position, self.velocity = state[:n], state[n:2 * n]
        self.controller.integral = state[2 * n:]
        self.time += self.step_size
        torque = current * self.model.drive.torque_per_amp
        return SimulationStep(self.time, self.position.copy(), self.velocity.copy(), current, torque)

    def run(self, setpoints, mode):
        """Run a sequence of setpoints, one per step.

        Parameters
        ----------
        setpoints : array_like, shape (k, n)
        mode : ControlMode or array_like, shape (n,)

        Returns
        -------
        dict of ndarray
            ``time`` (k,), ``position``, ``velocity``, ``current``, ``torque`` (k, n).
        """
        setpoints = np.asarray(setpoints, dtype=float)
        if setpoints.ndim != 2 or setpoints.shape[1] != self.n_wheels:
            msg = f'setpoints must have shape (k, {self.n_wheels}), got {setpoints.shape}'
            raise ValueError(msg)
        steps = [self.step(row, mode) for row in setpoints]
        return {'time': np.array([s.time for s in steps]),
                **{key: np.array([getattr(s, key) for s in steps])
                   for key in ('position', 'velocity', 'current', 'torque')}}
