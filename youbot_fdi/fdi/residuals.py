"""Residual generation: the observer and every residual the decision uses, one sample at a time.

Inputs are what the robot publishes (CONTRACT.md, driver convention): /joint_states samples
(position, velocity, effort from the measured current) and /wheel_commands. Internally everything
is in the kinematic convention. Residual families, per wheel ``<w>``:

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
    or integral limit) it is stepped period by period.
``encoder_<w>``
    Position increment minus speed times the interval: a reading that freezes while the wheel moves.

Each residual comes with its bound u (see :mod:`youbot_fdi.fdi.settings`).

:meth:`ResidualGenerator.update_batch` computes a block of samples at once (the replay);
:meth:`ResidualGenerator.update` is the same computation for one sample (the live node).
"""
from dataclasses import dataclass

import numpy as np

from youbot_fdi.fdi.learned import TorqueCorrection
from youbot_fdi.fdi.recursions import (affine_recursion, last_true_value, matvec, run_lengths,
                                       scalar_recursion)
from youbot_fdi.model.dynamics import zoh_discretize
from youbot_fdi.samples import CommandBatch, VELOCITY
from youbot_fdi.structure.generate import wheel_suffix

#: Why a sample restarted the generator: counters of :attr:`ResidualGenerator.counters`.
STAMP_COUNTERS = ('stamps_backwards', 'stamps_repeated', 'gaps')
FAMILIES = ('torque', 'observer', 'command', 'encoder')
#: Signals a frame carries besides its residuals: (label prefix, attribute).
SIGNALS = (('speed', 'velocity'), ('effort', 'torque'), ('commanded', 'command'),
           ('frozen', 'frozen'), ('effort_frozen', 'effort_frozen'),
           ('position_frozen', 'position_frozen'))
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
#: A position reading that repeats exactly while the wheel should have turned this many encoder
#: ticks within the interval is evidence of a frozen sensor [ticks].
FROZEN_MIN_TICKS = 2.0
DT_KEY_DECIMALS = 4  # discretisations are cached per interval rounded to 0.1 ms
#: Commands kept while no joint state arrives (a bound on memory, far above any input delay).
MAX_PENDING_COMMANDS = 256


def bound_weights(settings, family):
    """The weights of ``family``'s bound features (:data:`BOUND_TERMS`) in ``settings``, (k,)."""
    return np.array([getattr(settings, name) for name in BOUND_TERMS[family]])


def columns(*values):
    """The arrays (or scalars) ``values``, broadcast together, as the columns of one array
    (..., k): a bound's features (cheaper than stacking broadcast copies)."""
    shape = np.broadcast_shapes(*(np.shape(v) for v in values))
    out = np.empty(shape + (len(values),))
    for j, value in enumerate(values):
        out[..., j] = value
    return out


def scores(values, bounds):
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
    command_mode: str  # 'velocity' or 'effort'
    command: np.ndarray  # in force (after the watchdog), kinematic convention
    frozen: np.ndarray  # consecutive samples with position and speed unchanged (n,) int
    effort_frozen: np.ndarray  # consecutive samples with the effort unchanged too (n,) int
    position_frozen: np.ndarray  # consecutive samples with the position unchanged while moving (n,)
    load_factor: float = 1.0  # the platform-wide friction/load condition (1: as identified) [-]

    def names(self, wheel_names):
        """Residual names in family-major order, e.g. ``torque_fl``."""
        return [f'{family}_{wheel_suffix(w)}' for family in FAMILIES for w in wheel_names]

    def flat(self):
        """(values, bounds) as flat arrays in :meth:`names` order."""
        return (np.concatenate([self.values[f] for f in FAMILIES]),
                np.concatenate([self.bounds[f] for f in FAMILIES]))

    def scores(self):
        """|r| / u, shape (families, n) in FAMILIES order."""
        return scores(np.stack([self.values[f] for f in FAMILIES]),
                      np.stack([self.bounds[f] for f in FAMILIES]))

    def to_labelled(self, wheel_names):
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
            signals.append(np.asarray(getattr(self, array), dtype=float))
        labels += ['command_mode', 'load_factor']
        signals.append(np.array([1.0 if self.command_mode == 'velocity' else 0.0, self.load_factor]))
        extra = np.concatenate(signals)
        return (labels, np.concatenate([values, extra]),
                np.concatenate([bounds, np.full(len(extra), np.nan)]))

    @classmethod
    def from_labelled(cls, stamp, labels, values, bounds, wheel_names):
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

        signals = {array: pick(prefix, values) for prefix, array in SIGNALS}
        for label in ('command_mode', 'load_factor'):
            if label not in index:
                msg = f'residual vector lacks {label}'
                raise ValueError(msg)
        return cls(stamp=stamp,
                   values={f: pick(f, values) for f in FAMILIES},
                   bounds={f: pick(f, bounds) for f in FAMILIES},
                   velocity=signals['velocity'], torque=signals['torque'],
                   command_mode='velocity' if values[index['command_mode']] > 0.5 else 'effort',
                   command=signals['command'],
                   frozen=signals['frozen'].astype(int), effort_frozen=signals['effort_frozen'].astype(int),
                   position_frozen=signals['position_frozen'].astype(int),
                   load_factor=float(values[index['load_factor']]))



