"""Wheel samples from JointState-shaped data (a recording's or a topic's), matched by joint name.

One implementation for the bag reader and the nodes: bad messages (NaN, short arrays, missing
wheels) are skipped and counted, never fatal. Messages are validated in blocks that share their
joint names and array lengths (a recording's chunk, or one live message), so the replay handles a
chunk of messages in a few numpy operations.
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

    def complete(self):
        """True when every wheel has a reading (position and speed); a driver gives NaN for a
        module that did not answer its cycle."""
        return bool(np.isfinite(self.position).all() and np.isfinite(self.velocity).all())


@dataclass(frozen=True)
class CommandSample:
    """One /wheel_commands message, in the model's wheel order (driver convention)."""

    stamp: float  # [s]
    kind: str  # 'velocity' [rad/s] or 'effort' [N·m]
    values: np.ndarray


VELOCITY, EFFORT = 'velocity', 'effort'


@dataclass(frozen=True)
class JointBatch:
    """Consecutive /joint_states samples: ``stamp`` (N,) [s]; the rest (N, n), as in JointSample."""

    stamp: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    def __len__(self):
        return len(self.stamp)

    def sample(self, k):
        """Row ``k`` as a :class:`JointSample`."""
        return JointSample(float(self.stamp[k]), self.position[k], self.velocity[k], self.effort[k])

    def rows(self, start, stop):
        """Rows ``start:stop`` as a batch (views)."""
        return JointBatch(self.stamp[start:stop], self.position[start:stop],
                          self.velocity[start:stop], self.effort[start:stop])

    @classmethod
    def empty(cls, n):
        """No samples of ``n`` wheels."""
        return cls(np.empty(0), *(np.empty((0, n)) for _ in range(3)))

    @classmethod
    def of_sample(cls, sample):
        """One :class:`JointSample` as a batch of one row (views)."""
        return cls(np.array([sample.stamp]), *(np.asarray(a)[None] for a in
                                               (sample.position, sample.velocity, sample.effort)))

    def select(self, rows):
        """The rows picked by ``rows`` (a boolean mask or indices) as a batch."""
        return JointBatch(self.stamp[rows], self.position[rows], self.velocity[rows], self.effort[rows])

    def answered(self):
        """(N, n) bool: the wheels with a reading (position and speed) in each row; a driver
        gives NaN for a module that did not answer its cycle."""
        return np.isfinite(self.position) & np.isfinite(self.velocity)

    def complete(self):
        """(N,) bool: the rows with every wheel's reading."""
        return self.answered().all(axis=1)


def _same(now, before):
    """Row-wise: every value of ``now`` (N, n) equals ``before`` (N, n), NaN matching NaN."""
    return np.all((now == before) | (np.isnan(now) & np.isnan(before)), axis=1)


class RepeatedMessages:
    """Finds /joint_states messages that repeat the one before in every reading of every wheel
    (position, speed and effort) while that one showed a wheel turning: a logger or driver
    re-sending its last data under a new stamp (the Robotino's logger does, for up to a few
    samples). They carry no fresh data and are left out, like a gap, so that a long run of them
    is the base's comm_loss after ``data_timeout`` as a gap is; one wheel's readings repeating
    while the others change is that wheel's fault, and is kept. A base standing still repeats
    its readings legitimately (every speed reading zero) and is kept too.

    Stateful (the last message seen); :meth:`fresh` for a block, the same rule one row at a time.
    """

    def __init__(self):
        self._last = None  # (position, velocity, effort) of the last message seen, (n,) each
        self.count = 0  # messages left out so far

    def fresh(self, joints):
        """Mask (N,) of the rows of ``joints`` (:class:`JointBatch`) that carry fresh data."""
        if not len(joints):
            return np.ones(0, dtype=bool)
        arrays = (joints.position, joints.velocity, joints.effort)
        if self._last is None:
            self._last = tuple(np.full(a.shape[1], np.nan) for a in arrays)
        before = [np.concatenate([last[None], a[:-1]]) for last, a in zip(self._last, arrays)]
        repeated = (_same(joints.position, before[0]) & _same(joints.velocity, before[1])
                    & _same(joints.effort, before[2]) & np.any(before[1] != 0.0, axis=1))
        self._last = tuple(a[-1] for a in arrays)
        self.count += int(np.count_nonzero(repeated))
        return ~repeated

    def fresh_sample(self, sample):
        """Whether one :class:`JointSample` carries fresh data (the rule of :meth:`fresh`)."""
        return bool(self.fresh(JointBatch.of_sample(sample))[0])


