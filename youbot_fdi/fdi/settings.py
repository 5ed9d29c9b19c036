"""Settings of the FDI core (``config/fdi.yaml``): the uncertainty model and the decision rules.

Every residual r comes with a bound u, linear in features of the operating point: a noise floor
(``*_sigma``) plus weights (``*_fraction``) of what the model is least sure about: inertial
torque, the change of current within a sample interval, friction torque, speed, command change.
``identify`` fits the floor and the weights on a nominal recording by quantile regression (the
``bound_quantile`` of |r|, times ``bound_margin``); the values here are the defaults without one.
The decision accumulates the evidence of the scores |r| / u over time (a CUSUM), so a small
persistent fault is found and a single spike is not an alarm.
"""
from dataclasses import dataclass
import math

from youbot_fdi.errors import ConfigError
from youbot_fdi.settings import unbounded

INF = math.inf


#: Settings that may be negative: commands stamped after the samples they produce act "early".
SIGNED = ('input_delay',)


@dataclass(frozen=True)
class FdiSettings:
    """Units in the comments; see ``config/fdi.yaml`` for the reasoning behind the defaults."""

    profile: str = 'youbot'
    physics_only: bool = False  # ignore learned corrections in a parameter file (ablation)
    #: a learned correction holds within the operating range of its calibration widened by this
    #: share of the range's span on each side; outside it, the physics alone [-]
    calibration_range_margin: float = 0.1
    #: the WARN "operating point not seen in calibration" ends after this long back inside [s]
    unseen_release: float = 1.0
    residual_file: str = ''  # default: config/residuals/<profile's structural model>.yaml
    # torque_<w>: measured minus explained wheel torque [N·m]
    torque_sigma: float = 0.04
    torque_inertia_fraction: float = 0.3
    torque_current_change_fraction: float = 0.6
    torque_friction_fraction: float = 0.4
    # the contact law's range: a wheel whose rolling share (model/dynamics.py) is below the lowest
    # share seen turning in calibration (``identify`` measures it; 0: no limit) is judged with
    # that much more of its Coulomb level allowed (the law is extrapolated there) [-]
    contact_share_floor: float = 0.0
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
    #: the driver's watchdog: older commands mean zero speed [s] (the shim's; .inf: the driver
    #: holds its last command, which identify finds where a recording shows it)
    command_timeout: float = unbounded(0.25)
    startup_time: float = 0.5  # the command path is not judged while its prediction settles (after a
    # start, and after it took the measured state at a current calibration never saw; velocity
    # mode: at least three of the loop's slowest time constants, residuals.SETTLE_TIME_CONSTANTS) [s]
    # encoder_<w>: position increment minus speed * dt [rad]
    encoder_sigma: float = 0.002
    encoder_speed_fraction: float = 0.2
    encoder_change_fraction: float = 0.5  # of the speed change within the interval (trapezoid error)
    timing_jitter: float = 0.002  # how far a sample's stamp may be off its sampling instant [s]
    #: noise of the speed reading (``identify`` measures it) [rad/s]
    speed_sigma: float = 0.01
    # The range of each bound feature calibration covered (``identify`` records it; inf: none):
    # beyond it a feature's excess is weighed with the larger of its learned and its default weight
    # (the prior's uncertainty), so extrapolation widens the bound (youbot_fdi/fdi/residuals.py).
    torque_feature_range: tuple = (INF,) * 4
    observer_feature_range: tuple = (INF,) * 2
    command_feature_range: tuple = (INF,) * 4
    effort_feature_range: tuple = (INF,) * 2
    encoder_feature_range: tuple = (INF,) * 4
    #: how fast the base drove in calibration: the range of the norm of its wheel speeds while it
    #: moved [rad/s] (identify records it): beyond it, slower or faster, friction is extrapolated
    #: and the bounds allow the gap between its all-Coulomb and all-viscous extrapolations
    calibrated_speed_range: tuple = (0.0, INF)
    #: the largest wheel torque calibration measured [N·m] (inf: none): beyond it the firmware's
    #: current limit may act where calibration never saw it, so the command path does not predict
    calibrated_effort: float = unbounded(INF)
    #: the largest wheel speed no rigid base motion explains that calibration measured, the
    #: wheels' slip [rad/s] (identify records it; inf: none, or a base of three wheels, whose
    #: speeds always fit a motion): beyond it the contacts do not roll as the model assumes
    calibrated_slip: float = unbounded(INF)
    #: while the wheels slip beyond calibrated_slip, and for breakaway_time after, the torque
    #: bound is this many times wider: the rolling contact law it was learned under does not
    #: hold, only evidence clear against it counts [-]
    slip_bound_factor: float = 2.0
    # the platform-wide load condition (floor covering, payload, slope): common-mode rejection
    load_time_constant: float = 0.5  # smoothing of the per-wheel load estimates [s]
    load_allowance: float = 0.5  # share of the load's change to the friction torque the bound allows [-]
    load_warn: float = 0.25  # a load factor this far from 1 is reported (WARN) [-]
    # decision: evidence g_k = max(0, g_{k-1} + min(|r|/u, cap) - drift), alarm at g >= threshold
    evidence_drift: float = 1.0
    evidence_cap: float = 3.0
    #: the evidence each family needs to alarm (torque, observer, command, encoder); identify
    #: raises them where its recording says they would alarm more often than false_alarm_target.
    #: Floors: a dynamic residual at 1.5 bounds for 0.1 s (a transient beyond calibration, one
    #: time constant of a velocity loop) gathers 5; the encoder's is kinematic (config/fdi.yaml)
    family_thresholds: tuple = (5.0, 5.0, 5.0, 3.0)
    #: the false alarms per hour of nominal driving identify sets the thresholds for [1/h]
    false_alarm_target: float = 0.01
    # the torque residual's shift from its recent level (a fault is faster than friction drifts):
    # g_k = max(0, g_{k-1} + min(+-shift/u, cap) - shift_drift), alarm at g >= shift_threshold
    shift_time_constant: float = 3.0  # memory of the recent level [s]
    #: the level is a reference only at the operating point it was learned at: while no wheel's
    #: speed leaves its own mean since it started by more than this share of that mean plus three
    #: speed_sigma (DecisionMaker.operating_point_changes) [-]
    shift_operating_range: float = 0.25
    shift_drift: float = 0.5  # half the shift it is made for: one bound [-]
    shift_threshold: float = 6.0  # [-]
    release_time: float = 0.5  # excited time without evidence that clears an alarm [s]
    #: the time one sample's evidence stands for: a sample counts min(1, dt / this) of it [s]
    evidence_interval: float = 0.01
    shared_window: float = 1.0  # evidence rising on half the wheels within this is shared [s]
    second_fault_score: float = 3.0  # |r|/u from which a later-rising wheel is judged on its own [-]
    frozen_samples: int = 3  # identical readings that count as frozen
    stuck_speed: float = 0.3  # a wheel slower than this with its current up is stuck [rad/s]
    # torque evidence is not accumulated this long after the base leaves rest (every wheel slower
    # than stuck_speed): wheels slip and break static friction until the base catches up [s]
    breakaway_time: float = 0.2
    comm_timeout: float = 0.2  # a gap in /joint_states longer than this is comm_loss [s] ...
    comm_timeout_intervals: float = 15.0  # ... and longer than this many nominal sample intervals
    sample_interval: float = 0.0  # the nominal sample interval (identify measures it; 0: unknown) [s]
    # one wheel without a reading this many samples in a row while the others answer is its
    # comm_loss (identify sets it from the stated rate, fdi/alarm_rate.py; 0: after data_timeout)
    silent_samples: int = 0
    # identify: bounds = bound_margin * the bound_quantile of |r| on the nominal recording
    bound_quantile: float = 0.99
    bound_margin: float = 1.25
    # identify: the prior profile's dynamics as a Gaussian prior, each parameter's standard
    # deviation this share of its value [-]; a parameter is excited by a recording where the data
    # shrink its deviation below excitation_share of the prior's [-]
    prior_inertia_sd: float = 0.5
    prior_friction_sd: float = 1.0
    excitation_share: float = 0.5
    # identify: fit the rollers' drag (model/dynamics.py, roller_drag) with the friction; off:
    # held at the prior profile's value (docs/fdi.md: why it is not on by default)
    fit_roller_drag: bool = False
    # the rollers' drag a floor adds beyond the model's, measured online from what the wheels
    # share (ModelObserver._shared_drag); identify runs without it: calibration is the floor the
    # model is fitted to, and what the physics misses there is for the learned corrections
    shared_drag: bool = True
    # the loop's direction judged where the command path is not (ResidualEvaluator.
    # _excess_pushing_away); identify runs without it: the command bound it fits is the path's
    loop_direction: bool = True
    classification_window: float = 0.5  # data used to name the fault type [s]
    # the event lifecycle (youbot_fdi/fdi/lifecycle.py): an alarm is published once it stood
    # confirm_time, OK once it has been gone heal_time; no two events of a component within dwell
    confirm_time: float = 0.0  # [s]
    heal_time: float = 1.0  # [s]
    dwell: float = 0.5  # [s]

    @property
    def data_timeout(self):
        """The gap in /joint_states [s] that counts as comm_loss: ``comm_timeout``, or longer for a
        base that samples slowly (``comm_timeout_intervals`` nominal intervals)."""
        return max(self.comm_timeout, self.comm_timeout_intervals * self.sample_interval)

    @property
    def wheel_timeout(self):
        """How long [s] one wheel may go without a reading while the others answer before it is
        that wheel's comm_loss: ``silent_samples`` nominal intervals after its first missing
        sample (the silence counts from there), never longer than :attr:`data_timeout`."""
        if self.silent_samples < 1 or self.sample_interval <= 0.0:
            return self.data_timeout
        return min(self.data_timeout, (self.silent_samples - 1) * self.sample_interval)

    def validate(self, source='<settings>'):
        """Raise ConfigError for non-positive scales and counts."""
        problems = [name for name, value in self.__dict__.items()
                    if isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0
                    and name not in SIGNED]
        for name in ('frozen_samples',):
            if getattr(self, name) < 1:
                problems.append(name)
        for name in ('observer_time_constant', 'comm_timeout', 'command_timeout', 'release_time',
                     'evidence_interval',
                     'classification_window', 'load_time_constant', 'false_alarm_target',
                     'evidence_drift', 'shared_window', 'second_fault_score', 'shift_time_constant',
                     'shift_threshold', 'shift_operating_range'):
            if getattr(self, name) <= 0:
                problems.append(name)
        if not 0.5 <= self.bound_quantile < 1.0:
            problems.append('bound_quantile')
        if self.contact_share_floor > 1.0:
            problems.append('contact_share_floor')
        if problems:
            msg = f'{source}: out of range: {sorted(set(problems))}'
            raise ConfigError(msg)
