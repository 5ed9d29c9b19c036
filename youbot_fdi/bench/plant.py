"""Plants for the randomized fault suite, written apart from youbot_fdi's model code.

Nothing here imports the FDI's model: a rigid body on four mecanum wheels whose rollers **slip**
(traction saturating with the slip along each roller's axis), with load-dependent roller and
rolling resistance (so a wheel's current depends on the direction the base drives and on the
floor), bearing friction (viscous, Coulomb, different by direction), the firmware's own 1 kHz PI
speed loop or current mode with a current limit and a lagging current, an actuation delay, and
sensors that quantise, lag or add noise. Only the youBot's published geometry and drive-train
constants (what a user has from the datasheet and the URDF) are shared with the FDI's profile.

:func:`simulate` runs P plants at once, each with its own parameters, drive and fault, by
semi-implicit Euler at ``STEP`` (the contacts are stiff); each plant samples at its own rate with
its own jitter and drops, and sends commands at its own rate.
"""
from dataclasses import dataclass, field
import math

import numpy as np

STEP = 2.5e-4  # [s] integration step
FIRMWARE_PERIOD = 1e-3  # [s] the modules' PI loop and current command
GRAVITY = 9.81  # [m/s²]
# The youBot's published geometry and drive train (URDF, youbot-base.cfg, Maxon datasheet).
RADIUS = 0.0475  # [m]
WHEEL_X = np.array([0.235, 0.235, -0.235, -0.235])  # [m] fl, fr, bl, br
WHEEL_Y = np.array([0.15, -0.15, 0.15, -0.15])  # [m]
#: Each wheel's rollers constrain the contact along (1, ROLLER_TAN) (report eq. 3.8).
ROLLER_TAN = np.array([-1.0, 1.0, 1.0, -1.0])
DRIVE_SIGNS = np.array([-1.0, 1.0, -1.0, 1.0])  # driver convention: left motors mirrored
GEAR = 364.0 / 9405.0  # wheel rev per motor rev
TORQUE_CONSTANT = 0.0335  # [N·m/A] the datasheet's
TICKS = 4000  # per motor revolution
WHEELS = 4
#: Unit vectors of each roller's constrained (axis) and free directions in the base frame.
AXIS = np.stack([np.ones(WHEELS), ROLLER_TAN], axis=1) / np.sqrt(2.0)
FREE = np.stack([-ROLLER_TAN, np.ones(WHEELS)], axis=1) / np.sqrt(2.0)
SLIP_SPEED = 0.05  # [m/s] the slip at which traction reaches 76 % (tanh 1) of its limit
ROLL_SPEED = 0.02  # [m/s] regularisation of roller and rolling resistance at rest
COULOMB_SPEED = 0.05  # [rad/s] regularisation of bearing Coulomb friction
STUCK_FRICTION = 50.0  # [N·m·s/rad] a blocked wheel's bearing
CONTROLLER_TIMEOUT = 0.1  # [s] a module that hears nothing stops its motor


def inverse_kinematics(twist):
    """Wheel speeds (..., 4) [rad/s] of base twists (..., 3) (vx, vy [m/s], wz [rad/s]): the
    contact moves only along each roller's free direction."""
    twist = np.asarray(twist, dtype=float)
    vx, vy, wz = twist[..., 0:1], twist[..., 1:2], twist[..., 2:3]
    contact_x, contact_y = vx - wz * WHEEL_Y, vy + wz * WHEEL_X
    return (contact_x + ROLLER_TAN * contact_y) / RADIUS