#: The per-row arrays of a ResidualBatch besides ``values`` and ``bounds``.
ROW_ARRAYS = ('stamp', 'velocity', 'torque', 'velocity_mode', 'command', 'frozen', 'effort_frozen',
              'position_frozen', 'load_factor', 'command_speed')


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
    load_factor: np.ndarray
    command_speed: np.ndarray
    features: dict = None

    def __len__(self):
        return len(self.stamp)

    def frame(self, k):
        """Row ``k`` as a :class:`ResidualFrame`."""
        return ResidualFrame(
            stamp=float(self.stamp[k]), values={f: v[k] for f, v in self.values.items()},
            bounds={f: b[k] for f, b in self.bounds.items()}, velocity=self.velocity[k],
            torque=self.torque[k], command_mode=VELOCITY if self.velocity_mode[k] else 'effort',
            command=self.command[k], frozen=self.frozen[k], effort_frozen=self.effort_frozen[k],
            position_frozen=self.position_frozen[k], load_factor=float(self.load_factor[k]))

    def select(self, rows):
        """The rows ``rows`` (index array, mask or slice) as a batch."""
        pick = {f: getattr(self, f)[rows] for f in ROW_ARRAYS}
        return ResidualBatch(values={f: v[rows] for f, v in self.values.items()},
                             bounds={f: b[rows] for f, b in self.bounds.items()},
                             features={f: v[rows] for f, v in (self.features or {}).items()}, **pick)

    def scores(self):
        """|r| / u, shape (N, families, n); 0 where a residual cannot be computed (NaN)."""
        return scores(np.stack([self.values[f] for f in FAMILIES], axis=1),
                      np.stack([self.bounds[f] for f in FAMILIES], axis=1))

    @classmethod
    def concatenate(cls, batches):
        """One batch of several, in order."""
        batches = list(batches)
        join = {f: np.concatenate([getattr(b, f) for b in batches]) for f in ROW_ARRAYS}
        return cls(values={f: np.concatenate([b.values[f] for b in batches]) for f in FAMILIES},
                   bounds={f: np.concatenate([b.bounds[f] for b in batches]) for f in FAMILIES},
                   **join)


