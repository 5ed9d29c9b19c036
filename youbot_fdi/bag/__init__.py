"""rosbag2 recordings (sqlite3, mcap) via rosbags: a streaming reader and a writer. No rclpy."""
from youbot_fdi.bag.reader import (CommandSample, JointSample, RecordingError, RecordingReader)
from youbot_fdi.bag.writer import RecordingWriter

__all__ = ['CommandSample', 'JointSample', 'RecordingError', 'RecordingReader', 'RecordingWriter']
