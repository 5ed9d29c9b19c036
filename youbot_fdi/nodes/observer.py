"""``observer`` node: the dynamic-model observer and residual generator beside the driver shim.

Subscribes /wheel_commands and /joint_states; publishes ``/youbot_fdi/predicted`` (JointState:
wheel speeds predicted from the measured currents, driver convention) and
``/youbot_fdi/residuals`` (a labelled vector as JointState: ``name`` the residual or signal,
``position`` its value, ``velocity`` its bound; see ResidualFrame.to_labelled). Observer and residual
generation are one core object (:class:`~youbot_fdi.fdi.residuals.ResidualGenerator`) because they
share their state: splitting them into two nodes would double the work or add a hop.

Bad input (NaN, short arrays, unknown joint names, empty messages, stamps going backwards or
repeated) is skipped or restarts the residuals, never raises a fault; a WARN on ``/diagnostics``
names it (at most one every ``input_warn_interval`` s).

Parameters: the keys of ``config/fdi.yaml`` plus ``params_file`` (a ``youbot-fdi identify``
output) and ``input_warn_interval`` [s].
"""
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import JointState

from youbot_fdi.fdi.pipeline import configure
from youbot_fdi.fdi.residuals import ResidualGenerator
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.nodes.common import (declare_settings, NAME_PREFIX, now_seconds, seconds_to_stamp,
                                     SENSOR_QOS, spin_nodes, stamp_to_seconds, STREAM_QOS)
from youbot_fdi.nodes.conversions import joint_state, labelled_vector
from youbot_fdi.samples import InputReport, message_time, SampleMapper
from youbot_fdi.topics import DIAGNOSTICS, JOINT_STATES, PREDICTED, RESIDUALS, WHEEL_COMMANDS

NODE_NAME = 'observer'
INPUT_WARN_INTERVAL = 1.0  # [s] between input-problem WARNs on /diagnostics (rate limit)


class ObserverNode(Node):
    """Thin adapter over :class:`~youbot_fdi.fdi.residuals.ResidualGenerator`."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        params_file = self.declare_parameter('params_file', '').value
        warn_interval = float(self.declare_parameter('input_warn_interval', INPUT_WARN_INTERVAL).value)
        self.model, self.settings = configure(declare_settings(self, FdiSettings), params_file)
        self.names = self.model.wheel_names
        self.generator = ResidualGenerator(self.model, self.settings)
        self.mapper = SampleMapper(self.names)
        self.input_report = InputReport(warn_interval)
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS, 10)
        self.predicted_pub = self.create_publisher(JointState, PREDICTED, STREAM_QOS)
        self.residual_pub = self.create_publisher(JointState, RESIDUALS, STREAM_QOS)
        self.create_subscription(JointState, WHEEL_COMMANDS, self.on_command, SENSOR_QOS)
        self.create_subscription(JointState, JOINT_STATES, self.on_joint_states, SENSOR_QOS)

    def on_command(self, msg):
        stamp = float(message_time(stamp_to_seconds(msg.header.stamp), now_seconds(self)))
        sample = self.mapper.command_sample(stamp, msg.name, msg.velocity, msg.effort)
        if sample is not None:
            self.generator.command(sample)
        else:
            self.report_input()

    def on_joint_states(self, msg):
        stamp = float(message_time(stamp_to_seconds(msg.header.stamp), now_seconds(self)))
        sample = self.mapper.joint_sample(stamp, msg.name,
                                          msg.position, msg.velocity, msg.effort)
        if sample is None:
            self.report_input()
            return
        frame = self.generator.update(sample)
        if frame is None:
            self.report_input()
            return
        from_currents, _ = self.generator.predictions()
        self.predicted_pub.publish(joint_state(frame.stamp, self.names, velocity=from_currents))
        self.residual_pub.publish(labelled_vector(frame.stamp, *frame.to_labelled(self.names)))

    def report_input(self):
        """A WARN on /diagnostics naming the input problems counted since the last one (at most
        one every ``input_warn_interval`` s); the messages themselves were skipped or restarted
        the residuals, never raised a fault."""
        counters, now = {**self.mapper.counters, **self.generator.counters}, now_seconds(self)
        problems = self.input_report.check(counters, now)
        if not problems:
            return
        status = DiagnosticStatus(level=DiagnosticStatus.WARN, name=f'{NAME_PREFIX}/{NODE_NAME}: input',
                                  hardware_id=NODE_NAME, message='; '.join(problems))
        status.values = [KeyValue(key=k, value=str(v)) for k, v in counters.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = seconds_to_stamp(now)
        self.diag_pub.publish(array)
        self.get_logger().warning(status.message)


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi observer``."""
    return spin_nodes([ObserverNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