class ResidualGenerator:
    """Stateful residual generator for one base.

    Parameters
    ----------
    model : PlatformModel
    settings : FdiSettings
    """

    def __init__(self, model, settings):
        self.model = model
        self.settings = settings
        self.signs = model.kinematics.drive_signs
        dyn = model.dynamics
        self.n = dyn.n_wheels
        self.mass_matrix = dyn.mass_matrix
        self.friction = np.diag(dyn.friction_matrix)
        self._a_v = -dyn.mass_inverse @ dyn.friction_matrix
        self._b_v = dyn.mass_inverse
        self._cache = {}
        firmware, drive = model.firmware, model.drive
        self.period = firmware.period
        self._phi1, self._gamma1 = self._discrete(self.period)[:2]
        self.kp, self.ki = firmware.velocity_kp, firmware.velocity_ki
        self.torque_per_amp = drive.torque_per_amp
        #: one firmware period of the saturating loop: speed' = [phi | gamma k_t] [speed; current]
        self._period_map = np.hstack([self._phi1, self._gamma1 * self.torque_per_amp])
        self.max_current = drive.max_current
        self._integral_limit = self.max_current / self.ki if self.ki > 0 else np.inf
        self._loop_cache = {}
        self._has_coulomb = bool(np.any(dyn.coulomb > 0))
        learned = (model.profile.learned or {}).get('torque')
        #: the learned torque correction (youbot_fdi.fdi.learned), None: physics only
        self.correction = (None if learned is None or settings.physics_only else
                           TorqueCorrection.from_mapping(learned, self.n, str(model.profile.source)))
        self._known_commands = CommandBatch.empty(self.n)  # received, kinematic convention
        self.signed_effort = drive.signed_effort
        #: one encoder tick at the wheel [rad]
        self.position_quantum = 2.0 * np.pi * drive.gear_ratio / drive.encoder_ticks_per_revolution
        self._coefficients = {family: bound_weights(settings, family) for family in BOUND_TERMS}
        #: smoothed [load part; friction torque] per wheel, and the load factor; it outlives gaps
        self._load = (np.zeros(2 * self.n), 1.0)
        self._last = None
        #: samples that restart the generator, by cause (reported with the skipped messages)
        self.counters = dict.fromkeys(STAMP_COUNTERS, 0)

    # ------------------------------------------------------------------ helpers
    def _count_restarts(self, dt):
        """Count the steps ``dt`` [s] (array) that restart the generator, by cause: a stamp going
        backwards, a stamp repeated (a duplicated sample), a gap longer than ``data_timeout``."""
        for name, rows in zip(STAMP_COUNTERS, (dt < 0.0, dt == 0.0, dt > self.settings.data_timeout)):
            self.counters[name] += int(np.count_nonzero(rows))

    def _discrete(self, dt):
        """(Phi, Gamma, Gamma^-1) over ``dt`` [s], cached per 0.1 ms."""
        key = max(round(float(dt), DT_KEY_DECIMALS), 10.0 ** -DT_KEY_DECIMALS)
        if key not in self._cache:
            phi, gamma = zoh_discretize(self._a_v, self._b_v, key)
            self._cache[key] = (phi, gamma, np.linalg.inv(gamma))
        return self._cache[key]

    def _discrete_rows(self, dt):
        """(Phi, Gamma, Gamma^-1) per row of ``dt`` (N,): three (N, n, n) arrays."""
        if np.all(dt == dt[0]):
            return tuple(np.broadcast_to(m, (len(dt),) + m.shape) for m in self._discrete(dt[0]))
        keys, inverse = np.unique(np.round(dt, DT_KEY_DECIMALS), return_inverse=True)
        stacked = [np.stack(m) for m in zip(*(self._discrete(key) for key in keys))]
        return tuple(m[inverse] for m in stacked)

    def _coulomb(self, velocity):
        if not self._has_coulomb:
            return np.zeros_like(velocity)
        return self.model.dynamics.coulomb_torque(velocity)

    def _loop_step(self, steps):
        """Exact unsaturated map of ``steps`` firmware periods of the PI loop.

        State ``x = [speed; integral]``, ``x' = A x + B r + C c`` with r the speed target and c the
        friction torque held over the interval.
        """
        if steps not in self._loop_cache:
            n, period, g = self.n, self.period, self.torque_per_amp
            phi, gamma, eye = self._phi1, self._gamma1, np.eye(self.n)
            gain_p, gain_i = g * self.kp, g * self.ki
            a1 = np.block([[phi - gamma * (gain_p + gain_i * period), gamma * gain_i],
                           [-period * eye, eye]])
            b1 = np.vstack([gamma * (gain_p + gain_i * period), period * eye])
            c1 = np.vstack([-gamma, np.zeros((n, n))])
            a, b, c = np.eye(2 * n), np.zeros((2 * n, n)), np.zeros((2 * n, n))
            for _ in range(steps):
                a, b, c = a1 @ a, a1 @ b + b1, a1 @ c + c1
            self._loop_cache[steps] = (a, b, c)
        return self._loop_cache[steps]

    def _start_integral(self, torque, velocity, velocity_mode, target):
        """The PI integral that explains the measured current at a (re)start, shape (..., n)."""
        if self.ki <= 0:
            return np.zeros_like(velocity)
        current = np.where(np.isnan(torque), 0.0, torque) / self.torque_per_amp
        error = np.where(np.asarray(velocity_mode)[..., None], target - velocity, 0.0)
        return np.clip((current - self.kp * error) / self.ki, -self._integral_limit, self._integral_limit)

    # ------------------------------------------------------------------ commands
    def command(self, sample):
        """Take a /wheel_commands sample (:class:`~youbot_fdi.samples.CommandSample`)."""
        known = self._known_commands
        keep = max(len(known) + 1 - MAX_PENDING_COMMANDS, 0)
        self._known_commands = CommandBatch(
            np.append(known.stamp[keep:], sample.stamp),
            np.append(known.velocity_mode[keep:], sample.kind == VELOCITY),
            np.concatenate([known.values[keep:], self.signs * np.asarray(sample.values, dtype=float)[None]]))

    def _commands_in_force(self, stamp, commands=None, commands_before=None):
        """(velocity mode (N,) bool, target (N, n) kinematic) at each stamp (N,).

        The clock rule (docs/fdi.md): every message is placed by its own stamp, never by when it
        arrived. In force at a sample stamped t: the latest known command stamped at or before
        ``t - input_delay`` (the time a command takes to act, negative when commands are stamped
        after the samples they produce), or zero speed once that is older than the shim's watchdog
        (``command_timeout``) or when there is none. Known: the commands received so far (live),
        or the chunk's (replay). Keeps the commands that may still come into force.
        """
        known = self._known_commands
        if commands is not None and len(commands):
            known = CommandBatch(np.concatenate([known.stamp, commands.stamp]),
                                 np.concatenate([known.velocity_mode, commands.velocity_mode]),
                                 np.concatenate([known.values, self.signs * commands.values]))
        if len(known) > 1 and np.any(np.diff(known.stamp) < 0.0):
            order = np.argsort(known.stamp, kind='stable')
            known = CommandBatch(known.stamp[order], known.velocity_mode[order], known.values[order])
        delay = self.settings.input_delay
        received = np.searchsorted(known.stamp, stamp - delay, side='right')
        index = received - 1
        pick = np.maximum(index, 0)
        none = index < 0
        if len(known):
            command_stamp = np.where(none, -np.inf, known.stamp[pick])
            velocity_mode, values = known.velocity_mode[pick], known.values[pick]
        else:
            command_stamp = np.full(len(stamp), -np.inf)
            velocity_mode, values = np.ones(len(stamp), dtype=bool), np.zeros((len(stamp), self.n))
        expired = stamp - (command_stamp + delay) > self.settings.command_timeout
        first_kept = int(index[-1]) if len(stamp) else len(known) - MAX_PENDING_COMMANDS
        first_kept = max(first_kept, len(known) - MAX_PENDING_COMMANDS, 0)
        self._known_commands = CommandBatch(known.stamp[first_kept:], known.velocity_mode[first_kept:],
                                            known.values[first_kept:])
        return velocity_mode | expired, np.where(expired[:, None], 0.0, values)

    # ------------------------------------------------------------------ state
    def reset(self):
        """Forget the state (after a gap in the data)."""
        self._last = None

    def predictions(self):
        """(from currents, from commands): the observer's predicted wheel speeds [rad/s], driver
        convention, or None before the first sample."""
        if self._last is None:
            return None
        return self.signs * self._observer, self.signs * self._command_state[:self.n]

    def _restart(self, stamp, position, velocity, torque, velocity_mode, target):
        """(Re)start from one sample (kinematic convention, [s], [rad], [rad/s], [N·m]; the
        command in force): the predictions take the measurement, the PI integral the value that
        explains the measured current."""
        integral = self._start_integral(torque, velocity, velocity_mode, target)
        self._observer = velocity.copy()
        self._command_state = np.concatenate([velocity, integral])
        self._frozen = np.zeros(self.n, dtype=int)
        self._effort_frozen = np.zeros(self.n, dtype=int)
        self._position_frozen = np.zeros(self.n, dtype=int)
        torque = self._signed(torque, velocity)  # no explained torque yet: the speed's sign
        self._last = (stamp, position, velocity, torque)
        self._last_target = target
        self._started = stamp

    # ------------------------------------------------------------------ the command path
    def _saturated(self, before, after, target):
        """Rows (M,) where the PI loop leaves its linear range between states ``before`` and
        ``after`` (M, 2n) under ``target`` (M, n)."""
        n = self.n
        error0 = target - before[:, :n]
        start_current = self.kp * error0 + self.ki * (before[:, n:] + error0 * self.period)
        end_current = self.kp * (target - after[:, :n]) + self.ki * after[:, n:]
        return ((np.abs(start_current).max(axis=1) >= self.max_current)
                | (np.abs(end_current).max(axis=1) >= self.max_current)
                | (np.abs(after[:, n:]).max(axis=1) >= self._integral_limit))

    def _stepped(self, state, steps, target, friction):
        """``steps`` firmware periods of the saturating PI loop from ``state`` (2n,)."""
        n, period = self.n, self.period
        limit, max_current = self._integral_limit, self.max_current
        speed, integral = state[:n], state[n:]
        drift = self._gamma1 @ friction  # constant over the interval
        joint = np.empty(2 * n)  # [speed; current], one matrix product a period
        for _ in range(steps):
            error = target - speed
            integral = np.minimum(np.maximum(integral + error * period, -limit), limit)
            joint[:n] = speed
            joint[n:] = np.minimum(np.maximum(self.kp * error + self.ki * integral, -max_current),
                                   max_current)
            speed = self._period_map @ joint - drift
        return np.concatenate([speed, integral])

    def _command_step(self, state, steps, target, friction):
        """``steps`` firmware periods of the velocity loop from ``state`` (2n,): the exact linear
        map unless the loop saturates, then period by period. Returns (new state, saturated)."""
        loop_a, loop_b, loop_c = self._loop_step(steps)
        linear = loop_a @ state + loop_b @ target + loop_c @ friction
        if self._saturated(state[None], linear[None], target[None])[0]:
            return self._stepped(state, steps, target, friction), True
        return linear, False

    def _command_path(self, dt, hold, held, velocity_mode, target, friction):
        """Command-path states (N, 2n) = [predicted speed, PI integral] after each row.

        Velocity-mode rows advance the firmware loop over ``dt`` (N,) at its own period: exactly
        (a prefix scan) while it is linear, period by period where it saturates. ``hold`` rows
        (N,) bool take the state ``held`` (N, 2n) instead (a restart, current mode).
        """
        rows, n = len(dt), self.n
        steps = np.maximum(1, np.rint(dt / self.period)).astype(int)
        a = np.zeros((rows, 2 * n, 2 * n))
        b = np.array(held, dtype=float)
        advancing = ~hold
        for count in np.unique(steps[advancing]):
            pick = advancing & (steps == count)
            loop_a, loop_b, loop_c = self._loop_step(int(count))
            a[pick] = loop_a
            b[pick] = target[pick] @ loop_b.T + friction[pick] @ loop_c.T
        saturable = advancing & velocity_mode
        states = np.empty((rows, 2 * n))
        state, k = self._command_state, 0
        while k < rows:
            scanned = affine_recursion(a[k:], b[k:], state)
            before = np.concatenate([state[None], scanned[:-1]])
            bad = saturable[k:] & self._saturated(before, scanned, target[k:])
            good = int(np.argmax(bad)) if bad.any() else len(bad)
            states[k:k + good] = scanned[:good]
            k += good
            if k == rows:
                break
            state = before[good]
            saturated = True
            while saturated and k < rows and saturable[k]:  # one by one until linear again
                state, saturated = self._command_step(state, int(steps[k]), target[k], friction[k])
                states[k] = state
                k += 1
        return states

    # ------------------------------------------------------------------ the residual formulas
    # Shapes (n,) for one sample or (N, n) for a block; ``step`` is dt [s] (a scalar, or (N, 1)).
    # Each returns the residual and its bound's features (..., n, k) (:data:`BOUND_TERMS`).
    def bound(self, family, features):
        """The bound [residual units] of ``family`` from its features (..., n, k)."""
        return features @ self._coefficients[family]

    def _explained(self, velocity, prev_velocity, phi, gamma_inv):
        """(explained torque, its physics friction part, Coulomb torque, mean speed) over one
        interval: the torque the exactly discretised dynamics need for the measured speed change,
        with the learned correction (if any) in the explained and Coulomb torques only."""
        mean_speed = 0.5 * (velocity + prev_velocity)
        coulomb = self._coulomb(mean_speed)
        friction = self.friction * mean_speed + coulomb
        if self.correction is not None:  # learned friction the physics misses (see fdi/learned.py)
            coulomb = coulomb + self.correction(mean_speed)
        explained = matvec(gamma_inv, velocity - matvec(phi, prev_velocity)) + coulomb
        return explained, friction, coulomb, mean_speed

    def _signed(self, torque, reference):
        """The measured torque; a magnitude (``signed_effort: false``) takes the sign of
        ``reference`` (the explained torque, or at a restart the speed)."""
        return torque if self.signed_effort else np.abs(torque) * np.sign(reference)

    def _torque_terms(self, torque, prev_torque, velocity, prev_velocity, explained, friction, load, step):
        """(residual, features, allowance, mean torque) of the torque family; ``load`` the load
        factor (scalar or (N, 1)) scales the friction part of the explained torque, and the bound
        allows ``load_allowance`` of that change (the factor is an estimate: how friction splits
        into its viscous and Coulomb parts changes with the floor too)."""
        mean_torque = 0.5 * (torque + prev_torque)
        inertial = (velocity - prev_velocity) @ self.mass_matrix.T / step
        residual = mean_torque - explained - (load - 1.0) * friction
        allowance = self.settings.load_allowance * np.abs((load - 1.0) * friction)
        features = columns(1.0, np.abs(inertial), np.abs(torque - prev_torque), np.abs(load * friction))
        return residual, features, allowance, mean_torque

    def _load_votes(self, mean_torque, explained, friction):
        """Per wheel, (load part: measured minus inertial torque, friction part), zero where the
        wheel does not vote on the load factor (friction torque under the torque floor or under
        the inertial torque, effort unknown)."""
        inertial = explained - friction
        load_part = mean_torque - inertial
        # Only in near-steady driving: where inertia dominates, the model's error does too.
        votes = ((np.abs(friction) >= self.settings.torque_sigma) & (np.abs(inertial) <= np.abs(friction))
                 & np.isfinite(load_part))
        return np.where(votes, load_part, 0.0), np.where(votes, friction, 0.0)

    def _load_factor(self, smoothed, previous):
        """The platform-wide load factor from the smoothed (load part; friction) (..., 2n): the
        part of the departure that every voting wheel shares (all heavier: the least heavy, all
        lighter: the least light, else 1), bounded; ``previous`` where no wheel votes."""
        n, limit = self.n, self.settings.load_factor_limit
        load, friction = smoothed[..., :n], smoothed[..., n:]
        votes = np.abs(friction) >= self.settings.torque_sigma
        ratio = load / np.where(votes, friction, 1.0)
        heavier = np.all(~votes | (ratio > 1.0), axis=-1)
        lighter = np.all(~votes | (ratio < 1.0), axis=-1)
        shared = np.where(heavier, np.min(np.where(votes, ratio, np.inf), axis=-1),
                          np.where(lighter, np.max(np.where(votes, ratio, -np.inf), axis=-1), 1.0))
        shared = np.clip(shared, 1.0 / limit, limit)
        return shared, votes.any(axis=-1)

    def _observer_features(self, predicted):
        return columns(1.0, np.abs(predicted))

    def _command_terms(self, velocity, torque, speed, before, target, previous_target, velocity_mode,
                       settling, step):
        """(residual, bound) of the command family: ``speed`` predicted now, ``before`` at the
        previous sample, ``previous_target`` the command in force then; ``velocity_mode`` and
        ``settling`` broadcast against (…, n). In current mode a command may act up to
        ``command_delay`` later than predicted: that share of a step is allowed. Also the
        features of both bounds."""
        s = self.settings
        residual = np.where(settling, 0.0, np.where(velocity_mode, velocity - speed, torque - target))
        velocity_f = columns(1.0, np.abs(speed), np.maximum(np.abs(target - speed), np.abs(target - before)),
                             np.abs(speed - before) / step)
        effort_f = columns(1.0, np.abs(target))
        effort_u = (self.bound('effort', effort_f)
                    + np.minimum(1.0, s.command_delay / step) * np.abs(target - previous_target))
        bound = np.where(settling, 1.0, np.where(velocity_mode, self.bound('command', velocity_f), effort_u))
        return residual, bound, velocity_f, effort_f

    def _encoder_terms(self, position, prev_position, mean_speed, change, step):
        """(residual, features) of the encoder family."""
        residual = (position - prev_position) - mean_speed * step
        features = columns(1.0, np.abs(mean_speed) * step, np.abs(change) * step, np.abs(mean_speed))
        return residual, features

    def _moving(self, mean_speed, target, velocity_mode, step):
        """Wheels that should have turned at least ``FROZEN_MIN_TICKS`` within the interval, by the
        measured and (velocity mode) the commanded speed: only then is a repeated position reading
        evidence (a lagging speed reading keeps turning for a while after the wheel stops)."""
        speed = np.where(velocity_mode, np.minimum(np.abs(mean_speed), np.abs(target)), np.abs(mean_speed))
        return speed * step >= FROZEN_MIN_TICKS * self.position_quantum

    # ------------------------------------------------------------------ the update
    def _smoothing(self, step):
        """Per-row weight of the past in the load factor's smoothing (``load_time_constant``)."""
        return np.exp(-step / self.settings.load_time_constant)

    def update(self, sample):
        """Residuals for one /joint_states sample (:class:`~youbot_fdi.samples.JointSample`):
        a :class:`ResidualFrame`, or None (first sample, or after a gap/reorder).

        The live nodes' path: the computation of :meth:`update_batch` for one sample, step by step
        (the same formula helpers; a test holds the two equal on fault recordings).
        """
        s, n = self.settings, self.n
        stamp = sample.stamp
        position, velocity, torque = (self.signs * sample.position, self.signs * sample.velocity,
                                      self.signs * sample.effort)
        modes, targets = self._commands_in_force(np.array([stamp]))
        velocity_mode, target = bool(modes[0]), targets[0]
        dt = None if self._last is None else stamp - self._last[0]
        if dt is None or not 0.0 < dt <= s.data_timeout:
            if dt is not None:
                self._count_restarts(np.array([dt]))
            self._restart(stamp, position, velocity, torque, velocity_mode, target)
            return None
        _, last_position, last_velocity, last_torque = self._last
        phi, gamma, gamma_inv = self._discrete(dt)
        explained, friction, coulomb, mean_speed = self._explained(velocity, last_velocity, phi, gamma_inv)
        torque = self._signed(torque, explained)
        mean_torque = 0.5 * (torque + last_torque)
        keep = self._smoothing(dt)
        smoothed = keep * self._load[0] + (1.0 - keep) * np.concatenate(
            self._load_votes(mean_torque, explained, friction))
        shared, voted = self._load_factor(smoothed, self._load[1])
        load = float(shared) if voted else self._load[1]
        self._load = (smoothed, load)
        torque_r, torque_f, torque_a, mean_torque = self._torque_terms(
            torque, last_torque, velocity, last_velocity, explained, friction, load, dt)
        # The load condition adds to the friction the predictions work against (at the measured speed).
        coulomb = coulomb + (load - 1.0) * friction

        applied = mean_torque if np.isfinite(mean_torque).all() else 0.0
        predicted = phi @ self._observer + gamma @ (applied - coulomb)
        observer_r = velocity - predicted
        self._observer = predicted + (dt / s.observer_time_constant) * observer_r

        before = self._command_state[:n]
        steps = max(1, int(np.rint(dt / self.period)))
        self._command_state = (self._command_step(self._command_state, steps, target, coulomb)[0]
                               if velocity_mode else np.concatenate([velocity, np.zeros(n)]))
        speed = self._command_state[:n]
        command_r, command_u, _, _ = self._command_terms(
            velocity, torque, speed, before, target, self._last_target, velocity_mode,
            stamp - self._started < s.startup_time, dt)
        self._last_target = target
        encoder_r, encoder_f = self._encoder_terms(position, last_position, mean_speed,
                                                   velocity - last_velocity, dt)

        unchanged = (position == last_position) & (velocity == last_velocity)
        self._frozen = np.where(unchanged, self._frozen + 1, 0)
        self._effort_frozen = np.where(unchanged & (torque == last_torque), self._effort_frozen + 1, 0)
        stopped = (position == last_position) & self._moving(mean_speed, target, velocity_mode, dt)
        self._position_frozen = np.where(stopped, self._position_frozen + 1, 0)
        self._last = (stamp, position, velocity, torque)
        return ResidualFrame(
            stamp=stamp,
            values={'torque': torque_r, 'observer': observer_r, 'command': command_r, 'encoder': encoder_r},
            bounds={'torque': self.bound('torque', torque_f) + torque_a,
                    'observer': self.bound('observer', self._observer_features(predicted)),
                    'command': command_u, 'encoder': self.bound('encoder', encoder_f)},
            velocity=velocity, torque=torque, command_mode=VELOCITY if velocity_mode else 'effort',
            command=target, frozen=self._frozen, effort_frozen=self._effort_frozen,
            position_frozen=self._position_frozen, load_factor=load)

    def update_batch(self, joints, commands=None, commands_before=None):
        """Residuals of a block of /joint_states samples (:class:`~youbot_fdi.samples.JointBatch`),
        with the commands that arrived among them (``commands_before[k]`` of ``commands`` came
        before sample k; see :class:`~youbot_fdi.samples.SampleChunk`).

        Returns a :class:`ResidualBatch` of every sample but those that (re)start the generator:
        the first, and any after a gap longer than ``data_timeout`` or a stamp going backwards.
        """
        s, n, rows = self.settings, self.n, len(joints)
        stamp = joints.stamp
        position, velocity, torque = (self.signs * a for a in
                                      (joints.position, joints.velocity, joints.effort))
        velocity_mode, target = self._commands_in_force(stamp, commands, commands_before)
        if rows == 0:
            empty = np.empty((0, n))
            return self._batch(stamp, *(empty,) * 10, velocity_mode, target, *(empty.astype(int),) * 3,
                               np.empty(0), empty, {})
        first = self._last is None
        if first:
            self._restart(stamp[0], position[0], velocity[0], torque[0], velocity_mode[0], target[0])
        last_stamp, last_position, last_velocity, last_torque = self._last
        prev_stamp = np.concatenate([[last_stamp], stamp[:-1]])
        prev_position, prev_velocity = (np.concatenate([last[None], now[:-1]]) for last, now in
                                        ((last_position, position), (last_velocity, velocity)))
        dt = stamp - prev_stamp
        restart = ~((dt > 0.0) & (dt <= s.data_timeout))
        if first:
            restart[0] = True
        self._count_restarts(dt[1:] if first else dt)
        dt = np.where(restart, self.period, dt)  # rows that restart need any valid step
        phi, gamma, gamma_inv = self._discrete_rows(dt)
        step = dt[:, None]
        explained, friction, coulomb, mean_speed = self._explained(velocity, prev_velocity, phi, gamma_inv)
        torque = self._signed(torque, explained)
        if not self.signed_effort and restart.any():  # as _restart signs it
            torque[restart] = self._signed(torque[restart], velocity[restart])
        prev_torque = np.concatenate([last_torque[None], torque[:-1]])
        mean_torque = 0.5 * (torque + prev_torque)
        keep = self._smoothing(dt)
        smoothed = scalar_recursion(keep, (1.0 - keep)[:, None] * np.concatenate(
            self._load_votes(mean_torque, explained, friction), axis=1), self._load[0])
        shared, voted = self._load_factor(smoothed, self._load[1])
        load = last_true_value(voted, shared, self._load[1])
        torque_r, torque_f, torque_a, mean_torque = self._torque_terms(
            torque, prev_torque, velocity, prev_velocity, explained, friction, load[:, None], step)
        coulomb = coulomb + (load[:, None] - 1.0) * friction  # as in update()

        # The observer: x_k = (1 - K) (Phi x_{k-1} + Gamma u_k) + K y_k, K = dt / time constant.
        known = np.isfinite(mean_torque).all(axis=1, keepdims=True)
        forced = matvec(gamma, np.where(known, mean_torque, 0.0) - coulomb)
        correction = step / s.observer_time_constant
        a = (1.0 - correction)[:, :, None] * phi
        b = (1.0 - correction) * forced + correction * velocity
        a[restart], b[restart] = 0.0, velocity[restart]
        observer_before = self._observer
        observer = affine_recursion(a, b, observer_before)
        predicted = matvec(phi, np.concatenate([observer_before[None], observer[:-1]])) + forced
        observer_r = velocity - predicted
        observer_f = self._observer_features(predicted)

        hold = restart | ~velocity_mode
        integral = np.zeros_like(velocity)
        if restart.any():
            integral[restart] = self._start_integral(torque[restart], velocity[restart],
                                                     velocity_mode[restart], target[restart])
        held = np.concatenate([velocity, integral], axis=1)
        command_before = self._command_state
        path = self._command_path(dt, hold, held, velocity_mode, target, coulomb)
        speed = path[:, :n]
        before = np.concatenate([command_before[None, :n], speed[:-1]])
        started = last_true_value(restart, stamp, self._started)
        command_r, command_u, velocity_f, effort_f = self._command_terms(
            velocity, torque, speed, before, target,
            np.concatenate([self._last_target[None], target[:-1]]), velocity_mode[:, None],
            (stamp - started < s.startup_time)[:, None], step)
        encoder_r, encoder_f = self._encoder_terms(position, prev_position, mean_speed,
                                                   velocity - prev_velocity, step)

        unchanged = (position == prev_position) & (velocity == prev_velocity)
        frozen = run_lengths(unchanged, self._frozen, restart)
        effort_frozen = run_lengths(unchanged & (torque == prev_torque), self._effort_frozen, restart)
        stopped = (position == prev_position) & self._moving(mean_speed, target, velocity_mode[:, None], step)
        position_frozen = run_lengths(stopped, self._position_frozen, restart)

        self._last = (stamp[-1], position[-1], velocity[-1], torque[-1])
        self._observer, self._command_state = observer[-1], path[-1]
        self._frozen, self._effort_frozen, self._started = frozen[-1], effort_frozen[-1], started[-1]
        self._position_frozen = position_frozen[-1]
        self._load = (smoothed[-1], float(load[-1]))
        self._last_target = target[-1]
        features = {'torque': torque_f, 'observer': observer_f, 'command': velocity_f,
                    'effort': effort_f, 'encoder': encoder_f}
        batch = self._batch(stamp, torque_r, self.bound('torque', torque_f) + torque_a, observer_r,
                            self.bound('observer', observer_f), command_r, command_u, encoder_r,
                            self.bound('encoder', encoder_f), velocity, torque, velocity_mode, target,
                            frozen, effort_frozen, position_frozen, load, speed, features)
        return batch.select(~restart) if restart.any() else batch

    @staticmethod
    def _batch(stamp, torque_r, torque_u, observer_r, observer_u, command_r, command_u, encoder_r,
               encoder_u, velocity, torque, velocity_mode, target, frozen, effort_frozen,
               position_frozen, load_factor, command_speed, features):
        values = dict(zip(FAMILIES, (torque_r, observer_r, command_r, encoder_r)))
        bounds = dict(zip(FAMILIES, (torque_u, observer_u, command_u, encoder_u)))
        return ResidualBatch(stamp, values, bounds, velocity, torque, velocity_mode, target, frozen,
                             effort_frozen, position_frozen, load_factor, command_speed, features)
