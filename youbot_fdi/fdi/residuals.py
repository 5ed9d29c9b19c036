"""Residual generation: every residual the decision uses, from each sample and its prediction.

Inputs are what the robot publishes (CONTRACT.md, driver convention): /joint_states samples
(position, velocity, effort from the measured current), and for each the model's
:class:`~youbot_fdi.fdi.observer.Prediction` (:mod:`youbot_fdi.fdi.observer`, which takes the
/wheel_commands). Internally everything is in the kinematic convention. Residual families, per
wheel ``<w>``:

``torque_<w>``
    Measured wheel torque (mean over the sample interval) minus the torque the exactly discretised
    dynamics need to explain the measured speed change: ``tau - Gamma^-1 (w_k - Phi w_{k-1})``.
    This is the structural analysis' torque residual in discrete form; per wheel even with the dense
    M. Sensitive to actuator and friction faults of wheel w and to every speed sensor.
``observer_<w>``
    Measured speed minus the speed predicted from the measured currents alone by the dynamic model
    (the observer), with a slow correction (``observer_time_constant``). Sensitive to every actuator
    and friction fault and to wheel w's sensor. The Coulomb friction is taken at the measured speed
    (output injection): the observer error then follows linear dynamics, and a recording is
    processed in blocks by a prefix scan instead of sample by sample.
``command_<w>``
    The command path. Velocity mode: measured speed minus the speed the firmware's PI loop would
    reach from the commands (firmware emulation at its own period, with current limit). Current mode:
    measured minus commanded effort. Sensitive to a wheel that does not do what it is told (runaway).
    Coulomb friction at the measured speed, as for the observer; where the loop saturates (current
    or integral limit) it is stepped period by period. In velocity mode also the loop's direction:
    a current pushing the wheel away from its command that rises while the error does not shrink
    is no live PI loop's, nor one that has not fallen by what the error's growth asks of its
    proportional gain (:meth:`ResidualEvaluator._excess_pushing_away`).
``encoder_<w>``
    Position increment minus speed times the interval: a reading that freezes while the wheel moves.

Each residual comes with its bound u (see :mod:`youbot_fdi.fdi.settings`).

:class:`ResidualEvaluator` turns a sample and its prediction into residuals (the
``residual_generator`` node); :class:`ResidualGenerator` runs the observer and the evaluator
together (the replay, the fused ``observer`` node). Each has one implementation, ``update_batch``
for a block of samples (the replay); ``update`` (the live nodes) is a batch of one.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import functools
import math
from typing import TYPE_CHECKING

import numpy as np

from youbot_fdi.errors import ConfigError
from youbot_fdi.fdi.learned import mask_wheels, wheel_mask
from youbot_fdi.fdi.observer import (SPEED_NOISE_SIGMAS, ModelObserver, PredictionBatch, signed_torque,
                                     slip_limit)
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.fdi.recursions import (NEVER, decaying_peak, last_true_value, run_lengths,
                                        scalar_recursion, shifted)
from youbot_fdi.model.firmware import slowest_time_constant
from youbot_fdi.model.kinematics import RANK_TOLERANCE
from youbot_fdi.samples import JointBatch
from youbot_fdi.naming import wheel_suffix

if TYPE_CHECKING:  # names in annotations only
    from collections.abc import Iterable, Sequence
    from youbot_fdi.fdi.learned import TorqueCorrection
    from youbot_fdi.fdi.observer import Prediction
    from youbot_fdi.samples import CommandBatch, CommandSample, JointSample

FAMILIES = ('torque', 'observer', 'command', 'encoder')
#: Signals a frame carries besides its residuals: (label prefix, attribute).
SIGNALS = (('speed', 'velocity'), ('effort', 'torque'), ('commanded', 'command'),
           ('frozen', 'frozen'), ('effort_frozen', 'effort_frozen'),
           ('position_frozen', 'position_frozen'), ('silent', 'silent'),
           ('shift_scale', 'torque_scale'), ('confirmed', 'torque_confirmed'),
           ('friction_level', 'friction_level'))
#: Signals a newer residual generator publishes and an older one's vectors lack: the decision
#: takes them as unset (:meth:`ResidualFrame.signal`).
OPTIONAL_SIGNALS = ('friction_level',)
#: Each bound is linear in its operating-point features: u = sum_j settings[name_j] * feature_j.
#: Per bound, the settings that weigh its features, in feature order (``identify`` fits them by
#: quantile regression on a nominal recording). ``effort`` is the command family in current mode.
BOUND_TERMS = {
    'torque': ('torque_sigma', 'torque_inertia_fraction', 'torque_current_change_fraction',
               'torque_friction_fraction'),
    'observer': ('observer_sigma', 'observer_speed_fraction'),
    'command': ('command_sigma', 'command_speed_fraction', 'command_transient_fraction',
                'command_delay'),
    'effort': ('effort_sigma', 'effort_fraction'),
    'encoder': ('encoder_sigma', 'encoder_speed_fraction', 'encoder_change_fraction',
                'timing_jitter'),
}
#: The torque bound's friction feature (|load x friction level|, BOUND_TERMS order).
FRICTION_FEATURE = BOUND_TERMS['torque'].index('torque_friction_fraction')
#: The command bound's terms of the predicted transient (its distance to the command, its
#: acceleration), which the loop remembers after the transient has ended
#: (:meth:`ResidualEvaluator._remembered_transient`).
COMMAND_TRANSIENT_TERMS = ('command_transient_fraction', 'command_delay')
#: The command bound's noise floor, its constant and speed terms
#: (:meth:`ResidualEvaluator._shared_lag`).
COMMAND_NOISE_TERMS = ('command_sigma', 'command_speed_fraction')
#: A position reading that repeats exactly while the wheel should have turned this many encoder
#: ticks within the interval is evidence of a frozen sensor [ticks].
FROZEN_MIN_TICKS = 2.0
#: An encoder residual is a stopped reading's only where it is at least this share of the larger
#: of the two readings' motions over the interval
#: (:meth:`ResidualEvaluator._stopped_reading_bound`) [-]
STOPPED_SHARE = 0.5
#: How many other wheels must need one lag alike before it is shared (:meth:`_shared_lag`): one
#: wheel's need may be its own fault [-]
MIN_SHARED_LAG_VOTERS = 2
#: A command-path prediction started from a guessed loop state is judged once the guess has faded
#: through this many of the loop's slowest time constants (to e^-3, 5 %) [-]
SETTLE_TIME_CONSTANTS = 3.0


def bound_weights(settings: FdiSettings, family: str) -> np.ndarray:
    """The weights of ``family``'s bound features (:data:`BOUND_TERMS`) in ``settings``, (k,)."""
    return np.array([getattr(settings, name) for name in BOUND_TERMS[family]])


def feature_range(settings: FdiSettings, family: str) -> np.ndarray:
    """The range (k,) of ``family``'s bound features calibration covered (inf: no limit); a
    ConfigError naming the setting when its length does not fit."""
    values = np.asarray(getattr(settings, f'{family}_feature_range'), dtype=float).reshape(-1)
    if len(values) != len(BOUND_TERMS[family]):
        msg = (f'{family}_feature_range has {len(values)} values; {family} bounds have '
               f'{len(BOUND_TERMS[family])} features ({", ".join(BOUND_TERMS[family])})')
        raise ConfigError(msg)
    return values


#: The prior's uncertainty: the default weights (config/fdi.yaml's values), which a feature's
#: excess beyond the calibrated range is weighed with where the learned weight is smaller.
PRIOR_SETTINGS = FdiSettings()


def columns(*values: float | np.ndarray) -> np.ndarray:
    """The arrays (or scalars) ``values``, broadcast together, as the columns of one array
    (..., k): a bound's features (cheaper than stacking broadcast copies)."""
    shape = ()
    for value in values:
        own = getattr(value, 'shape', ())  # a Python float has none
        if own != shape and own:
            shape = np.broadcast_shapes(shape, own) if shape else own
    out = np.empty(shape + (len(values),))
    for j, value in enumerate(values):
        out[..., j] = value
    return out


