"""Events are durable: a process killed with SIGKILL at any moment leaves every event it had
reported in its events file, as whole JSON lines (replay, echo; demo writes through the same
EventLog)."""
import json
import os
import signal
import subprocess
import sys

import pytest

from youbot_fdi.model import load_model
from youbot_fdi.model.scenario import load_script
from youbot_fdi.tmcm.recordings import record_drive

KILL_AFTER = 2  # events reported before the kill

# Replay in a fresh interpreter that kills itself (SIGKILL: no exit handlers, no buffer flushing)
# right after reporting its KILL_AFTER-th event.
KILLED_REPLAY = """
import os, signal, sys
from youbot_fdi.app import eventlog
write = eventlog.EventLog.write
def write_then_die(self, event):
    write(self, event)
    if self.count == int(sys.argv[3]):
        os.kill(os.getpid(), signal.SIGKILL)
eventlog.EventLog.write = write_then_die
from youbot_fdi.cli.main import main
main(['replay', sys.argv[1], '--events', sys.argv[2]])
"""


def read_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_a_killed_replay_keeps_every_event_it_had_reported(tmp_path):
    path = tmp_path / 'drive'
    record_drive(path, load_model('youbot'), load_script(duration=10.0)[1], fault='friction',
                 wheel='wheel_joint_fl', fault_time=1.0, more_faults=[('stuck', 'wheel_joint_br', 5.0)])
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.replay import replay_recording
    whole = [e.to_dict() for e in replay_recording(build_pipeline()[1], path).events]
    assert len(whole) > KILL_AFTER  # the kill comes before the end
    events = tmp_path / 'events.jsonl'
    result = subprocess.run([sys.executable, '-c', KILLED_REPLAY, str(path), str(events),
                             str(KILL_AFTER)], capture_output=True, text=True, timeout=120)
    assert result.returncode == -signal.SIGKILL, result.stderr
    assert read_lines(events) == whole[:KILL_AFTER]
    assert events.read_text().endswith('\n')


def test_a_killed_echo_keeps_every_event_it_had_printed(tmp_path):
    pytest.importorskip('rclpy')
    from diagnostic_msgs.msg import DiagnosticArray
    from ros_harness import Harness
    from youbot_fdi.fdi.decision import FaultEvent
    from youbot_fdi.nodes.common import LATCHED_QOS
    from youbot_fdi.nodes.conversions import fault_array
    sent = [FaultEvent(100.0 + k, 'ERROR', f'wheel_{k}', 'stuck', ('torque_x',), 'test')
            for k in range(3)]
    events = tmp_path / 'echo.jsonl'
    echo = subprocess.Popen([sys.executable, '-m', 'youbot_fdi.cli.main', 'echo', '--events',
                             str(events)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            env=os.environ.copy())
    harness = Harness()
    try:
        publisher = harness.probe.create_publisher(DiagnosticArray, '/youbot_fdi/faults', LATCHED_QOS)
        for k, event in enumerate(sent):
            publisher.publish(fault_array([event], event.stamp))

            def arrived(count=k + 1):
                return events.exists() and events.read_text().count('\n') >= count
            assert harness.spin_until(arrived, 30.0), 'echo did not write the event'
        assert echo.poll() is None  # still running when killed
        echo.send_signal(signal.SIGKILL)
        echo.wait(timeout=10)
    finally:
        if echo.poll() is None:
            echo.kill()
        harness.close()
    assert read_lines(events) == [e.to_dict() for e in sent]
