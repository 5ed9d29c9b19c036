"""Run nodes in a private rclpy context and spin until a condition holds (no launch_testing here)."""
import time

import pytest

rclpy = pytest.importorskip('rclpy')
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402


class Harness:
    """A context, an executor, the nodes under test and a probe node for pubs/subs."""

    def __init__(self):
        self.context = Context()
        rclpy.init(context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes = []
        self.probe = self.add(Node('test_probe', context=self.context))

    def add(self, node):
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def spin_until(self, predicate, timeout, step=0.01):
        """Spin until ``predicate()`` is true; returns its last value (False on timeout)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=step)
            value = predicate()
            if value:
                return value
        return predicate()

    def spin_for(self, seconds, every=None, action=None):
        """Spin for ``seconds``, calling ``action`` every ``every`` seconds."""
        deadline = time.monotonic() + seconds
        next_action = time.monotonic()
        while time.monotonic() < deadline:
            if action is not None and time.monotonic() >= next_action:
                action()
                next_action += every
            self.executor.spin_once(timeout_sec=0.005)

    def close(self):
        from youbot_fdi.nodes.common import shutdown_nodes
        shutdown_nodes(self.executor, self.nodes, self.context)


@pytest.fixture()
def harness():
    """A fresh :class:`Harness` per test, closed after it (import the fixture by name)."""
    made = Harness()
    yield made
    made.close()
