"""A host-side, model-based wheel controller in current mode (the report's future work, §6).

The firmware PI (velocity mode) closes each wheel's loop on its own at 1 kHz and knows nothing of
the base. :class:`ModelBasedController` runs on the robot PC once per process-data cycle instead
and commands currents: inverse-dynamics feedforward on the identified model (mass matrix ``M``,
viscous ``D`` and Coulomb friction of ``model/dynamics.py``) along a first-order reference, plus
PI feedback in the model's own coordinates,

    tau = M (r_dot + k_p e + k_i ∫e) + D r + tau_c(r),    e = r - theta_dot,

so that each mode of the coupled base sees the same error dynamics (``k_p`` the bandwidth,
``k_i = integral_ratio * k_p²``; 0.25 is critically damped). Torques are clipped at the drive's
maximum; the integral stops while its push is clipped (anti-windup).

Plain numpy, kinematic convention, SI units at the wheel.
"""
from dataclasses import dataclass
import math

import numpy as np

from youbot_fdi.errors import ConfigError


@dataclass(frozen=True)
class ModelBasedSettings:
    """Tuning of :class:`ModelBasedController` (``config/control.yaml``)."""

    bandwidth: float = 25.0  # feedback bandwidth k_p [rad/s]; keep well below 1 / (cycle period)
    integral_ratio: float = 0.25  # k_i / k_p² [-] (0.25: critically damped)
    reference_time_constant: float = 0.03  # first-order reference model of the set-point [s]

    def validate(self, source='<settings>'):
        """Raise ConfigError on a tuning no base can run with."""
        for name in ('bandwidth', 'reference_time_constant'):
            if not getattr(self, name) > 0.0:
                msg = f'{source}: {name} must be > 0, got {getattr(self, name)}'
                raise ConfigError(msg)
        if self.integral_ratio < 0.0:
            msg = f'{source}: integral_ratio must be >= 0, got {self.integral_ratio}'
            raise ConfigError(msg)


class ModelBasedController:
    """Wheel torques [N·m] from wheel-speed set-points and measured speeds [rad/s], one cycle at a time.

    Parameters
    ----------
    model : PlatformModel
        The identified model (its dynamics and drive train).
    period : float
        The host cycle [s] (the process-data cycle).
    settings : ModelBasedSettings
    """

    def __init__(self, model, period, settings=ModelBasedSettings()):
        settings.validate()
        if not period > 0.0:
            msg = f'period must be > 0, got {period}'
            raise ValueError(msg)
        self.dynamics = model.dynamics
        self.n_wheels = model.kinematics.n_wheels
        self.period = float(period)
        self.max_torque = float(model.drive.max_torque)
        self.gain = settings.bandwidth
        self.integral_gain = settings.integral_ratio * settings.bandwidth ** 2
        self.time_constant = settings.reference_time_constant
        self._blend = 1.0 - math.exp(-self.period / self.time_constant)  # exact first-order step
        self.reset()

    def reset(self, speeds=None):
        """Start over from wheel speeds ``speeds`` (n,) [rad/s] (at rest by default)."""
        n = self.n_wheels
        self.reference = np.zeros(n) if speeds is None else np.array(speeds, dtype=float)
        self.integral = np.zeros(n)

    def torque(self, target, measured):
        """The wheel torques (n,) [N·m] for this cycle.

        Parameters
        ----------
        target : array_like, shape (n,)
            Wheel-speed set-points [rad/s].
        measured : array_like, shape (n,)
            Measured wheel speeds [rad/s] (the last process-data reply).
        """
        target = np.asarray(target, dtype=float)
        measured = np.asarray(measured, dtype=float)
        if target.shape != (self.n_wheels,) or measured.shape != (self.n_wheels,):
            msg = f'target and measured must be {self.n_wheels} values each'
            raise ValueError(msg)
        acceleration = (target - self.reference) / self.time_constant
        error = self.reference - measured
        dynamics = self.dynamics
        push = acceleration + self.gain * error + self.integral_gain * self.integral
        wanted = (dynamics.mass_matrix @ push + dynamics.friction_matrix @ self.reference
                  + dynamics.coulomb_torque(self.reference))
        torque = np.clip(wanted, -self.max_torque, self.max_torque)
        clipped = (wanted != torque) & (np.sign(error) == np.sign(wanted))
        self.integral = np.where(clipped, self.integral, self.integral + error * self.period)
        self.reference = self.reference + (target - self.reference) * self._blend
        return torque
