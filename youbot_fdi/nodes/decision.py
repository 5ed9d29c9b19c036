"""``decision`` node: /youbot_fdi/residuals -> /youbot_fdi/faults (latched) and /diagnostics.

Runs :class:`~youbot_fdi.fdi.decision.DecisionMaker` on the residual frames the observer publishes.
``/youbot_fdi/faults`` (DiagnosticArray, transient-local) carries one status per component whose
fault state changed, with the event in its KeyValues (stamp, level, wheel, fault, residuals,
detail). ``/diagnostics`` gets one status per wheel and one for the base, at ``diagnostics_rate``
and on every change. Service ``~/reset`` (std_srvs/Trigger) clears latched faults after a repair,
answers what it cleared and publishes an OK event for each.

The black box (:mod:`youbot_fdi.app.incidents`, parameters ``incident_*`` in
``config/incidents.yaml``): the node keeps the raw messages of the FDI's inputs and outputs for
``incident_before`` seconds (:class:`BufferedTopics`: serialized, taken every
``INCIDENT_TAKE_PERIOD`` without a callback per message) and writes an incident recording for
every new alarm episode, in a background thread. Receive times are the middleware's (system
clock), as ``ros2 bag record`` stamps them.

Silence is judged on what the base sends: no residual for ``data_timeout`` (ROS time, so replayed
recordings with use_sim_time work) is comm_loss of the base only if no /joint_states came after
the last sample judged either. If samples came (an FDI node is behind or down: starting, starved
of CPU), that is not a base fault: a WARN ``pipeline`` status on ``/diagnostics`` says so until
residuals flow again. The decision reads /joint_states only then (:class:`NewestMessage`: no
callback per sample).
"""
import dataclasses
import math
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from youbot_fdi.app.config import configure, residual_data_for
from youbot_fdi.app.incidents import IncidentRecorder, IncidentSettings, RECORDED_TOPICS, RunContext
from youbot_fdi.faults import CONDITIONS, Level
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.residuals import ResidualFrame
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.nodes.common import (BufferedTopics, declare_settings, diagnostics_publisher, LATCHED_QOS,
                                     NAME_PREFIX, NewestMessage, now_seconds, seconds_to_stamp,
                                     SENSOR_QOS, spin_nodes, stamp_to_seconds, timing_report)
from youbot_fdi.nodes.conversions import BASE_COMPONENT, fault_array, LEVELS
from youbot_fdi.topics import FAULTS, JOINT_STATES, RESIDUALS

NODE_NAME = 'decision'
#: How often the recorded topics' messages are taken into the incident recorder [s], and how
#: many each topic keeps meanwhile [messages]: 2.5 s of 100 Hz /joint_states, so an executor held
#: up for that long loses none.
INCIDENT_TAKE_PERIOD = 0.1
INCIDENT_BUFFER_DEPTH = 256


def message_class(type_name):
    """The rclpy message class of ``pkg/msg/Name``."""
    import importlib
    package, kind, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), name)


def plain(value):
    """A settings value as plain YAML (tuples as lists)."""
    return list(value) if isinstance(value, tuple) else value


