"""Benchmark of the FDI node suite: CPU share at 100 Hz and latency from /joint_states to decision.

Baseline, measured in the same run: a bare relay node (subscribe JointState, republish), the
cheapest thing a node on this stream can do.
"""
import tempfile
import time

import numpy as np
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
import rclpy

from youbot_fdi.nodes.common import SENSOR_QOS, shutdown_nodes, stamp_to_seconds, STREAM_QOS
from youbot_fdi.nodes.conversions import joint_state
from youbot_fdi.nodes.decision import DecisionNode
from youbot_fdi.nodes.kinematics_bridge import KinematicsBridgeNode
from youbot_fdi.nodes.observer import ObserverNode
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS

RATE = 100.0  # [Hz]


class _Feeder(Node):
    """Publishes recorded samples at 100 Hz with fresh stamps; remembers when each went out."""

    def __init__(self, samples, names, **kwargs):
        super().__init__('bench_feeder', **kwargs)
        self.samples, self.names, self.index = samples, names, 0
        self.sent = {}
        self.joint_pub = self.create_publisher(JointState, JOINT_STATES, STREAM_QOS)
        self.command_pub = self.create_publisher(JointState, WHEEL_COMMANDS, STREAM_QOS)
        self.create_timer(1.0 / RATE, self.on_timer)

    def on_timer(self):
        stamp = time.time()
        while True:  # the commands recorded since the last sample, then the sample
            kind, sample = self.samples[self.index % len(self.samples)]
            self.index += 1
            if kind == 'joint':
                break
            self.command_pub.publish(joint_state(stamp, self.names, velocity=sample.values))
        self.sent[round(stamp, 6)] = time.perf_counter()
        self.joint_pub.publish(joint_state(stamp, self.names, sample.position, sample.velocity,
                                           sample.effort))


class _Relay(Node):
    def __init__(self, **kwargs):
        super().__init__('bench_relay', **kwargs)
        self.done = {}
        self.pub = self.create_publisher(JointState, '/relay', STREAM_QOS)
        self.create_subscription(JointState, JOINT_STATES, self.on_msg, SENSOR_QOS)

    def on_msg(self, msg):
        self.pub.publish(msg)
        self.done[round(stamp_to_seconds(msg.header.stamp), 6)] = time.perf_counter()


def _run(make_nodes, samples, names, seconds):
    context = Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        feeder = _Feeder(samples, names, context=context)
        nodes = [feeder] + make_nodes(context)
        for node in nodes:
            executor.add_node(node)
        for _ in range(50):  # warm up: discovery, first callbacks
            executor.spin_once(timeout_sec=0.01)
        cpu, wall = time.process_time(), time.perf_counter()
        end = wall + seconds
        while time.perf_counter() < end:
            executor.spin_once(timeout_sec=0.01)
        share = (time.process_time() - cpu) / (time.perf_counter() - wall)
        done = nodes[-1].done
        latency = [done[s] - feeder.sent[s] for s in done if s in feeder.sent]
        return share, np.array(latency)
    finally:
        shutdown_nodes(executor, nodes, context)


class _TimedDecision(DecisionNode):
    """The decision node, remembering when it finished each sample."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.done = {}

    def on_residuals(self, msg):
        super().on_residuals(msg)
        self.done[round(stamp_to_seconds(msg.header.stamp), 6)] = time.perf_counter()


def bench_node_suite(seconds=5.0):
    """(suite CPU share, relay CPU share, suite latencies [s], relay latencies [s])."""
    from youbot_fdi.bag.reader import RecordingReader
    from youbot_fdi.model.profile import load_model
    from youbot_fdi.model.scenario import DriveScript, Segment
    from youbot_fdi.tmcm.recordings import record_drive

    model = load_model('youbot')
    names = model.wheel_names
    script = DriveScript((Segment('forward', (0.3, 0.0, 0.0), 2.0), Segment('turn', (0.1, 0.2, 0.8), 2.0)))
    with tempfile.TemporaryDirectory() as tmp:
        record_drive(f'{tmp}/rec', model, script)
        with RecordingReader(f'{tmp}/rec', names) as reader:
            samples = [('command' if hasattr(s, 'kind') else 'joint', s) for s in reader.samples()]
    suite = _run(lambda c: [KinematicsBridgeNode(context=c), ObserverNode(context=c),
                            _TimedDecision(context=c)], samples, names, seconds)
    relay = _run(lambda c: [_Relay(context=c)], samples, names, seconds)
    return suite[0], relay[0], suite[1], relay[1]