@dataclass(frozen=True)
class PlantParameters:
    """P plants: arrays (P,) or (P, 4); units in brackets."""

    mass: np.ndarray  # base [kg]
    yaw_inertia: np.ndarray  # [kg·m²]
    wheel_inertia: np.ndarray  # wheel + reflected rotor [kg·m²]
    viscous: np.ndarray  # (P, 4) bearing [N·m·s/rad]
    coulomb: np.ndarray  # (P, 4) bearing [N·m]
    asymmetry: np.ndarray  # (P, 4) Coulomb x (1 + a) forward, (1 - a) backward [-]
    traction: np.ndarray  # roller friction coefficient along its axis [-]
    roller_resistance: np.ndarray  # along the free direction, per newton of load [-]
    rolling_resistance: np.ndarray  # of the wheel, per newton of load [m]
    torque_scale: np.ndarray  # true torque constant over the datasheet's [-]
    kp: np.ndarray  # [A/(rad/s)] at the wheel
    ki: np.ndarray  # [A/rad]
    current_limit: np.ndarray  # [A]
    current_lag: np.ndarray  # [s] the current follows its command with this time constant
    delay: np.ndarray  # [s] commands act this long after they are sent
    current_mode: np.ndarray  # bool: commands are currents (open loop), else speeds
    sample_rate: np.ndarray  # [Hz]
    jitter: np.ndarray  # sampling instants off by up to this share of an interval [-]
    drop: np.ndarray  # share of samples lost [-]
    command_rate: np.ndarray  # [Hz]; 0: a command with every sample
    on_change: np.ndarray  # bool: a command is sent only when it changed
    quantised: np.ndarray  # bool: integer ticks, rpm and mA
    speed_reading: np.ndarray  # 0: encoder-derived, 1: lagging, 2: noisy
    speed_lag: np.ndarray  # [s] of a lagging speed reading
    speed_noise: np.ndarray  # [rad/s] of a noisy one
    current_noise: np.ndarray  # [A]

    def __len__(self):
        return len(self.mass)

    def select(self, index):
        """Plant ``index`` as a one-plant set."""
        return PlantParameters(**{f: getattr(self, f)[index:index + 1] for f in self.__dataclass_fields__})


@dataclass(frozen=True)
class Drive:
    """What one plant drives in one run: twist knots (times [s] (m,), twists (m, 3)), piecewise
    linear; the floor and the payload (each may change once); a fault."""

    knots: np.ndarray
    twists: np.ndarray
    duration: float  # [s]
    floor: float = 1.0  # resistance factor of the floor at the start [-]
    floor_after: float = 1.0
    floor_time: float = math.inf  # [s]
    payload: float = 0.0  # [kg]
    payload_after: float = 0.0
    payload_time: float = math.inf  # [s]
    payload_offset: tuple = (0.0, 0.0)  # its centre off the base's centre [m]
    fault: object = None  # 'stuck', 'torque_loss', 'friction', 'runaway', 'encoder_freeze', 'comm_loss'
    wheel: int = 0
    fault_time: float = math.inf  # [s]
    magnitude: float = 1.0  # torque_loss: torque kept [-]; friction: bearing friction factor [-]


@dataclass
class Recording:
    """What one plant's driver published: /joint_states rows (wheel side, driver convention, NaN
    where a module did not answer) and /wheel_commands rows."""

    stamp: np.ndarray  # (N,) [s] from the drive's start
    position: np.ndarray  # (N, 4) [rad]
    velocity: np.ndarray  # (N, 4) [rad/s]
    effort: np.ndarray  # (N, 4) [N·m] the datasheet's torque per measured amp
    command_stamp: np.ndarray  # (M,) [s]
    command: np.ndarray  # (M, 4) [rad/s] or [N·m]
    current_mode: bool
    fault_visible: float = math.nan  # [s] when the fault could first be seen (its wheel driven; runaway: its command changed)
    extra: dict = field(default_factory=dict)


def _schedule(params, drives, rng):
    """Per plant: sampling instants [s] (jittered, some dropped: a mask) and command instants."""
    samples, kept, commands = [], [], []
    for p, drive in enumerate(drives):
        interval = 1.0 / params.sample_rate[p]
        nominal = np.arange(0.0, drive.duration, interval)
        times = nominal + rng.uniform(-1.0, 1.0, len(nominal)) * params.jitter[p] * interval
        # Each instant on the integration grid, once (the stamps are the true sampling instants).
        steps = np.unique(np.rint(np.clip(times, 0.0, drive.duration - STEP) / STEP).astype(int))
        times = steps * STEP
        samples.append(times)
        kept.append(rng.random(len(times)) >= params.drop[p])
        rate = params.command_rate[p]
        commands.append(times.copy() if rate <= 0 else np.arange(0.0, drive.duration, 1.0 / rate))
    return samples, kept, commands


def _command_values(params, drive, times, p):
    """The host's commands at ``times`` (M,): wheel speeds [rad/s] (kinematic convention) of the
    drive's twist, or in current mode the open-loop torque a nominal youBot needs [N·m]."""
    twist = np.stack([np.interp(times, drive.knots, drive.twists[:, axis]) for axis in range(3)], axis=1)
    speeds = inverse_kinematics(twist)
    if params.current_mode[p]:  # the host's nominal friction model, not this plant's
        return 0.035 * speeds + 0.02 * np.tanh(speeds / 0.2)
    return speeds


