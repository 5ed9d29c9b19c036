"""Write rosbag2 recordings (sqlite3 or mcap) with the topics of CONTRACT.md, via rosbags."""
from pathlib import Path

import numpy as np

from youbot_fdi.bag.reader import JOINT_STATE_TYPE, NANOSECONDS, RecordingError
from youbot_fdi.topics import CMD_VEL, JOINT_STATES, WHEEL_COMMANDS

STORAGES = ('sqlite3', 'mcap')
SAME = object()  # a message's header stamp is its receive time unless told otherwise
BAG_VERSION = 9  # what Jazzy's rosbag2 writes


class RecordingWriter:
    """A rosbag2 writer for wheel samples and commands (context manager)."""

    def __init__(self, path, wheel_names, storage='sqlite3'):
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import get_typestore, Stores

        if storage not in STORAGES:
            msg = f'storage must be one of {STORAGES}, got {storage!r}'
            raise RecordingError(msg)
        self.path = Path(path)
        self.names = list(wheel_names)
        self.typestore = get_typestore(Stores.ROS2_JAZZY)
        types = self.typestore.types
        self._joint_state = types[JOINT_STATE_TYPE]
        self._header = types['std_msgs/msg/Header']
        self._time = types['builtin_interfaces/msg/Time']
        self._twist = types['geometry_msgs/msg/Twist']
        self._vector = types['geometry_msgs/msg/Vector3']
        plugin = StoragePlugin.SQLITE3 if storage == 'sqlite3' else StoragePlugin.MCAP
        try:
            self._writer = Writer(self.path, version=BAG_VERSION, storage_plugin=plugin)
            self._writer.open()
        except Exception as err:  # noqa: BLE001 - rosbags' WriterError, OSError, ...
            msg = f'{self.path}: cannot create a recording here ({err})'
            raise RecordingError(msg) from err
        self._joints = self._writer.add_connection(JOINT_STATES, JOINT_STATE_TYPE,
                                                   typestore=self.typestore)
        self._commands = self._writer.add_connection(WHEEL_COMMANDS, JOINT_STATE_TYPE,
                                                     typestore=self.typestore)
        self._cmd_vel = None

    def _msg(self, stamp, position=(), velocity=(), effort=()):
        stamp = stamp or 0.0  # None: no header stamp (zero)
        sec = int(stamp // 1)
        header = self._header(stamp=self._time(sec=sec, nanosec=int(round((stamp - sec) * NANOSECONDS))
                                               % 1_000_000_000), frame_id='')
        return self._joint_state(header=header, name=self.names,
                                 position=np.asarray(position, dtype=float),
                                 velocity=np.asarray(velocity, dtype=float),
                                 effort=np.asarray(effort, dtype=float))

    def _write(self, connection, stamp, msg):
        raw = self.typestore.serialize_cdr(msg, connection.msgtype)
        self._writer.write(connection, int(round(stamp * NANOSECONDS)), raw)

    def joint_state(self, stamp, position, velocity, effort, header_stamp=SAME):
        """Write a /joint_states sample (driver convention, [rad], [rad/s], [N·m]) received at
        ``stamp`` [s]; its header stamp is ``stamp`` unless given (None: zero, no stamp)."""
        header = stamp if header_stamp is SAME else header_stamp
        self._write(self._joints, stamp, self._msg(header, position, velocity, effort))

    def wheel_command(self, stamp, kind, values, header_stamp=SAME):
        """Write a /wheel_commands message: ``kind`` 'velocity' [rad/s] or 'effort' [N·m]; stamps
        as :meth:`joint_state`."""
        fields = {'velocity': values} if kind == 'velocity' else {'effort': values}
        header = stamp if header_stamp is SAME else header_stamp
        self._write(self._commands, stamp, self._msg(header, **fields))

    def cmd_vel(self, stamp, twist):
        """Write a /cmd_vel Twist (v_x, v_y, w_z)."""
        if self._cmd_vel is None:
            self._cmd_vel = self._writer.add_connection(CMD_VEL, 'geometry_msgs/msg/Twist',
                                                        typestore=self.typestore)
        vx, vy, wz = (float(v) for v in twist)
        msg = self._twist(linear=self._vector(x=vx, y=vy, z=0.0),
                          angular=self._vector(x=0.0, y=0.0, z=wz))
        self._write(self._cmd_vel, stamp, msg)

    def close(self):
        """Finish the recording (writes metadata.yaml)."""
        self._writer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
