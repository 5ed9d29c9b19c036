"""A youBot simulator written independently of youbot_fdi's model code, for recordings 'not made by
this project's simulator': RK4 on the continuous dynamics at 0.1 ms, its own 1 kHz PI loop,
Coulomb friction, /joint_states at 50 Hz (as the youBot driver publishes) with the ROS 1 driver's
extra caster joints and a scrambled joint order, integer ticks, rpm and mA. It only shares the
written-down physics (report eq. 3.8, 3.19) and the contract, not code.
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


def simulate(path, segments, fault=None, wheel=0, fault_time=math.inf, seed=0, m=26.0, jz=1.1,
             jw=0.0105, friction=0.045, coulomb=0.03, kp=0.8, ki=7.0):
    """Drive ``segments`` [(vx, vy, wz, seconds)] and write a rosbag2 recording at ``path``."""
    rng = np.random.default_rng(seed)
    inv_m = np.linalg.inv(mass_matrix(m, jz, jw))
    d = np.full(4, friction)
    theta, omega, integral, current = np.zeros(4), np.zeros(4), np.zeros(4), np.zeros(4)
    gain = np.ones(4)
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
            if t >= next_command:
                next_command += COMMAND
                cmd = SIGNS * target
                writer.names = list(NAMES)
                writer.wheel_command(start + t, 'velocity', cmd)
            if t >= next_control:
                next_control += CONTROL
                error = target - omega
                integral = np.clip(integral + error * CONTROL, -I_MAX / ki, I_MAX / ki)
                current = np.clip(kp * error + ki * integral, -I_MAX, I_MAX)
            if t >= next_sample:
                next_sample += SAMPLE
                values = {n: (0.0, 0.0, 0.0) for n in PUBLISHED}
                for i, name in enumerate(NAMES):
                    ticks = round(SIGNS[i] * theta[i] / (2 * math.pi * GEAR) * TICKS)
                    rpm = round(SIGNS[i] * omega[i] / GEAR * 60 / (2 * math.pi) + rng.normal(0, 1.0))
                    milliamps = round(SIGNS[i] * current[i] * 1000 + rng.normal(0, 8.0))
                    values[name] = (ticks / TICKS * 2 * math.pi * GEAR, rpm * 2 * math.pi / 60 * GEAR,
                                    milliamps / 1000 * KT / GEAR)
                writer.names = list(PUBLISHED)
                writer.joint_state(start + t, *zip(*(values[n] for n in PUBLISHED)))

            def acceleration(w):
                torque = gain * current * KT / GEAR - d * w - coulomb * np.tanh(w / 0.05)
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