def by_family(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """The families' arrays ({family: (N, n)}) as one (N, families, n) in FAMILIES order
    (``np.stack(..., axis=1)`` of float arrays, without its per-call cost on the live path)."""
    first = arrays[FAMILIES[0]]
    out = np.empty((len(first), len(FAMILIES)) + first.shape[1:])
    for j, family in enumerate(FAMILIES):
        out[:, j] = arrays[family]
    return out


def scores(values: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """|r| / u; 0 where a residual cannot be computed (NaN: no effort recorded), so it is silent."""
    z = np.abs(values) / bounds
    z[np.isnan(z)] = 0.0
    return z


@dataclass(frozen=True)
class ResidualFrame:
    """Residuals of one sample; per-family arrays of shape (n,) in wheel order."""

    stamp: float  # [s]
    values: dict  # family -> residual (n,)
    bounds: dict  # family -> bound (n,)
    velocity: np.ndarray  # measured, kinematic convention [rad/s]
    torque: np.ndarray  # measured, kinematic convention [N·m] (NaN if not recorded)
    velocity_mode: bool  # the command in force is a speed (True) or a torque (False)
    command: np.ndarray  # in force (after the watchdog), kinematic convention
    frozen: np.ndarray  # consecutive samples with position and speed unchanged (n,) int
    effort_frozen: np.ndarray  # consecutive samples with the effort unchanged too (n,) int
    position_frozen: np.ndarray  # consecutive samples with the position unchanged while moving (n,)
    #: time since each wheel's last reading (0: it has one now; a driver's NaN: it had none) [s]
    silent: np.ndarray
    load_factor: float = 1.0  # the platform-wide friction/load condition (1: as identified) [-]
    #: wheels outside the learned correction's calibrated range (bit mask, see Prediction)
    outside_calibration: float = 0.0
    #: the scale of the torque residual's shift [N·m], in which a steady bias cancels: the torque
    #: bound without its allowances for steady biases (a floor, a load, friction at speeds
    #: calibration did not see), with the change of Coulomb friction a speed the reading cannot
    #: resolve allows (ResidualEvaluator.shift_scale; None: the bound)
    torque_scale: np.ndarray = None
    #: the share (0..1) of each wheel's torque residual a fault of that wheel alone would also
    #: show in the parity relations (:meth:`ResidualEvaluator.parity_confirmed`; None: all)
    torque_confirmed: np.ndarray = None
    #: each wheel's friction level at the load factor [N·m] (the torque bound's friction feature):
    #: the friction whose split into Coulomb and viscous a calibration at one speed cannot pin
    #: down, so its change with the speed is unknown (None: 0, nothing allowed for it)
    friction_level: np.ndarray = None
    #: the batch of one this frame is (:meth:`ResidualBatch.frame`), which the decision takes as
    #: it is instead of building it again (the live path); None for a frame made otherwise
    batch: ResidualBatch | None = field(default=None, repr=False, compare=False)

    def signal(self, name: str) -> np.ndarray:
        """The per-wheel signal ``name`` (a field of :data:`SIGNALS`), an unset one as it stands
        for: the shift scale the torque bound, the confirmed share 1 (all), the friction level 0."""
        value = getattr(self, name)
        if value is not None:
            return value
        if name == 'torque_scale':
            return self.bounds['torque']
        return np.zeros(len(self.velocity)) if name == 'friction_level' else np.ones(len(self.velocity))

    def names(self, wheel_names: Sequence[str]) -> list[str]:
        """Residual names in family-major order, e.g. ``torque_fl``."""
        return [f'{family}_{wheel_suffix(w)}' for family in FAMILIES for w in wheel_names]

    def flat(self) -> tuple[np.ndarray, np.ndarray]:
        """(values, bounds) as flat arrays in :meth:`names` order."""
        return (np.concatenate([self.values[f] for f in FAMILIES]),
                np.concatenate([self.bounds[f] for f in FAMILIES]))

    def scores(self):
        """|r| / u, shape (families, n) in FAMILIES order."""
        return scores(np.stack([self.values[f] for f in FAMILIES]),
                      np.stack([self.bounds[f] for f in FAMILIES]))

    def to_labelled(self, wheel_names: Sequence[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
        """(labels, values, bounds): the residuals, then the signals the decision needs.

        The residuals carry their bounds; the signals (``speed_<w>``, ``torque_<w>``,
        ``command_<w>``, ``frozen_<w>``, ``effort_frozen_<w>``, ``command_mode``: 1 velocity,
        0 effort) have NaN bounds. :meth:`from_labelled` inverts it exactly.
        """
        suffixes = [wheel_suffix(w) for w in wheel_names]
        values, bounds = self.flat()
        labels = self.names(wheel_names)
        signals = []
        for prefix, array in SIGNALS:
            labels += [f'{prefix}_{s}' for s in suffixes]
            signals.append(np.asarray(self.signal(array), dtype=float))
        labels += list(SCALAR_SIGNALS)
        signals.append(np.array([float(self.velocity_mode), self.load_factor,
                                 self.outside_calibration]))
        extra = np.concatenate(signals)
        return (labels, np.concatenate([values, extra]),
                np.concatenate([bounds, np.full(len(extra), np.nan)]))

    @classmethod
    def from_labelled(cls, stamp: float, labels: Sequence[str], values: np.ndarray,
                      bounds: np.ndarray, wheel_names: Sequence[str]) -> ResidualFrame:
        """Rebuild a frame from :meth:`to_labelled` output (matched by label)."""
        index = {label: i for i, label in enumerate(labels)}
        suffixes = [wheel_suffix(w) for w in wheel_names]
        values, bounds = np.asarray(values, dtype=float), np.asarray(bounds, dtype=float)

        def pick(prefix, array):
            try:
                return array[[index[f'{prefix}_{s}'] for s in suffixes]]
            except KeyError as err:
                msg = f'residual vector lacks {err.args[0]}'
                raise ValueError(msg) from None

        signals = {array: (None if array in OPTIONAL_SIGNALS and f'{prefix}_{suffixes[0]}' not in index
                           else pick(prefix, values)) for prefix, array in SIGNALS}
        for label in SCALAR_SIGNALS:
            if label not in index:
                msg = f'residual vector lacks {label}'
                raise ValueError(msg)
        return cls(stamp=stamp,
                   values={f: pick(f, values) for f in FAMILIES},
                   bounds={f: pick(f, bounds) for f in FAMILIES},
                   velocity=signals['velocity'], torque=signals['torque'],
                   velocity_mode=bool(values[index['command_mode']] > 0.5),
                   command=signals['command'],
                   frozen=signals['frozen'].astype(int), effort_frozen=signals['effort_frozen'].astype(int),
                   position_frozen=signals['position_frozen'].astype(int),
                   silent=signals['silent'], torque_scale=signals['torque_scale'],
                   torque_confirmed=signals['torque_confirmed'],
                   friction_level=signals['friction_level'],
                   load_factor=float(values[index['load_factor']]),
                   outside_calibration=float(values[index['outside_calibration']]))



#: The scalar signals of a labelled residual vector, after the per-wheel ones.
SCALAR_SIGNALS = ('command_mode', 'load_factor', 'outside_calibration')
#: The per-row arrays of a ResidualBatch besides ``values`` and ``bounds``.
ROW_ARRAYS = ('stamp', 'velocity', 'torque', 'velocity_mode', 'command', 'frozen', 'effort_frozen',
              'position_frozen', 'silent', 'load_factor', 'command_speed', 'outside_calibration',
              'torque_scale', 'torque_confirmed', 'friction_level')


@dataclass(frozen=True)
class ResidualBatch:
    """The residual frames of a block of samples: ``stamp`` (N,), ``velocity_mode`` (N,) bool,
    everything else (N, n) as in :class:`ResidualFrame` (``values``/``bounds`` per family), and
    ``command_speed``: the speed the command path predicts [rad/s] (kinematic convention),
    ``load_factor`` (N,), and ``features``: family -> (N, n, k) the bound's operating-point
    features (:data:`BOUND_TERMS`; not kept by :meth:`concatenate`)."""

    stamp: np.ndarray
    values: dict
    bounds: dict
    velocity: np.ndarray
    torque: np.ndarray
    velocity_mode: np.ndarray
    command: np.ndarray
    frozen: np.ndarray
    effort_frozen: np.ndarray
    position_frozen: np.ndarray
    silent: np.ndarray
    load_factor: np.ndarray
    command_speed: np.ndarray
    outside_calibration: np.ndarray  # (N,) wheels outside the learned range (bit mask)
    torque_scale: np.ndarray  # (N, n) as in ResidualFrame
    torque_confirmed: np.ndarray  # (N, n) as in ResidualFrame
    friction_level: np.ndarray  # (N, n) as in ResidualFrame [N·m]
    features: dict = None

    def __len__(self):
        return len(self.stamp)

    def frame(self, k: int) -> ResidualFrame:
        """Row ``k`` as a :class:`ResidualFrame`."""
        return ResidualFrame(
            stamp=float(self.stamp[k]), values={f: v[k] for f, v in self.values.items()},
            bounds={f: b[k] for f, b in self.bounds.items()}, velocity=self.velocity[k],
            torque=self.torque[k], velocity_mode=bool(self.velocity_mode[k]),
            command=self.command[k], frozen=self.frozen[k], effort_frozen=self.effort_frozen[k],
            position_frozen=self.position_frozen[k], silent=self.silent[k],
            torque_scale=self.torque_scale[k], torque_confirmed=self.torque_confirmed[k],
            friction_level=self.friction_level[k], load_factor=float(self.load_factor[k]),
            outside_calibration=float(self.outside_calibration[k]),
            batch=self if len(self.stamp) == 1 else None)

    def select(self, rows: np.ndarray | slice) -> ResidualBatch:
        """The rows ``rows`` (index array, mask or slice) as a batch."""
        pick = {f: getattr(self, f)[rows] for f in ROW_ARRAYS}
        return ResidualBatch(values={f: v[rows] for f, v in self.values.items()},
                             bounds={f: b[rows] for f, b in self.bounds.items()},
                             features={f: v[rows] for f, v in (self.features or {}).items()}, **pick)

    def scores(self):
        """|r| / u, shape (N, families, n); 0 where a residual cannot be computed (NaN)."""
        return scores(by_family(self.values), by_family(self.bounds))

    @classmethod
    def of_frames(cls, frames: Iterable[ResidualFrame]) -> ResidualBatch:
        """The :class:`ResidualFrame` s ``frames`` as one batch (a frame without a
        ``torque_scale`` has its torque bound as one; no command-path speed: NaN)."""
        frames = list(frames)
        if len(frames) == 1 and frames[0].batch is not None:  # the live path: the batch it was
            return frames[0].batch
        if len(frames) == 1:  # one frame: views, no copies
            def rows(read):
                return np.asarray(read(frames[0]))[None]
        else:
            def rows(read):
                return np.array([read(f) for f in frames])
        n = len(frames[0].velocity)
        return cls(stamp=rows(lambda f: f.stamp),
                   values={family: rows(lambda f, k=family: f.values[k]) for family in FAMILIES},
                   bounds={family: rows(lambda f, k=family: f.bounds[k]) for family in FAMILIES},
                   velocity=rows(lambda f: f.velocity), torque=rows(lambda f: f.torque),
                   velocity_mode=rows(lambda f: f.velocity_mode),
                   command=rows(lambda f: f.command), frozen=rows(lambda f: f.frozen),
                   effort_frozen=rows(lambda f: f.effort_frozen),
                   position_frozen=rows(lambda f: f.position_frozen), silent=rows(lambda f: f.silent),
                   load_factor=rows(lambda f: f.load_factor), command_speed=np.full((len(frames), n), np.nan),
                   outside_calibration=rows(lambda f: f.outside_calibration),
                   torque_scale=rows(lambda f: f.signal('torque_scale')),
                   torque_confirmed=rows(lambda f: f.signal('torque_confirmed')),
                   friction_level=rows(lambda f: f.signal('friction_level')))

    @classmethod
    def concatenate(cls, batches: Iterable[ResidualBatch]) -> ResidualBatch:
        """One batch of several, in order."""
        batches = list(batches)
        join = {f: np.concatenate([getattr(b, f) for b in batches]) for f in ROW_ARRAYS}
        features = None
        if all(b.features for b in batches):
            features = {f: np.concatenate([b.features[f] for b in batches])
                        for f in batches[0].features}
        return cls(values={f: np.concatenate([b.values[f] for b in batches]) for f in FAMILIES},
                   bounds={f: np.concatenate([b.bounds[f] for b in batches]) for f in FAMILIES},
                   features=features, **join)


class ResidualEvaluator:
    """Residuals and bounds from each /joint_states sample and its model prediction.

    Keeps the last sample (the interval's start) and the frozen-reading counters. A prediction
    spans the interval from ``since`` to its sample: it is used only when ``since`` is the sample
    this evaluator saw last; otherwise (a prediction lost between nodes) the evaluator restarts
    at the sample, counted in ``counters['unpaired']`` (unless it has seen no sample yet: a node
    started after its observer).

    Parameters
    ----------
    model : PlatformModel
    settings : FdiSettings
    """

    def __init__(self, model, settings):
        self.settings = settings
        self.signs = model.kinematics.drive_signs
        self.n = model.dynamics.n_wheels
        self.mass_matrix = model.dynamics.mass_matrix
        self.signed_effort = model.drive.signed_effort
        drive = model.drive
        #: one encoder tick at the wheel [rad]
        self.position_quantum = 2.0 * np.pi * drive.gear_ratio / drive.encoder_ticks_per_revolution
        #: the torque the firmware's proportional gain answers a speed error with, k_p k_t
        #: [N·m per rad/s] (0 without a loop)
        self.loop_stiffness = stiffness = model.firmware.velocity_kp * drive.torque_per_amp
        #: speed lost per unit of unexpected friction under the firmware's proportional gain
        #: [rad/s per N·m] (0 without a loop)
        self.loop_compliance = 1.0 / stiffness if stiffness > 0.0 else 0.0
        #: how fast a wheel's speed answers a torque disturbance under that gain, its own share of
        #: the inertia over the gain's stiffness, M_ii / (k_p k_t) (n,) [s] (0 without a loop)
        self.loop_time_constant = np.diag(model.dynamics.loop.mass_matrix) * self.loop_compliance
        #: its inverse [1/s] (inf for 0 s: no memory; every step is positive)
        self._loop_rate = np.divide(1.0, self.loop_time_constant,
                                    out=np.full(self.n, np.inf), where=self.loop_time_constant > 0.0)
        #: how long a velocity-mode command path started from a guessed state is not judged: the
        #: configured startup_time, or SETTLE_TIME_CONSTANTS of the loop's slowest time constant
        #: if longer [s]. Why: the guess (the integral the measured current implies, by
        #: ``1 / k_i``) fades only as fast as the loop's slowest mode; judged before, a wrong
        #: guess is judged as the wheel's fault. A loop with a weak integral forgets slowly (the
        #: Robotino's identified k_i / k_p = 0.06 /s: 17 s; a youBot's 0.09 s).
        memory = slowest_time_constant(model.dynamics.loop, drive.torque_per_amp, model.firmware)
        self.settle_time = max(settings.startup_time, SETTLE_TIME_CONSTANTS * memory)
        #: how fast the loop forgets an error of the predicted path: 1 / its slowest time
        #: constant [1/s] (0: a mode that never decays)
        self._forget_rate = 1.0 / memory if memory > 0.0 else math.inf
        self._disturbance = np.zeros(self.n)  # that disturbance, low-passed (n,) [N·m]
        #: per wheel, the stretch of pushing away from its command (:meth:`_excess_pushing_away`):
        #: (in one, the torque [N·m], the speed error's size [rad/s] and the speed's rate of
        #: change [rad/s^2] at its start)
        self._away = self._no_stretch()
        #: how long the speed reading may trail the firmware's own (the input delay ``identify``
        #: fits stands for every lag between a command and the reading) [s]
        self._reading_lag = max(0.0, settings.input_delay)
        #: a torque measurably at the drive's current limit (within three ``torque_sigma``) [N·m]
        self._at_limit = drive.max_torque - SPEED_NOISE_SIGMAS * settings.torque_sigma
        #: the command bound's transient the loop still remembers: (reference stamp [s], the
        #: log of its peak carried to it (n,), -inf: none) (:meth:`_remembered_transient`)
        self._transient = (0.0, np.full(self.n, -np.inf))
        #: the same for the torque bound (:meth:`_remembered_torque_extrapolation`)
        self._torque_extrapolated = (0.0, np.full(self.n, -np.inf))
        self._coefficients = {family: bound_weights(settings, family) for family in BOUND_TERMS}
        #: the command features of :data:`COMMAND_TRANSIENT_TERMS`, and their learned weights
        self._transient_terms = [BOUND_TERMS['command'].index(name) for name in COMMAND_TRANSIENT_TERMS]
        self._transient_weights = self._coefficients['command'][self._transient_terms]
        #: the command features of :data:`COMMAND_NOISE_TERMS`, and their learned weights
        self._noise_terms = [BOUND_TERMS['command'].index(name) for name in COMMAND_NOISE_TERMS]
        self._noise_weights = self._coefficients['command'][self._noise_terms]
        self._ranges = {family: feature_range(settings, family) for family in BOUND_TERMS}
        self._calibrated = {family: bool(np.isfinite(r).any()) for family, r in self._ranges.items()}
        #: beyond these the WARN names a wheel: the ranges widened by their margin
        self._warn_ranges = {family: (1.0 + settings.calibration_range_margin) * r
                             for family, r in self._ranges.items()}
        self._beyond = {family: np.maximum(self._coefficients[family],
                                           bound_weights(PRIOR_SETTINGS, family))
                        for family in BOUND_TERMS}
        self.kinematics = model.kinematics
        self.dynamics = model.dynamics
        #: how far a speed reading may be from the speed (SPEED_NOISE_SIGMAS x speed_sigma) [rad/s]
        self._speed_uncertainty = SPEED_NOISE_SIGMAS * settings.speed_sigma
        #: each wheel's share (n,) of the parity relations (``Kinematics.parity_basis``), |B_w|^2:
        #: the wheels they see, and that share (1 for the others, which it does not divide)
        weight = np.sum(self.kinematics.parity_basis ** 2, axis=1)
        self._parity_observable = weight > RANK_TOLERANCE
        self._parity_weight = np.where(self._parity_observable, weight, 1.0)
        #: the wheels slip beyond calibration where the speed no rigid motion explains exceeds
        #: what calibration measured (widened by its margin) and three times the speed
        #: reading's noise on it [rad/s] (inf: never)
        self.slip_limit = slip_limit(settings)
        #: how far (n,) [rad/s] the speed the other wheels' rigid motion gives a wheel
        #: (:meth:`rigid_speed`) may be from its own on nominal data: a part no rigid motion
        #: explains of at most ``slip_limit`` on the wheel's own relation, |(P w)_w| <= slip_limit,
        #: is a wheel error of at most slip_limit / |B_w|^2 (inf: no relation sees the wheel)
        self._rigid_tolerance = np.where(self._parity_observable,
                                         self.slip_limit / self._parity_weight, np.inf)
        #: whether the wheels' speeds can fit no motion of the base (more wheels than its three
        #: degrees of freedom: a part of their speeds no motion explains)
        self.shows_slip = bool(np.abs(self.kinematics.slip_matrix).max() > RANK_TOLERANCE)
        self._slip_stamp = NEVER  # [s] of the last row in which the wheels slipped so
        self._last = None  # (stamp, position, velocity, signed torque), kinematic convention
        self._silent_since = None  # (n,) stamp from which each wheel's silence counts [s]
        self._answering = np.ones(self.n, dtype=bool)  # each wheel read in the last sample
        self._frozen = np.zeros(self.n, dtype=int)
        self._effort_frozen = np.zeros(self.n, dtype=int)
        self._position_frozen = np.zeros(self.n, dtype=int)
        #: how far [rad/s] each wheel's reading stood off the others' rigid motion (its parity
        #: error, ``_standing_off``) in the row its position last moved (inf: none seen)
        self._offset_at_move = np.full(self.n, np.inf)
        self.counters = {'unpaired': 0}

    @property
    def last_stamp(self) -> float | None:
        """Stamp of the last sample taken [s], None before the first."""
        return None if self._last is None else self._last[0]

    def restart(self, sample: JointSample) -> None:
        """(Re)start at ``sample`` (:class:`~youbot_fdi.samples.JointSample`): the one the
        observer restarted at, which has no prediction."""
        position, velocity, torque = (self.signs * a for a in (sample.position, sample.velocity,
                                                               sample.effort))
        self._frozen = np.zeros(self.n, dtype=int)
        self._effort_frozen = np.zeros(self.n, dtype=int)
        self._position_frozen = np.zeros(self.n, dtype=int)
        self._offset_at_move = self._standing_off(self._parity_alone(velocity[None]))[0]  # witness
        # no explained torque yet: the speed's sign
        self._last = (sample.stamp, position, velocity,
                      signed_torque(torque, velocity, self.signed_effort))
        self._started = np.full(self.n, sample.stamp)  # of each wheel's command-path prediction [s]
        self._silent_since = np.full(self.n, sample.stamp)
        self._answering = np.ones(self.n, dtype=bool)
        self._disturbance = np.zeros(self.n)
        self._away = self._no_stretch()
        self._transient = (sample.stamp, np.full(self.n, -np.inf))
        self._torque_extrapolated = (sample.stamp, np.full(self.n, -np.inf))
        self._slip_stamp = NEVER

    def slipping(self, velocity: np.ndarray, stamps: np.ndarray) -> np.ndarray:
        """Rows (N,) of wheel speeds ``velocity`` (N, n) [rad/s] at ``stamps`` (N,) [s] judged
        as slipping: the speed no rigid base motion explains (``Kinematics.slip_speed``) beyond :attr:`slip_limit`, or less than ``breakaway_time`` after such a
        row (the base catching up with its wheels). Continues (and leaves) the state.

        Why: the model is a rolling contact law. When the wheels' speeds fit no motion of the
        base, some contacts slip, and the torque they pass is the traction's, not what the
        base's inertia asks through the rolling constraint: a gentle calibration never saw it,
        an aggressive drive on a slippery floor does. Only a base of four wheels or more can
        show it (three always fit a motion)."""
        if not np.isfinite(self.slip_limit):
            return np.zeros(len(stamps), dtype=bool)
        last = last_true_value(self.fit_no_motion(velocity), stamps, self._slip_stamp)
        self._slip_stamp = float(last[-1])
        return stamps - last < self.settings.breakaway_time

    def fit_no_motion(self, velocity: np.ndarray) -> np.ndarray:
        """Rows (N,) of wheel speeds ``velocity`` (N, n) [rad/s] with a part no rigid base motion
        explains (``Kinematics.slip_speed``) beyond :attr:`slip_limit` (never where calibration
        measured none: a base of three wheels always fits a motion)."""
        if not np.isfinite(self.slip_limit):
            return np.zeros(len(velocity), dtype=bool)
        return self.kinematics.slip_speed(velocity) > self.slip_limit

    def fit_a_motion(self, velocity: np.ndarray) -> np.ndarray:
        """Rows (N,) of wheel speeds ``velocity`` (N, n) [rad/s] that show a motion of the base:
        they fit one within :attr:`slip_limit`, on a base whose speeds can show they do not (four
        wheels or more, the slip calibrated); none where they cannot."""
        if not (np.isfinite(self.slip_limit) and self.shows_slip):
            return np.zeros(len(velocity), dtype=bool)
        return ~self.fit_no_motion(velocity)

    def follow_commands(self, velocity: np.ndarray, prev_velocity: np.ndarray,
                        commanded: np.ndarray, velocity_mode: np.ndarray) -> np.ndarray:
        """Rows (N,) in velocity mode (``velocity_mode`` (N,)) whose every wheel moves toward its
        commanded speed ``commanded`` (N, n) [rad/s]: its error is smaller at ``velocity`` (N, n)
        than at ``prev_velocity`` (N, n) [rad/s], or within three ``speed_sigma`` (the reading's
        noise). A blocked wheel moves away from its command, a frozen reading not at all; NaN:
        not followed. (:meth:`_remembered_torque_extrapolation`: a turn the wheels slip through
        on command.)"""
        error = np.abs(velocity - commanded)
        toward = (error < np.abs(prev_velocity - commanded)) | (error <= self._speed_uncertainty)
        return velocity_mode & toward.all(axis=-1)

    def shift_scale(self, learned_bound: np.ndarray, velocity: np.ndarray,
                    load: np.ndarray | float) -> np.ndarray:
        """The scale [N·m] (N, n) of each wheel's torque residual's shift from its recent level
        (the decision's shift test): the torque bound's learned part ``learned_bound`` (N, n)
        (without its allowances for steady biases, which cancel in a departure from the level),
        and the change the Coulomb friction may make at the speeds ``velocity`` (N, n) [rad/s]
        the reading cannot tell apart (``Dynamics.coulomb_span`` within SPEED_NOISE_SIGMAS x
        ``speed_sigma``: a standing or creeping wheel's static friction), at the load factor
        ``load`` (scalar or (N, 1))."""
        return learned_bound + np.abs(load) * self.dynamics.coulomb_span(velocity, self._speed_uncertainty)

    def parity_confirmed(self, torque_residual: np.ndarray, slipping: np.ndarray) -> np.ndarray:
        """The share (0..1) (N, n) of each wheel's torque residual ``torque_residual`` (N, n)
        [N·m] that the parity relations confirm as that wheel's alone: the size a fault of wheel w
        alone would have to give them what they show, ``(B_w . B^T r) / |B_w|^2`` (B the
        ``Kinematics.parity_basis``), over the size of its residual, at most 1, and 0 where it points
        the other way. 1 where nothing can be said: no parity relations (three wheels), a wheel
        outside them, a residual missing or zero, and the rows ``slipping`` (N,) (the rolling
        law, whose forces the relations rest on, does not hold there).

        Why: a fault of one wheel shows on its own torque residual and, in proportion, in the
        parity relations; what every wheel shares as a force or torque on the base (a payload,
        a slope, a floor's drag sideways, the model's mass) is in the range of the kinematics
        and leaves them untouched. So a wheel's torque evidence counts only as far as the
        parity relations say it is that wheel's (docs/fdi.md, "Decision")."""
        share = np.ones_like(torque_residual)
        if not self.kinematics.parity_basis.shape[1]:
            return share
        known = np.isfinite(torque_residual).all(axis=1) & ~slipping
        every = known.all()  # (usually; always live) no rows to pick
        if not every and not known.any():
            return share
        residual = torque_residual if every else torque_residual[known]
        alone = self._parity_alone(residual)  # (M, n)
        size = np.abs(residual)
        judged = self._parity_observable & (size > 0.0)
        ratio = np.divide(np.abs(alone), size, out=np.ones_like(size), where=judged)
        confirmed = np.where(judged, np.where(np.sign(alone) == np.sign(residual),
                                              np.minimum(1.0, ratio), 0.0), 1.0)
        if every:
            return confirmed
        share[known] = confirmed
        return share

    def _parity_alone(self, values: np.ndarray) -> np.ndarray:
        """Per wheel (N, n), the size a value of wheel w alone would need to give the parity
        relations what ``values`` (N, n) give them: ``(B_w . B^T x) / |B_w|^2`` (B the
        ``Kinematics.parity_basis``; 0 where it has no relations)."""
        basis = self.kinematics.parity_basis
        return ((values @ basis) @ basis.T) / self._parity_weight

    def rigid_speed(self, velocity: np.ndarray, parity: np.ndarray | None = None) -> np.ndarray:
        """The speed [rad/s] (N, n) the other wheels' rigid base motion gives each wheel, from
        the wheel speeds ``velocity`` (N, n) [rad/s]: its own reading less the error of its
        reading alone that the parity relations show (:meth:`_parity_alone`; ``parity`` (N, n),
        that error where the caller has it already). Its own reading where no relation sees it
        (three wheels); within :attr:`_rigid_tolerance` of the reading on nominal data."""
        return velocity - (self._parity_alone(velocity) if parity is None else parity)

    # ------------------------------------------------------------------ missing readings
    def silence(self, stamps: np.ndarray, answered: np.ndarray) -> np.ndarray:
        """How long [s] (N, n) each wheel has been silent at each of ``stamps`` (N,), from which
        wheels ``answered`` (N, n) bool in each row; continues (and leaves) the state.

        A wheel's silence counts from the first sample that came without its reading, not from
        its last reading: only a cycle closed without its module shows that module silent. A
        gap with no samples at all (the base's stream stalled, or this host) says nothing about
        one wheel; it is the base's own ``comm_loss`` when it lasts."""
        stamps = np.asarray(stamps, dtype=float)
        answered = np.asarray(answered, dtype=bool)
        if self._silent_since is None:  # silence counts from the first sample seen
            self._silent_since = np.full(self.n, stamps[0])
        before = shifted(self._answering, answered)
        since = last_true_value(answered | before, stamps, self._silent_since)
        self._silent_since, self._answering = since[-1], answered[-1]
        return stamps[:, None] - since

    def missing_batch(self, joints: JointBatch) -> ResidualBatch:
        """Frames for rows of ``joints`` (:class:`~youbot_fdi.samples.JointBatch`) in which some
        wheels have no reading (NaN from the driver: their module did not answer the cycle):
        missing data. Nothing is computed from them (every residual NaN, scored 0: no evidence),
        the observer and the interval's start are left as they were, and the frames carry each
        wheel's ``silent`` time, from which the decision names a wheel that stays silent
        ``comm_loss``. A :class:`ResidualBatch` (features NaN)."""
        rows, n = len(joints), self.n
        silent = self.silence(joints.stamp, joints.answered())
        nan = np.full((rows, n), np.nan)
        counters = (np.broadcast_to(c, (rows, n)).copy() for c in
                    (self._frozen, self._effort_frozen, self._position_frozen))
        features = {family: np.full((rows, n, len(BOUND_TERMS[family])), np.nan)
                    for family in BOUND_TERMS}
        frozen, effort_frozen, position_frozen = counters
        return ResidualBatch(
            stamp=joints.stamp, values=dict.fromkeys(FAMILIES, nan),
            bounds={family: np.ones((rows, n)) for family in FAMILIES},
            velocity=self.signs * joints.velocity, torque=nan,
            velocity_mode=np.ones(rows, dtype=bool), command=nan, frozen=frozen,
            effort_frozen=effort_frozen, position_frozen=position_frozen, silent=silent,
            load_factor=np.full(rows, np.nan), command_speed=nan,
            outside_calibration=np.zeros(rows), torque_scale=np.ones((rows, n)),
            torque_confirmed=np.ones((rows, n)), friction_level=np.zeros((rows, n)), features=features)

    def missing(self, sample: JointSample) -> ResidualFrame:
        """:meth:`missing_batch` for one sample (:class:`~youbot_fdi.samples.JointSample`): a
        :class:`ResidualFrame`."""
        return self.missing_batch(JointBatch.of_sample(sample)).frame(0)

    # ------------------------------------------------------------------ the residual formulas
    # Rows (N, n) (a live sample is one); ``step`` is dt [s] (N, 1).
    # Each returns the residual and its bound's features (..., n, k) (:data:`BOUND_TERMS`).
    def bound(self, family: str, features: np.ndarray) -> np.ndarray:
        """The bound [residual units] of ``family`` from its features (..., n, k): the learned
        weights within the range calibration covered; a feature's excess beyond it weighed with
        the larger of its learned and its default weight (honest extrapolation)."""
        within, beyond = self.bound_parts(family, features)
        return within if beyond is None else within + beyond

    def bound_parts(self, family: str, features: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`bound` in its two parts (..., n): within the range calibration covered, and
        beyond it (None where the family was not calibrated: no range, nothing beyond)."""
        inside = np.minimum(features, self._ranges[family])
        within = inside @ self._coefficients[family]
        if not self._calibrated[family]:
            return within, None
        return within, (features - inside) @ self._beyond[family]

    def beyond_calibration(self, features: dict[str, np.ndarray]) -> np.ndarray:
        """Wheels (..., n) bool whose bound features ({family: (..., n, k)}) leave the range
        calibration covered in any family by more than ``calibration_range_margin`` of it (the
        WARN: the bounds widen from the range on)."""
        beyond = None
        for family, values in features.items():
            out = (values > self._warn_ranges[family]).any(axis=-1)
            beyond = out if beyond is None else beyond | out
        return beyond

    def _torque_terms(self, torque, prev_torque, velocity, prev_velocity, explained, friction, unseen,
                      load, spread, step):
        """(residual, features, allowance) of the torque family; ``load`` the load factor (scalar
        or (N, 1)) scales the friction part of the explained torque, and the bound allows the
        larger of ``load_allowance`` of that change (the factor is an estimate: how friction
        splits into its viscous and Coulomb parts changes with the floor too) and the ``spread``
        (N, n) [-] of the other wheels about the factor (observer.py, ``load_spread``: how far one
        factor describes the wheels beside this one), of the friction; and the ``unseen``
        friction of a wheel outside the contact law's calibrated range (observer.py), at the
        load."""
        mean_torque = 0.5 * (torque + prev_torque)
        inertial = (velocity - prev_velocity) @ self.mass_matrix.T / step
        residual = mean_torque - explained - (load - 1.0) * friction
        share = np.maximum(self.settings.load_allowance * np.abs(load - 1.0), spread)
        allowance = share * np.abs(friction) + np.abs(load * unseen)
        features = columns(1.0, np.abs(inertial), np.abs(torque - prev_torque), np.abs(load * friction))
        return residual, features, allowance

    def _command_terms(self, velocity, torque, speed, before, target, previous_target, latest,
                       velocity_mode, settling, unseen, disturbance, step):
        """(residual, bound) of the command family: ``speed`` predicted now, ``before`` at the
        previous sample, ``previous_target`` the command in force then, ``latest`` the newest one
        sent; ``velocity_mode`` and ``settling`` broadcast against (…, n). In current mode a
        command may act up to ``command_delay`` later than predicted: that share of a step is
        allowed. In velocity mode the ``unseen`` friction [N·m] (observer.py) may slow the wheel
        by what the loop's proportional gain leaves of it, and so may the torque the wheel
        measurably carries beyond the model, ``disturbance`` [N·m] (:meth:`_loop_disturbance`):
        the larger of the two is allowed; and the wheel may already be on its way to a command
        sent but not yet acting by the input delay: the step to it is allowed.

        Why the last: ``identify`` fits the input delay as one pure delay, and it stands for every
        lag between a command and the speed reading (a filtered or lagging reading, the current
        loop, a compliant contact, the transport), which a calibration's gentle ramps cannot tell
        apart. A lag answers from the first instant where a delay waits: within the delay after a
        step, the wheel moves toward a command the model still holds back (on a randomized plant
        whose speed reading lags 39 ms, fitted as a 57 ms delay, the wheel had turned 0.8 rad/s
        toward a new command when it came into force, three bounds). After the delay the
        predicted transient's own allowance takes over. Also the features of both bounds."""
        s = self.settings
        speeds, efforts = bool(velocity_mode.any()), not velocity_mode.all()
        measured = (np.where(velocity_mode, velocity - speed, torque - target) if speeds and efforts
                    else velocity - speed if speeds else torque - target)
        residual = np.where(settling, 0.0, measured)
        velocity_f = columns(1.0, np.abs(speed), np.maximum(np.abs(target - speed), np.abs(target - before)),
                             np.abs(speed - before) / step)
        effort_f = columns(1.0, np.abs(target))
        if efforts:
            effort_u = (self.bound('effort', effort_f)
                        + np.minimum(1.0, s.command_delay / step) * np.abs(target - previous_target))
        if speeds:
            velocity_u = (self.bound('command', velocity_f)
                          + np.maximum(np.abs(unseen), np.abs(disturbance)) * self.loop_compliance
                          + np.abs(latest - target)
                          + self._shared_lag(
                              residual, (speed - before) / step,
                              velocity_f[..., self._noise_terms] @ self._noise_weights,
                              velocity_mode & ~settling))
        # one mode (always live): only its bound is worked out
        mode_u = (np.where(velocity_mode, velocity_u, effort_u) if speeds and efforts
                  else velocity_u if speeds else effort_u)
        bound = np.where(settling, 1.0, mode_u)
        return residual, bound, velocity_f, effort_f

    def _shared_lag(self, residual, acceleration, noise, voting):
        """The allowance (N, n) [rad/s] for a lag every other wheel's command residual shares:
        the lag of least size that each other wheel's residual ``residual`` (N, n) [rad/s]
        needs within its noise floor ``noise`` (N, n) [rad/s], times this wheel's predicted
        acceleration ``acceleration`` (N, n) [rad/s^2]; 0 where fewer than two other wheels vote
        (``voting`` (N, n): judged, in velocity mode) need a lag of one sign, or none fits all.

        Why: a lag between the firmware's speed and the reading (a filtered reading, a loop
        slower than identified, a battery that sags) is one for every wheel: the same firmware
        and the same reading serve them all. A calibration's gentle drive may hide it
        (``identify`` fits gains and a pure delay that stand for it at the accelerations it
        saw); a harder drive then shows it on every wheel at once, each by its own acceleration
        (on a randomized plant whose reading lags 38 ms: three wheels 0.8-1.3 bounds behind
        their predictions together, at the end of an acceleration). A residual r_j = lag x a_j
        + noise bounds the lag to [(r_j - s_j) / a_j, (r_j + s_j) / a_j], s_j its noise floor; a
        wheel departing beyond it without accelerating allows no shared lag, one within it any.
        What every other wheel needs is the intersection of theirs, and its value nearest 0 is
        the least they share. One wheel's fault needs a lag the healthy wheels do not, so the
        intersection is empty or holds 0 and widens no bound; were one other wheel's need
        enough, its fault (or what it does to the base) would pass as shared: two at least. A
        wheel's own residual does not vote on its allowance: its fault stays its own."""
        n = residual.shape[-1]
        allowance = np.zeros(residual.shape)
        # a wheel within its noise floor needs no lag (its interval holds 0; NaN: no reading)
        departing = voting & (np.abs(residual) > noise)
        if n < 3 or departing.sum(axis=-1).max() < MIN_SHARED_LAG_VOTERS:
            return allowance  # nearly every row: no two wheels need a lag
        voting = voting & np.isfinite(residual) & np.isfinite(acceleration)
        with np.errstate(divide='ignore', invalid='ignore'):
            ends = np.stack(((residual - noise) / acceleration, (residual + noise) / acceleration))
        ends = np.where(np.isnan(ends), np.array([-np.inf, np.inf])[:, None, None], ends)
        low = np.where(voting, ends.min(axis=0), -np.inf)  # a wheel not voting: any lag
        high = np.where(voting, ends.max(axis=0), np.inf)
        # wheels that need their reading ahead of the prediction (r / a > 0), or behind it
        ahead, behind = low > 0.0, high < 0.0
        if max(ahead.sum(axis=1).max(), behind.sum(axis=1).max()) < MIN_SHARED_LAG_VOTERS:
            return allowance  # no two wheels need a lag alike
        for wheel in range(n):
            others = np.arange(n) != wheel
            lag_low, lag_high = low[:, others].max(axis=1), high[:, others].min(axis=1)
            least = np.where(lag_low > 0.0, lag_low, np.where(lag_high < 0.0, lag_high, 0.0))
            needing = np.where(least > 0.0, ahead[:, others].sum(axis=1),
                               behind[:, others].sum(axis=1))
            fits = (needing >= MIN_SHARED_LAG_VOTERS) & (lag_low <= lag_high)
            shared = np.where(fits, least, 0.0)
            allowance[:, wheel] = np.abs(shared * acceleration[:, wheel])
        return np.where(np.isfinite(allowance), allowance, 0.0)

    def _settling_limit(self, velocity_mode):
        """How long a command path started from a guess is not judged, per row (N, 1) [s]
        (a scalar where every row is of one mode: always live)."""
        if velocity_mode.all():
            return self.settle_time
        if not velocity_mode.any():
            return self.settings.startup_time
        return np.where(velocity_mode, self.settle_time, self.settings.startup_time)[:, None]

    def _loop_disturbance(self, torque_residual, step, restart):
        """The torque each wheel carries beyond the model (its torque residual ``torque_residual``
        (N, n) [N·m], NaN: none known), low-passed with the loop's time constant
        (:attr:`loop_time_constant`) over the intervals ``step`` (N, 1) [s], from 0 at the rows
        that ``restart`` (N,); continues (and leaves) the state.

        Why: a wheel's firmware loop answers a torque it was not told of (a floor's or a payload's
        drag, a roller dragged by the base) with a speed error; under its proportional gain that
        error is the disturbance, low-passed with that time constant, times
        :attr:`loop_compliance` (the integral only shrinks it), so the command path allows it. A
        runaway carries no such torque: its wheel does what its current says."""
        fresh = restart[:, None]
        known = np.where(np.isfinite(torque_residual) & ~fresh, torque_residual, 0.0)
        keep = np.where(fresh, 0.0, np.exp(-step * self._loop_rate))  # 0 s: no memory
        smoothed = scalar_recursion(keep, (1.0 - keep) * known, self._disturbance)
        self._disturbance = smoothed[-1]
        return smoothed

    def _excess_pushing_away(self, velocity, prev_velocity, torque, target, latest, velocity_mode,
                             restart, step):
        """Per wheel (N, n) [N·m], how far the torque of a velocity-mode wheel whose current pushes
        it away from its command stands above what a live PI loop could still push with, in rows
        where its speed error has not shrunk since that began (0 elsewhere): a wheel pushes away
        where its measured torque, beyond three ``torque_sigma``, has the opposite sign of its
        speed error to the command in force and to the latest sent (the loop may act on either),
        beyond three ``speed_sigma``. ``prev_velocity`` (N, n) [rad/s] is each row's sample
        before, ``step`` (N, 1) [s] the interval. Continues (and leaves) the state; 0 in current
        mode, without a signed effort or with ``loop_direction`` off.

        Why: a PI loop's output changes by k_p (e - e_0) + k_i (the error summed since). Pushing
        away, it is not saturated (the integral that would need is beyond its limit), so while the
        error keeps its sign and does not shrink (read through the lag, below), both terms lower the
        current that pushes away, whatever the integral gain and the current limit: a current that
        rises is not a live loop's (a runaway: the wheel holds a set-point of its own against the
        base). The proportional term says more: where the error grew by ``d`` since the stretch
        began, a live loop's current has fallen by at least k_p k_t d (:attr:`loop_stiffness`), and
        not past zero (there it would push toward the command and the stretch would end). So what
        the torque measured now stands above the start's less min(k_p k_t d, the start's) no live
        loop gives (a runaway held at rest while its command moved 11 rad/s off: a whole current the
        loop should have turned round, held for 0.7 s). The integral's part is not counted: it sums
        the error over the whole stretch, where the reading's lag weighs on every sample (counted
        with the identified k_i, it raised 19 false alarms on 6 randomized plants, three of whose
        k_i had been identified below the truth); what it adds to a live loop's fall is the margin
        for a k_p identified too high. The error's growth is read from the host's speed reading,
        which may trail the firmware's by up to :attr:`_reading_lag`, and whose speed and current
        need not stand for one instant of the sample's interval (an encoder-derived speed is the
        interval's mean, a measured current may trail the loop's output): its rate of change at both
        ends times that lag and the interval is taken off the growth first (a wheel whose lagging
        reading crossed its command late, after an overshoot the firmware had long been braking: a
        randomized plant, 34 ms of lag; a wheel braked from 21 rad/s at the current limit, read at
        100 Hz with no delay identified, that crossed zero between two samples), and an error that
        has not grown past that has not been seen to keep from shrinking: a wheel of seed 3's plant
        123 (200 Hz, its reading lagging 20 ms) slowing to a command stepped 0.75 rad/s toward zero
        read 0.18 rad/s off it 35 ms after the firmware's error had shrunk below that, while the
        loop's current returned to the friction's after its proportional kick (a false ``runaway``).
        An unknown rate takes no growth. Nor is a fall asked of a torque measurably at the current
        limit: that a loop pushing away is not saturated rests on its integral's share being clipped
        at the limit, and a firmware's own clip (the TMCM's I-clip is a parameter of its own) may
        allow more, holding the output at the limit while the proportional term lowers what lies
        beyond. Where the current reaches what calibration never saw, the command path is not judged
        (observer.py); this is."""
        if not self.signed_effort or not self.settings.loop_direction or not velocity_mode.any():
            self._away = self._no_stretch()
            return np.zeros_like(velocity)
        error = target - velocity
        distance = np.abs(error)
        away = distance > self._speed_uncertainty
        if away.any():  # the usual row of steady driving has none: no stretch, and none goes on
            size = np.abs(torque)
            away &= ((torque * error < 0.0) & (torque * (latest - velocity) < 0.0)
                     & (size > SPEED_NOISE_SIGMAS * self.settings.torque_sigma)
                     & velocity_mode[:, None] & ~restart[:, None])
        if not away.any():
            self._away = self._no_stretch()
            return np.zeros_like(velocity)
        rate = np.abs(velocity - prev_velocity) / step  # [rad/s^2]
        was_away, start_torque, start_distance, start_rate = self._away
        begins = away & ~shifted(was_away, away)
        start_torque = last_true_value(begins, size, start_torque)
        start_distance = last_true_value(begins, distance, start_distance)
        start_rate = last_true_value(begins, rate, start_rate)
        self._away = (away[-1], start_torque[-1], start_distance[-1], start_rate[-1])
        grown = distance - start_distance - (self._reading_lag + step) * (rate + start_rate)
        fallen = np.where((grown > 0.0) & (size < self._at_limit),
                          np.minimum(self.loop_stiffness * grown, start_torque), 0.0)
        excess = np.where(away & (grown >= 0.0), size - (start_torque - fallen), 0.0)
        return np.maximum(excess, 0.0)

    def _no_stretch(self):
        """The state of :meth:`_excess_pushing_away` where no wheel pushes away (its start values
        are read only where a stretch goes on)."""
        return np.zeros(self.n, dtype=bool), np.zeros(self.n), np.zeros(self.n), np.zeros(self.n)

    def _judge_loop_direction(self, residual, bound, settling, error, excess):
        """The command residual and bound (N, n) with the loop's direction judged: where a
        current pushing away from the command stands ``excess`` [N·m] above what a live loop could
        push with (:meth:`_excess_pushing_away`), the residual is the speed error to the command
        ``error`` [rad/s] and its score is that excess over what two readings of the torque
        differ by (three ``torque_sigma``, times sqrt 2), wherever that scores more than the
        path's own (always, while the path is not judged)."""
        if not excess.any():  # the usual row
            return residual, bound
        noise = SPEED_NOISE_SIGMAS * math.sqrt(2.0) * self.settings.torque_sigma
        score = excess / noise
        judged = (excess > 0.0) & (settling | (score * bound > np.abs(residual)))
        return (np.where(judged, error, residual),
                np.where(judged, np.abs(error) / np.where(judged, score, 1.0), bound))

    def _remembered_transient(self, velocity_f, velocity_mode, settling, stamp, restart):
        """What the command bound (N, n) adds for the transients of earlier rows the loop still
        remembers: the bound's transient part (the terms of :data:`COMMAND_TRANSIENT_TERMS`
        within calibration's range, and every feature's part beyond it; velocity-mode rows),
        carried as a peak that decays with the loop's slowest time constant, less the row's own
        (which the bound has); 0 while settling. Continues (and leaves) the state.

        Why: the bound's features describe the predicted path now, and the model's error in a
        transient is still in the wheel's speed after the predicted transient has ended: it
        fades only as the loop forgets it, as a guessed start does (:attr:`settle_time`). Two
        errors do this. A transient beyond what calibration covered (an aggressive stop judged
        from a gentle calibration, a payload's inertia, a current limit acting): judged by the
        row's own features the bound had collapsed to its in-range size while the error stood
        (the randomized suite's `runaway` false alarms 0.05-0.2 s after hard stops and
        reversals). And the loop's own response: ``identify`` cannot tell a slower loop from a
        later one on a gentle calibration (a lagging reading or current is fitted as more delay
        and higher gains), so the model's path reaches a command sooner than the wheel does and
        the wheel lags it for as long as the loop remembers the step (randomized plants whose
        gains were identified 1.5-2.5 times too high: `runaway` alarms a tenth of a second after
        ordinary command steps, in range)."""
        beyond = self.bound_parts('command', velocity_f)[1]
        if beyond is None:  # not calibrated: no learned transient, no range
            return 0.0
        inside = np.minimum(velocity_f[..., self._transient_terms],
                            self._ranges['command'][self._transient_terms])
        # zero in current mode, so that a current-mode stretch is idle (_idle)
        transient = np.where(velocity_mode[:, None], inside @ self._transient_weights + beyond, 0.0)
        carried, self._transient = self._remembered(transient, stamp, restart, self._transient)
        # a current-mode row's bound is of effort [N·m]: the speed's memory is not added to it;
        # a peak that is the row's own comes back from the logarithms a rounding off zero
        return np.where(settling | ~velocity_mode[:, None], 0.0, np.maximum(0.0, carried))

    def _torque_bounds(self, features, allowance, velocity, load, stamp, restart, followed):
        """The torque bound (N, n) [N·m] from its ``features`` (N, n, k) and ``allowance`` (N, n)
        [N·m], with what a manoeuvre beyond calibration left (:meth:`_remembered_torque_
        extrapolation`; ``followed()`` (N,): the rows whose wheels all move toward their commanded
        speeds, asked for where needed), and the scale of the residual's shift
        (:meth:`shift_scale`), at the wheel speeds ``velocity`` (N, n) [rad/s] and load factor
        ``load`` (N, 1). Continues the state.

        The shift's scale leaves out the allowances for steady biases (they cancel in a departure
        from the recent level) but keeps what a manoeuvre left: a model error that stands in the
        residual while the base settles after it, a departure from the level by its nature (a
        wheel braking from 9 rad/s, beyond the manoeuvres calibration drove, shifted its residual
        by 1.2 to 1.75 of a scale without it for 50 ms: a false torque_loss alarm of the
        randomized suite)."""
        within, beyond = self.bound_parts('torque', features)
        learned = within if beyond is None else within + beyond
        remembered = self._remembered_torque_extrapolation(beyond, velocity, stamp, restart, followed)
        return learned + allowance + remembered, self.shift_scale(learned + remembered, velocity, load)

    def _remembered_torque_extrapolation(self, beyond, velocity, stamp, restart, followed):
        """What the torque bound (N, n) adds for the manoeuvres of earlier rows beyond calibration
        which the base still remembers: the part of the torque bound beyond calibration's range
        (``beyond`` (N, n) [N·m], :meth:`bound_parts`; None: not calibrated) in the rows whose
        wheel speeds ``velocity`` (N, n) [rad/s] fit a rigid motion (:meth:`fit_a_motion`), or
        fit none while every wheel moves toward its commanded speed (``followed()`` (N,)), carried
        as a peak that decays with the loop's slowest time constant, less the row's own
        (which the bound has). Continues (and leaves) the state.

        Why: the torque residual's features (the inertial torque, the current's change) describe
        the row; an error the model made in a transient it extrapolated (the wheels slipping
        together while a hard reversal outran their traction, a lagging speed reading, the
        base's compliance) stands in the wheels' speeds and currents while the base and its
        loops settle, after the transient's features have ended. Judged by the row's own
        features, the bound had collapsed to its in-range size 0.1-0.2 s after a hard reversal
        while the residual still stood at two of it (the randomized suite's torque false alarms
        after aggressive reversals and stops, calibrated on a gentle drive). Only a manoeuvre is
        remembered, a motion of the base that every wheel follows: a wheel's own transient (it
        stops dead, its reading freezes) leaves speeds no motion explains (:meth:`fit_no_motion`),
        and is what the residual is there to show. But speeds that fit no motion while every
        wheel moves toward its command are a manoeuvre too: the commands asked for a turn faster
        than the floor's traction gave it, and the wheels slip through it together (the
        randomized suite's last false alarm: a hard turn at 50 Hz, one wheel from 8.6 to -1.5
        rad/s and another from 8.6 to -10.8 in 0.15 s, its residual standing at 2.5-3.3 bounds
        for 60 ms after the bound had collapsed); a blocked wheel moves away from its command, a
        frozen reading not at all (velocity mode; current mode has no commanded speed to tell
        them apart). A base of three wheels always fits a motion: its speeds cannot tell a
        manoeuvre from a fault, so nothing is remembered there (the Robotino folds: remembered, a
        jammed wheel was found in 12 of 86 runs, 86 without)."""
        if beyond is None:
            return 0.0
        idle = self._idle(beyond, stamp, restart, self._torque_extrapolated)
        if idle is not None:  # nearly every row: the gate is not worked out
            self._torque_extrapolated = idle
            return 0.0
        rows = self.fit_a_motion(velocity) | (followed() & self.fit_no_motion(velocity))
        manoeuvre = np.where(rows[:, None], beyond, 0.0)
        carried, self._torque_extrapolated = self._remembered(manoeuvre, stamp, restart,
                                                              self._torque_extrapolated)
        return np.maximum(0.0, carried + manoeuvre - beyond)  # the peak less the row's own

    def _remembered(self, values, stamp, restart, state):
        """The peaks (N, n) of a bound's part to remember, ``values`` (N, n) (>= 0; 0 where a
        row has nothing to remember), decaying at the loop's forget rate, less each row's own,
        and the state after the last row: ``state`` is (reference stamp [s], the log of the peak
        carried to it (n,), -inf: none); a row that ``restart`` s (N,) forgets everything before
        it and adds nothing itself."""
        idle = self._idle(values, stamp, restart, state)
        if idle is not None:
            return 0.0, idle
        reference, level = state
        if not restart.any():  # one stretch (always live)
            carried, levels = decaying_peak(values, (stamp - reference)[:, None], self._forget_rate,
                                            level)
            return carried - values, (reference, levels[-1])
        excess = np.where(restart[:, None], 0.0, values)
        parts, start = [], 0
        for first in [*np.flatnonzero(restart), len(stamp)]:
            if first > start:  # rows since the last restart, from the state before them
                elapsed = (stamp[start:first] - reference)[:, None]
                peaks, levels = decaying_peak(excess[start:first], elapsed, self._forget_rate, level)
                parts.append(peaks)
                level = levels[-1]
            if first < len(stamp):  # a restart: nothing remembered from before it
                parts.append(np.zeros((1, self.n)))
                reference, level = stamp[first], np.full(self.n, -np.inf)
            start = first + 1
        carried = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return carried - excess, (reference, level)

    @staticmethod
    def _idle(values, stamp, restart, state):
        """The state of :meth:`_remembered` after rows in which nothing is to be remembered
        (``values`` (N, n) all 0) and none is remembered (nearly every row), or None where
        something is: only a restart (``restart`` (N,) at ``stamp`` (N,) [s]) moves its reference."""
        reference, level = state
        if not np.isneginf(level).all() or values.any():
            return None
        if restart.any():  # the reference a restart sets, as in _remembered
            reference = stamp[np.flatnonzero(restart)[-1]]
        return reference, level

    def _encoder_terms(self, position, prev_position, mean_speed, change, step):
        """(residual, features) of the encoder family."""
        residual = (position - prev_position) - mean_speed * step
        features = columns(1.0, np.abs(mean_speed) * step, np.abs(change) * step, np.abs(mean_speed))
        return residual, features

    @staticmethod
    def _stopped_reading_bound(residual, bound, turned, read):
        """The encoder bound (N, n) [rad] judged: ``bound`` where the encoder residual
        ``residual`` (N, n) [rad] is at least :data:`STOPPED_SHARE` of the larger of the two
        readings' motions over the interval (the position's change ``turned`` and the speed
        readings' ``read`` = mean speed x interval, (N, n) [rad]), else at least the residual
        itself (a score of at most 1: no evidence).

        Why: the family is there for a reading that stopped (a frozen position, a speed reading
        held or forced to zero, a module repeating its last answer), which leaves the residual
        the whole motion of the reading that still moves (half of it in the interval the stop
        falls in). Where both readings moved and the residual is less than half the larger
        motion, neither stopped: the difference is the speed's variation within the interval,
        which two samples at its ends cannot show, and no fault the contract names. It is
        largest at low rates: at 20 Hz, a wheel beside a base reversing hard (its neighbours 12
        rad/s apart in two samples) turned 13 % less than its readings at both ends said, and a
        wheel whose loop rang faster than the sampling (its readings alternating by 0.2 rad/s)
        3.5 % off them, both at 2-4 of a bound that a gentle calibration had learned where the
        two always agreed (false ``encoder_freeze`` alarms of the randomized suite, seed 3)."""
        motion = np.maximum(np.abs(turned), np.abs(read))
        stopped = np.abs(residual) >= STOPPED_SHARE * motion
        return np.where(stopped, bound, np.maximum(bound, np.abs(residual)))

    def _moving(self, mean_speed, target, velocity_mode, step, encoder_bound, witnessed):
        """Wheels that should have turned at least ``FROZEN_MIN_TICKS`` within the interval, by the
        measured speed less its noise and (velocity mode) the commanded speed, or (current mode)
        by the speed the other wheels' motion witnesses, ``witnessed`` (N, n) [rad/s]
        (:meth:`_rigid_witness`), less the encoder
        bound ``encoder_bound`` (N, n) [rad]: only then is a repeated position reading evidence
        (a lagging speed reading keeps turning for a while after the wheel stops; a noisy one is
        not zero at rest; an interval too short for a tick proves nothing).

        Why the encoder bound: it is how far the position's change may fall short of what the
        speed reading says on nominal data, at this operating point (``identify`` learns it; a
        reading that lags the wheel by tau reads ``tau |dw/dt|`` more than the wheel turns
        while it slows, its ``encoder_change_fraction`` term). A position that stays within that
        of the reading has not shown a freeze: a current-mode plant of the randomized suite,
        whose speed reading lags 40 ms, had its wheel read as turning 0.4 rad/s after it had
        stopped, an ``encoder_freeze`` without a fault."""
        measured = np.maximum(0.0, np.abs(mean_speed) - self._speed_uncertainty)
        speed = np.where(velocity_mode, np.minimum(measured, np.abs(target)),
                         np.maximum(measured, witnessed))
        return speed * step - encoder_bound >= FROZEN_MIN_TICKS * self.position_quantum

    def _rigid_witness(self, mean_speed, velocity, repeated, unchanged, torque, restart):
        """The speed [rad/s] (N, n) the other wheels' rigid motion says a wheel turns at, beyond
        what calibration saw of speeds no rigid motion explains (:meth:`rigid_speed`, less
        :meth:`_witness_tolerance`) and beyond how far the wheel's reading stood off that motion
        in the row its position last moved, for the one wheel of a row whose position reading
        repeated (``repeated`` (N, n)), if its speed reading repeated too (``unchanged`` (N,
        n)); 0 elsewhere, and on a base of three wheels. ``mean_speed`` (N, n) [rad/s] the
        interval's speed readings, ``velocity`` (N, n) [rad/s] the row's own, ``torque`` (N, n)
        [N·m] the measured torques, ``restart`` (N,) the rows that start afresh (nothing before
        them is known: their own readings stand for the last move). Continues (and leaves) the
        state.

        Why: a speed reading differentiated from the encoder freezes with it, and in current
        mode no command says the wheel turns; on a base of four wheels or more the others' rigid
        motion still can, from kinematics alone (no floor, load or friction in it). The
        relations tell how far the readings are from a rigid motion, not which reading is off
        (four mecanum wheels have one relation, which sees every wheel alike): a repeated
        position names a wheel only when it is the row's only one, as two repeated readings (a
        frozen one, and one of a wheel standing while the base turns about it) cannot be told
        apart. A wheel that truly stands while the others move (held by its friction) has its
        contact slide at that speed (the tolerance, :meth:`_witness_tolerance`). A frozen
        encoder stops the wheel's whole reading, its position and the speed differentiated from
        it (or held); a blocked wheel's speed reading still shows its noise, and the torque path
        names it ``stuck``: so the witness counts only for a reading whose speed repeated too.

        And a freeze stops a reading that was following the base: what the wheel's reading
        already stood off the others' rigid motion when its position last moved, it stood off
        while its encoder still counted (the wheel standing, its contacts sliding, its position
        creeping by a tick now and then), and repeats say that again, not that the encoder
        stopped: only what the witness says beyond it counts. Two current-mode plants of the
        randomized suite (seed 3) had a wheel hold at 0 rad/s under a small current while the
        others' motion said 6 rad/s, its position stepping one tick every second or third
        sample: false ``encoder_freeze`` alarms."""
        witnessed = np.zeros_like(mean_speed)
        if not self.shows_slip:
            return witnessed
        # each wheel's parity error, once: where its position last moved it is how far the
        # wheel stood off the motion (a restart: the row's own readings); in the other rows it
        # gives the rigid speed (:meth:`rigid_speed`)
        read = np.where(restart[:, None], velocity, mean_speed) if restart.any() else mean_speed
        parity = self._parity_alone(read)
        offset_at_move = last_true_value(~repeated | restart[:, None], self._standing_off(parity),
                                         self._offset_at_move)
        self._offset_at_move = offset_at_move[-1]
        only = unchanged & ~restart[:, None] & (np.count_nonzero(repeated, axis=1) == 1)[:, None]
        if not only.any():
            return witnessed
        rows = np.flatnonzero(only.any(axis=1))
        speed = (np.abs(self.rigid_speed(mean_speed[rows], parity[rows]))
                 - self._witness_tolerance(torque[rows]) - offset_at_move[rows])
        witnessed[rows] = np.where(only[rows], np.maximum(0.0, np.nan_to_num(speed, nan=0.0)), 0.0)
        return witnessed

    @staticmethod
    def _standing_off(parity):
        """How far [rad/s] (N, n) each wheel's speed reading stands off the others' rigid
        motion, from its parity error ``parity`` (N, n) (:meth:`_parity_alone`); infinite where a
        reading is not known."""
        size = np.abs(parity)
        return np.where(np.isnan(size), np.inf, size)

    def _witness_tolerance(self, torque):
        """How far (N, 1) [rad/s] a wheel's speed may stand off the others' rigid motion in rows
        of measured torques ``torque`` (N, n) [N·m] without a fault: calibration measured the
        contacts sliding up to ``calibrated_slip`` under torques up to ``calibrated_effort``,
        and a contact slides in proportion to the force it passes, so beyond that torque the
        tolerance grows with the largest wheel torque of the row (extrapolation widens,
        docs/fdi.md); infinite where calibration measured no torque or a torque is unknown."""
        # the force over calibration's: inf where calibration measured no torque (no witness),
        # NaN where a torque is unknown (no witness either), 0 without a calibrated effort
        with np.errstate(divide='ignore', invalid='ignore'):
            force = np.abs(torque).max(axis=1) / self.settings.calibrated_effort
        return self._rigid_tolerance * np.maximum(1.0, np.nan_to_num(force, nan=np.inf))[:, None]

    @staticmethod
    def _observer_features(predicted):
        return columns(1.0, np.abs(predicted))

    # ------------------------------------------------------------------ the update
    def update(self, sample: JointSample, prediction: Prediction) -> ResidualFrame | None:
        """The :class:`ResidualFrame` of one sample (:class:`~youbot_fdi.samples.JointSample`)
        and its :class:`~youbot_fdi.fdi.observer.Prediction`, or None (restarted: the prediction
        does not start at the last sample taken): :meth:`update_batch` of a batch of one."""
        if self._last is None or self._last[0] != prediction.since:
            self.counters['unpaired'] += self._last is not None  # not at the very start
            self.restart(sample)
            return None
        return self.update_batch(JointBatch.of_sample(sample),
                                 PredictionBatch.of_prediction(prediction)).frame(0)

    def update_batch(self, joints: JointBatch, predictions: PredictionBatch) -> ResidualBatch:
        """Residuals of a block of samples (:class:`~youbot_fdi.samples.JointBatch`) and their
        predictions (:class:`~youbot_fdi.fdi.observer.PredictionBatch`, one row per sample, from
        :meth:`ModelObserver.update_batch` on the same block): a :class:`ResidualBatch` of every
        sample but those that restart (``predictions.restart``), with the bounds' features."""
        n, rows = self.n, len(joints)
        p, restart = predictions, predictions.restart
        if rows == 0:
            empty, counts = np.empty((0, n)), np.empty((0, n), dtype=int)
            return ResidualBatch(
                stamp=joints.stamp, values=dict.fromkeys(FAMILIES, empty),
                bounds=dict.fromkeys(FAMILIES, empty), velocity=empty, torque=empty,
                velocity_mode=p.velocity_mode, command=empty, frozen=counts, effort_frozen=counts,
                position_frozen=counts, silent=empty, load_factor=np.empty(0),
                command_speed=empty, outside_calibration=np.empty(0), torque_scale=empty,
                torque_confirmed=empty, friction_level=empty,
                features={})
        stamp = joints.stamp
        position, velocity, torque = (self.signs * a for a in
                                      (joints.position, joints.velocity, joints.effort))
        if self._last is None:  # the first row restarts (the observer's first sample)
            self.restart(joints.sample(0))
        last_stamp, last_position, last_velocity, last_torque = self._last
        prev_stamp = shifted(last_stamp, stamp)
        prev_position, prev_velocity = (shifted(last, now) for last, now in
                                        ((last_position, position), (last_velocity, velocity)))
        dt = np.where(restart, 1.0, stamp - prev_stamp)  # rows that restart need any valid step
        step = dt[:, None]
        torque = signed_torque(torque, p.explained, self.signed_effort)
        if not self.signed_effort and restart.any():  # as restart() signs it
            torque[restart] = signed_torque(torque[restart], velocity[restart], False)
        prev_torque = shifted(last_torque, torque)
        load = p.load_factor[:, None]
        torque_r, torque_f, torque_a = self._torque_terms(
            torque, prev_torque, velocity, prev_velocity, p.explained, p.friction, p.unseen_friction,
            load, p.load_spread, step)
        observer_f = self._observer_features(p.from_currents)
        # A wheel's command-path prediction settles (settle_time; current mode: startup_time)
        # after it started from a guessed state: a restart, or the measured state taken where its
        # current reached what calibration never saw (observer.py: the integral the measured
        # current implies is only a guess where the current limit acts, and the loop winds up
        # unseen).
        if rows == 1 and not restart[0] and not p.resynced[0]:  # one row (the live path) starting none
            started = self._started[None]
        else:
            started = last_true_value(restart[:, None] | mask_wheels(p.resynced, n), stamp, self._started)
        settling = stamp[:, None] - started < self._settling_limit(p.velocity_mode)
        command_r, command_u, velocity_f, effort_f = self._command_terms(
            velocity, torque, p.from_commands, p.commands_before,
            p.commanded, p.commanded_before, p.commanded_latest, p.velocity_mode[:, None], settling,
            load * p.unseen_friction, self._loop_disturbance(torque_r, step, restart), step)
        command_u = command_u + self._remembered_transient(velocity_f, p.velocity_mode, settling,
                                                           stamp, restart)
        command_r, command_u = self._judge_loop_direction(
            command_r, command_u, settling, velocity - p.commanded,
            self._excess_pushing_away(velocity, prev_velocity, torque, p.commanded,
                                      p.commanded_latest, p.velocity_mode, restart, step))
        mean_speed = 0.5 * (velocity + prev_velocity)
        encoder_r, encoder_f = self._encoder_terms(position, prev_position, mean_speed,
                                                   velocity - prev_velocity, step)

        repeated = position == prev_position
        unchanged = repeated & (velocity == prev_velocity)
        frozen = run_lengths(unchanged, self._frozen, restart)
        effort_frozen = run_lengths(unchanged & (torque == prev_torque), self._effort_frozen, restart)
        encoder_u = self.bound('encoder', encoder_f)
        velocity_mode = p.velocity_mode[:, None]
        # the witness serves current mode only (velocity mode's is the command): its speed is not
        # computed for a velocity-mode row, whose _moving ignores it (its state is kept in every
        # row: where each wheel's position last moved)
        witnessed = self._rigid_witness(mean_speed, velocity, repeated, unchanged & ~velocity_mode,
                                        torque, restart)
        stopped = repeated & self._moving(mean_speed, p.commanded, velocity_mode, step, encoder_u,
                                          witnessed)
        position_frozen = run_lengths(stopped, self._position_frozen, restart)

        self._last = (stamp[-1], position[-1], velocity[-1], torque[-1])
        self._frozen, self._effort_frozen, self._started = frozen[-1], effort_frozen[-1], started[-1]
        self._position_frozen = position_frozen[-1]
        self._silent_since, self._answering = np.full(n, stamp[-1]), np.ones(n, dtype=bool)
        features = {'torque': torque_f, 'observer': observer_f, 'command': velocity_f,
                    'effort': effort_f, 'encoder': encoder_f}
        judged = {f: features[f] for f in ('torque', 'observer', 'encoder')}
        if p.velocity_mode.all() or not p.velocity_mode.any():  # one mode (always live): one call
            beyond = self.beyond_calibration(
                {**judged, **({'command': velocity_f} if p.velocity_mode[0] else {'effort': effort_f})})
        else:
            beyond = self.beyond_calibration(judged) | np.where(
                p.velocity_mode[:, None], self.beyond_calibration({'command': velocity_f}),
                self.beyond_calibration({'effort': effort_f}))
        outside = (p.outside_calibration.astype(np.int64)
                   | wheel_mask(~beyond).astype(np.int64)).astype(float)
        # asked for only where a manoeuvre may be remembered (rarely: not worked out live)
        followed = functools.partial(self.follow_commands, velocity, prev_velocity, p.commanded,
                                     p.velocity_mode)
        torque_bound, torque_scale = self._torque_bounds(torque_f, torque_a, velocity, load, stamp,
                                                         restart, followed)
        slipping = self.slipping(velocity, stamp)
        if slipping.any():  # beyond calibration: the bound wider, every wheel named in the WARN
            torque_bound = np.where(slipping[:, None], self.settings.slip_bound_factor * torque_bound,
                                    torque_bound)
            outside = np.where(slipping, wheel_mask(np.zeros(n, dtype=bool)), outside)
        batch = ResidualBatch(
            stamp=stamp,
            values=dict(zip(FAMILIES, (torque_r, velocity - p.from_currents, command_r, encoder_r))),
            bounds=dict(zip(FAMILIES, (torque_bound, self.bound('observer', observer_f), command_u,
                                       self._stopped_reading_bound(encoder_r, encoder_u,
                                                                   position - prev_position,
                                                                   mean_speed * step)))),
            velocity=velocity, torque=torque, velocity_mode=p.velocity_mode, command=p.commanded,
            frozen=frozen, effort_frozen=effort_frozen, position_frozen=position_frozen,
            silent=np.zeros((rows, n)), load_factor=p.load_factor, command_speed=p.from_commands,
            outside_calibration=outside, torque_scale=torque_scale,
            torque_confirmed=self.parity_confirmed(torque_r, slipping),
            friction_level=torque_f[..., FRICTION_FEATURE], features=features)
        return batch.select(~restart) if restart.any() else batch


class ResidualSpread:
    """The pooled RMS of each residual family over the batches added (rows and wheels; NaN left
    out): the spread ``identify`` and the fault benchmark print, physics-only against learned."""

    def __init__(self):
        self._sums = dict.fromkeys(FAMILIES, 0.0)
        self._counts = dict.fromkeys(FAMILIES, 0)

    def add(self, batch: ResidualBatch) -> ResidualSpread:
        """Add a :class:`ResidualBatch`; returns self."""
        for family, values in batch.values.items():
            finite = values[np.isfinite(values)]
            self._sums[family] += float(np.sum(finite ** 2))
            self._counts[family] += finite.size
        return self

    def merge(self, other: ResidualSpread) -> ResidualSpread:
        """Pool another spread into this one; returns self."""
        for family in FAMILIES:
            self._sums[family] += other._sums[family]
            self._counts[family] += other._counts[family]
        return self

    def rms(self) -> dict[str, float]:
        """{family: RMS}, NaN for a family without a finite value."""
        return {f: math.sqrt(self._sums[f] / self._counts[f]) if self._counts[f] else math.nan
                for f in FAMILIES}


class ResidualGenerator:
    """The model observer and the residual evaluator of one base, run together: residuals from
    /joint_states and /wheel_commands (the replay, ``identify`` and the fused ``observer`` node).

    Parameters
    ----------
    model : PlatformModel
    settings : FdiSettings
    """

    def __init__(self, model, settings):
        self.model = model
        self.settings = settings
        self.observer = ModelObserver(model, settings)
        self.evaluator = ResidualEvaluator(model, settings)
        #: samples that restart the generator, by cause (the observer's counters)
        self.counters = self.observer.counters
        self.last_prediction = None

    @property
    def correction(self) -> TorqueCorrection | None:
        """The learned torque correction in use, None: physics only."""
        return self.observer.correction

    def command(self, sample: CommandSample) -> None:
        """Take a /wheel_commands sample (:class:`~youbot_fdi.samples.CommandSample`)."""
        self.observer.command(sample)

    def reset(self) -> None:
        """Forget the state (after a gap in the data)."""
        self.observer.reset()

    def update(self, sample: JointSample) -> ResidualFrame | None:
        """Residuals for one /joint_states sample (:class:`~youbot_fdi.samples.JointSample`):
        a :class:`ResidualFrame`, or None (first sample, or after a gap/reorder). Also
        :attr:`last_prediction`, the observer's :class:`~youbot_fdi.fdi.observer.Prediction`."""
        if not sample.complete():
            self.last_prediction = None
            return self.evaluator.missing(sample)  # some wheels without a reading
        joints = JointBatch.of_sample(sample)  # a batch of one, handed on as the observer gives it
        predictions = self.observer.update_batch(joints)
        if predictions.restart[0]:
            self.last_prediction = None
            self.evaluator.restart(sample)
            return None
        self.last_prediction = predictions.prediction(0)
        return self.evaluator.update_batch(joints, predictions).frame(0)

    def update_batch(self, joints: JointBatch, commands: CommandBatch | None = None,
                     commands_before: np.ndarray | None = None) -> ResidualBatch:
        """Residuals of a block of /joint_states samples (:class:`~youbot_fdi.samples.JointBatch`),
        with the commands that arrived among them (``commands_before[k]`` of ``commands`` came
        before sample k; see :class:`~youbot_fdi.samples.SampleChunk`).

        Returns a :class:`ResidualBatch` of every sample but those that (re)start the generator:
        the first, and any after a gap longer than ``data_timeout`` or a stamp going backwards.
        Rows in which some wheels have no reading are missing data
        (:meth:`ResidualEvaluator.missing_batch`): the model spans them, as a longer interval.
        """
        complete = joints.complete()
        if complete.all():
            return self.evaluator.update_batch(joints, self.observer.update_batch(
                joints, commands, commands_before))
        parts, commands_taken = [], False
        changes = np.flatnonzero(complete[1:] != complete[:-1]) + 1
        for start, stop in zip([0, *changes], [*changes, len(joints)]):
            rows = joints.rows(start, stop)
            if not complete[start]:
                parts.append(self.evaluator.missing_batch(rows))
                continue
            # Every command of the block goes with the first complete rows: which one is in
            # force at a sample is decided by the stamps (the clock rule), not by this split.
            predictions = self.observer.update_batch(rows, None if commands_taken else commands)
            commands_taken = True
            parts.append(self.evaluator.update_batch(rows, predictions))
        if not commands_taken and commands is not None:  # kept for the samples to come
            self.observer.update_batch(JointBatch.empty(self.evaluator.n), commands)
        return ResidualBatch.concatenate(parts)
