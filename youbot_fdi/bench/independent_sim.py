"""A youBot simulator written independently of youbot_fdi's model code, for recordings 'not made by
this project's simulator': RK4 on the continuous dynamics at 0.1 ms, its own 1 kHz PI loop (or
current mode: open-loop efforts), Coulomb friction, an actuation delay, /joint_states at 50 Hz (as
the youBot driver publishes) with the ROS 1 driver's extra caster joints and a scrambled joint
order, integer ticks, rpm and mA, commands stamped before, with or after the samples. Every fault
type of the contract. It only shares the written-down physics (report eq. 3.8, 3.19) and the
contract, not code.
"""
import math

import numpy as np

from youbot_fdi.bag import RecordingWriter

R, HALF_SUM = 0.0475, 0.385
GEAR, KT, TICKS, I_MAX = 364 / 9405, 0.0335, 4000, 3.564
SIGNS = np.array([-1.0, 1.0, -1.0, 1.0])
NAMES = ['wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl', 'wheel_joint_br']
PUBLISHED = ['caster_joint_fl', 'wheel_joint_br', 'caster_joint_fr', 'wheel_joint_fl',
             'wheel_joint_bl', 'caster_joint_bl', 'wheel_joint_fr', 'caster_joint_br']
SUBSTEP, CONTROL, SAMPLE, COMMAND = 1e-4, 1e-3, 0.02, 0.05  # [s]


def inverse(vx, vy, wz):
    """Report eq. 3.8 (kinematic convention)."""
    return np.array([vx - vy - HALF_SUM * wz, vx + vy + HALF_SUM * wz,
                     vx + vy - HALF_SUM * wz, vx - vy + HALF_SUM * wz]) / R


def mass_matrix(m, jz, jw):
    """Report §3.2 closed form."""
    a, b = m * R ** 2 / 8, jz * R ** 2 / (16 * HALF_SUM ** 2)
    return np.array([[a + b + jw, -b, b, a - b], [-b, a + b + jw, a - b, b],
                     [b, a - b, a + b + jw, -b], [a - b, b, -b, a + b + jw]])


FAULTS = ('stuck', 'torque_loss', 'friction', 'runaway', 'encoder_freeze', 'comm_loss')
STAMPINGS = {'before': -0.5, 'with': 0.0, 'after': 0.5}  # command stamp shift, in samples


