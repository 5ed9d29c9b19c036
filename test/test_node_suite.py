"""The node suite as a ROS 2 user meets it (issue 13): the residual generator as its own node,
the decision's ~/reset service, read-only parameters validated at start, the launch file and the
diagnostic aggregator configuration."""
import ast
from pathlib import Path

import pytest

from ros_harness import harness  # noqa: F401 - the fixture

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
import numpy as np  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from youbot_fdi.errors import ConfigError  # noqa: E402
from youbot_fdi.bag.reader import RecordingReader  # noqa: E402
from youbot_fdi.fdi.decision import FaultEvent  # noqa: E402
from youbot_fdi.fdi.observer import Prediction  # noqa: E402
from youbot_fdi.fdi.residuals import FAMILIES, ResidualFrame, ResidualGenerator  # noqa: E402
from youbot_fdi.fdi.settings import FdiSettings  # noqa: E402
from youbot_fdi.model.profile import load_model  # noqa: E402
from youbot_fdi.model.scenario import load_script  # noqa: E402
from youbot_fdi.nodes.common import LATCHED_QOS, stamp_to_seconds, STREAM_QOS  # noqa: E402
from youbot_fdi.nodes.conversions import event_from_status, joint_state  # noqa: E402
from youbot_fdi.nodes.decision import DecisionNode  # noqa: E402
from youbot_fdi.nodes.residual_generator import ResidualGeneratorNode  # noqa: E402
from youbot_fdi.tmcm.recordings import record_drive  # noqa: E402
from youbot_fdi.yamlio import load_yaml  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def test_prediction_vector_round_trip_is_exact():
    model = load_model('youbot')
    names, signs = model.wheel_names, model.kinematics.drive_signs
    rng = np.random.default_rng(3)
    wheels = {f: rng.normal(size=4) for f in ('from_currents', 'from_commands', 'commands_before',
                                              'commanded', 'commanded_before', 'commanded_latest',
                                              'explained', 'friction', 'unseen_friction',
                                              'load_spread')}
    prediction = Prediction(stamp=1.5, since=1.49, velocity_mode=False, load_factor=1.2, **wheels)
    labels, values = Prediction.labels(names), prediction.to_vector(signs)
    back = Prediction.from_labelled(1.5, labels, values, names, signs)
    for field, array in wheels.items():
        np.testing.assert_array_equal(getattr(back, field), array)
    assert (back.since, back.velocity_mode, back.load_factor) == (1.49, False, 1.2)
    shuffled = rng.permutation(len(labels))  # matched by label, not by position
    again = Prediction.from_labelled(1.5, [labels[i] for i in shuffled], values[shuffled], names, signs)
    np.testing.assert_array_equal(again.explained, prediction.explained)
    with pytest.raises(ValueError, match='lacks from_currents_fl'):
        Prediction.from_labelled(1.5, labels[1:], values[1:], names, signs)
    # an observer from before commanded_latest: the command in force stands in for it
    older = [i for i, label in enumerate(labels) if not label.startswith('commanded_latest_')]
    before = Prediction.from_labelled(1.5, [labels[i] for i in older], values[older], names, signs)
    np.testing.assert_array_equal(before.commanded_latest, prediction.commanded)
    np.testing.assert_array_equal(before.explained, prediction.explained)
    # an observer from before load_spread: no spread (the configured allowance alone)
    older = [i for i, label in enumerate(labels) if not label.startswith('load_spread_')]
    before = Prediction.from_labelled(1.5, [labels[i] for i in older], values[older], names, signs)
    np.testing.assert_array_equal(before.load_spread, np.zeros(4))
    np.testing.assert_array_equal(before.friction, prediction.friction)
    assert np.any(values[:4] != prediction.from_currents)  # published in driver convention


