"""Scripted drives: a sequence of base twists held for given durations (demo, benchmarks, tests)."""
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
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
class DriveScript:
    """An ordered list of segments; after the last one the base is commanded to stand still."""

    segments: tuple

    @property
    def duration(self):
        """Total duration [s]."""
        return float(sum(s.duration for s in self.segments))

    @classmethod
    def from_config(cls, raw_segments, source='<drive script>'):
        """Validate a list of ``{name, vx, vy, wz, duration}`` mappings."""
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
            values = {}
            for key in ('duration', *TWIST_KEYS):
                value = raw.get(key, 0.0)
                if isinstance(value, bool) or not isinstance(value, (int, float)) \
                        or not np.isfinite(value):
                    msg = f'{where}.{key} must be a finite number, got {value!r}'
                    raise ConfigError(msg)
                values[key] = float(value)
            if values['duration'] <= 0.0:
                msg = f'{where}.duration must be > 0 s, got {values["duration"]:g}'
                raise ConfigError(msg)
            segments.append(Segment(str(raw.get('name', f'segment {index}')),
                                    tuple(values[k] for k in TWIST_KEYS), values['duration']))
        return cls(tuple(segments))

    def scaled_to(self, duration):
        """The same script stretched or shrunk in time to last ``duration`` [s]."""
        if not duration > 0.0:
            msg = f'duration must be > 0 s, got {duration!r}'
            raise ValueError(msg)
        factor = duration / self.duration
        return DriveScript(tuple(Segment(s.name, s.twist, s.duration * factor)
                                 for s in self.segments))

    def twists(self, times):
        """Commanded twist at each time [s]; shape (k, 3). Zero after the end."""
        times = np.asarray(times, dtype=float)
        ends = np.cumsum([s.duration for s in self.segments])
        table = np.vstack([np.array([s.twist for s in self.segments]), np.zeros((1, 3))])
        return table[np.searchsorted(ends, times, side='right')]


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
    script = DriveScript.from_config(data.get('segments'), str(path))
    return data.get('profile', DEFAULT_PROFILE), (script.scaled_to(duration) if duration else script)
