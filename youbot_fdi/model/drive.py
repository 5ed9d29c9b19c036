"""Motor-side to wheel-side conversions of a geared drive (youBot: Maxon EC 45 flat + 364/9405 gear).

The contract's units: at the wheel rad, rad/s, N·m; at the motor rpm, mA, encoder ticks.

- wheel torque [N·m] = motor current [A] * torque_constant [N·m/A] / gear_ratio
- wheel speed [rad/s] = motor speed [rad/s] * gear_ratio
- wheel angle [rad] = ticks / ticks_per_motor_revolution * 2*pi * gear_ratio

``gear_ratio`` is wheel revolutions per motor revolution (< 1 for a reduction), as in the youBot
driver's configuration.
"""
from dataclasses import dataclass
import math

import numpy as np

SECONDS_PER_MINUTE = 60.0
MILLIAMPS_PER_AMP = 1000.0


@dataclass(frozen=True)
class DriveTrain:
    """Per-wheel motor, gear and encoder constants (the same for every wheel of a base)."""

    gear_ratio: float  # wheel rev per motor rev [-]
    torque_constant: float  # [N·m/A]
    encoder_ticks_per_revolution: float  # per motor revolution [ticks]
    max_current: float  # firmware current limit [A]
    signed_effort: bool = True  # False: the measured current is a magnitude (the FDI signs it)

    @property
    def torque_per_amp(self):
        """Wheel torque per motor current [N·m/A]."""
        return self.torque_constant / self.gear_ratio

    @property
    def max_torque(self):
        """Wheel torque at the current limit [N·m]."""
        return self.max_current * self.torque_per_amp

    def current_to_torque(self, current):
        """Wheel torque [N·m] for motor current [A] (array-like in, ndarray out)."""
        return np.asarray(current, dtype=float) * self.torque_per_amp

    def torque_to_current(self, torque):
        """Motor current [A] for wheel torque [N·m]."""
        return np.asarray(torque, dtype=float) / self.torque_per_amp

    def milliamps_to_torque(self, milliamps):
        """Wheel torque [N·m] for motor current [mA]."""
        return self.current_to_torque(np.asarray(milliamps, dtype=float) / MILLIAMPS_PER_AMP)

    def torque_to_milliamps(self, torque):
        """Motor current [mA] for wheel torque [N·m] (not rounded)."""
        return self.torque_to_current(torque) * MILLIAMPS_PER_AMP

    def rpm_to_wheel_speed(self, rpm):
        """Wheel speed [rad/s] for motor speed [rpm]."""
        return np.asarray(rpm, dtype=float) * (2.0 * math.pi / SECONDS_PER_MINUTE) * self.gear_ratio

    def wheel_speed_to_rpm(self, wheel_speed):
        """Motor speed [rpm] for wheel speed [rad/s] (not rounded)."""
        return (np.asarray(wheel_speed, dtype=float) / self.gear_ratio
                * (SECONDS_PER_MINUTE / (2.0 * math.pi)))

    def ticks_to_wheel_angle(self, ticks):
        """Wheel angle [rad] for motor encoder position [ticks]."""
        return (np.asarray(ticks, dtype=float) / self.encoder_ticks_per_revolution
                * 2.0 * math.pi * self.gear_ratio)

    def wheel_angle_to_ticks(self, angle):
        """Motor encoder position [ticks] for wheel angle [rad] (not rounded)."""
        return (np.asarray(angle, dtype=float) / (2.0 * math.pi * self.gear_ratio)
                * self.encoder_ticks_per_revolution)
