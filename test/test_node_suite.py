"""The node suite as a ROS 2 user meets it (issue 13): the decision's ~/reset service, read-only
parameters validated at start, the launch file and the diagnostic aggregator configuration."""
import ast
from pathlib import Path

import pytest

from ros_harness import harness  # noqa: F401 - the fixture

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from youbot_fdi.errors import ConfigError  # noqa: E402
from youbot_fdi.fdi.decision import FaultEvent  # noqa: E402
from youbot_fdi.nodes.common import LATCHED_QOS  # noqa: E402
from youbot_fdi.nodes.conversions import event_from_status  # noqa: E402
from youbot_fdi.nodes.decision import DecisionNode  # noqa: E402
from youbot_fdi.yamlio import load_yaml  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def test_reset_clears_latched_faults_and_says_what(harness):
    decision = harness.add(DecisionNode(context=harness.context))
    faults = []
    harness.probe.create_subscription(DiagnosticArray, '/youbot_fdi/faults',
                                      lambda m: faults.extend(event_from_status(s) for s in m.status),
                                      LATCHED_QOS)
    latched = FaultEvent(100.0, 'ERROR', 'wheel_joint_fl', 'stuck', ('torque_fl',), 'test')
    decision.decision._transition('wheel_joint_fl', 'ERROR', 'stuck', 100.0)
    decision.emit([latched])
    client = harness.probe.create_client(Trigger, '/decision/reset')
    assert client.wait_for_service(timeout_sec=10.0)
    future = client.call_async(Trigger.Request())
    assert harness.spin_until(future.done, 10.0)
    answer = future.result()
    assert answer.success and answer.message == 'cleared: wheel_joint_fl: stuck'
    assert harness.spin_until(lambda: any(e.level == 'OK' for e in faults), 10.0)
    ok = [e for e in faults if e.level == 'OK'][0]
    assert (ok.wheel, ok.fault, ok.detail) == ('wheel_joint_fl', 'stuck', 'reset after a repair')
    assert decision.decision.states()['wheel_joint_fl'] == ('OK', '')
    again = client.call_async(Trigger.Request())
    assert harness.spin_until(again.done, 10.0) and again.result().message == 'nothing to clear'


def test_parameters_are_read_only_and_validated_at_start(harness):
    decision = harness.add(DecisionNode(context=harness.context))
    result = decision.set_parameters([Parameter('torque_sigma', value=0.5)])[0]
    assert not result.successful  # read-only: refused, not silently ignored
    with pytest.raises(ConfigError, match='release'):
        DecisionNode(context=harness.context, parameter_overrides=[Parameter('release', value=0)])


def test_the_launch_file_compiles_and_names_what_exists():
    launch = REPO / 'launch' / 'youbot_fdi.launch.py'
    tree = ast.parse(launch.read_text())  # compiles
    compile(tree, str(launch), 'exec')
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    setup = (REPO / 'setup.py').read_text()
    executables = {'driver_shim', 'kinematics_bridge', 'observer', 'decision', 'youbot_fdi_suite'}
    assert executables <= strings
    for name in executables:
        assert f"'{name} = youbot_fdi.nodes." in setup, name
    for params in (s for s in strings if s.endswith('.yaml')):
        assert (REPO / 'config' / params).is_file(), params
    assert 'composed' in strings
    assert "glob('launch/*.launch.py')" in setup  # installed under share/


def test_the_aggregator_groups_what_the_nodes_publish():
    data = load_yaml((REPO / 'config' / 'diagnostic_aggregator.yaml').read_text())
    analyzers = data['analyzers']['ros__parameters']
    prefixes = {name: spec['startswith'] for name, spec in analyzers.items() if isinstance(spec, dict)}
    names = ['youbot_fdi/decision: wheel_joint_fl', 'youbot_fdi/decision: base',
             'youbot_fdi/driver_shim: bus', 'youbot_fdi/observer: input']
    for status in names:
        assert any(status.startswith(p) for group in prefixes.values() for p in group), status
