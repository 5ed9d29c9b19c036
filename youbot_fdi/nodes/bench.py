"""Benchmark of the FDI node suite, per layout: CPU share at 100 Hz and latency from /joint_states
to the decision node having judged the sample (when a fault would go out on /youbot_fdi/faults).

Each layout (:data:`CASES`) is measured beside its baseline in the same run: as many bare relay
nodes (subscribe JointState, republish) in the same arrangement: one relay per FDI node, chained
like the FDI nodes' hops (observer -> [residual_generator ->] decision) with the kinematics
bridge's counterpart beside the chain, in one executor or one process each like the layout.
CPU counts every process of the case (the feeder included, the same in both). Clocks: latency
uses CLOCK_MONOTONIC (``time.monotonic``), shared by the processes of a case.

``python -m youbot_fdi.nodes.bench --help``: the worker a process-per-node case starts.
"""
import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time

import numpy as np
from rclpy.context import Context
from rclpy.node import Node
from sensor_msgs.msg import JointState
import rclpy

from youbot_fdi.nodes.common import (EXECUTOR_VARIABLE, executor_kind, freeze_startup_heap,
                                     keep_discovery_local, make_executor, node_module, ros_init,
                                     SENSOR_QOS, shutdown_nodes, spin_until_stopped, stop_on_signals,
                                     stamp_to_seconds, stop_node_processes, STREAM_QOS)
from youbot_fdi.nodes.composed import LAYOUTS, node_name
from youbot_fdi.nodes.conversions import joint_state
from youbot_fdi.nodes.decision import DecisionNode
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS

RATE = 100.0  # [Hz]
WARM_UP = 2.0  # [s] after every node is on the graph: discovery, first callbacks, caches
START_TIMEOUT = 60.0  # [s] for the processes of a case to appear on the graph
#: (name, FDI layout, one process per node, executor (:func:`make_executor`)). The events
#: executor cases are the opt-in of our executables (``YOUBOT_FDI_EXECUTOR=events``, driven one
#: callback at a time so that SIGINT stops it; docs/nodes.md).
CASES = (('composed', 'separate', False, 'single'), ('fused', 'fused', False, 'single'),
         ('separate', 'separate', True, 'single'),
         ('composed, events executor', 'separate', False, 'events'),
         ('separate, events executor', 'separate', True, 'events'))
KEY_DECIMALS = 6  # samples are matched by their stamp rounded to 1 µs


def stamp_key(stamp):
    return round(stamp, KEY_DECIMALS)


class _Feeder(Node):
    """Publishes recorded samples at 100 Hz with fresh stamps; remembers when each went out."""

    def __init__(self, samples, names, **kwargs):
        super().__init__('bench_feeder', **kwargs)
        self.samples, self.names, self.index = samples, names, 0
        self.sent = {}
        self.joint_pub = self.create_publisher(JointState, JOINT_STATES, STREAM_QOS)
        self.command_pub = self.create_publisher(JointState, WHEEL_COMMANDS, STREAM_QOS)
        self.running = False
        self.create_timer(1.0 / RATE, self.on_timer)

    def on_timer(self):
        if not self.running:
            return
        stamp = time.time()
        while True:  # the commands recorded since the last sample, then the sample
            kind, sample = self.samples[self.index % len(self.samples)]
            self.index += 1
            if kind == 'joint':
                break
            self.command_pub.publish(joint_state(stamp, self.names, velocity=sample.values))
        self.sent[stamp_key(stamp)] = time.monotonic()
        self.joint_pub.publish(joint_state(stamp, self.names, sample.position, sample.velocity,
                                           sample.effort))


