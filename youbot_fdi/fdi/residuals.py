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
    and friction fault and to wheel w's sensor only.
``command_<w>``
    The command path. Velocity mode: measured speed minus the speed the firmware's PI loop would
    reach from the commands (firmware emulation at its own period, with current limit). Current mode:
    measured minus commanded effort. Sensitive to a wheel that does not do what it is told (runaway).
``encoder_<w>``
    Position increment minus speed times the interval: a reading that freezes while the wheel moves.

Each residual comes with its bound u (see :mod:`youbot_fdi.fdi.settings`).
"""
from dataclasses import dataclass

import numpy as np

from youbot_fdi.model.dynamics import zoh_discretize
from youbot_fdi.structure.generate import wheel_suffix

FAMILIES = ('torque', 'observer', 'command', 'encoder')
#: Signals a frame carries besides its residuals: (label prefix, attribute).
SIGNALS = (('speed', 'velocity'), ('effort', 'torque'), ('commanded', 'command'),
           ('frozen', 'frozen'), ('effort_frozen', 'effort_frozen'))
DT_KEY_DECIMALS = 4  # discretisations are cached per interval rounded to 0.1 ms


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

    def names(self, wheel_names):
        """Residual names in family-major order, e.g. ``torque_fl``."""
        return [f'{family}_{wheel_suffix(w)}' for family in FAMILIES for w in wheel_names]

    def flat(self):
        """(values, bounds) as flat arrays in :meth:`names` order."""
        return (np.concatenate([self.values[f] for f in FAMILIES]),
                np.concatenate([self.bounds[f] for f in FAMILIES]))

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
        labels.append('command_mode')
        signals.append(np.array([1.0 if self.command_mode == 'velocity' else 0.0]))
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
        if 'command_mode' not in index:
            raise ValueError('residual vector lacks command_mode')
        return cls(stamp=stamp,
                   values={f: pick(f, values) for f in FAMILIES},
                   bounds={f: pick(f, bounds) for f in FAMILIES},
                   velocity=signals['velocity'], torque=signals['torque'],
                   command_mode='velocity' if values[index['command_mode']] > 0.5 else 'effort',
                   command=signals['command'],
                   frozen=signals['frozen'].astype(int), effort_frozen=signals['effort_frozen'].astype(int))


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
        self.max_current = drive.max_current
        self._integral_limit = self.max_current / self.ki if self.ki > 0 else np.inf
        self._loop_cache = {}
        self._has_coulomb = bool(np.any(dyn.coulomb > 0))
        self._no_torque = np.zeros(self.n)
        self.command_mode = 'velocity'
        self.command_values = np.zeros(self.n)
        self.command_stamp = -np.inf
        self._last = None
        self.skipped = 0

    # ------------------------------------------------------------------ helpers
    def _discrete(self, dt):
        key = round(dt, DT_KEY_DECIMALS)
        if key not in self._cache:
            phi, gamma = zoh_discretize(self._a_v, self._b_v, key)
            self._cache[key] = (phi, gamma, np.linalg.inv(gamma))
        return self._cache[key]

    def _coulomb(self, velocity):
        if not self._has_coulomb:
            return self._no_torque
        return self.model.dynamics.coulomb_torque(velocity)

    def _loop_step(self, steps):
        """Exact unsaturated map of ``steps`` firmware periods of the PI loop.

        State ``x = [speed; integral]``, ``x' = A x + B r + C c`` with r the speed target and c the
        friction torque held over the interval (Coulomb, evaluated at its start).
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

    def command(self, sample):
        """Take a /wheel_commands sample (:class:`~youbot_fdi.bag.reader.CommandSample`)."""
        self.command_mode = sample.kind
        self.command_values = self.signs * np.asarray(sample.values, dtype=float)
        self.command_stamp = sample.stamp

    def _command_in_force(self, stamp):
        if stamp - self.command_stamp > self.settings.command_timeout:
            return 'velocity', np.zeros(self.n)  # the shim's watchdog: zero speed
        return self.command_mode, self.command_values

    def reset(self):
        """Forget the state (after a gap in the data)."""
        self._last = None

    def predict_command_path(self, stamp, dt, velocity):
        """Advance only the command-path prediction by ``dt`` [s] to ``stamp``; returns the
        predicted wheel speeds [rad/s] (kinematic convention). ``velocity`` is the measured speed
        (kinematic), used in current mode where the path follows the measurement."""
        mode, target = self._command_in_force(stamp)
        self._predict_command_path(dt, mode, target, velocity)
        return self._cmd_speed

    def predictions(self):
        """(from currents, from commands): the observer's predicted wheel speeds [rad/s], driver
        convention, or None before the first sample."""
        if self._last is None:
            return None
        return self.signs * self._observer, self.signs * self._cmd_speed

    def start(self, stamp, position, velocity, torque):
        """(Re)start from one sample: kinematic convention, [s], [rad], [rad/s], [N·m]."""
        mode, target = self._command_in_force(stamp)
        self._observer = velocity.copy()
        self._cmd_speed = velocity.copy()
        current = np.where(np.isnan(torque), 0.0, torque) / self.torque_per_amp
        error = target - velocity if mode == 'velocity' else np.zeros(self.n)
        self._cmd_integral = np.clip((current - self.kp * error) / self.ki if self.ki > 0 else 0.0,
                                     -self._integral_limit, self._integral_limit)
        self._frozen = np.zeros(self.n, dtype=int)
        self._effort_frozen = np.zeros(self.n, dtype=int)
        self._last = (stamp, position, velocity, torque)
        self._started = stamp

    def _predict_command_path(self, dt, mode, target, velocity):
        """Advance the firmware-loop prediction over ``dt`` (velocity mode), at the firmware period.

        The loop is linear while neither the current nor the integral is at its limit: then one
        exact step covers the interval; otherwise it is stepped period by period.
        """
        if mode != 'velocity':
            self._cmd_speed = velocity.copy()
            self._cmd_integral = np.zeros(self.n)
            return
        steps = max(1, int(round(dt / self.period)))
        speed, integral = self._cmd_speed, self._cmd_integral
        limit, max_current = self._integral_limit, self.max_current
        a, b, c = self._loop_step(steps)
        state = a @ np.concatenate([speed, integral]) + b @ target + c @ self._coulomb(speed)
        new_speed, new_integral = state[:self.n], state[self.n:]
        start_current = self.kp * (target - speed) + self.ki * (integral + (target - speed) * self.period)
        end_current = self.kp * (target - new_speed) + self.ki * new_integral
        if (np.abs(start_current).max() < max_current and np.abs(end_current).max() < max_current
                and np.abs(new_integral).max() < limit):
            self._cmd_speed, self._cmd_integral = new_speed, new_integral
            return
        period = self.period
        for _ in range(steps):
            error = target - speed
            integral = np.minimum(np.maximum(integral + error * period, -limit), limit)
            current = np.minimum(np.maximum(self.kp * error + self.ki * integral, -max_current),
                                 max_current)
            speed = self._phi1 @ speed + self._gamma1 @ (current * self.torque_per_amp
                                                        - self._coulomb(speed))
        self._cmd_speed, self._cmd_integral = speed, integral

    # ------------------------------------------------------------------ the update
    def update(self, sample):
        """Residuals for one /joint_states sample, or None (first sample, or after a gap/reorder)."""
        stamp = sample.stamp
        position = self.signs * sample.position
        velocity = self.signs * sample.velocity
        torque = self.signs * sample.effort
        self._torque_known = not np.isnan(torque).any()
        if self._last is None:
            self.start(stamp, position, velocity, torque)
            return None
        last_stamp, last_position, last_velocity, last_torque = self._last
        dt = stamp - last_stamp
        if dt <= 0.0 or dt > self.settings.comm_timeout:
            self.skipped += 1
            self.start(stamp, position, velocity, torque)
            return None
        s = self.settings
        phi, gamma, gamma_inv = self._discrete(dt)
        mean_torque = 0.5 * (torque + last_torque)
        mean_speed = 0.5 * (velocity + last_velocity)
        coulomb = self._coulomb(mean_speed)

        explained = gamma_inv @ (velocity - phi @ last_velocity) + coulomb
        inertial = self.mass_matrix @ (velocity - last_velocity) / dt
        torque_r = mean_torque - explained
        torque_u = (s.torque_sigma + s.torque_inertia_fraction * np.abs(inertial)
                    + s.torque_current_change_fraction * np.abs(torque - last_torque)
                    + s.torque_friction_fraction * (np.abs(self.friction * mean_speed) + np.abs(coulomb)))

        applied = mean_torque if self._torque_known else self._no_torque
        self._observer = phi @ self._observer + gamma @ (applied - self._coulomb(self._observer))
        observer_r = velocity - self._observer
        observer_u = s.observer_sigma + s.observer_speed_fraction * np.abs(self._observer)
        self._observer += (dt / s.observer_time_constant) * observer_r

        mode, target = self._command_in_force(stamp)
        before = self._cmd_speed.copy()
        self._predict_command_path(dt, mode, target, velocity)
        if stamp - self._started < s.startup_time:
            command_r, command_u = np.zeros(self.n), np.ones(self.n)  # the prediction settles
        elif mode == 'velocity':
            command_r = velocity - self._cmd_speed
            command_u = (s.command_sigma + s.command_speed_fraction * np.abs(self._cmd_speed)
                         + s.command_transient_fraction * np.maximum(np.abs(target - self._cmd_speed),
                                                                     np.abs(target - before))
                         + s.command_delay * np.abs(self._cmd_speed - before) / dt)
        else:
            command_r = torque - target
            command_u = s.effort_sigma + s.effort_fraction * np.abs(target)

        encoder_r = (position - last_position) - mean_speed * dt
        encoder_u = (s.encoder_sigma + (s.encoder_speed_fraction * np.abs(mean_speed)
                                        + s.encoder_change_fraction * np.abs(velocity - last_velocity)) * dt
                     + s.timing_jitter * np.abs(mean_speed))

        unchanged = (position == last_position) & (velocity == last_velocity)
        self._frozen = np.where(unchanged, self._frozen + 1, 0)
        self._effort_frozen = np.where(unchanged & (torque == last_torque), self._effort_frozen + 1, 0)
        self._last = (stamp, position, velocity, torque)
        return ResidualFrame(
            stamp=stamp,
            values={'torque': torque_r, 'observer': observer_r, 'command': command_r,
                    'encoder': encoder_r},
            bounds={'torque': torque_u, 'observer': observer_u, 'command': command_u,
                    'encoder': encoder_u},
            velocity=velocity, torque=torque, command_mode=mode, command=target,
            frozen=self._frozen.copy(), effort_frozen=self._effort_frozen.copy())