@dataclass(frozen=True)
class CommandBatch:
    """Consecutive /wheel_commands: ``stamp`` (M,) [s], ``velocity_mode`` (M,) bool (else effort),
    ``values`` (M, n) in driver convention ([rad/s] or [N·m])."""

    stamp: np.ndarray
    velocity_mode: np.ndarray
    values: np.ndarray

    def __len__(self):
        return len(self.stamp)

    def sample(self, k):
        """Row ``k`` as a :class:`CommandSample`."""
        return CommandSample(float(self.stamp[k]), VELOCITY if self.velocity_mode[k] else EFFORT,
                             self.values[k])

    @classmethod
    def empty(cls, n):
        """No commands for ``n`` wheels."""
        return cls(np.empty(0), np.empty(0, dtype=bool), np.empty((0, n)))

    @classmethod
    def from_samples(cls, samples):
        """Stack :class:`CommandSample` s."""
        return cls(np.array([s.stamp for s in samples], dtype=float),
                   np.array([s.kind == VELOCITY for s in samples], dtype=bool),
                   np.array([s.values for s in samples], dtype=float).reshape(len(samples), -1))


@dataclass(frozen=True)
class SampleChunk:
    """A stretch of a recording: its joint samples, its commands, and their interleaving:
    ``commands_before[k]`` commands of this chunk arrived before joint sample ``k``."""

    joints: JointBatch
    commands: CommandBatch
    commands_before: np.ndarray  # (N,) int


COUNTERS = ('joint_states', 'wheel_commands', 'skipped_nan', 'skipped_short',
            'skipped_missing_joint', 'skipped_no_values', 'partial_samples')


#: What each counted input problem means, for people (the mapper's skips and the residual
#: generator's restarts, :data:`youbot_fdi.fdi.observer.STAMP_COUNTERS`).
INPUT_PROBLEMS = {
    'skipped_nan': 'NaN or infinite values',
    'partial_samples': "some wheels' readings missing (NaN: their module did not answer the cycle)",
    'skipped_short': 'arrays shorter than the joint names',
    'skipped_missing_joint': 'a wheel joint missing (unknown or absent names)',
    'skipped_no_values': 'no values (empty or undecodable message)',
    'stamps_backwards': 'header stamp going backwards',
    'stamps_repeated': 'header stamp repeated (duplicated sample)',
    'gaps': 'gap in the samples',
    'messages_repeated': 'every reading re-sent unchanged while the base moved (no fresh data)',
    'unpaired': 'a prediction not starting at the last sample (one lost between nodes)',
    'dropped_unpaired': 'a sample or prediction whose counterpart never came',
    'skipped_unstamped': 'no header stamp: cannot be paired with its prediction (run the observer fused)',
    'commands_late': ('a command that came after samples it was in force for had been judged (this '
                      'host is behind; their command path was judged without it)'),
}


class InputReport:
    """Rate-limited account of input problems for live diagnostics: at most one report every
    ``interval`` seconds, naming what was counted since the last report."""

    def __init__(self, interval):
        self.interval = interval  # [s]
        self._reported = {}
        self._last = -math.inf

    def check(self, counters, now):
        """Lines naming the problems counted since the last report, or [] (nothing new, or
        reported less than ``interval`` ago). ``counters``: name -> running count; ``now`` [s]."""
        new = {k: v - self._reported.get(k, 0) for k, v in counters.items()
               if k in INPUT_PROBLEMS and v > self._reported.get(k, 0)}
        if not new or now - self._last < self.interval:
            return []
        self._last = now
        self._reported.update({k: counters[k] for k in new})
        return [f'{INPUT_PROBLEMS[k]}: {n} new ({counters[k]} in all)' for k, n in sorted(new.items())]


def message_time(header_stamps, receive_times):
    """The clock rule (docs/fdi.md): a message's time is its header stamp, or its receive time
    when the header carries none (zero). The same for /joint_states and /wheel_commands, offline
    and live. Arrays of [s]."""
    return np.where(header_stamps > 0.0, header_stamps, receive_times)


def as_rows(array, rows):
    """A message field (one message's sequence, or a block's (rows, m) array) as (rows, m) floats."""
    return np.asarray(array, dtype=float).reshape(rows, -1)