class Relay(Node):
    """A bare relay: ``source`` -> ``target`` (JointState), remembering when it passed each."""

    def __init__(self, index, source, target, **kwargs):
        super().__init__(f'bench_relay_{index}', **kwargs)
        self.done = {}
        self.pub = self.create_publisher(JointState, target, STREAM_QOS)
        self.create_subscription(JointState, source, self.on_msg, SENSOR_QOS)

    def on_msg(self, msg):
        self.pub.publish(msg)
        self.done[stamp_key(stamp_to_seconds(msg.header.stamp))] = time.monotonic()


class TimedDecision(DecisionNode):
    """The decision node, remembering when it finished each sample."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.done = {}

    def on_residuals(self, msg):
        super().on_residuals(msg)
        self.done[stamp_key(stamp_to_seconds(msg.header.stamp))] = time.monotonic()


#: The incident bench opens an incident this often [s] (an alarm every few seconds: far more
#: than a robot should see), so the writer thread works through most of the measured time.
INCIDENT_PERIOD = 2.0
BENCH_EVENT = {'stamp': 0.0, 'level': 'ERROR', 'wheel': 'wheel_joint_fl', 'fault': 'torque_loss',
               'residuals': ['torque_fl'], 'detail': 'incident bench'}


class IncidentBenchDecision(TimedDecision):
    """The decision node timing each take of the recorded messages (the callback its incident
    recorder adds) [s], opening an incident every ``period`` [s] (None: never)."""

    def __init__(self, period=INCIDENT_PERIOD, **kwargs):
        super().__init__(**kwargs)
        self.take_seconds = []
        self.recorder_cpu = 0.0
        if period is not None and self.recorder is not None:
            self.create_timer(period, lambda: self.recorder.open(
                BENCH_EVENT, time.time_ns(), self.decision.freeze_frame(self._frame)))

    def destroy_node(self):
        if self.recorder is not None:
            self.recorder_cpu = self.recorder.writer_cpu  # before the recorder closes
        return super().destroy_node()

    def take_recorded(self):
        started = time.perf_counter()
        super().take_recorded()
        self.take_seconds.append(time.perf_counter() - started)


#: Rounds of the incident bench: the three cases run in turn this many times and each case's CPU
#: share is the median of its rounds (one 10 s run of a case varied by +-15 % on the dev machine).
INCIDENT_ROUNDS = 3


def bench_incident_recorder(seconds=5.0, progress=None, period=INCIDENT_PERIOD,
                            rounds=INCIDENT_ROUNDS, cases=None):
    """The composed suite at 100 Hz without its incident recorder, with it and no alarm, and with
    it opening an incident every ``period`` [s], the three in turn ``rounds`` times: {case:
    (median CPU share, latencies [s], durations of the recorder's callback [s] (empty without),
    incidents written, writer thread CPU [s])}. ``cases`` {name: (recorder enabled, incident
    period [s] or None)} replaces the three, run in its order."""
    from rclpy.parameter import Parameter

    from youbot_fdi.app.incidents import list_incidents
    from youbot_fdi.bag.reader import RecordingReader
    from youbot_fdi.model.profile import load_model
    from youbot_fdi.model.scenario import DriveScript, Segment
    from youbot_fdi.tmcm.recordings import record_drive

    keep_discovery_local()
    model = load_model('youbot')
    names = model.wheel_names
    script = DriveScript((Segment('forward', (0.3, 0.0, 0.0), 2.0), Segment('turn', (0.1, 0.2, 0.8), 2.0)))
    factories = list(LAYOUTS['separate'][:-1])
    fdi_names = [node_name(f) for f in LAYOUTS['separate']]
    cases = cases or {'without': (False, None), 'no alarm': (True, None), 'alarms': (True, period)}
    runs = {case: [] for case in cases}
    with tempfile.TemporaryDirectory() as tmp:
        record_drive(f'{tmp}/rec', model, script)
        with RecordingReader(f'{tmp}/rec', names) as reader:
            samples = [('command' if hasattr(s, 'kind') else 'joint', s) for s in reader.samples()]
        for round_number in range(rounds):
            for case, (enabled, every) in cases.items():
                if progress is not None:
                    progress(f'  incidents: round {round_number + 1} of {rounds}, recorder {case} ...')
                folder = f'{tmp}/incidents-{round_number}-{len(runs[case])}-{enabled}-{every}'
                overrides = [Parameter('incidents_enabled', value=enabled),
                             Parameter('incident_dir', value=folder)]
                made = []

                def decision(context, overrides=overrides, every=every, made=made):
                    made.append(IncidentBenchDecision(every, context=context,
                                                      parameter_overrides=overrides))
                    return made[-1]
                share, latency = _run(factories + [decision], [], fdi_names, samples, names,
                                      seconds, 'single')
                node = made[-1]
                runs[case].append((share, latency, np.array(node.take_seconds),
                                   len(list_incidents(folder)), node.recorder_cpu))
    return {case: (float(np.median([r[0] for r in rows])), np.concatenate([r[1] for r in rows]),
                   np.concatenate([r[2] for r in rows]), sum(r[3] for r in rows),
                   sum(r[4] for r in rows)) for case, rows in runs.items()}


def relay_arrangement(count):
    """(source, target) of ``count`` relays: one beside the chain (the kinematics bridge's
    counterpart), the others chained from /joint_states; the last is the chain's end."""
    topics = [JOINT_STATES] + [f'/bench_relay/hop_{k}' for k in range(1, count)]
    return [(JOINT_STATES, '/bench_relay/side')] + list(zip(topics[:-1], topics[1:]))


