"""``observer`` node: the dynamic-model observer beside the driver shim.

Subscribes /wheel_commands and /joint_states; publishes ``/youbot_fdi/predicted``: for each
/joint_states sample, what the model predicts for it (:class:`~youbot_fdi.fdi.observer.Prediction`)
as a labelled vector (sensor_msgs/JointState stamped like the sample, ``name`` the field,
``position`` its value; driver convention, per wheel ``<w>``):

=====================  ======================================================================
``from_currents_<w>``  wheel speed the dynamic model reaches from the measured currents [rad/s]
``from_commands_<w>``  wheel speed the firmware PI loop reaches from the commands [rad/s]
                       (current mode: the measured speed)
``commands_before_<w>`` the same at the sample before [rad/s]
``commanded_<w>``      the command in force: speed [rad/s], or in current mode the effort the
                       command implies [N·m]
``commanded_before_<w>`` the command in force at the sample before
``explained_<w>``      torque the dynamics need for the measured speed change [N·m]
``friction_<w>``       its friction part [N·m]
``unseen_friction_<w>`` friction the model may miss out of its calibrated range (a gliding
                       roller, the contact law's range, other speeds) [N·m]
``since``              stamp of the sample before: the interval the prediction spans [s]
``velocity_mode``      1 velocity mode, 0 current mode
``load_factor``        the platform-wide friction/load condition (1: as identified) [-]
``outside_calibration`` wheels whose operating point the learned correction's calibration
                       did not cover (bit w for wheel w; physics only for them) [-]
``resynced``           1: the command path took the measured state at this sample (a current
                       calibration never saw); its prediction settles again from there
=====================  ======================================================================

The ``residual_generator`` node turns a sample and its prediction into /youbot_fdi/residuals.
With ``fused: true`` (a weak robot PC) this node does that itself and publishes the residuals
too: one hop and one message fewer, the same numbers.

Bad input (NaN, short arrays, unknown joint names, empty messages, stamps going backwards or
repeated) is skipped or restarts the observer, never raises a fault; a WARN on ``/diagnostics``
names it (at most one every ``input_warn_interval`` s).

Parameters: the keys of ``config/fdi.yaml`` plus ``params_file`` (a ``youbot-fdi identify``
output), ``fused`` (read-only) and ``input_warn_interval`` [s].
"""
import sys

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import JointState

from youbot_fdi.fdi.observer import Prediction
from youbot_fdi.app.config import configure
from youbot_fdi.fdi.residuals import ResidualGenerator
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.nodes.common import (declare_settings, INPUT_WARN_INTERVAL, InputWarnings,
                                     now_seconds, SENSOR_QOS, spin_nodes, stamp_to_seconds,
                                     STREAM_QOS, timing_report)
from youbot_fdi.nodes.conversions import joint_state, labelled_vector
from youbot_fdi.samples import message_time, RepeatedMessages, SampleMapper
from youbot_fdi.topics import JOINT_STATES, PREDICTED, RESIDUALS, WHEEL_COMMANDS

NODE_NAME = 'observer'


class ObserverNode(Node):
    """Thin adapter over :class:`~youbot_fdi.fdi.observer.ModelObserver` (fused: the whole
    :class:`~youbot_fdi.fdi.residuals.ResidualGenerator`). ``fused`` sets the parameter's
    default (the composed executables)."""

    def __init__(self, fused=False, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        params_file = self.declare_parameter('params_file', '').value
        warn_interval = float(self.declare_parameter('input_warn_interval', INPUT_WARN_INTERVAL).value)
        self.fused = bool(self.declare_parameter(
            'fused', bool(fused), ParameterDescriptor(
                read_only=True, description='also evaluate and publish the residuals (no '
                                            'residual_generator node)')).value)
        self.model, self.settings = configure(declare_settings(self, FdiSettings), params_file)
        self.names = self.model.wheel_names
        self.signs = self.model.kinematics.drive_signs
        self.labels = Prediction.labels(self.names)
        self.generator = ResidualGenerator(self.model, self.settings)
        self.observer = self.generator.observer
        self.mapper = SampleMapper(self.names, keep_partial=True)
        self.repeated = RepeatedMessages()  # re-sent messages, left out as in replay
        self.warnings = InputWarnings(self, warn_interval)
        self.timing = timing_report(self, self.settings)
        self.predicted_pub = self.create_publisher(JointState, PREDICTED, STREAM_QOS)
        self.residual_pub = (self.create_publisher(JointState, RESIDUALS, STREAM_QOS)
                             if self.fused else None)
        self.create_subscription(JointState, WHEEL_COMMANDS, self.on_command, SENSOR_QOS)
        self.create_subscription(JointState, JOINT_STATES, self.on_joint_states, SENSOR_QOS)

    def on_command(self, msg):
        stamp = float(message_time(stamp_to_seconds(msg.header.stamp), now_seconds(self)))
        sample = self.mapper.command_sample(stamp, msg.name, msg.velocity, msg.effort)
        if sample is not None:
            self.observer.command(sample)
        self.report_input()  # rate-limited: a skipped command, or one that came late

    def on_joint_states(self, msg):
        stamp = float(message_time(stamp_to_seconds(msg.header.stamp), now_seconds(self)))
        self.timing.tick(stamp)
        sample = self.mapper.joint_sample(stamp, msg.name,
                                          msg.position, msg.velocity, msg.effort)
        if sample is None or not self.repeated.fresh_sample(sample):  # bad, or re-sent: no fresh data
            self.report_input()
            return
        if self.fused:  # a sample missing some wheels gives a frame with their silence only
            frame = self.generator.update(sample)
            prediction = self.generator.last_prediction
        elif not sample.complete():  # missing data: the residual generator takes it alone
            frame, prediction = None, None
        else:
            frame, prediction = None, self.observer.update(sample)
        if prediction is not None:
            self.predicted_pub.publish(joint_state(sample.stamp, self.labels,
                                                   position=prediction.to_vector(self.signs)))
        if frame is not None:
            self.residual_pub.publish(labelled_vector(frame.stamp, *frame.to_labelled(self.names)))
        if prediction is None:
            self.report_input()

    def report_input(self):
        """A rate-limited WARN on /diagnostics naming the input problems counted so far."""
        self.warnings.check({**self.mapper.counters, **self.observer.counters,
                             'messages_repeated': self.repeated.count})


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi observer``."""
    return spin_nodes([ObserverNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