class SampleMapper:
    """Maps JointState fields to the model's wheel order and validates them.

    The ``*_rows`` methods take a block of messages that share ``names`` and array lengths: a stamp
    array (N,) and fields of shape (N, m) (m = 0: the field is absent). They return the usable rows
    as a batch and their indices into the block, and count the rest.

    ``keep_partial``: keep the /joint_states rows in which some wheels' readings are NaN (a driver
    marks a module that did not answer its cycle so) as long as one wheel has a reading; those
    wheels' position, speed and effort are all NaN (counted as ``partial_samples``). The FDI keeps
    them: a wheel that stays silent is that wheel's ``comm_loss``. Otherwise (odometry) such rows
    are skipped like any row with NaN.
    """

    def __init__(self, wheel_names, keep_partial=False):
        self.wheel_names = tuple(wheel_names)
        self.keep_partial = keep_partial
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

    def _usable(self, names, fields, rows):
        """The wheel index of ``names`` and the fields picked in wheel order (None: absent), or
        None when the whole block is unusable (counted)."""
        if not len(names) and not any(field.shape[1] for field in fields):
            self.counters['skipped_no_values'] += rows  # an empty message
            return None
        index = self._indices(names)
        if index is None:
            self.counters['skipped_missing_joint'] += rows
            return None
        picked = []
        for field in fields:
            if field.shape[1] == 0:
                picked.append(None)
            elif field.shape[1] < len(names):
                self.counters['skipped_short'] += rows
                return None
            else:
                picked.append(field[:, index])
        return picked

    def _keep_finite(self, arrays, rows):
        finite = np.ones(rows, dtype=bool)
        for array in arrays:
            finite &= np.isfinite(array).all(axis=1)
        self.counters['skipped_nan'] += int(rows - np.count_nonzero(finite))
        return np.flatnonzero(finite)

    def joint_rows(self, stamp, names, position, velocity, effort):
        """(JointBatch, kept row indices) of a block, or None when no row is usable."""
        rows = len(stamp)
        picked = self._usable(names, [as_rows(a, rows) for a in (position, velocity, effort)], rows)
        if picked is None:
            return None
        position, velocity, effort = picked
        if position is None or velocity is None:
            self.counters['skipped_no_values'] += rows
            return None
        if effort is None:
            effort = np.full(position.shape, math.nan)
        if self.keep_partial:
            answered = np.isfinite(position) & np.isfinite(velocity)
            partial = ~answered.all(axis=1) & answered.any(axis=1)
            if partial.any():  # a silent wheel is silent in every reading
                position, velocity, effort = (np.where(answered, a, math.nan)
                                              for a in (position, velocity, effort))
                self.counters['partial_samples'] += int(np.count_nonzero(partial))
            kept = np.flatnonzero(answered.any(axis=1))
            self.counters['skipped_nan'] += rows - len(kept)
        else:
            kept = self._keep_finite((position, velocity), rows)
        if not len(kept):
            return None
        self.counters['joint_states'] += len(kept)
        if len(kept) < rows:
            stamp, position, velocity, effort = (a[kept] for a in (stamp, position, velocity, effort))
        return JointBatch(np.asarray(stamp, dtype=float), position, velocity, effort), kept

    def command_rows(self, stamp, names, velocity, effort):
        """(CommandBatch, kept row indices) of a block (velocity preferred), or None."""
        rows = len(stamp)
        picked = self._usable(names, [as_rows(a, rows) for a in (velocity, effort)], rows)
        if picked is None:
            return None
        for velocity_mode, values in zip((True, False), picked):
            if values is None:
                continue
            kept = self._keep_finite((values,), rows)
            if not len(kept):
                return None
            self.counters['wheel_commands'] += len(kept)
            return (CommandBatch(np.asarray(stamp, dtype=float)[kept], np.full(len(kept), velocity_mode),
                                 values[kept]), kept)
        self.counters['skipped_no_values'] += rows
        return None

    def joint_sample(self, stamp, names, position, velocity, effort):
        """A :class:`JointSample` of one message, or None (counted) when it cannot be used."""
        found = self.joint_rows(np.array([stamp], dtype=float), names, position, velocity, effort)
        return None if found is None else found[0].sample(0)

    def command_sample(self, stamp, names, velocity, effort):
        """A :class:`CommandSample` of one message (velocity preferred), or None (counted)."""
        found = self.command_rows(np.array([stamp], dtype=float), names, velocity, effort)
        return None if found is None else found[0].sample(0)
