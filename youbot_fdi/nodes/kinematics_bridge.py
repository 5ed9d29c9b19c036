"""``kinematics_bridge`` node: /cmd_vel -> /wheel_commands (inverse kinematics), /joint_states -> /odom.

Wheel speeds are limited to ``max_wheel_speed`` (``degraded_max_wheel_speed`` of
``config/reactions.yaml`` while driving degraded): a faster command is scaled down as a whole, so the
base keeps its direction. Odometry integrates the measured wheel angles (exact SE(2) steps) and is
published in frame ``odom`` with child ``base_footprint`` (REP-105, like the youBot driver).

Fault reactions (``react: true``, policy in ``config/reactions.yaml``,
:class:`~youbot_fdi.fdi.reactions.Reactor`): the bridge owns /wheel_commands, so it applies them.
It listens to /youbot_fdi/faults; a runaway wheel's motor goes off through the driver shim's
``~/switch_off_motor_<w>`` service and the base stops; stuck and comm_loss stop the base (zero
commands at once and on every /cmd_vel); torque_loss and friction drive the base on the other
wheels; a frozen encoder's reading is replaced by its kinematic estimate for odometry and degraded
driving, and its motor goes off (the module's loop runs on the frozen reading). An OK event
(the fault cleared, or the decision's ``~/reset``) ends the wheel's reaction. A reaction starts only
once its alarm has stood ``confirmation_time`` (on the /joint_states clock) without clearing, and
never substitutes readings or stops the base because several wheels look frozen at once (a
base-level data problem). Each reaction is
published on ``/youbot_fdi/reactions`` (latched DiagnosticArray, one INFO event per status) and
logged.
"""
import math
import sys

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry as OdometryMsg
import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from youbot_fdi.fdi.reactions import ReactionSettings, Reactor, SWITCHES_OFF
from youbot_fdi.model.kinematics import limit_wheel_speeds, Odometry
from youbot_fdi.model.profile import load_model
from youbot_fdi.nodes.common import (declare_settings, LATCHED_QOS, now_seconds, SENSOR_QOS,
                                     seconds_to_stamp, spin_nodes, stamp_to_seconds, STREAM_QOS)
from youbot_fdi.nodes.conversions import event_from_status, joint_state, reaction_array
from youbot_fdi.samples import SampleMapper
from youbot_fdi.naming import wheel_suffix
from youbot_fdi.topics import CMD_VEL, FAULTS, JOINT_STATES, ODOM, REACTIONS, WHEEL_COMMANDS

