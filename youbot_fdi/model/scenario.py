"""Scripted drives: a sequence of base twists held for given durations (demo, benchmarks, tests),
optionally reached through acceleration-limited ramps, as a velocity smoother (Nav2's
``velocity_smoother``) hands commands to a base."""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.settings import finite_number
from youbot_fdi.yamlio import load_yaml

DEFAULT_SCRIPT = 'demo.yaml'
DEFAULT_PROFILE = 'youbot'

TWIST_KEYS = ('vx', 'vy', 'wz')


@dataclass(frozen=True)
class Segment:
    """One piece of a drive: a base twist held for ``duration`` [s]."""

    name: str
    twist: tuple  # (v_x [m/s], v_y [m/s], w_z [rad/s])
    duration: float  # [s]


@dataclass(frozen=True)
class AccelerationLimit:
    """The commanded twist's largest rate of change: ``linear`` [m/s^2] of the planar velocity
    vector, ``angular`` [rad/s^2] of the yaw rate. A change of command is a straight-line ramp
    in (v_x, v_y, w_z) that meets both limits, so every axis arrives together and the direction
    of the change is kept (Nav2's velocity_smoother with ``scale_velocities``)."""

    linear: float  # [m/s^2]
    angular: float  # [rad/s^2]

    def ramp_time(self, change):
        """Duration [s] of a ramp through the twist change ``change`` (3,)."""
        return max(float(np.hypot(change[0], change[1])) / self.linear,
                   abs(float(change[2])) / self.angular)

    @classmethod
    def from_config(cls, raw, source='<drive script>'):
        """Validate ``{linear: m/s^2, angular: rad/s^2}``; both > 0."""
        if not isinstance(raw, dict) or set(raw) != {'linear', 'angular'}:
            msg = f'{source}: max_acceleration must be a mapping with linear and angular, got {raw!r}'
            raise ConfigError(msg)
        values = {key: finite_number(raw[key], f'{source}: max_acceleration.{key}')
                  for key in ('linear', 'angular')}
        for key, value in values.items():
            if value <= 0.0:
                msg = f'{source}: max_acceleration.{key} must be > 0, got {value:g}'
                raise ConfigError(msg)
        return cls(**values)


@dataclass(frozen=True)
class DriveScript:
    """An ordered list of segments; after the last one the base is commanded to stand still.

    Without ``max_acceleration`` each segment's twist is commanded from its first instant (steps);
    with it, the command ramps from where it stands (rest before the first segment) to each
    segment's twist, a ramp a segment is too short for being cut off where the segment ends.
    """

    segments: tuple
    max_acceleration: object = None  # AccelerationLimit or None

    @property
    def duration(self):
        """Total duration [s]."""
        return float(sum(s.duration for s in self.segments))

    @classmethod
    def from_config(cls, raw_segments, source='<drive script>', max_acceleration=None):
        """Validate a list of ``{name, vx, vy, wz, duration}`` mappings and an optional
        ``{linear, angular}`` acceleration limit (:class:`AccelerationLimit`)."""
        if not isinstance(raw_segments, list) or not raw_segments:
            msg = f'{source}: segments must be a non-empty list'
            raise ConfigError(msg)
        segments = []
        for index, raw in enumerate(raw_segments):
            where = f'{source}: segments[{index}]'
            if not isinstance(raw, dict):
                msg = f'{where} must be a mapping, got {raw!r}'
                raise ConfigError(msg)
            unknown = set(raw) - {'name', 'duration', *TWIST_KEYS}
            if unknown:
                msg = f'{where}: unknown keys {sorted(unknown)}'
                raise ConfigError(msg)
            values = {key: finite_number(raw.get(key, 0.0), f'{where}.{key}')
                      for key in ('duration', *TWIST_KEYS)}
            if values['duration'] <= 0.0:
                msg = f'{where}.duration must be > 0 s, got {values["duration"]:g}'
                raise ConfigError(msg)
            segments.append(Segment(str(raw.get('name', f'segment {index}')),
                                    tuple(values[k] for k in TWIST_KEYS), values['duration']))
        limit = None if max_acceleration is None else AccelerationLimit.from_config(max_acceleration, source)
        return cls(tuple(segments), limit)

    def scaled_to(self, duration):
        """The same script stretched or shrunk in time to last ``duration`` [s]."""
        if not duration > 0.0:
            msg = f'duration must be > 0 s, got {duration!r}'
            raise ValueError(msg)
        factor = duration / self.duration
        return DriveScript(tuple(Segment(s.name, s.twist, s.duration * factor)
                                 for s in self.segments), self.max_acceleration)

    def repeated(self, count):
        """The script driven ``count`` times in a row (a soak)."""
        if int(count) != count or count < 1:
            msg = f'count must be a whole number >= 1, got {count!r}'
            raise ValueError(msg)
        return DriveScript(self.segments * int(count), self.max_acceleration)

    def as_steps(self):
        """The same segments without the acceleration limit: each twist commanded at once."""
        return DriveScript(self.segments)

    def twists(self, times):
        """Commanded twist at each time [s] from the start; shape (k, 3). Zero after the end
        (once the last ramp has ended)."""
        times = np.asarray(times, dtype=float)
        if self.max_acceleration is None:
            ends = np.cumsum([s.duration for s in self.segments])
            table = np.vstack([np.array([s.twist for s in self.segments]), np.zeros((1, 3))])
            return table[np.searchsorted(ends, times, side='right')]
        knots, values = self._ramp_knots()
        flat = times.reshape(-1)
        out = np.column_stack([np.interp(flat, knots, values[:, axis]) for axis in range(3)])
        return out.reshape(times.shape + (3,))

    def _ramp_knots(self):
        """Corners (times [s] (m,), twists (m, 3)) of the piecewise-linear ramped command."""
        knots, values = [0.0], [np.zeros(3)]
        start, current = 0.0, np.zeros(3)
        targets = [(np.array(s.twist), s.duration) for s in self.segments] + [(np.zeros(3), np.inf)]
        for target, duration in targets:
            ramp = self.max_acceleration.ramp_time(target - current)
            if ramp > 0.0:
                reached = min(ramp, duration)
                current = current + (target - current) * (reached / ramp)
                knots.append(start + reached)
                values.append(current)
            start += duration
            if np.isfinite(start):
                knots.append(start)
                values.append(current)
        return np.array(knots), np.array(values)


def load_script(path=None, duration=None):
    """(profile name, DriveScript) from a script YAML (default ``config/demo.yaml``).

    ``duration`` [s] stretches or shrinks the script to that length.
    """
    path = Path(path) if path else config_dir() / DEFAULT_SCRIPT
    try:
        data = load_yaml(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as err:
        msg = f'{path}: cannot read the drive script: {err}'
        raise ConfigError(msg) from err
    if not isinstance(data, dict):
        msg = f'{path}: a drive script is a mapping with segments'
        raise ConfigError(msg)
    script = DriveScript.from_config(data.get('segments'), str(path), data.get('max_acceleration'))
    return data.get('profile', DEFAULT_PROFILE), (script.scaled_to(duration) if duration else script)