def simulate(params, drives, seed=0):
    """Run every plant through its drive; returns a :class:`Recording` per plant.

    ``params``: :class:`PlantParameters` of P plants; ``drives``: P :class:`Drive` s.
    """
    rng = np.random.default_rng(seed)
    count = len(params)
    duration = max(d.duration for d in drives)
    steps = int(math.ceil(duration / STEP))
    firmware_every = int(round(FIRMWARE_PERIOD / STEP))
    sample_times, sample_kept, command_times = _schedule(params, drives, rng)
    # Commands per plant, padded: what the host sends and when (kinematic convention).
    sent, sent_at = [], []
    for p, drive in enumerate(drives):
        values = _command_values(params, drive, command_times[p], p)
        if params.on_change[p] and len(values) > 1:
            changed = np.concatenate([[True], np.any(np.abs(np.diff(values, axis=0)) > 1e-9, axis=1)])
            values, times = values[changed], command_times[p][changed]
        else:
            times = command_times[p]
        sent.append(values)
        sent_at.append(times)
    width = max(len(t) for t in sent_at)
    command_at = np.full((count, width + 1), np.inf)
    command_value = np.zeros((count, width + 1, WHEELS))
    for p in range(count):
        command_at[p, :len(sent_at[p])] = sent_at[p]
        command_value[p, :len(sent[p])] = sent[p]
    pointer = np.full(count, -1)  # the command in force at the firmware (after the delay)
    sample_step = [np.rint(t / STEP).astype(int) for t in sample_times]
    next_sample = np.array([s[0] if len(s) else steps for s in sample_step])
    sample_index = np.zeros(count, dtype=int)
    rows = [np.zeros((len(s), 3, WHEELS)) for s in sample_step]  # position, speed, current

    # Per-run conditions as arrays.
    floor = np.array([d.floor for d in drives])
    floor_after = np.array([d.floor_after for d in drives])
    floor_time = np.array([d.floor_time for d in drives])
    payload = np.array([d.payload for d in drives])
    payload_after = np.array([d.payload_after for d in drives])
    payload_time = np.array([d.payload_time for d in drives])
    offset = np.array([d.payload_offset for d in drives])
    fault = [d.fault for d in drives]
    fault_wheel = np.array([d.wheel for d in drives])
    fault_time = np.array([d.fault_time for d in drives])
    magnitude = np.array([d.magnitude for d in drives])
    has = {kind: np.array([f == kind for f in fault]) for kind in
           ('stuck', 'torque_loss', 'friction', 'runaway', 'encoder_freeze', 'comm_loss')}
    plants = np.arange(count)

    # State: base twist in the base frame, wheel angles and speeds, firmware, sensors.
    twist = np.zeros((count, 3))
    angle = np.zeros((count, WHEELS))
    speed = np.zeros((count, WHEELS))
    integral = np.zeros((count, WHEELS))
    current = np.zeros((count, WHEELS))
    current_command = np.zeros((count, WHEELS))
    lagged_speed = np.zeros((count, WHEELS))
    frozen_speed = np.zeros((count, WHEELS))  # encoder_freeze: what the firmware and host see
    frozen_angle = np.zeros((count, WHEELS))
    held_target = np.full((count, WHEELS), np.nan)  # runaway: the set-point it keeps
    torque_per_amp = params.torque_scale[:, None] * TORQUE_CONSTANT / GEAR  # true [N·m/A]
    integral_limit = (params.current_limit / np.maximum(params.ki, 1e-9))[:, None]
    lag_gain = np.minimum(1.0, STEP / np.maximum(params.current_lag, STEP))[:, None]
    speed_gain = np.where(params.speed_reading == 1,
                          np.minimum(1.0, STEP / np.maximum(params.speed_lag, STEP)), 1.0)[:, None]
    active = np.zeros((count, WHEELS), dtype=bool)  # fault active on (plant, wheel)
    target = np.zeros((count, WHEELS))

    for k in range(steps):
        t = k * STEP
        # Faults switched on at their time.
        starting = (t >= fault_time) & ~active[plants, fault_wheel]
        if starting.any():
            for p in np.flatnonzero(starting):
                w = fault_wheel[p]
                active[p, w] = True
                if has['runaway'][p]:
                    held_target[p, w] = target[p, w]
                if has['encoder_freeze'][p]:  # an encoder-derived speed reads 0 from then on
                    frozen_angle[p, w] = angle[p, w]
                    frozen_speed[p, w] = lagged_speed[p, w] if params.speed_reading[p] else 0.0
        # Commands in force at the firmware, ``delay`` after they were sent.
        while True:
            due = t - params.delay >= command_at[plants, pointer + 1]
            if not due.any():
                break
            pointer = pointer + due
        target = np.where((pointer >= 0)[:, None], command_value[plants, np.maximum(pointer, 0)], 0.0)
        target = np.where(np.isnan(held_target), target, held_target)
        if k % firmware_every == 0:
            seen = np.where(active & has['encoder_freeze'][:, None], frozen_speed, speed)
            error = target - seen
            integral = np.clip(integral + error * FIRMWARE_PERIOD, -integral_limit, integral_limit)
            wanted = np.where(params.current_mode[:, None],
                              target / torque_per_amp * params.torque_scale[:, None],  # nominal amps
                              params.kp[:, None] * error + params.ki[:, None] * integral)
            silent = active & has['comm_loss'][:, None] & (t >= fault_time + CONTROLLER_TIMEOUT)[:, None]
            wanted = np.where(silent, 0.0, wanted)
            limit = params.current_limit[:, None]
            current_command = np.clip(wanted, -limit, limit)
        current += (current_command - current) * lag_gain

        # Loads: the base plus payload, its centre shifting the wheels' share.
        load = np.where(t >= payload_time, payload_after, payload)
        total = params.mass + load
        centre = offset * (load / total)[:, None]
        share = 0.25 * (1.0 + centre[:, 0:1] * np.sign(WHEEL_X) / np.abs(WHEEL_X)
                        + centre[:, 1:2] * np.sign(WHEEL_Y) / np.abs(WHEEL_Y))
        normal = np.maximum(share, 0.02) * (total * GRAVITY)[:, None]  # (P, 4) [N]
        resistance = np.where(t >= floor_time, floor_after, floor)[:, None]

        # Contacts: slip along each roller's axis meets traction; along its free direction the
        # roller's resistance; the wheel's own rolling resistance.
        vx, vy, wz = twist[:, 0:1], twist[:, 1:2], twist[:, 2:3]
        contact_x = vx - wz * WHEEL_Y - RADIUS * speed
        contact_y = vy + wz * WHEEL_X
        slip = contact_x * AXIS[:, 0] + contact_y * AXIS[:, 1]
        glide = contact_x * FREE[:, 0] + contact_y * FREE[:, 1]
        grip = -params.traction[:, None] * normal * np.tanh(slip / SLIP_SPEED)
        drag = -params.roller_resistance[:, None] * resistance * normal * np.tanh(glide / ROLL_SPEED)
        force_x = grip * AXIS[:, 0] + drag * FREE[:, 0]
        force_y = grip * AXIS[:, 1] + drag * FREE[:, 1]
        rolling = (params.rolling_resistance[:, None] * resistance * normal
                   * np.tanh(RADIUS * speed / ROLL_SPEED))

        # Wheels: motor torque against bearing friction, rolling resistance and the contact.
        gain = np.where(active & has['torque_loss'][:, None], magnitude[:, None], 1.0)
        viscous = np.where(active & has['friction'][:, None], params.viscous * magnitude[:, None],
                           params.viscous)
        viscous = np.where(active & has['stuck'][:, None], STUCK_FRICTION, viscous)
        coulomb = np.where(active & has['friction'][:, None], params.coulomb * magnitude[:, None],
                           params.coulomb)
        direction = np.tanh(speed / COULOMB_SPEED)
        coulomb_torque = coulomb * direction * (1.0 + params.asymmetry * direction)
        wheel_torque = (gain * torque_per_amp * current - coulomb_torque - rolling - RADIUS * force_x)
        # The bearing's viscous part implicitly: stable for any friction (a blocked wheel's too).
        inertia = params.wheel_inertia[:, None]
        speed = (speed + STEP * wheel_torque / inertia) / (1.0 + STEP * viscous / inertia)
        angle = angle + STEP * speed

        # The base (base-frame velocities: the rotating frame's terms).
        fx, fy = force_x.sum(axis=1), force_y.sum(axis=1)
        moment = (WHEEL_X * force_y - WHEEL_Y * force_x).sum(axis=1)
        twist = twist + STEP * np.stack([fx / total + twist[:, 2] * twist[:, 1],
                                         fy / total - twist[:, 2] * twist[:, 0],
                                         moment / (params.yaw_inertia + load * 0.05)], axis=1)
        lagged_speed += (speed - lagged_speed) * speed_gain

        # Samples due now (each plant on its own clock).
        due = next_sample == k
        if due.any():
            for p in np.flatnonzero(due):
                i = sample_index[p]
                frozen = active[p] & has['encoder_freeze'][p]
                rows[p][i, 0] = np.where(frozen, frozen_angle[p], angle[p])
                rows[p][i, 1] = np.where(frozen, frozen_speed[p], lagged_speed[p])
                rows[p][i, 2] = current[p]
                sample_index[p] = i + 1
                next_sample[p] = sample_step[p][i + 1] if i + 1 < len(sample_step[p]) else steps
    return [_publish(params, drives[p], p, sample_times[p], sample_kept[p], rows[p],
                     sent_at[p], sent[p], rng) for p in range(count)]


