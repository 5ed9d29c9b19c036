"""``residual_generator`` node: /joint_states + /youbot_fdi/predicted -> /youbot_fdi/residuals.

Pairs each /joint_states sample with the observer's prediction for it by header stamp (never by
arrival: either may come first) and publishes the residuals with their bounds and the signals the
decision needs (a labelled vector, see
:meth:`~youbot_fdi.fdi.residuals.ResidualFrame.to_labelled`). The computation is
:class:`~youbot_fdi.fdi.residuals.ResidualEvaluator`, the one ``replay`` runs, so the separate
nodes give the replay's events.

A sample waits for its prediction (and a prediction for its sample) among at most
``pending_limit`` others; a prediction that does not start at the last sample evaluated (one was
lost between the nodes) restarts the residuals, counted as ``unpaired``. Samples without a header
stamp cannot be paired: they are counted and reported (run the observer with ``fused: true``
for such a driver). Input problems are a rate-limited WARN on ``/diagnostics``.

Parameters: the keys of ``config/fdi.yaml``, ``params_file`` (a ``youbot-fdi identify`` output),
``input_warn_interval`` [s], ``pending_limit`` [messages].
"""
import sys

from rclpy.node import Node
from sensor_msgs.msg import JointState

from youbot_fdi.fdi.observer import Prediction
from youbot_fdi.app.config import configure
from youbot_fdi.fdi.residuals import ResidualEvaluator
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.nodes.common import (declare_settings, INPUT_WARN_INTERVAL, InputWarnings,
                                     SENSOR_QOS, spin_nodes, stamp_to_seconds, STREAM_QOS,
                                     timing_report)
from youbot_fdi.nodes.conversions import labelled_vector
from youbot_fdi.samples import SampleMapper
from youbot_fdi.topics import JOINT_STATES, PREDICTED, RESIDUALS

NODE_NAME = 'residual_generator'
#: Samples (and predictions) kept waiting for their counterpart; far above the observer's lag.
PENDING_LIMIT = 64


def hold(pending, stamp, item, limit):
    """Keep ``item`` under ``stamp`` in ``pending`` (insertion-ordered), dropping the oldest
    beyond ``limit``; returns how many were dropped."""
    pending[stamp] = item
    dropped = 0
    while len(pending) > limit:
        del pending[next(iter(pending))]
        dropped += 1
    return dropped


def drop_through(pending, stamp):
    """Remove the entries stamped at or before ``stamp``."""
    for key in [key for key in pending if key <= stamp]:
        del pending[key]


class ResidualGeneratorNode(Node):
    """Thin adapter over :class:`~youbot_fdi.fdi.residuals.ResidualEvaluator`."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        params_file = self.declare_parameter('params_file', '').value
        warn_interval = float(self.declare_parameter('input_warn_interval', INPUT_WARN_INTERVAL).value)
        self.pending_limit = int(self.declare_parameter('pending_limit', PENDING_LIMIT).value)
        self.model, self.settings = configure(declare_settings(self, FdiSettings), params_file)
        self.names = self.model.wheel_names
        self.signs = self.model.kinematics.drive_signs
        self.evaluator = ResidualEvaluator(self.model, self.settings)
        self.mapper = SampleMapper(self.names, keep_partial=True)
        self.counters = {'skipped_unstamped': 0, 'dropped_unpaired': 0}
        self.samples, self.predictions = {}, {}  # stamp -> waiting for its counterpart
        self.warnings = InputWarnings(self, warn_interval)
        self.timing = timing_report(self, self.settings)
        self.residual_pub = self.create_publisher(JointState, RESIDUALS, STREAM_QOS)
        self.create_subscription(JointState, JOINT_STATES, self.on_joint_states, SENSOR_QOS)
        self.create_subscription(JointState, PREDICTED, self.on_prediction, SENSOR_QOS)

    def on_joint_states(self, msg):
        stamp = stamp_to_seconds(msg.header.stamp)
        self.timing.tick(stamp)
        if stamp <= 0.0:
            self.counters['skipped_unstamped'] += 1
            self.report_input()
            return
        sample = self.mapper.joint_sample(stamp, msg.name, msg.position, msg.velocity, msg.effort)
        if sample is None:
            self.report_input()
            return
        if not sample.complete():  # some wheels without a reading: no prediction comes for it
            frame = self.evaluator.missing(sample)
            self.residual_pub.publish(labelled_vector(frame.stamp, *frame.to_labelled(self.names)))
            self.report_input()
            return
        prediction = self.predictions.pop(stamp, None)
        if prediction is None:
            self.counters['dropped_unpaired'] += hold(self.samples, stamp, sample, self.pending_limit)
        else:
            self.evaluate(sample, prediction)

    def on_prediction(self, msg):
        stamp = stamp_to_seconds(msg.header.stamp)
        try:
            prediction = Prediction.from_labelled(stamp, msg.name, msg.position, self.names, self.signs)
        except ValueError as err:
            self.get_logger().warning(f'prediction ignored: {err}', throttle_duration_sec=2.0)
            return
        sample = self.samples.pop(stamp, None)
        if sample is None:
            self.counters['dropped_unpaired'] += hold(self.predictions, stamp, prediction,
                                                      self.pending_limit)
        else:
            self.evaluate(sample, prediction)

    def evaluate(self, sample, prediction):
        """Residuals of a paired sample; the sample the prediction starts from restarts the
        evaluator when it is not the last one evaluated (the observer restarted there)."""
        if self.evaluator.last_stamp != prediction.since:
            start = self.samples.get(prediction.since)
            if start is not None:
                self.evaluator.restart(start)
        frame = self.evaluator.update(sample, prediction)
        drop_through(self.samples, sample.stamp)
        drop_through(self.predictions, sample.stamp)
        if frame is None:
            self.report_input()
            return
        self.residual_pub.publish(labelled_vector(frame.stamp, *frame.to_labelled(self.names)))

    def report_input(self):
        """A rate-limited WARN on /diagnostics naming the input problems counted so far."""
        self.warnings.check({**self.mapper.counters, **self.evaluator.counters, **self.counters})


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi residual_generator``."""
    return spin_nodes([ResidualGeneratorNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
