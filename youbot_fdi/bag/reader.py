"""Read rosbag2 recordings (sqlite3 or mcap) into wheel samples, streaming, with rosbags.

Messages are matched to the model's wheels **by joint name**. Bad messages (NaN, arrays shorter
than the names, a wheel missing) are skipped and counted, never fatal; an unreadable recording or
one without the joint-state topic raises :class:`RecordingError` with a one-line reason.
"""
from pathlib import Path

from youbot_fdi.errors import FdiError
from youbot_fdi.fdi.samples import CommandSample, JointSample, SampleMapper

__all__ = ['CommandSample', 'JointSample', 'RecordingError', 'RecordingReader']

JOINT_STATES = '/joint_states'
WHEEL_COMMANDS = '/wheel_commands'
CMD_VEL = '/cmd_vel'
JOINT_STATE_TYPE = 'sensor_msgs/msg/JointState'
NANOSECONDS = 1e9


class RecordingError(FdiError):
    """A recording cannot be read, or lacks what is needed."""


def _stamp(header):
    return header.stamp.sec + header.stamp.nanosec / NANOSECONDS


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

    Attributes
    ----------
    counters : dict
        ``joint_states``, ``wheel_commands`` (used), ``skipped_nan``, ``skipped_short``,
        ``skipped_missing_joint``, ``skipped_no_values``.
    """

    def __init__(self, path, wheel_names, joint_topic=JOINT_STATES, command_topic=WHEEL_COMMANDS):
        from rosbags.rosbag2 import Reader
        from rosbags.typesys import get_typestore, Stores

        self.path = Path(path)
        self.wheel_names = tuple(wheel_names)
        self.joint_topic, self.command_topic = joint_topic, command_topic
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        self.mapper = SampleMapper(wheel_names)
        self.counters = self.mapper.counters
        if not self.path.exists():
            msg = f'{self.path}: no such recording'
            raise RecordingError(msg)
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as err:  # noqa: BLE001 - rosbags raises several types for broken bags
            msg = f'{self.path}: not a readable rosbag2 recording ({type(err).__name__}: {err})'
            raise RecordingError(msg) from err
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

    def _sample(self, topic, msg, bag_time):
        if topic == self.joint_topic:
            return self.mapper.joint_sample(_stamp(msg.header), msg.name, msg.position,
                                            msg.velocity, msg.effort)
        return self.mapper.command_sample(bag_time, msg.name, msg.velocity, msg.effort)

    def samples(self):
        """Yield :class:`JointSample` and :class:`CommandSample` in recording order.

        A recording that breaks part-way raises :class:`RecordingError` after the samples
        read so far have been yielded.
        """
        deserialize = self.typestore.deserialize_cdr
        try:
            for connection, timestamp, raw in self._reader.messages(connections=self.connections):
                try:
                    msg = deserialize(raw, connection.msgtype)
                except Exception:  # noqa: BLE001 - a corrupt message is skipped, not fatal
                    self.counters['skipped_no_values'] += 1
                    continue
                sample = self._sample(connection.topic, msg, timestamp / NANOSECONDS)
                if sample is not None:
                    yield sample
        except RecordingError:
            raise
        except Exception as err:  # noqa: BLE001
            msg = f'{self.path}: recording broken part-way ({type(err).__name__}: {err})'
            raise RecordingError(msg) from err

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