def _publish(params, drive, p, times, kept, rows, command_times, commands, rng):
    """What the plant's driver publishes: readings in motor units as the modules give them
    (quantised or not), the speed reading of its kind, noise, NaN while a module is silent,
    dropped samples left out; wheel side, driver convention."""
    angle, true_speed, current = rows[:, 0], rows[:, 1], rows[:, 2]
    motor_turn = 2.0 * np.pi / GEAR  # wheel rad -> motor rad
    position = angle.copy()
    if params.quantised[p]:
        position = np.round(angle * motor_turn / (2 * np.pi) * TICKS) / TICKS * 2 * np.pi / motor_turn
    kind = params.speed_reading[p]
    if kind == 0:  # differentiated from the encoder over the last sampling interval
        speed = np.vstack([np.zeros((1, WHEELS)), np.diff(position, axis=0) / np.diff(times)[:, None]])
    else:
        speed = true_speed.copy()
    if kind == 2:
        speed = speed + rng.normal(0.0, params.speed_noise[p], speed.shape)
    measured = current + rng.normal(0.0, params.current_noise[p], current.shape)
    if params.quantised[p]:
        rpm = np.round(speed / GEAR * 60.0 / (2 * np.pi))
        speed = rpm * GEAR * 2 * np.pi / 60.0
        measured = np.round(measured * 1000.0) / 1000.0
    effort = measured * TORQUE_CONSTANT / GEAR  # the driver's datasheet conversion
    if drive.fault == 'comm_loss':
        silent = times >= drive.fault_time
        for array in (position, speed, effort):
            array[silent, drive.wheel] = np.nan
    keep = kept.copy()
    keep[0] = True
    recording = Recording(times[keep], DRIVE_SIGNS * position[keep], DRIVE_SIGNS * speed[keep],
                          DRIVE_SIGNS * effort[keep], command_times, DRIVE_SIGNS * commands,
                          bool(params.current_mode[p]))
    recording.fault_visible = _visible(drive, command_times, commands, params.current_mode[p])
    return recording


