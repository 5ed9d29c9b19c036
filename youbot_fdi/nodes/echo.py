"""Print fault events from /youbot_fdi/faults as JSON lines (``youbot-fdi echo``)."""
import time

from diagnostic_msgs.msg import DiagnosticArray
import rclpy
from rclpy.node import Node

from youbot_fdi.nodes.common import LATCHED_QOS
from youbot_fdi.nodes.conversions import event_from_status
from youbot_fdi.topics import FAULTS


def echo_faults(topic=FAULTS, count=0, timeout=0.0, write=print):
    """Subscribe (latched) and ``write`` each :class:`~youbot_fdi.fdi.decision.FaultEvent` as it
    arrives; stop after ``count`` events or ``timeout`` [s]."""
    rclpy.init()
    node = Node('youbot_fdi_echo')
    seen = []

    def on_faults(msg):
        for status in msg.status:
            write(event_from_status(status))
            seen.append(status)

    node.create_subscription(DiagnosticArray, topic, on_faults, LATCHED_QOS)
    deadline = time.monotonic() + timeout if timeout > 0 else None
    try:
        while rclpy.ok() and not (count and len(seen) >= count):
            if deadline is not None and time.monotonic() > deadline:
                break
            rclpy.spin_once(node, timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return len(seen)