def _cpu_seconds(pid):
    """utime + stime of process ``pid`` [s] (Linux /proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def _worker_command(role, timings=None, source=None, target=None, index=0):
    command = [sys.executable, '-m', __name__, role]
    if role == 'relay':
        command += ['--index', str(index), '--source', source, '--target', target]
    return command + (['--timings', str(timings)] if timings else [])


def _run(local_nodes, commands, names_on_graph, samples, names, seconds, executor_kind,
         timings=None):
    """Feed 100 Hz for ``seconds`` to ``local_nodes`` (factories taking ``context``) and the
    processes ``commands``, everything on ``executor_kind`` executors; returns (CPU share of one
    core, latencies [s] at the chain's end: the last local node's ``done``, or the ``timings``
    file a process wrote)."""
    context = Context()
    rclpy.init(context=context)
    executor = make_executor(executor_kind, context)
    nodes, processes = [], []
    try:
        feeder = _Feeder(samples, names, context=context)
        nodes = [feeder] + [make(context=context) for make in local_nodes]
        for node in nodes:
            executor.add_node(node)
        environment = {**os.environ, EXECUTOR_VARIABLE: executor_kind}
        processes = [subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      env=environment) for c in commands]
        deadline = time.monotonic() + START_TIMEOUT
        while not set(names_on_graph) <= set(feeder.get_node_names()):
            if time.monotonic() > deadline or any(p.poll() is not None for p in processes):
                msg = f'bench nodes did not start: {sorted(set(names_on_graph) - set(feeder.get_node_names()))}'
                raise RuntimeError(msg)
            executor.spin_once(timeout_sec=0.05)
        feeder.running = True
        warm_end = time.monotonic() + WARM_UP
        while time.monotonic() < warm_end:
            executor.spin_once(timeout_sec=0.01)
        cpu = time.process_time() + sum(_cpu_seconds(p.pid) for p in processes)
        wall = time.monotonic()
        sent_before = set(feeder.sent)
        while time.monotonic() < wall + seconds:
            executor.spin_once(timeout_sec=0.01)
        cpu = time.process_time() + sum(_cpu_seconds(p.pid) for p in processes) - cpu
        share = cpu / (time.monotonic() - wall)
        feeder.running = False
    finally:
        stop_node_processes(processes)
        shutdown_nodes(executor, nodes, context)
    done = (nodes[-1].done if timings is None else
            {float(k): v for k, v in json.loads(Path(timings).read_text()).items()})
    latency = [done[s] - feeder.sent[s] for s in done if s in feeder.sent and s not in sent_before]
    return share, np.array(latency)


def bench_layout(layout, processes, executor_kind, samples, names, seconds, tmp):
    """((FDI CPU share, latencies), (relay CPU share, latencies)) of one layout."""
    factories = LAYOUTS[layout]
    count = len(factories)
    arrangement = relay_arrangement(count)
    relay_names = [f'bench_relay_{k}' for k in range(count)]
    fdi_names = [node_name(f) for f in factories]
    if not processes:
        fdi = _run(list(factories[:-1]) + [TimedDecision], [], fdi_names, samples, names, seconds,
                   executor_kind)
        relay = _run([lambda context, k=k, st=st: Relay(k, *st, context=context)
                      for k, st in enumerate(arrangement)], [], relay_names, samples, names, seconds,
                     executor_kind)
        return fdi, relay
    fdi_timings, relay_timings = Path(tmp) / f'{layout}-fdi.json', Path(tmp) / f'{layout}-relay.json'
    fdi_commands = ([[sys.executable, '-m', node_module(f)] for f in factories[:-1]]
                    + [_worker_command('decision', fdi_timings)])
    relay_commands = [_worker_command('relay', relay_timings if k == count - 1 else None, *st, index=k)
                      for k, st in enumerate(arrangement)]
    fdi = _run([], fdi_commands, fdi_names, samples, names, seconds, executor_kind, fdi_timings)
    relay = _run([], relay_commands, relay_names, samples, names, seconds, executor_kind,
                 relay_timings)
    return fdi, relay


def bench_node_suite(seconds=5.0, progress=None):
    """{case name: ((FDI CPU share, latencies [s]), (relay CPU share, latencies [s]))} for every
    layout of :data:`CASES`."""
    from youbot_fdi.bag.reader import RecordingReader
    from youbot_fdi.model.profile import load_model
    from youbot_fdi.model.scenario import DriveScript, Segment
    from youbot_fdi.tmcm.recordings import record_drive

    keep_discovery_local()
    model = load_model('youbot')
    names = model.wheel_names
    script = DriveScript((Segment('forward', (0.3, 0.0, 0.0), 2.0), Segment('turn', (0.1, 0.2, 0.8), 2.0)))
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        record_drive(f'{tmp}/rec', model, script)
        with RecordingReader(f'{tmp}/rec', names) as reader:
            samples = [('command' if hasattr(s, 'kind') else 'joint', s) for s in reader.samples()]
        for case, layout, processes, executor_kind in CASES:
            if progress is not None:
                progress(f'  nodes: {case} and its relays ...')
            results[case] = bench_layout(layout, processes, executor_kind, samples, names, seconds, tmp)
    return results


def worker_main(argv=None):
    """A node of a process-per-node bench case; writes its timings (``--timings``) at SIGINT."""
    parser = argparse.ArgumentParser(prog='python -m youbot_fdi.nodes.bench',
                                     description='One timed node of the node-suite benchmark.')
    parser.add_argument('role', choices=['decision', 'relay'])
    parser.add_argument('--index', type=int, default=0)
    parser.add_argument('--source', default=JOINT_STATES)
    parser.add_argument('--target', default='/bench_relay/out')
    parser.add_argument('--timings', help='JSON file for {stamp: time.monotonic()} at exit')
    args = parser.parse_args(argv)
    kind = executor_kind()
    stop = stop_on_signals()
    ros_init()
    node = (TimedDecision() if args.role == 'decision' else
            Relay(args.index, args.source, args.target))
    executor = make_executor(kind)
    executor.add_node(node)
    freeze_startup_heap()
    try:
        spin_until_stopped(executor, stop)
    finally:
        if args.timings:
            Path(args.timings).write_text(json.dumps({repr(k): v for k, v in node.done.items()}))
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(worker_main())