#: A runaway shows once its wheel's command has changed by this much (velocity [rad/s], current
#: mode [N·m]): a wheel that keeps its drive does what it is told.
VISIBLE_CHANGE = {False: 0.5, True: 0.05}


def _visible(drive, command_times, commands, current_mode):
    """When the fault could first be seen [s]: a lost link at once; a runaway once its wheel's
    command has changed (:data:`VISIBLE_CHANGE`) after the fault; any other fault (actuator,
    friction, a frozen encoder) once its wheel is driven (its command at least
    :data:`VISIBLE_CHANGE`): a wheel told to stand shows none of them. NaN: never."""
    if drive.fault is None:
        return math.nan
    if drive.fault == 'comm_loss':
        return drive.fault_time
    before = command_times <= drive.fault_time
    held = commands[np.flatnonzero(before)[-1], drive.wheel] if before.any() else 0.0
    threshold = VISIBLE_CHANGE[bool(current_mode)]
    if drive.fault == 'runaway':
        shows = (~before) & (np.abs(commands[:, drive.wheel] - held) > threshold)
    elif abs(held) > threshold:
        return drive.fault_time
    else:
        shows = (~before) & (np.abs(commands[:, drive.wheel]) > threshold)
    return float(command_times[np.argmax(shows)]) if shows.any() else math.nan