def simulate(path, segments, fault=None, wheel=0, fault_time=math.inf, seed=0, m=26.0, jz=1.1,
             jw=0.0105, friction=0.045, coulomb=0.03, kp=0.8, ki=7.0, mode='velocity', delay=0.004,
             stamping='before', surface_factor=1.0, surface_time=math.inf, coulomb_asymmetry=0.0):
    """Drive ``segments`` [(vx, vy, wz, seconds)] and write a rosbag2 recording at ``path``.

    ``mode`` velocity (PI loop) or effort (open-loop current commands); commands act ``delay`` [s]
    late; ``stamping`` places a command's stamp relative to the sample it goes out with; from
    ``surface_time`` [s] every wheel's friction is ``surface_factor`` times higher (another floor
    covering: not a fault); ``coulomb_asymmetry`` makes Coulomb friction differ by direction
    (``coulomb * (1 + a)`` turning forward, ``coulomb * (1 - a)`` backward: what the project's
    model does not have). Returns the start stamp [s]."""
    rng = np.random.default_rng(seed)
    inv_m = np.linalg.inv(mass_matrix(m, jz, jw))
    d = np.full(4, friction)
    wheel_coulomb = np.full(4, coulomb)
    surface_changed = False
    theta, omega, integral, current = np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4)
    gain = np.ones(4)
    held = None  # runaway: the wheel's command at the fault
    frozen_reading = None
    queue = []  # (due time, target) of commands in flight
    applied = np.zeros(4)
    ends = np.cumsum([s[3] for s in segments])
    t, start = 0.0, 1_750_000_000.0
    next_control, next_sample, next_command = 0.0, 0.0, 0.0
    with RecordingWriter(path, PUBLISHED) as writer:
        while t < ends[-1]:
            k = int(np.searchsorted(ends, t, side='right'))
            target = inverse(*segments[k][:3]) if k < len(segments) else np.zeros(4)
            if t >= fault_time and fault == 'stuck':
                d[wheel] = 50.0  # blocks the wheel (~0.06 rad/s at full current); RK4-stable
            if t >= fault_time and fault == 'torque_loss':
                gain[wheel] = 0.35
            if t >= fault_time and fault == 'friction':
                d[wheel] = friction * 6.0
            if t >= surface_time and not surface_changed:
                surface_changed = True
                d, wheel_coulomb = d * surface_factor, wheel_coulomb * surface_factor
            wanted = target if mode == 'velocity' else friction * target + coulomb * np.tanh(target / 0.05)
            if t >= next_command:
                next_command += COMMAND
                cmd = SIGNS * wanted
                writer.names = list(NAMES)
                shift = STAMPINGS[stamping] * SAMPLE
                writer.wheel_command(start + t + shift, mode, cmd)
                queue.append((t + delay, wanted.copy()))
            while queue and queue[0][0] <= t:
                applied = queue.pop(0)[1]
            if t >= fault_time and fault == 'runaway':
                held = applied[wheel] if held is None else held
                applied = applied.copy()
                applied[wheel] = held
            if t >= next_control:
                next_control += CONTROL
                if mode == 'velocity':
                    error = applied - omega
                    integral = np.clip(integral + error * CONTROL, -I_MAX / ki, I_MAX / ki)
                    current = np.clip(kp * error + ki * integral, -I_MAX, I_MAX)
                else:
                    current = np.clip(applied * GEAR / KT, -I_MAX, I_MAX)
            if t >= next_sample and fault == 'comm_loss' and t >= fault_time:
                next_sample += SAMPLE  # the base stops publishing
            if t >= next_sample:
                next_sample += SAMPLE
                values = {n: (0.0, 0.0, 0.0) for n in PUBLISHED}
                for i, name in enumerate(NAMES):
                    ticks = round(SIGNS[i] * theta[i] / (2 * math.pi * GEAR) * TICKS)
                    rpm = round(SIGNS[i] * omega[i] / GEAR * 60 / (2 * math.pi) + rng.normal(0, 1.0))
                    milliamps = round(SIGNS[i] * current[i] * 1000 + rng.normal(0, 8.0))
                    values[name] = (ticks / TICKS * 2 * math.pi * GEAR, rpm * 2 * math.pi / 60 * GEAR,
                                    milliamps / 1000 * KT / GEAR)
                if fault == 'encoder_freeze' and t >= fault_time:
                    frozen_reading = frozen_reading or values[NAMES[wheel]][:2]
                    values[NAMES[wheel]] = (*frozen_reading, values[NAMES[wheel]][2])
                writer.names = list(PUBLISHED)
                writer.joint_state(start + t, *zip(*(values[n] for n in PUBLISHED)))

            def acceleration(w):
                direction = np.tanh(w / 0.05)
                torque = (gain * current * KT / GEAR - d * w
                          - wheel_coulomb * direction * (1.0 + coulomb_asymmetry * direction))
                return inv_m @ torque

            for _ in range(int(round(min(CONTROL, SAMPLE) / SUBSTEP))):  # RK4
                k1 = acceleration(omega)
                k2 = acceleration(omega + 0.5 * SUBSTEP * k1)
                k3 = acceleration(omega + 0.5 * SUBSTEP * k2)
                k4 = acceleration(omega + SUBSTEP * k3)
                theta = theta + SUBSTEP * omega + SUBSTEP ** 2 / 6 * (k1 + k2 + k3)
                omega = omega + SUBSTEP / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                t += SUBSTEP
    return start
