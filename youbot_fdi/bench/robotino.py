"""Real recordings of a Festo Robotino (``shared/real_data/robotino``) as rosbag2 recordings, with
faults injected into the recorded signals, and the real-data fault benchmark suite.

The data stay in ``shared/`` (Apache-2.0, see its README); this module converts them on the fly.
Columns used (motor side): ``t`` [ms], ``m{1,2,3}setvel`` set speed [rad/s], ``m{1,2,3}pos`` encoder
[ticks], ``m{1,2,3}vel`` measured speed [rad/s], ``m{1,2,3}cur`` |current| [A]. Converted to the
contract's wheel side with the ``robotino`` profile's drive train: speeds x gear ratio, ticks to
wheel rad, |current| x torque per amp (``effort`` is a magnitude: the profile says so).

Each CSV row is one sample; its set speeds go out as a /wheel_commands message stamped like the
sample (the logger stamps both alike: the case the clock rule in docs/fdi.md is about).
"""
from dataclasses import dataclass, replace
import math
import os
from pathlib import Path

import numpy as np

ENV_DATA = 'YOUBOT_FDI_ROBOTINO_DATA'
#: Where the data live when ``$YOUBOT_FDI_ROBOTINO_DATA`` is not set: ``shared/`` beside the repo.
DEFAULT_DATA = Path(__file__).resolve().parents[2].parent / 'shared' / 'real_data' / 'robotino'
PROFILE = 'robotino'
SURFACES = ('green_surface', 'gray_surface')
CROSSINGS = ('green_gray_validation_data.csv', 'table_green_validation_data.csv')
IDENTIFICATION_DIR = 'dc_motor_model_identification'
START_STAMP = 1_650_000_000.0  # [s] recordings start here so stamps look like a robot's
TICKS_PER_MOTOR_RAD = 314.6  # what the runs integrate to (README)
#: Faults injected into the recorded signals of one wheel from the onset on.
FAULTS = {
    'encoder_freeze': 'position reading held',
    'current_up': 'current x 1.8 (the wheel needs more torque)',
    'current_down': 'current x 0.5',
    'speed_zero': 'speed reading forced to 0 while commanded',
    'jam': 'the wheel blocked: position held, speed 0, current rising to the drive limit',
    'ramp': 'current ramping x1 -> x2 over RAMP_TIME (a bearing going bad), then x2',
    'intermittent': 'every reading held for 3-5 samples every INTERMITTENT_PERIOD (a flaky module)',
}
#: Faults that begin at once (the issue's delay targets are about these).
ABRUPT = ('encoder_freeze', 'current_up', 'current_down', 'speed_zero', 'jam')
CURRENT_SCALE = {'current_up': 1.8, 'current_down': 0.5}
EXPECTED_KIND = {'encoder_freeze': 'encoder_freeze', 'current_up': 'friction',
                 'current_down': 'torque_loss', 'speed_zero': 'encoder_freeze', 'jam': 'stuck',
                 'ramp': 'friction', 'intermittent': None}
RAMP_TIME = 4.0  # [s] x1 -> x2
JAM_RISE = 0.1  # [s] the blocked wheel's current reaches the limit in this time
INTERMITTENT_PERIOD = 0.5  # [s] between held stretches
INTERMITTENT_HOLDS = (3, 4, 5)  # samples held, in turn
STAMPINGS = ('with', 'before', 'after', 'bag_time')


def data_dir():
    """The Robotino data folder (``$YOUBOT_FDI_ROBOTINO_DATA`` or shared/ beside the repo), or None."""
    path = Path(os.environ.get(ENV_DATA) or DEFAULT_DATA)
    return path if (path / SURFACES[0]).is_dir() else None


@dataclass(frozen=True)
class RobotinoRun:
    """One CSV run, motor side as logged: ``time`` (k,) [s], the rest (k, 3)."""

    name: str
    time: np.ndarray
    set_speed: np.ndarray  # [rad/s]
    ticks: np.ndarray  # [ticks]
    speed: np.ndarray  # [rad/s]
    current: np.ndarray  # [A], magnitude

    def __len__(self):
        return len(self.time)

    def rows(self, start, stop):
        """Rows ``start:stop``."""
        return replace(self, **{f: getattr(self, f)[start:stop] for f in
                                ('time', 'set_speed', 'ticks', 'speed', 'current')})


def read_run(path):
    """Read a Robotino CSV (three header rows: names, units, keys; ``;``-separated)."""
    path = Path(path)
    lines = path.read_text().splitlines()
    if len(lines) < 4:
        msg = f'{path}: not a Robotino run (needs three header rows and data)'
        raise ValueError(msg)
    keys = [k for k in lines[2].strip().split(';') if k]
    rows = []
    for line in lines[3:]:
        cells = [c for c in line.strip().split(';')][:len(keys)]
        if len(cells) == len(keys):
            rows.append([float(c) if c else math.nan for c in cells])
    data = np.array(rows, dtype=float)
    column = {k: data[:, i] for i, k in enumerate(keys)}

    def wheels(key):
        return np.column_stack([column[f'm{i}{key}'] for i in (1, 2, 3)])

    return RobotinoRun(path.stem, column['t'] / 1000.0, wheels('setvel'), wheels('pos'),
                       wheels('vel'), np.abs(wheels('cur')))