def test_residual_generator_node_pairs_by_stamp_not_by_arrival(harness, tmp_path):
    """Predictions computed offline, published before or after their samples (alternating): the
    node's residuals equal the offline generator's, bit for bit (the command bound, whose
    allowance low-passes the torque carried, to 1e-9 once it has settled after a restart). A lost
    prediction: the next interval starts afresh at its sample (as after an observer restart); a
    lost sample: the prediction after it cannot be paired, counted, no residual from the wrong
    interval."""
    model = load_model('youbot')
    names, signs = model.wheel_names, model.kinematics.drive_signs
    settings = FdiSettings()
    _, script = load_script()
    path = record_drive(tmp_path / 'rec', model, script.scaled_to(3.0), fault='friction',
                        wheel='wheel_joint_fl', fault_time=1.5).path
    generator = ResidualGenerator(model, settings)
    pairs, expected = [], {}
    with RecordingReader(path, names) as reader:
        for sample in reader.samples():
            if hasattr(sample, 'kind'):
                generator.command(sample)
                continue
            frame = generator.update(sample)
            pairs.append((sample, generator.last_prediction))
            if frame is not None:
                expected[frame.stamp] = frame
    node = harness.add(ResidualGeneratorNode(context=harness.context))
    joint_pub = harness.probe.create_publisher(JointState, '/joint_states', STREAM_QOS)
    predicted_pub = harness.probe.create_publisher(JointState, '/youbot_fdi/predicted', STREAM_QOS)
    got = {}
    harness.probe.create_subscription(
        JointState, '/youbot_fdi/residuals',
        lambda m: got.setdefault(stamp_to_seconds(m.header.stamp), ResidualFrame.from_labelled(
            stamp_to_seconds(m.header.stamp), m.name, m.position, m.velocity, names)), STREAM_QOS)
    assert harness.spin_until(lambda: node.count_publishers('/youbot_fdi/predicted') >= 1
                              and joint_pub.get_subscription_count() >= 1, 10.0)
    stamps = [sample.stamp for sample, _ in pairs]
    lost_prediction, lost_sample = stamps[len(stamps) // 3], stamps[2 * len(stamps) // 3]
    for k, (sample, prediction) in enumerate(pairs):
        messages = []
        if sample.stamp != lost_sample:
            messages.append((joint_pub, joint_state(sample.stamp, names, sample.position,
                                                    sample.velocity, sample.effort)))
        if prediction is not None and sample.stamp != lost_prediction:
            vector = joint_state(sample.stamp, Prediction.labels(names), position=prediction.to_vector(signs))
            messages.insert(k % 2, (predicted_pub, vector))  # the prediction first every other sample
        for publisher, message in messages:
            publisher.publish(message)
        harness.spin_for(0.004)
    assert harness.spin_until(lambda: stamps[-1] in got, 10.0)
    after_sample = stamps[stamps.index(lost_sample) + 1]
    assert set(got) == set(expected) - {lost_prediction, lost_sample, after_sample}
    assert node.evaluator.counters['unpaired'] == 1  # the prediction after the lost sample
    restarts = [lost_prediction, after_sample]  # the residuals settle again after each
    for stamp, frame in got.items():
        settling = any(0.0 <= stamp - r < settings.startup_time for r in restarts)
        for family in FAMILIES if not settling else ('torque', 'observer', 'encoder'):
            np.testing.assert_array_equal(frame.values[family], expected[stamp].values[family])
            if family == 'command':  # its allowance remembers the torque carried before a restart
                np.testing.assert_allclose(frame.bounds[family], expected[stamp].bounds[family], rtol=1e-9)
            else:
                np.testing.assert_array_equal(frame.bounds[family], expected[stamp].bounds[family])
        assert frame.load_factor == expected[stamp].load_factor


def test_reset_clears_latched_faults_and_says_what(harness):
    decision = harness.add(DecisionNode(context=harness.context))
    faults = []
    harness.probe.create_subscription(DiagnosticArray, '/youbot_fdi/faults',
                                      lambda m: faults.extend(event_from_status(s) for s in m.status),
                                      LATCHED_QOS)
    latched = FaultEvent(100.0, 'ERROR', 'wheel_joint_fl', 'stuck', ('torque_fl',), 'test')
    decision.decision._transition('wheel_joint_fl', 'ERROR', 'stuck', 100.0)
    decision.emit(decision.decision.lifecycle.feed([latched], [100.0]))  # published, as the decision would
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
    with pytest.raises(ConfigError, match='release_time'):
        DecisionNode(context=harness.context, parameter_overrides=[Parameter('release_time', value=0.0)])


def test_the_launch_file_compiles_and_names_what_exists():
    launch = REPO / 'launch' / 'youbot_fdi.launch.py'
    tree = ast.parse(launch.read_text())  # compiles
    compile(tree, str(launch), 'exec')
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    setup = (REPO / 'setup.py').read_text()
    executables = {'driver_shim', 'kinematics_bridge', 'observer', 'residual_generator', 'decision',
                   'youbot_fdi_suite', 'youbot_fdi_fused'}
    assert executables <= strings
    for name in executables:
        assert f"'{name} = youbot_fdi.nodes." in setup, name
    for params in (s for s in strings if s.endswith('.yaml')):
        assert (REPO / 'config' / params).is_file(), params
    assert {'composed', 'fused'} <= strings
    assert "glob('launch/*.launch.py')" in setup  # installed under share/


def test_the_aggregator_groups_what_the_nodes_publish():
    data = load_yaml((REPO / 'config' / 'diagnostic_aggregator.yaml').read_text())
    analyzers = data['analyzers']['ros__parameters']
    prefixes = {name: spec['startswith'] for name, spec in analyzers.items() if isinstance(spec, dict)}
    names = ['youbot_fdi/decision: wheel_joint_fl', 'youbot_fdi/decision: base',
             'youbot_fdi/driver_shim: bus', 'youbot_fdi/observer: input']
    for status in names:
        assert any(status.startswith(p) for group in prefixes.values() for p in group), status


def _frozen_start():
    """In a fresh interpreter: the FDI nodes built, the start-up heap frozen; returns (objects
    frozen, objects the collector still tracks, whether a new reference cycle is still freed)."""
    import gc
    import weakref
    import rclpy
    from youbot_fdi.nodes.common import freeze_startup_heap
    from youbot_fdi.nodes.composed import LAYOUTS
    rclpy.init()
    nodes = [factory() for factory in LAYOUTS['separate']]
    freeze_startup_heap()
    frozen, tracked = gc.get_freeze_count(), len(gc.get_objects())

    class Cycle:
        pass

    cycle = Cycle()
    cycle.self = cycle
    alive = weakref.ref(cycle)
    del cycle
    gc.collect()
    for node in nodes:
        node.destroy_node()
    rclpy.shutdown()
    return frozen, tracked, alive() is None


def test_nodes_freeze_their_start_up_heap_and_still_collect_new_garbage():
    """After start-up a node process's collections scan only what spinning allocates (the models
    and modules, tens of thousands of objects, are frozen), and new garbage is still freed."""
    from fresh_process import in_fresh_process
    frozen, tracked, freed = in_fresh_process(_frozen_start)
    assert frozen > 10_000 and tracked < frozen / 10
    assert freed
