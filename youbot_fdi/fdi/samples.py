"""Wheel samples from JointState-shaped data (a recording's or a topic's), matched by joint name.

One implementation for the bag reader and the nodes: bad messages (NaN, short arrays, missing
wheels) are skipped and counted, never fatal.
"""
from dataclasses import dataclass
import math

import numpy as np


@dataclass(frozen=True)
class JointSample:
    """One /joint_states message, in the model's wheel order (driver convention)."""

    stamp: float  # header stamp [s]
    position: np.ndarray  # [rad]
    velocity: np.ndarray  # [rad/s]
    effort: np.ndarray  # [N·m]; NaN where the message had none


@dataclass(frozen=True)
class CommandSample:
    """One /wheel_commands message, in the model's wheel order (driver convention)."""

    stamp: float  # [s]
    kind: str  # 'velocity' [rad/s] or 'effort' [N·m]
    values: np.ndarray


COUNTERS = ('joint_states', 'wheel_commands', 'skipped_nan', 'skipped_short',
            'skipped_missing_joint', 'skipped_no_values')


class SampleMapper:
    """Maps JointState fields to the model's wheel order and validates them."""

    def __init__(self, wheel_names):
        self.wheel_names = tuple(wheel_names)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self._index_cache = {}

    def _indices(self, names):
        key = tuple(names)
        if key not in self._index_cache:
            position = {name: i for i, name in enumerate(key)}
            missing = [n for n in self.wheel_names if n not in position]
            self._index_cache[key] = (None if missing else
                                      np.array([position[n] for n in self.wheel_names]))
        return self._index_cache[key]

    def _pick(self, array, index, n_names):
        if len(array) == 0:
            return None
        if len(array) < n_names:
            self.counters['skipped_short'] += 1
            return False
        return np.asarray(array, dtype=float)[index]

    def joint_sample(self, stamp, names, position, velocity, effort):
        """A :class:`JointSample`, or None (counted) for a message that cannot be used."""
        index = self._indices(names)
        if index is None:
            self.counters['skipped_missing_joint'] += 1
            return None
        n = len(names)
        position, velocity, effort = (self._pick(a, index, n) for a in (position, velocity, effort))
        if position is False or velocity is False or effort is False:
            return None
        if position is None or velocity is None:
            self.counters['skipped_no_values'] += 1
            return None
        if effort is None:
            effort = np.full(len(self.wheel_names), math.nan)
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(velocity))):
            self.counters['skipped_nan'] += 1
            return None
        self.counters['joint_states'] += 1
        return JointSample(stamp, position, velocity, effort)

    def command_sample(self, stamp, names, velocity, effort):
        """A :class:`CommandSample` (velocity preferred), or None (counted)."""
        index = self._indices(names)
        if index is None:
            self.counters['skipped_missing_joint'] += 1
            return None
        n = len(names)
        for kind, array in (('velocity', velocity), ('effort', effort)):
            values = self._pick(array, index, n)
            if values is False:
                return None
            if values is None:
                continue
            if not np.all(np.isfinite(values)):
                self.counters['skipped_nan'] += 1
                return None
            self.counters['wheel_commands'] += 1
            return CommandSample(stamp, kind, values)
        self.counters['skipped_no_values'] += 1
        return None