NODE_NAME = 'kinematics_bridge'
MIN_CONFIRM_PERIOD = 0.01  # [s] the confirmation timer's shortest period


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
        self.reactor = Reactor(self.kinematics, declare_settings(self, ReactionSettings))
        self._measured = None  # last measured wheel speeds, kinematic convention [rad/s]
        self._twist = None  # last /cmd_vel set-point (vx, vy, wz)
        self._raw_positions = None  # last measured wheel angles, kinematic convention [rad]
        self._positions = None  # the angles odometry integrates (frozen readings substituted)
        self.command_pub = self.create_publisher(JointState, WHEEL_COMMANDS, STREAM_QOS)
        self.odom_pub = self.create_publisher(OdometryMsg, ODOM, STREAM_QOS)
        self.create_subscription(Twist, CMD_VEL, self.on_cmd_vel, 10)
        self.create_subscription(JointState, JOINT_STATES, self.on_joint_states, SENSOR_QOS)
        if self.reactor.settings.react:
            self.reaction_pub = self.create_publisher(DiagnosticArray, REACTIONS, LATCHED_QOS)
            self.motor_off = {name: self.create_client(
                Trigger, f'{self.reactor.settings.motor_off_service}_{wheel_suffix(name)}')
                for name in self.model.wheel_names}
            self.create_subscription(DiagnosticArray, FAULTS, self.on_faults, LATCHED_QOS)
            # Confirms alarms when no sample comes to do it (a silent base); idle otherwise.
            self.confirm_timer = self.create_timer(
                max(self.reactor.settings.confirmation_time, MIN_CONFIRM_PERIOD), self.on_confirm_timer)
            self.confirm_timer.cancel()

    def on_cmd_vel(self, msg):
        twist = (msg.linear.x, msg.linear.y, msg.angular.z)
        if not all(math.isfinite(v) for v in twist):
            self.get_logger().warning(f'/cmd_vel with non-finite values ignored: {twist}',
                                      throttle_duration_sec=2.0)
            return
        self._twist = twist
        self.publish_speeds(self.reactor.wheel_speeds(twist, self._measured))

    def publish_speeds(self, speeds):
        """/wheel_commands for wheel speeds (kinematic convention), within ``max_wheel_speed``, or
        ``degraded_max_wheel_speed`` while the other wheels carry a lost one."""
        cap = (self.reactor.settings.degraded_max_wheel_speed if self.reactor.driving_degraded
               else self.max_wheel_speed)
        speeds = limit_wheel_speeds(speeds, cap)
        self.command_pub.publish(joint_state(now_seconds(self), self.model.wheel_names,
                                             velocity=self.kinematics.to_driver(speeds)))

    def on_faults(self, msg):
        """Fault events -> reactions (an alarm's once it is confirmed, :meth:`on_joint_states`)."""
        reactions = []
        for status in msg.status:
            reactions += self.reactor.on_event(event_from_status(status))
        self.apply(reactions)
        if self.reactor.pending and self.confirm_timer.is_canceled():
            self.confirm_timer.reset()

    def on_confirm_timer(self):
        self.apply(self.reactor.confirm(now_seconds(self)))
        if not self.reactor.pending:
            self.confirm_timer.cancel()

    def apply(self, reactions):
        """Reactions started or ended: published, logged, and acted on at once."""
        if not reactions:
            return
        for reaction in reactions:  # the motors a reaction switches off now
            if reaction.action in SWITCHES_OFF:
                self.motor_off[reaction.wheel].call_async(Trigger.Request())
        if self.reactor.stopped:
            self.publish_speeds(np.zeros(len(self.model.wheel_names)))
        self.reaction_pub.publish(reaction_array(reactions, reactions[-1].stamp))
        for reaction in reactions:
            self.get_logger().warning(f'reaction {reaction.action} on {reaction.wheel or "base"} '
                                      f'({reaction.fault}): {reaction.detail}')

    def on_joint_states(self, msg):
        stamp = stamp_to_seconds(msg.header.stamp)
        if self.reactor.settings.react and self.reactor.pending:  # the samples' clock, any sample
            self.apply(self.reactor.confirm(stamp))
        sample = self.mapper.joint_sample(stamp, msg.name, msg.position, msg.velocity, msg.effort)
        if sample is None or (self._last_stamp is not None and stamp <= self._last_stamp):
            return
        dt = 0.0 if self._last_stamp is None else stamp - self._last_stamp
        self._last_stamp = stamp
        self._measured = self.reactor.readings(self.kinematics.from_driver(sample.velocity))
        if self.reactor.degraded and self._twist is not None and not self.reactor.stopped:
            # degraded driving follows the lost wheels' speeds at the sample rate, not /cmd_vel's
            self.publish_speeds(self.reactor.wheel_speeds(self._twist, self._measured))
        raw = self.kinematics.from_driver(sample.position)
        if self._positions is None or not self.reactor.substituted:
            self._positions = raw.copy()
        else:  # increments, frozen readings replaced by their kinematic estimate
            self._positions = self._positions + self.reactor.readings(raw - self._raw_positions)
        self._raw_positions = raw
        pose = self.odometry.update(self._positions, dt or 1.0)
        if self.odom_pub.get_subscription_count() == 0:
            return  # nobody listens: the pose is kept, the message not built
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
