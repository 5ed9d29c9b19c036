"""Publish a rosbag2 recording live on its topics with /clock (``youbot-fdi play``).

Messages are published as the recorded CDR bytes (no decoding), paced by their recording times;
``/clock`` follows the recording, so nodes started with ``use_sim_time:=true`` run on its time.
"""
import time

import rclpy
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from youbot_fdi.bag.reader import NANOSECONDS, RecordingError
from youbot_fdi.nodes.common import seconds_to_stamp, STREAM_QOS
from youbot_fdi.topics import CLOCK

MESSAGE_TYPES = {
    'sensor_msgs/msg/JointState': ('sensor_msgs.msg', 'JointState'),
    'geometry_msgs/msg/Twist': ('geometry_msgs.msg', 'Twist'),
    'nav_msgs/msg/Odometry': ('nav_msgs.msg', 'Odometry'),
    'diagnostic_msgs/msg/DiagnosticArray': ('diagnostic_msgs.msg', 'DiagnosticArray'),
}


def _message_class(msgtype):
    module, name = MESSAGE_TYPES[msgtype]
    return getattr(__import__(module, fromlist=[name]), name)


def play(path, rate=1.0, clock=True, topics=None, progress=None):
    """Publish the recording at ``path``; returns the number of messages published."""
    from rosbags.rosbag2 import Reader
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:  # noqa: BLE001
        msg = f'{path}: not a readable rosbag2 recording ({type(err).__name__}: {err})'
        raise RecordingError(msg) from err
    rclpy.init()
    node = Node('youbot_fdi_play')
    published = 0
    try:
        connections = [c for c in reader.connections if c.msgtype in MESSAGE_TYPES
                       and (not topics or c.topic in topics)]
        publishers = {c.id: node.create_publisher(_message_class(c.msgtype), c.topic, STREAM_QOS)
                      for c in connections}
        clock_pub = node.create_publisher(Clock, CLOCK, 10) if clock else None
        time.sleep(0.5)  # let subscribers discover the publishers
        start_wall, start_bag = time.monotonic(), None
        for connection, timestamp, raw in reader.messages(connections=connections):
            stamp = timestamp / NANOSECONDS
            if start_bag is None:
                start_bag = stamp
            delay = (stamp - start_bag) / rate - (time.monotonic() - start_wall)
            if delay > 0:
                time.sleep(delay)
            if clock_pub is not None:
                clock_pub.publish(Clock(clock=seconds_to_stamp(stamp)))
            publishers[connection.id].publish(bytes(raw))
            published += 1
            if progress is not None and published % 1000 == 0:
                progress(published)
    except KeyboardInterrupt:
        pass
    finally:
        reader.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return published
