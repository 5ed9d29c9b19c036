"""The live demo: virtual youBot, driver shim and every FDI node over ROS 2 topics.

/cmd_vel -> kinematics_bridge -> /wheel_commands -> driver_shim -> CAN -> virtual_youbot -> CAN ->
/joint_states -> observer -> /youbot_fdi/predicted -> residual_generator -> /youbot_fdi/residuals
-> decision -> /youbot_fdi/faults, /diagnostics. The virtual base and the shim share this process
(python-can's virtual bus connects them only within a process) with a scripted driver that
publishes /cmd_vel, injects the fault into the virtual base at its time, and shows what happens.
The FDI nodes run in the chosen layout (:data:`LAYOUT_CHOICES`): ``separate`` (default) starts
each as its own process, as ``ros2 run`` would; ``composed`` runs them in this process and
executor; ``fused`` the same with the observer computing the residuals itself.
"""
from dataclasses import dataclass, replace
import gc
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time
import uuid

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Twist
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
import rclpy

from youbot_fdi.app.eventlog import EventLog
from youbot_fdi.faults import Level
from youbot_fdi.model.kinematics import tracking_rms
from youbot_fdi.nodes.common import (freeze_startup_heap, keep_discovery_local, LATCHED_QOS,
                                     node_module, now_seconds, SENSOR_QOS, shutdown_nodes,
                                     stop_node_processes)
from youbot_fdi.nodes.composed import LAYOUTS, node_name
from youbot_fdi.nodes.conversions import event_from_status, reaction_from_status
from youbot_fdi.nodes.decision import DecisionNode
from youbot_fdi.nodes.driver_shim import DriverShimNode
from youbot_fdi.nodes.virtual_youbot import VirtualYoubotNode
from youbot_fdi.naming import wheel_suffix
from youbot_fdi.topics import (CMD_VEL, FAULTS, JOINT_STATES, PREDICTED, REACTIONS, RESIDUALS,
                               WHEEL_COMMANDS)

COMMAND_RATE = 20.0  # /cmd_vel [Hz]
STATUS_PERIOD = 1.0  # console line [s]
SETTLE_AFTER = 1.0  # keep running after the script ends [s]
LAYOUT_CHOICES = ('separate', 'composed', 'fused')
PROCESS_START_TIMEOUT = 60.0  # [s] for the FDI node processes to appear on the graph
#: With the FDI nodes as processes, the drive starts once residuals have arrived for this long
#: [s] without a gap longer than PIPELINE_GAP [s]: processes that have just started keep the CPU
#: busy for a moment and the shim's stream, on two cores, stalls by up to a quarter second then
#: (a base comm_loss in a test run on a fresh clone). The base stands still meanwhile.
PIPELINE_WARMUP = 1.0
PIPELINE_GAP = 0.1


@dataclass(frozen=True)
class DemoPlan:
    """What the demo drives and injects."""

    script: object  # DriveScript
    fault: object  # fault name or None
    wheel: str
    fault_at: float  # [s] into the drive
    console: bool = True
    record: object = None  # a new rosbag2 directory for /joint_states and /wheel_commands
    layout: str = 'separate'  # one of LAYOUT_CHOICES
    react: bool = False  # the kinematics bridge applies the fault reactions (config/reactions.yaml)
    base_overrides: tuple = ()  # (name, value) of VirtualBaseSettings, e.g. fault magnitudes
    bridge_overrides: tuple = ()  # (name, value) parameters of the kinematics bridge
    incident_dir: str = ''  # the decision node's incident folder ('' = its default)
    incident_max_count: int = 0  # the decision node's incident budget (0 = its default)

    def bridge_parameters(self):
        """The kinematics bridge's parameter overrides {name: value} (``react`` included)."""
        return {**dict(self.bridge_overrides), **({'react': True} if self.react else {})}

    def node_parameters(self, factories):
        """Parameter overrides {node module: {name: value}} of the FDI nodes of ``factories``
        (the first, the kinematics bridge, applies the reactions; the decision keeps incidents)."""
        overrides = {node_module(factories[0]): self.bridge_parameters()}
        incidents = {name: value for name, value in (('incident_dir', str(self.incident_dir)),
                                                     ('incident_max_count', self.incident_max_count))
                     if value}
        if incidents:
            overrides[DecisionNode.__module__] = incidents
        return overrides


