"""``decision`` node: /youbot_fdi/residuals -> /youbot_fdi/faults (latched) and /diagnostics.

Runs :class:`~youbot_fdi.fdi.decision.DecisionMaker` on the residual frames the observer publishes.
``/youbot_fdi/faults`` (DiagnosticArray, transient-local) carries one status per component whose
fault state changed, with the event in its KeyValues (stamp, level, wheel, fault, residuals,
detail). ``/diagnostics`` gets one status per wheel and one for the base, at ``diagnostics_rate``
and on every change. Service ``~/reset`` (std_srvs/Trigger) clears latched faults after a repair,
answers what it cleared and publishes an OK event for each. No residuals for longer than ``comm_timeout`` (ROS time, so replayed
recordings with use_sim_time work) is comm_loss of the base.
"""
import sys

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from youbot_fdi.fdi.decision import DecisionMaker, OK
from youbot_fdi.fdi.pipeline import configure, load_residual_data
from youbot_fdi.fdi.residuals import ResidualFrame
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.nodes.common import (declare_settings, diagnostics_publisher, LATCHED_QOS,
                                     NAME_PREFIX, now_seconds, seconds_to_stamp, SENSOR_QOS,
                                     spin_nodes, stamp_to_seconds, timing_report)
from youbot_fdi.nodes.conversions import BASE_COMPONENT, fault_array, LEVELS
from youbot_fdi.topics import FAULTS, RESIDUALS

NODE_NAME = 'decision'


class DecisionNode(Node):
    """Thin adapter over :class:`~youbot_fdi.fdi.decision.DecisionMaker`."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        params_file = self.declare_parameter('params_file', '').value
        rate = float(self.declare_parameter('diagnostics_rate', 1.0).value)
        self.model, self.settings = configure(declare_settings(self, FdiSettings), params_file)
        self.names = self.model.wheel_names
        self.decision = DecisionMaker(self.names, self.settings,
                                      load_residual_data(self.settings.residual_file or None,
                                                         self.model.wheel_names))
        self.events = []
        self._last_stamp = None
        self.faults_pub = self.create_publisher(DiagnosticArray, FAULTS, LATCHED_QOS)
        self.diag_pub = diagnostics_publisher(self)
        self.timing = timing_report(self, self.settings)
        self.create_subscription(JointState, RESIDUALS, self.on_residuals, SENSOR_QOS)
        self.create_service(Trigger, '~/reset', self.on_reset)
        self.create_timer(1.0 / rate, self.publish_diagnostics)
        # Fires only after data_timeout without residuals: every residual restarts it (no
        # periodic wake-ups while data flow).
        self.stall_timer = self.create_timer(self.settings.data_timeout, self.check_stall)

    def on_residuals(self, msg):
        stamp = stamp_to_seconds(msg.header.stamp)
        self.timing.tick(stamp)
        try:
            frame = ResidualFrame.from_labelled(stamp, msg.name, msg.position, msg.velocity, self.names)
        except ValueError as err:
            self.get_logger().warning(f'residual vector ignored: {err}', throttle_duration_sec=2.0)
            return
        self._last_stamp = stamp
        self.stall_timer.reset()
        self.emit(self.decision.data_resumed(stamp) + self.decision.update(frame))

    def on_reset(self, _request, response):
        """``~/reset`` (std_srvs/Trigger): clear latched faults after a repair; says what it
        cleared and publishes an OK event for each."""
        events, cleared = self.decision.reset(now_seconds(self))
        self.emit(events)
        response.success = True
        response.message = ('cleared: ' + ', '.join(cleared)) if cleared else 'nothing to clear'
        self.get_logger().info(f'reset: {response.message}')
        return response

    def check_stall(self):
        """No residual for ``data_timeout`` (the timer ran out): comm_loss of the base."""
        if self._last_stamp is not None:
            self.emit(self.decision.data_stalled(self._last_stamp))

    def emit(self, events):
        if not events:
            return
        self.events.extend(events)
        self.faults_pub.publish(fault_array(events, events[-1].stamp))
        for event in events:
            text = f'{event.level} {event.wheel or BASE_COMPONENT}: {event.fault} ({event.detail})'
            if event.level == 'ERROR':
                self.get_logger().error(text)
            else:
                self.get_logger().info(text)
        self.publish_diagnostics()

    def publish_diagnostics(self):
        array = DiagnosticArray()
        array.header.stamp = seconds_to_stamp(now_seconds(self))
        for key, (level, fault) in self.decision.states().items():
            status = DiagnosticStatus()
            status.level = LEVELS[level]
            component = key or BASE_COMPONENT
            status.name = f'{NAME_PREFIX}/{NODE_NAME}: {component}'
            status.hardware_id = component
            status.message = 'ok' if level == OK else fault
            status.values = [KeyValue(key='fault', value=fault if level != OK else '')]
            if self._last_stamp is None:
                status.level, status.message = DiagnosticStatus.STALE, 'no residuals yet'
            array.status.append(status)
        self.diag_pub.publish(array)


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi decision``."""
    return spin_nodes([DecisionNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
