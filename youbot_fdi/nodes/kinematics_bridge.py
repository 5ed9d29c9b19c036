"""``kinematics_bridge`` node: /cmd_vel -> /wheel_commands (inverse kinematics), /joint_states -> /odom.

Wheel speeds are limited to ``max_wheel_speed``: a faster command is scaled down as a whole, so the
base keeps its direction. Odometry integrates the measured wheel angles (exact SE(2) steps) and is
published in frame ``odom`` with child ``base_footprint`` (REP-105, like the youBot driver).
"""
import math
import sys

from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry as OdometryMsg
from rclpy.node import Node
from sensor_msgs.msg import JointState

from youbot_fdi.model.kinematics import Odometry
from youbot_fdi.model.profile import load_model
from youbot_fdi.nodes.common import (now_seconds, SENSOR_QOS, seconds_to_stamp, spin_nodes,
                                     stamp_to_seconds, STREAM_QOS)
from youbot_fdi.nodes.conversions import joint_state
from youbot_fdi.samples import SampleMapper
from youbot_fdi.topics import CMD_VEL, JOINT_STATES, ODOM, WHEEL_COMMANDS

NODE_NAME = 'kinematics_bridge'


class KinematicsBridgeNode(Node):
    """Thin adapter over :class:`~youbot_fdi.model.kinematics.Kinematics` and ``Odometry``."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        profile = self.declare_parameter('profile', 'youbot').value
        self.max_wheel_speed = float(self.declare_parameter('max_wheel_speed', 10.0).value)
        self.odom_frame = self.declare_parameter('odom_frame', 'odom').value
        self.base_frame = self.declare_parameter('base_frame', 'base_footprint').value
        self.model = load_model(profile)
        self.kinematics = self.model.kinematics
        self.mapper = SampleMapper(self.model.wheel_names)
        self.odometry = Odometry(self.kinematics)
        self._last_stamp = None
        self.command_pub = self.create_publisher(JointState, WHEEL_COMMANDS, STREAM_QOS)
        self.odom_pub = self.create_publisher(OdometryMsg, ODOM, STREAM_QOS)
        self.create_subscription(Twist, CMD_VEL, self.on_cmd_vel, 10)
        self.create_subscription(JointState, JOINT_STATES, self.on_joint_states, SENSOR_QOS)

    def on_cmd_vel(self, msg):
        twist = (msg.linear.x, msg.linear.y, msg.angular.z)
        if not all(math.isfinite(v) for v in twist):
            self.get_logger().warning(f'/cmd_vel with non-finite values ignored: {twist}',
                                      throttle_duration_sec=2.0)
            return
        speeds = self.kinematics.inverse(twist)
        fastest = float(max(abs(speeds)))
        if fastest > self.max_wheel_speed:
            speeds = speeds * (self.max_wheel_speed / fastest)
        self.command_pub.publish(joint_state(now_seconds(self), self.model.wheel_names,
                                             velocity=self.kinematics.to_driver(speeds)))

    def on_joint_states(self, msg):
        stamp = stamp_to_seconds(msg.header.stamp)
        sample = self.mapper.joint_sample(stamp, msg.name, msg.position, msg.velocity, msg.effort)
        if sample is None or (self._last_stamp is not None and stamp <= self._last_stamp):
            return
        dt = 0.0 if self._last_stamp is None else stamp - self._last_stamp
        self._last_stamp = stamp
        pose = self.odometry.update(self.kinematics.from_driver(sample.position), dt or 1.0)
        odom = OdometryMsg()
        odom.header.stamp = seconds_to_stamp(stamp)
        odom.header.frame_id, odom.child_frame_id = self.odom_frame, self.base_frame
        odom.pose.pose.position.x, odom.pose.pose.position.y = float(pose[0]), float(pose[1])
        odom.pose.pose.orientation.z = math.sin(pose[2] / 2.0)
        odom.pose.pose.orientation.w = math.cos(pose[2] / 2.0)
        twist = self.odometry.twist
        odom.twist.twist.linear.x, odom.twist.twist.linear.y = float(twist[0]), float(twist[1])
        odom.twist.twist.angular.z = float(twist[2])
        self.odom_pub.publish(odom)


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi kinematics_bridge``."""
    return spin_nodes([KinematicsBridgeNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