class DemoDriverNode(Node):
    """Publishes the scripted /cmd_vel, injects the fault, and shows wheel states and faults."""

    def __init__(self, plan, base, log=None, waits_for=(), on_start=None, **kwargs):
        super().__init__('demo_driver', **kwargs)
        self.plan, self.base, self.log = plan, base, log
        self.on_start = on_start  # called once when the drive starts
        self.waits_for = set(waits_for)  # node names that must be on the graph before driving
        self.cmd_pub = self.create_publisher(Twist, CMD_VEL, 10)
        self.create_subscription(DiagnosticArray, FAULTS, self.on_faults, LATCHED_QOS)
        self.create_subscription(DiagnosticArray, REACTIONS, self.on_reactions, LATCHED_QOS)
        self.reactions = []
        #: per timer tick after the start: (time [s], commanded twist (3,), true twist (3,))
        self.tracking = []
        self.create_subscription(JointState, JOINT_STATES, self.on_joint_states, SENSOR_QOS)
        self.events, self.injected_at, self.last_state = [], None, None
        #: events and reactions before the drive started (the nodes starting up), kept apart
        self.before_drive = []
        self.start = None
        self.recorder = None
        if plan.record:
            from youbot_fdi.bag.writer import RecordingWriter
            from youbot_fdi.nodes.common import stamp_to_seconds
            self._stamp = stamp_to_seconds
            self.recorder = RecordingWriter(plan.record, base.model.wheel_names)
            self.create_subscription(JointState, WHEEL_COMMANDS, self.on_wheel_commands, 10)
        self.done = False
        self._residuals_seen = None  # while warming up: (first, last) arrival of a steady run [s]
        self._warmup = None  # the residual subscription of the warm-up
        self._next_status = 0.0
        self.create_timer(1.0 / COMMAND_RATE, self.on_timer)

    def say(self, text):
        if self.plan.console:
            print(text, flush=True)

    def elapsed(self):
        return now_seconds(self) - self.start

    def _connected(self):
        """True once the FDI nodes are on the graph and every link of the pipeline has both ends
        (a node on the graph may not have announced its topics yet: driving then would go
        unseen)."""
        if not self.waits_for <= set(self.get_node_names()):
            return False
        if self.count_subscribers(CMD_VEL) == 0 or self.count_publishers(FAULTS) == 0:
            return False
        return all(self.count_publishers(topic) > 0 and self.count_subscribers(topic) > 0
                   for topic in (WHEEL_COMMANDS, PREDICTED, RESIDUALS))

    def _flowing(self):
        """True once residuals have flowed for PIPELINE_WARMUP without a gap (see there)."""
        if self._warmup is None:
            self._warmup = self.create_subscription(JointState, RESIDUALS, self._on_residuals,
                                                    SENSOR_QOS)
            return False
        seen, now = self._residuals_seen, now_seconds(self)
        if seen is None or now - seen[1] > PIPELINE_GAP or now - seen[0] < PIPELINE_WARMUP:
            return False
        self.destroy_subscription(self._warmup)
        return True

    def _on_residuals(self, _msg):
        now = now_seconds(self)
        seen = self._residuals_seen
        self._residuals_seen = (now if seen is None or now - seen[1] > PIPELINE_GAP else seen[0], now)

    def on_timer(self):
        if self.start is None:
            if self.waits_for and not (self._connected() and self._flowing()):
                return
            self.start = now_seconds(self)
            if self.on_start is not None:
                self.on_start()
        t = self.elapsed()
        vx, vy, wz = (float(v) for v in self.plan.script.twists([t])[0])
        _, true_speeds = self.base.wheel_state()
        kinematics = self.base.model.kinematics
        self.tracking.append((now_seconds(self), (vx, vy, wz),
                              tuple(kinematics.forward(kinematics.from_driver(true_speeds)))))
        msg = Twist()
        msg.linear.x, msg.linear.y, msg.angular.z = vx, vy, wz
        self.cmd_pub.publish(msg)
        if self.plan.fault and self.injected_at is None and t >= self.plan.fault_at:
            self.base.inject(self.plan.fault, self.plan.wheel)
            self.injected_at = now_seconds(self)
            self.say(f'[{t:6.2f} s] >>> injected {self.plan.fault} on {self.plan.wheel}')
        if t >= self._next_status:
            self._next_status += STATUS_PERIOD
            self.show_status(t)
        if t > self.plan.script.duration + SETTLE_AFTER:
            self.done = True

    def on_joint_states(self, msg):
        self.last_state = msg
        if self.recorder is not None and self.start is not None:  # the drive, as the nodes saw it
            self.recorder.joint_state(self._stamp(msg.header.stamp), msg.position, msg.velocity,
                                      msg.effort)

    def on_wheel_commands(self, msg):
        """Recorded with the receive time, as the observer stamps commands (from the drive's
        start, as the joint states: the nodes' start-up, when nothing watched, is not recorded)."""
        if self.start is None:
            return
        if msg.velocity:
            self.recorder.wheel_command(now_seconds(self), 'velocity', msg.velocity)
        elif msg.effort:
            self.recorder.wheel_command(now_seconds(self), 'effort', msg.effort)

    def close(self):
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None

    def show_status(self, t):
        if self.last_state is None:
            return
        speeds = '  '.join(f'{wheel_suffix(n)} {v:+6.2f}' for n, v in
                           zip(self.last_state.name, self.last_state.velocity))
        faults = ', '.join(f'{e.wheel or "base"}: {e.fault}' for e in self.active()) or 'none'
        self.say(f'[{t:6.2f} s] wheels [rad/s] {speeds}   faults: {faults}')

    def active(self):
        state = {}
        for event in self.events:
            state[event.wheel] = event
        return [e for e in state.values() if e.level == Level.ERROR]

    def _record(self, item, seen):
        """Keep a new event or reaction ``item`` in ``seen`` (before the drive: in
        ``before_drive``) and the log file; its time since the start [s] (NaN before the start),
        or None when it was seen already."""
        if self.start is None:
            seen = self.before_drive
        if item in seen:
            return None
        seen.append(item)
        if self.log is not None:
            self.log.write(item)
        return item.stamp - self.start if self.start is not None else float('nan')

    def on_reactions(self, msg):
        for status in msg.status:
            reaction = reaction_from_status(status)
            t = self._record(reaction, self.reactions)
            if t is None:
                continue
            self.say(f'[{t:6.2f} s] --> {reaction.action} on {reaction.wheel or "base"} '
                     f'({reaction.fault}): {reaction.detail}')

    def on_faults(self, msg):
        for status in msg.status:
            event = event_from_status(status)
            t = self._record(event, self.events)
            if t is None:
                continue
            note = ''
            if event.level == Level.ERROR and self.injected_at is not None:
                note = f'   ({(event.stamp - self.injected_at) * 1000:.0f} ms after the injection)'
            self.say(f'[{t:6.2f} s] *** {event.level} {event.wheel or "base"}: {event.fault}{note}')


