"""Read rosbag2 recordings (sqlite3 or mcap) into wheel samples, streaming, with rosbags.

:meth:`RecordingReader.chunks` reads a recording in chunks of messages and decodes the messages of
a chunk that share a layout as one block (:mod:`youbot_fdi.bag.cdr`); rosbags decodes the rest.
Messages are matched to the model's wheels **by joint name**. Bad messages (NaN, arrays shorter
than the names, a wheel missing) are skipped and counted, never fatal. A damaged recording (cut
short, no metadata.yaml, broken part-way) is read as far as it can be (:mod:`~youbot_fdi.bag.salvage`)
and says what was lost in :attr:`RecordingReader.damage`; one of which nothing can be read, or
without the joint-state topic, raises :class:`RecordingError` with a one-line reason.
"""
from pathlib import Path

import numpy as np

from youbot_fdi.bag.cdr import JointStateLayout
from youbot_fdi.errors import FdiError
from youbot_fdi.samples import (CommandBatch, CommandSample, JointBatch, JointSample,
                                message_time, SampleChunk, SampleMapper)
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS

__all__ = ['CommandSample', 'JointSample', 'RecordingError', 'RecordingReader']

JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'
NANOSECONDS = 1e9
CHUNK_MESSAGES = 2048  # messages decoded and handed on together by chunks() (about 10 s at 100 Hz)


class RecordingError(FdiError):
    """A recording cannot be read, or lacks what is needed."""


def _stamp(header):
    return header.stamp.sec + header.stamp.nanosec / NANOSECONDS


def _merge(parts, empty):
    """One batch in recording order from (positions, batch) parts; returns (batch, positions)."""
    if not parts:
        return empty, np.empty(0, dtype=int)
    if len(parts) == 1:
        return parts[0][1], parts[0][0]
    positions = np.concatenate([p for p, _ in parts])
    order = np.argsort(positions, kind='stable')
    fields = [np.concatenate([getattr(b, f) for _, b in parts])[order]
              for f in type(empty).__dataclass_fields__]
    return type(empty)(*fields), positions[order]