def inject(run, fault, wheel, onset, max_current=None):
    """``run`` with ``fault`` (a key of :data:`FAULTS`) on wheel index ``wheel`` from row ``onset``
    (``max_current`` [A, motor]: the drive's limit a jammed wheel's current rises to)."""
    ticks, speed, current = run.ticks.copy(), run.speed.copy(), run.current.copy()
    since = run.time[onset:] - run.time[onset]  # [s]
    if fault == 'encoder_freeze':
        ticks[onset:, wheel] = ticks[onset, wheel]
    elif fault == 'speed_zero':
        speed[onset:, wheel] = 0.0
    elif fault in CURRENT_SCALE:
        current[onset:, wheel] *= CURRENT_SCALE[fault]
    elif fault == 'ramp':
        current[onset:, wheel] *= 1.0 + np.clip(since / RAMP_TIME, 0.0, 1.0)
    elif fault == 'jam':
        if max_current is None:
            msg = 'a jam needs the drive\'s max_current'
            raise ValueError(msg)
        ticks[onset:, wheel] = ticks[onset, wheel]
        speed[onset:, wheel] = 0.0
        start = current[onset, wheel]
        current[onset:, wheel] = start + (max_current - start) * np.clip(since / JAM_RISE, 0.0, 1.0)
    elif fault == 'intermittent':
        dt = float(np.median(np.diff(run.time)))
        period = max(1, int(round(INTERMITTENT_PERIOD / dt)))
        for k, first in enumerate(range(onset, len(run) - 1, period)):
            last = min(len(run), first + 1 + INTERMITTENT_HOLDS[k % len(INTERMITTENT_HOLDS)])
            for array in (ticks, speed, current):
                array[first + 1:last, wheel] = array[first, wheel]
    else:
        msg = f'unknown fault {fault!r}; known: {sorted(FAULTS)}'
        raise ValueError(msg)
    return replace(run, ticks=ticks, speed=speed, current=current)


def splice(first, second, at):
    """A run that drives ``first`` up to its row ``at`` and ``second`` from its row ``at`` on (the
    floor covering changes under the robot): time and encoder continue without a jump."""
    head, tail = first.rows(0, at), second.rows(at, len(second))
    dt = float(np.median(np.diff(first.time)))
    time_shift = head.time[-1] + dt - tail.time[0]
    tick_shift = head.ticks[-1] - second.ticks[at - 1]
    return RobotinoRun(f'{first.name}+{second.name}@{at}',
                       np.concatenate([head.time, tail.time + time_shift]),
                       *(np.concatenate([getattr(head, f), getattr(tail, f) + shift]) for f, shift in
                         (('set_speed', 0.0), ('ticks', tick_shift), ('speed', 0.0), ('current', 0.0))))


def write_recording(runs, path, model, stamping='with', gap=1.0, storage='sqlite3'):
    """Write ``runs`` (one or several, one after the other with ``gap`` [s] between) as a rosbag2
    recording at ``path``, wheel side, driver convention.

    ``stamping``: ``with`` (command and sample stamped alike, as logged), ``before``/``after`` (the
    command stamped half a sample interval before/after its sample), ``bag_time`` (no header stamps:
    zero, the receive time carries the time). Returns the start stamp of each run [s].
    """
    from youbot_fdi.bag.writer import RecordingWriter
    drive = model.drive
    rad_per_tick = drive.gear_ratio / TICKS_PER_MOTOR_RAD
    torque_per_amp = drive.torque_per_amp
    offset, starts = START_STAMP, []
    with RecordingWriter(path, model.wheel_names, storage) as writer:
        for run in runs:
            starts.append(offset)
            dt = float(np.median(np.diff(run.time)))
            for k in range(len(run)):
                stamp = offset + run.time[k] - run.time[0]
                shift = {'before': -0.5 * dt, 'after': 0.5 * dt}.get(stamping, 0.0)
                header = None if stamping == 'bag_time' else stamp
                writer.wheel_command(stamp + shift, 'velocity', run.set_speed[k] * drive.gear_ratio,
                                     header_stamp=None if header is None else header + shift)
                writer.joint_state(stamp, run.ticks[k] * rad_per_tick, run.speed[k] * drive.gear_ratio,
                                   run.current[k] * torque_per_amp, header_stamp=header)
            offset = stamp + gap
    return starts


# ---------------------------------------------------------------------- injection sites
ONSET_SHARE = 0.5  # a fault begins at this share of the run
MOVING_SHARE = 0.5  # faults go on wheels set to at least this share of the run's fastest wheel