#: ``python -c`` start of a node process on Linux: SIGTERM when the demo dies, even by SIGKILL
#: (prctl PR_SET_PDEATHSIG = 1), so no node outlives it on the ROS graph; then the node's module.
_END_WITH_PARENT = ('import ctypes, runpy, signal, sys; ctypes.CDLL(None).prctl(1, signal.SIGTERM); '
                    "sys.argv = sys.argv[1:]; runpy.run_module(sys.argv[0], run_name='__main__', "
                    'alter_sys=True)')


def parameter_text(value):
    """A parameter value as ``-p name:=TEXT`` wants it (YAML: true/false for booleans)."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def node_log_stem(factory):
    """The name (without ``.log``) of a node process's log file: its module's last part."""
    return node_module(factory).rsplit('.', 1)[-1]


def start_node_processes(factories, log_dir, parameters=None):
    """Each FDI node as its own process (``python -m <its module>``, as ``ros2 run`` starts it),
    output to ``log_dir/<stem>.log`` (:func:`node_log_stem`), with ``parameters`` {module: {name: value}} as
    ``--ros-args -p``; returns the Popen objects."""
    processes = []
    for factory in factories:
        module = node_module(factory)
        overrides = (parameters or {}).get(module, {})
        arguments = ['--ros-args'] + [a for name, value in overrides.items()
                                      for a in ('-p', f'{name}:={parameter_text(value)}')] if overrides else []
        log = open(Path(log_dir) / f'{node_log_stem(factory)}.log', 'w')  # noqa: SIM115
        start = ['-c', _END_WITH_PARENT] if sys.platform == 'linux' else ['-m']
        processes.append(subprocess.Popen([sys.executable, *start, module, *arguments], stdout=log,
                                          stderr=subprocess.STDOUT, env=dict(os.environ)))
        log.close()
    return processes


@dataclass(frozen=True)
class DemoRun:
    """What a demo run saw: fault events, when the fault went in and the drive started [s],
    the reactions, and the tracking record (time, commanded twist, true twist of the simulator)."""

    events: list
    injected_at: object
    start: object
    reactions: list
    tracking: list
    before_drive: list = ()  # events and reactions while the nodes started, before the drive
    #: the driver shim's cycle over the run: counters and timing (:func:`shim_figures`)
    shim: dict = None
    #: the same figures from the shim's start to the drive's (the FDI nodes connecting)
    shim_startup: dict = None
    #: the FDI node processes' log folder, kept because a process did not stop cleanly (its
    #: exit codes in ``node_exits``); None: no processes, or removed after a clean stop
    node_logs: str = None
    node_exits: dict = None

    def tracking_error(self, since):
        """RMS body-velocity tracking error from ``since`` [s] to the end: (linear [m/s],
        angular [rad/s]), against the simulator's true velocity; None without samples."""
        rows = [(c, t) for stamp, c, t in self.tracking if stamp >= since]
        if not rows:
            return None
        commanded, actual = zip(*rows)
        return tracking_rms(commanded, actual)


