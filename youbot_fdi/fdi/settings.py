"""Settings of the FDI core (``config/fdi.yaml``): the uncertainty model and the decision rules.

Every residual r comes with a bound u; the decision compares |r| / u with 1. The bound has a
noise floor (``*_sigma``, learned by ``identify``) plus terms proportional to what the model is
least sure about: inertial torque, the change of current within a sample interval, friction
torque, speed. That keeps the thresholds quiet in transients (report §6.2) without making them
blind in steady state.
"""
from dataclasses import dataclass

from youbot_fdi.errors import ConfigError


@dataclass(frozen=True)
class FdiSettings:
    """Units in the comments; see ``config/fdi.yaml`` for the reasoning behind the defaults."""

    profile: str = 'youbot'
    residual_file: str = ''  # default: config/residuals/<profile's structural model>.yaml
    # torque_<w>: measured minus explained wheel torque [N·m]
    torque_sigma: float = 0.04
    torque_inertia_fraction: float = 0.3
    torque_current_change_fraction: float = 0.6
    torque_friction_fraction: float = 0.4
    # observer_<w>: measured minus current-driven predicted speed [rad/s]
    observer_sigma: float = 0.3
    observer_speed_fraction: float = 0.3
    observer_time_constant: float = 1.0  # [s] of the slow correction
    # command_<w>: velocity mode, measured minus command-path predicted speed [rad/s]
    command_sigma: float = 0.4
    command_speed_fraction: float = 0.15
    command_transient_fraction: float = 1.0
    input_delay: float = 0.0  # a command acts this long after its stamp (``identify`` estimates it) [s]
    command_delay: float = 0.04  # how far the input delay may vary (timing jitter allowance) [s]
    # command_<w>: current mode, measured minus commanded effort [N·m]
    effort_sigma: float = 0.02
    effort_fraction: float = 0.1
    command_timeout: float = 0.25  # the shim's watchdog: older commands mean zero speed [s]
    startup_time: float = 0.5  # the command path is not judged while its prediction settles [s]
    # encoder_<w>: position increment minus speed * dt [rad]
    encoder_sigma: float = 0.002
    encoder_speed_fraction: float = 0.2
    encoder_change_fraction: float = 0.5  # of the speed change within the interval (trapezoid error)
    timing_jitter: float = 0.002  # how far a sample's stamp may be off its sampling instant [s]
    # decision
    persistence: int = 3  # samples over the bound to raise an alarm
    release: int = 50  # samples under the bound to clear it
    frozen_samples: int = 3  # identical readings that count as frozen
    stuck_speed: float = 0.3  # a wheel slower than this with its current up is stuck [rad/s]
    comm_timeout: float = 0.2  # a gap in /joint_states longer than this is comm_loss [s]
    classification_window: float = 0.5  # data used to name the fault type [s]

    def validate(self, source='<settings>'):
        """Raise ConfigError for non-positive scales and counts."""
        problems = [name for name, value in self.__dict__.items()
                    if isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0]
        for name in ('persistence', 'release', 'frozen_samples'):
            if getattr(self, name) < 1:
                problems.append(name)
        for name in ('observer_time_constant', 'comm_timeout', 'command_timeout',
                     'classification_window'):
            if getattr(self, name) <= 0:
                problems.append(name)
        if problems:
            msg = f'{source}: out of range: {sorted(set(problems))}'
            raise ConfigError(msg)