class RecordingReader:
    """Streams the wheel samples of a rosbag2 directory.

    Parameters
    ----------
    path : str or Path
        The recording directory (or a single .db3/.mcap file).
    wheel_names : sequence of str
        Joint names in model order.
    joint_topic, command_topic : str
        Topic names (CONTRACT.md defaults).
    keep_partial : bool
        Keep /joint_states rows in which only some wheels have readings (the FDI's replay: a
        silent wheel is its comm_loss); otherwise they are skipped as NaN
        (:class:`~youbot_fdi.samples.SampleMapper`).

    Attributes
    ----------
    counters : dict
        ``joint_states``, ``wheel_commands`` (used), ``skipped_nan``, ``skipped_short``,
        ``skipped_missing_joint``, ``skipped_no_values``.
    """

    def __init__(self, path, wheel_names, joint_topic=JOINT_STATES, command_topic=WHEEL_COMMANDS,
                 keep_partial=False):
        from rosbags.rosbag2 import Reader
        from rosbags.typesys import get_typestore, Stores

        self.path = Path(path)
        self.wheel_names = tuple(wheel_names)
        self.joint_topic, self.command_topic = joint_topic, command_topic
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.mapper = SampleMapper(wheel_names, keep_partial=keep_partial)
        self.counters = self.mapper.counters
        #: :class:`~youbot_fdi.bag.salvage.Damage` when rosbags could not read the recording whole
        #: (cut short, no metadata.yaml), or it broke part-way; None otherwise
        self.damage = None
        if not self.path.exists():
            msg = f'{self.path}: no such recording'
            raise RecordingError(msg)
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as err:  # noqa: BLE001 - rosbags raises several types for broken bags
            self._reader = self._salvage(err)
            self.damage = self._reader.damage
        topics = {c.topic: c for c in self._reader.connections}
        if joint_topic not in topics or topics[joint_topic].msgcount == 0:
            self._reader.close()
            with_data = sorted(t for t, c in topics.items() if c.msgcount)
            msg = f'{self.path}: no {joint_topic} messages (topics with data: {with_data})'
            raise RecordingError(msg)
        self.connections = [c for c in self._reader.connections
                            if c.topic in (joint_topic, command_topic)]
        bad = [c.topic for c in self.connections if c.msgtype != JOINT_STATE_TYPE]
        if bad:
            self._reader.close()
            msg = f'{self.path}: {bad[0]} is not {JOINT_STATE_TYPE}'
            raise RecordingError(msg)
        self.has_commands = command_topic in topics

    def _salvage(self, error):
        """The readable part, streamed without rosbags (:mod:`youbot_fdi.bag.salvage`), or
        RecordingError naming rosbags' complaint when nothing can be read."""
        from youbot_fdi.bag.salvage import SalvageError, SalvageReader
        try:
            return SalvageReader(self.path)
        except (SalvageError, OSError) as salvage_error:
            msg = (f'{self.path}: not a readable rosbag2 recording ({type(error).__name__}: {error}; '
                   f'read without rosbags: {salvage_error})')
            raise RecordingError(msg) from error

    @property
    def duration(self):
        """Recording length [s]."""
        return self._reader.duration / NANOSECONDS

    @property
    def message_count(self):
        """Messages on the topics read."""
        return sum(c.msgcount for c in self.connections)

    @property
    def start_time(self):
        """Bag time of the first message [s]."""
        return self._reader.start_time / NANOSECONDS

    def samples(self):
        """Yield :class:`JointSample` and :class:`CommandSample` in recording order (up to the
        damage of a damaged recording, see :attr:`damage`)."""
        for chunk in self.chunks():
            joints, commands = chunk.joints, chunk.commands
            done = 0
            for k, before in enumerate(chunk.commands_before):
                while done < before:
                    yield commands.sample(done)
                    done += 1
                yield joints.sample(k)
            for k in range(done, len(commands)):
                yield commands.sample(k)

    def chunks(self, size=CHUNK_MESSAGES, on_progress=None):
        """Yield :class:`~youbot_fdi.samples.SampleChunk` s of up to ``size`` messages.

        ``on_progress(messages read, total)`` is called after each chunk. A recording that breaks
        part-way ends after the chunks read so far, with :attr:`damage` saying where.
        """
        layouts = {self.joint_topic: None, self.command_topic: None}
        pending, read, total, span = [], 0, self.message_count, [None, None]
        try:
            for connection, timestamp, raw in self._reader.messages(connections=self.connections):
                topic = connection.topic
                layout = layouts[topic]
                if layout is None or not layout.matches(raw):
                    layout = layouts[topic] = JointStateLayout.parse(raw)
                pending.append((topic == self.joint_topic, layout, raw, timestamp))
                if len(pending) >= size:
                    read += len(pending)
                    span = [pending[0][3] if span[0] is None else span[0], pending[-1][3]]
                    yield self._chunk(pending)
                    pending = []
                    if on_progress is not None:
                        on_progress(read, total)
        except Exception as err:  # noqa: BLE001 - rosbags raises several types for broken bags
            from youbot_fdi.bag.salvage import Damage
            if pending:
                read += len(pending)
                span = [pending[0][3] if span[0] is None else span[0], pending[-1][3]]
                yield self._chunk(pending)
            first, last = (np.nan if t is None else t / NANOSECONDS for t in span)
            self.damage = Damage((self.path.name,), f'broken part-way: {type(err).__name__}: {err}',
                                 read, first, last, total, None, None, False)
            return
        if pending:
            read += len(pending)
            yield self._chunk(pending)
            if on_progress is not None:
                on_progress(read, total)

    def _decoded(self, entries, layout):
        """(stamps, names, [position, velocity, effort], bag times) of entries sharing ``layout``;
        a None layout means one message for rosbags (None if it cannot be decoded)."""
        bag_times = np.array([e[3] for e in entries], dtype=float) / NANOSECONDS
        if layout is not None:
            stamps, arrays = layout.decode([e[2] for e in entries])
            return stamps, layout.names, arrays, bag_times
        try:
            msg = self.typestore.deserialize_cdr(entries[0][2], JOINT_STATE_TYPE)
        except Exception:  # noqa: BLE001 - a corrupt message is skipped, not fatal
            self.counters['skipped_no_values'] += 1
            return None
        return (np.array([_stamp(msg.header)]), msg.name,
                [np.asarray(a, dtype=float).reshape(1, -1) for a in (msg.position, msg.velocity, msg.effort)],
                bag_times)

    def _chunk(self, pending):
        """Decode and validate a chunk of (is_joint, layout, raw, bag time) entries."""
        groups = {}
        for position, entry in enumerate(pending):
            key = (entry[0], id(entry[1])) if entry[1] is not None else (entry[0], -position)
            groups.setdefault(key, []).append(position)
        kept_joints, kept_commands = [], []
        for (is_joint, _), positions in groups.items():
            decoded = self._decoded([pending[p] for p in positions], pending[positions[0]][1])
            if decoded is None:
                continue
            stamps, names, (position, velocity, effort), bag_times = decoded
            stamps = message_time(stamps, bag_times)
            if is_joint:
                found = self.mapper.joint_rows(stamps, names, position, velocity, effort)
            else:
                found = self.mapper.command_rows(stamps, names, velocity, effort)
            if found is not None:
                batch, kept = found
                (kept_joints if is_joint else kept_commands).append((np.asarray(positions)[kept], batch))
        n = len(self.wheel_names)
        joints, joint_order = _merge(kept_joints, JointBatch.empty(n))
        commands, command_order = _merge(kept_commands, CommandBatch.empty(n))
        return SampleChunk(joints, commands, np.searchsorted(command_order, joint_order))

    def decode_only(self):
        """Read and deserialize every message of the topics, doing nothing else (benchmark baseline)."""
        deserialize = self.typestore.deserialize_cdr
        count = 0
        for connection, _, raw in self._reader.messages(connections=self.connections):
            deserialize(raw, connection.msgtype)
            count += 1
        return count

    def close(self):
        """Close the recording."""
        self._reader.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