def shim_figures(driver):
    """The driver shim's cycle over the drive (from its start: the node processes' start-up left
    out): cycles, samples, cycles later than the modules' controller timeout, incomplete cycles (a
    module's NaN), late answers, recovered controller timeouts, and the cycle's period and
    lateness (p50/p99/max [ms])."""
    summary = driver.timing.summary()
    return {'cycles': summary.cycles, 'samples': driver.samples_closed,
            'late_cycles': summary.late_cycles,
            'controller_timeout_ms': round(1000.0 * driver.settings.controller_timeout, 3),
            'incomplete_cycles': int(driver.missed_cycles.sum()), 'late_answers': driver.late_answers,
            'controller_timeouts_cleared': driver.timeout_recoveries,
            **{key: round(1000.0 * getattr(summary, key), 3) for key in
               ('period_p50', 'period_p99', 'period_max', 'lateness_p50', 'lateness_p99',
                'lateness_max')}}


def run_demo(plan, events_path=None, max_wall_time=None):
    """Run the live demo; returns a :class:`DemoRun`."""
    keep_discovery_local()
    if plan.layout not in LAYOUT_CHOICES:
        msg = f'unknown layout {plan.layout!r}; choose one of {", ".join(LAYOUT_CHOICES)}'
        raise ValueError(msg)
    factories = LAYOUTS['fused' if plan.layout == 'fused' else 'separate']
    context = Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    channel = [Parameter('can_channel', value=f'demo-{uuid.uuid4()}')]
    nodes, processes, log_dir, finished = [], [], None, False
    log = EventLog(events_path) if events_path else None
    try:
        base_node = VirtualYoubotNode(context=context, parameter_overrides=channel + [
            Parameter(name, value=value) for name, value in plan.base_overrides])
        nodes.append(base_node)
        shim = DriverShimNode(context=context, parameter_overrides=channel)
        nodes.append(shim)
        waits_for = ()
        overrides = plan.node_parameters(factories)
        if plan.layout == 'separate':
            log_dir = tempfile.mkdtemp(prefix='youbot-fdi-demo-')
            processes = start_node_processes(factories, log_dir, overrides)
            waits_for = [node_name(f) for f in factories]
            if plan.console:
                print(f'FDI nodes in {len(processes)} processes (logs: {log_dir}, removed after a '
                      f'clean stop); waiting for them on the graph ...', flush=True)
        else:
            nodes += [factory(context=context, parameter_overrides=[
                Parameter(name, value=value)
                for name, value in overrides.get(node_module(factory), {}).items()])
                for factory in factories]
        startup = {}

        def drive_starts():
            startup.update(shim_figures(shim.driver))
            shim.driver.restart_counters()

        driver = DemoDriverNode(plan, base_node.base, log, waits_for, context=context,
                                on_start=drive_starts)
        nodes.append(driver)
        executor.add_node(driver)
        freeze_startup_heap()
        start_deadline = time.monotonic() + PROCESS_START_TIMEOUT

        def spin_until(done, what):
            while not done() and time.monotonic() < start_deadline:
                executor.spin_once(timeout_sec=0.01)
                if any(p.poll() is not None for p in processes):
                    msg = f'an FDI node process ended at start (logs: {log_dir})'
                    raise RuntimeError(msg)
            if not done():
                msg = f'{what} within {PROCESS_START_TIMEOUT:g} s' + (
                    f' (logs: {log_dir})' if log_dir else '')
                raise RuntimeError(msg)

        # The base and its driver run once the FDI node processes are on the graph: their start
        # (imports, models) takes every core for seconds, and a driver starved meanwhile stalls
        # its stream (the base's comm_loss, the modules' controller timeout). On a robot the
        # driver runs first, at real-time priority (docs/tmcm.md, "Cycle timing").
        spin_until(lambda: set(waits_for) <= set(driver.get_node_names()),
                   'the FDI node processes did not appear')
        for node in nodes[:-1]:
            executor.add_node(node)
        spin_until(lambda: driver.start is not None, 'the FDI nodes did not connect')
        deadline = time.monotonic() + (max_wall_time or plan.script.duration * 3 + 30)
        while not driver.done and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.01)
        for _ in range(20):  # deliver the last fault messages
            executor.spin_once(timeout_sec=0.01)
        run = DemoRun(list(driver.events), driver.injected_at, driver.start,
                      list(driver.reactions), list(driver.tracking), list(driver.before_drive),
                      shim_figures(shim.driver), startup)
        finished = True
    finally:
        stop_node_processes(processes)
        shutdown_nodes(executor, nodes, context)
        gc.unfreeze()  # a caller that runs demos in turn gets this one's objects collected
        if log is not None:
            log.close()
        exits = {node_log_stem(f): p.returncode for f, p in zip(factories, processes)}
        log_dir = kept_node_logs(log_dir, exits, finished)
    return replace(run, node_logs=log_dir, node_exits=exits if log_dir else None)


def kept_node_logs(log_dir, exits, finished):
    """The node processes' log folder ``log_dir`` if it is worth keeping, else None (removed):
    kept where the run did not finish or a process did not stop cleanly (``exits`` {log file
    stem: exit code}; our mains exit 0 on the demo's SIGINT, nodes.common.stop_on_signals). A
    clean run's logs say nothing its summary does not, and a folder per run left in the
    temporary directory adds up."""
    if log_dir is None or not finished or any(exits.values()):
        return log_dir
    shutil.rmtree(log_dir, ignore_errors=True)
    return None