class DecisionNode(Node):
    """Thin adapter over :class:`~youbot_fdi.fdi.decision.DecisionMaker`."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        params_file = self.declare_parameter('params_file', '').value
        rate = float(self.declare_parameter('diagnostics_rate', 1.0).value)
        self.model, self.settings = configure(declare_settings(self, FdiSettings), params_file)
        self.names = self.model.wheel_names
        self.decision = DecisionMaker(self.names, self.settings,
                                      residual_data_for(self.model, self.settings))
        self.events = []
        self._last_stamp = None  # of the last residual frame [s]
        self._heard = -math.inf  # the newest /joint_states stamp seen at a stall [s]
        self._heard_at = -math.inf  # this node's time when it saw that sample [s]
        self._behind_since = None  # residuals stopped while /joint_states flowed: since [s]
        self.base_watch = NewestMessage(self, JointState, JOINT_STATES)
        self.faults_pub = self.create_publisher(DiagnosticArray, FAULTS, LATCHED_QOS)
        self.diag_pub = diagnostics_publisher(self)
        self.timing = timing_report(self, self.settings)
        self.create_subscription(JointState, RESIDUALS, self.on_residuals, SENSOR_QOS)
        self.create_service(Trigger, '~/reset', self.on_reset)
        self._frame = None  # the last residual frame judged (the incidents' freeze-frame)
        self._alarmed = set()  # components in an alarm episode
        self.recorder = self._start_recorder(declare_settings(self, IncidentSettings), params_file)
        self.create_timer(1.0 / rate, self.publish_diagnostics)
        # Fires only after data_timeout without residuals: every residual restarts it (no
        # periodic wake-ups while data flow).
        self.stall_timer = self.create_timer(self.settings.data_timeout, self.check_stall)

    def _start_recorder(self, settings, params_file):
        """The incident recorder and its buffered subscriptions (None when disabled)."""
        if not settings.incidents_enabled:
            return None
        context = RunContext(params_file=params_file or '',
                             settings={k: plain(v) for k, v in
                                       dataclasses.asdict(self.settings).items()},
                             profile=self.model.profile.name)
        recorder = IncidentRecorder(settings, context, log=self.get_logger().info)
        self._buffer = BufferedTopics(self, {topic: message_class(type_name) for topic, type_name
                                             in RECORDED_TOPICS.items()}, INCIDENT_BUFFER_DEPTH)
        self.create_timer(INCIDENT_TAKE_PERIOD, self.take_recorded)
        self.get_logger().info(f'incidents: {settings.folder()} ({settings.incident_before:g} s '
                               f'before an alarm, {settings.incident_after:g} s after)')
        return recorder

    def take_recorded(self):
        """Move what the recorded topics received into the incident recorder (its ring buffer
        and open incidents), and close the incidents whose time is up."""
        self.recorder.record_batch(self._buffer.take())
        self.recorder.poll(time.time_ns())

    def on_residuals(self, msg):
        stamp = stamp_to_seconds(msg.header.stamp)
        self.timing.tick(stamp)
        try:
            frame = ResidualFrame.from_labelled(stamp, msg.name, msg.position, msg.velocity, self.names)
        except ValueError as err:
            self.get_logger().warning(f'residual vector ignored: {err}', throttle_duration_sec=2.0)
            return
        self._last_stamp = stamp
        self._frame = frame
        self.stall_timer.reset()
        if self._behind_since is not None:
            self.get_logger().info('residuals flow again')
            self._behind_since = None
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
        """No residual for ``data_timeout`` (the timer ran out, and runs out again every
        ``data_timeout`` while none comes): the base is silent (comm_loss) unless a /joint_states
        sample came after the last one judged, or since the last check; then the FDI nodes are
        behind (a WARN on /diagnostics, no fault). Silent means for ``data_timeout`` on this
        node's clock since the base data it last saw, however soon the timer fires again."""
        if self._last_stamp is None:
            return
        since = max(self._last_stamp, self._heard)
        now = now_seconds(self)
        newest = self.base_watch.take()
        if newest is not None:
            stamp = stamp_to_seconds(newest.header.stamp)
            heard = stamp if stamp > 0.0 else now  # unstamped: it came just now
            if heard > since:
                self._heard, self._heard_at = heard, now
                if self._behind_since is None:
                    self._behind_since = since
                    self.get_logger().warning(
                        f'no residuals for {self.settings.data_timeout:g} s while /joint_states '
                        'flow: an FDI node is behind or down (not a base fault)')
                    self.publish_diagnostics()
                return
        if now - self._heard_at < self.settings.data_timeout:
            # The timer keeps its period's grid: a firing held up by a busy host is followed by
            # an on-time one soon after, and a take that soon may find no new sample. Silence
            # counts from the last base data this node saw, on its own clock.
            return
        self._behind_since = None
        self.emit(self.decision.data_stalled(since))

    def emit(self, events):
        if not events:
            return
        self.events.extend(events)
        self.faults_pub.publish(fault_array(events, events[-1].stamp))
        self._open_incidents(events)
        for event in events:
            text = f'{event.level} {event.wheel or BASE_COMPONENT}: {event.fault} ({event.detail})'
            if event.level == Level.ERROR:
                self.get_logger().error(text)
            else:
                self.get_logger().info(text)
        self.publish_diagnostics()

    def _open_incidents(self, events):
        """An incident for each new alarm episode among ``events``."""
        for event in events:
            if event.fault in CONDITIONS:  # the base's load and range conditions: WARNs, not alarms
                continue
            if event.level != Level.ERROR:
                if event.level == Level.OK:
                    self._alarmed.discard(event.wheel)
                continue
            if event.wheel in self._alarmed:
                continue  # the same episode (its type refined)
            self._alarmed.add(event.wheel)
            if self.recorder is not None:
                self.take_recorded()  # the ring up to now, then the incident opens
                self.recorder.open(event.to_dict(), time.time_ns(),
                                   self.decision.freeze_frame(self._frame))

    def destroy_node(self):
        if self.recorder is not None:
            self.take_recorded()
            self.recorder.close()
            self.recorder = None
            self._buffer.close()
        self.base_watch.close()
        return super().destroy_node()

    def pipeline_status(self):
        """The FDI pipeline's status: WARN while residuals stop and /joint_states flow."""
        status = DiagnosticStatus()
        status.name = f'{NAME_PREFIX}/{NODE_NAME}: pipeline'
        status.hardware_id = 'fdi'
        if self._behind_since is None:
            status.level, status.message = DiagnosticStatus.OK, 'residuals flow'
        else:
            status.level = DiagnosticStatus.WARN
            status.message = (f'no residuals since {self._behind_since:.3f} s while /joint_states '
                              'flow: an FDI node is behind or down')
        return status

    def publish_diagnostics(self):
        array = DiagnosticArray()
        array.header.stamp = seconds_to_stamp(now_seconds(self))
        for key, (level, fault) in self.decision.states().items():
            status = DiagnosticStatus()
            status.level = LEVELS[level]
            component = key or BASE_COMPONENT
            status.name = f'{NAME_PREFIX}/{NODE_NAME}: {component}'
            status.hardware_id = component
            status.message = 'ok' if level == Level.OK else fault
            status.values = [KeyValue(key='fault', value=fault if level != Level.OK else '')]
            if self._last_stamp is None:
                status.level, status.message = DiagnosticStatus.STALE, 'no residuals yet'
            array.status.append(status)
        array.status.append(self.pipeline_status())
        self.diag_pub.publish(array)


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi decision``."""
    return spin_nodes([DecisionNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
