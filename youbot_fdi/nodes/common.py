"""Helpers shared by the nodes: parameters from settings dataclasses, QoS, diagnostics, main()."""
import dataclasses
import gc
import os
import signal
import sys
import threading

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, qos_profile_sensor_data, \
    ReliabilityPolicy

from youbot_fdi.errors import ConfigError, FdiError
from youbot_fdi.settings import settings_from_mapping
from youbot_fdi.topics import DIAGNOSTICS

#: Subscriptions to sensor streams accept reliable and best-effort publishers alike.
SENSOR_QOS = qos_profile_sensor_data
#: Our own streams are published reliably (robot_state_publisher and `ros2 topic echo` connect).
STREAM_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        history=HistoryPolicy.KEEP_LAST)
#: Latched state (fault events): a late subscriber gets the last message.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
NAME_PREFIX = 'youbot_fdi'
INPUT_WARN_INTERVAL = 1.0  # [s] between input-problem WARNs on /diagnostics (rate limit)
#: The sample interval a node's timing report expects when identify measured none [s].
DEFAULT_SAMPLE_INTERVAL = 0.01


def timing_report(node, settings):
    """A :class:`TimingReport` for an FDI node's input stream: nominal period the identified
    sample interval (``DEFAULT_SAMPLE_INTERVAL`` without one); a sample is late once it arrives a
    full period after its stamp."""
    period = settings.sample_interval or DEFAULT_SAMPLE_INTERVAL
    return TimingReport(node, period, late_after=period)


def keep_discovery_local():
    """ROS 2 discovery on this machine only, in a per-process domain, unless the caller's
    environment says otherwise (Fast DDS multicasts off every interface by default)."""
    import os
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 1))


def declare_settings(node, cls, runtime=()):
    """Declare one ROS parameter per dataclass field (default = field default); return settings.

    Values come from ``--ros-args --params-file`` / ``-p`` overrides; they are validated by the
    dataclass like the offline tools' YAML (ConfigError naming the parameter on a bad value, at
    start). They are read once, so each is declared read-only (``ros2 param set`` is refused
    rather than silently ignored) except the ``runtime`` names the node handles itself.
    """
    from rcl_interfaces.msg import ParameterDescriptor
    values = {}
    for field in dataclasses.fields(cls):
        default = field.default
        descriptor = ParameterDescriptor(
            read_only=field.name not in runtime,
            description=f'{cls.__name__}.{field.name}' + ('' if field.name in runtime else
                                                          '; read at start (see config/)'))
        value = node.declare_parameter(field.name, list(default) if isinstance(default, tuple)
                                       else default, descriptor).value
        values[field.name] = value
    return settings_from_mapping(cls, values, source=f'node {node.get_name()}')


def stamp_to_seconds(stamp):
    """builtin_interfaces/Time -> float seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def seconds_to_stamp(seconds):
    """float seconds -> builtin_interfaces/Time."""
    from builtin_interfaces.msg import Time
    sec = int(seconds // 1)
    return Time(sec=sec, nanosec=int(round((seconds - sec) * 1e9)) % 1_000_000_000)


def now_seconds(node):
    """The node clock (ROS time: sim time when use_sim_time is set) in seconds."""
    return node.get_clock().now().nanoseconds * 1e-9


def health_to_diagnostics(node, records, component, hardware_ids=None, default_hardware=''):
    """Convert core :class:`~youbot_fdi.tmcm.driver.Health` records to a DiagnosticArray.

    ``hardware_ids`` maps a record name to its hardware id; others get ``default_hardware``
    (or their own name).
    """
    hardware_ids = hardware_ids or {}
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    array = DiagnosticArray()
    array.header.stamp = node.get_clock().now().to_msg()
    for record in records:
        status = DiagnosticStatus()
        status.level = bytes([int(record.level)])
        status.name = f'{NAME_PREFIX}/{component}: {record.name}'
        status.message = record.message
        status.hardware_id = hardware_ids.get(record.name, default_hardware or record.name)
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in record.values.items()]
        array.status.append(status)
    return array


def diagnostics_publisher(node):
    """The node's one /diagnostics publisher (created on first use)."""
    publisher = getattr(node, '_diagnostics_publisher', None)
    if publisher is None:
        from diagnostic_msgs.msg import DiagnosticArray
        publisher = node._diagnostics_publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS, 10)
    return publisher


class TimingReport:
    """A node's input timing on /diagnostics (``<node>: timing``, level OK, at most ``rate`` Hz,
    from the sample callback: no timer of its own, one entity fewer in the executor's wait set):
    the period between the samples it receives and their lateness, how long after its header
    stamp each arrived (p50, p99, max; :class:`~youbot_fdi.timing.CycleTiming`); a sample later
    than ``late_after`` [s] is counted as late."""

    def __init__(self, node, nominal_period, late_after, rate=1.0):
        from youbot_fdi.timing import CycleTiming
        self.node = node
        self.timing = CycleTiming(nominal_period, late_after=late_after)
        self.publisher = diagnostics_publisher(node)
        self.interval = 1.0 / rate
        self._published = None

    def tick(self, stamp):
        """A sample stamped ``stamp`` [s] arrived now (publishes when the interval has passed)."""
        now = now_seconds(self.node)
        self.timing.tick(now, due=stamp)
        if self._published is None:
            self._published = now
        elif now - self._published >= self.interval:
            self._published = now
            self.publish()

    def publish(self):
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        if not self.timing.cycles:
            return
        name = self.node.get_name()
        summary = self.timing.summary()
        status = DiagnosticStatus(level=DiagnosticStatus.OK, name=f'{NAME_PREFIX}/{name}: timing',
                                  hardware_id=name,
                                  message=f'input period p50 {1000 * summary.period_p50:.1f} ms, '
                                          f'lateness p99 {1000 * summary.lateness_p99:.1f} ms')
        status.values = [KeyValue(key=k, value=v) for k, v in summary.values('input_').items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = seconds_to_stamp(now_seconds(self.node))
        self.publisher.publish(array)


def unspun_node(owner, suffix):
    """A node beside ``owner`` (named ``<owner>_<suffix>``, same namespace and context) that no
    executor spins: its subscriptions are read on demand, with no callback per message."""
    return rclpy.create_node(f'{owner.get_name()}_{suffix}', namespace=owner.get_namespace(),
                             context=owner.context, start_parameter_services=False,
                             enable_rosout=False)


class NewestMessage:
    """The newest message on a topic, read when asked, at no cost per message.

    The subscription lives on a node of its own that no executor spins: the middleware keeps
    the newest message (depth 1) and :meth:`take` reads it, so a node that only needs to know
    *whether* a stream still flows (the decision asking whether the base is silent or the FDI
    nodes behind it) adds no callback and no executor wake-up per message. Best effort: matches
    reliable and best-effort publishers alike.
    """

    QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                     history=HistoryPolicy.KEEP_LAST)

    def __init__(self, owner, msg_type, topic):
        self._node = unspun_node(owner, 'watch')
        self._subscription = self._node.create_subscription(msg_type, topic, lambda _msg: None,
                                                            self.QOS)

    def take(self):
        """The newest message received since the last take, or None if none came."""
        with self._subscription.handle:
            taken = self._subscription.handle.take_message(self._subscription.msg_type, False)
        return taken[0] if taken else None

    def close(self):
        self._node.destroy_node()


class BufferedTopics:
    """The raw (serialized) messages of several topics, kept by the middleware and taken in
    bunches, at no callback per message.

    As :class:`NewestMessage`, the subscriptions live on a node of their own that no executor
    spins; each keeps up to ``depth`` messages, and :meth:`take` reads every one that came since
    the last take, with its receive time (the middleware's, system clock [ns]). A node that only
    keeps what it receives (the incident recorder's ring buffer) adds no executor wake-up per
    message: one take every few tens of milliseconds reads them all, about 8 µs each on the
    2-core dev machine. Best effort: matches reliable and best-effort publishers alike.
    """

    def __init__(self, owner, topics, depth):
        """``topics``: {topic: message class}; ``depth`` [messages] kept per topic between takes."""
        self._node = unspun_node(owner, 'buffer')
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT,
                         history=HistoryPolicy.KEEP_LAST)
        self._subscriptions = [(topic, self._node.create_subscription(msg_type, topic,
                                                                      lambda _msg: None, qos,
                                                                      raw=True))
                               for topic, msg_type in topics.items()]

    def take(self):
        """Every message received since the last take as (topic, receive time [ns], bytes),
        oldest first."""
        taken = []
        for topic, subscription in self._subscriptions:
            with subscription.handle:
                while True:
                    message = subscription.handle.take_message(subscription.msg_type, True)
                    if not message:
                        break
                    taken.append((topic, message[1]['received_timestamp'], message[0]))
        taken.sort(key=lambda item: item[1])
        return taken

    def close(self):
        self._node.destroy_node()


class InputWarnings:
    """A node's WARN on /diagnostics naming the input problems counted since the last one (at
    most one every ``interval`` s; :class:`~youbot_fdi.samples.InputReport`): the messages
    themselves were skipped or restarted the residuals, never raised a fault."""

    def __init__(self, node, interval):
        from youbot_fdi.samples import InputReport
        self.node = node
        self.report = InputReport(interval)
        self.publisher = diagnostics_publisher(node)

    def check(self, counters):
        """Publish (and log) a WARN if ``counters`` (name -> running count) has new problems."""
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
        now = now_seconds(self.node)
        problems = self.report.check(counters, now)
        if not problems:
            return
        name = self.node.get_name()
        status = DiagnosticStatus(level=DiagnosticStatus.WARN, name=f'{NAME_PREFIX}/{name}: input',
                                  hardware_id=name, message='; '.join(problems))
        status.values = [KeyValue(key=k, value=str(v)) for k, v in counters.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = seconds_to_stamp(now)
        self.publisher.publish(array)
        self.node.get_logger().warning(status.message)


NODE_PROCESS_STOP_TIMEOUT = 10.0  # [s] after SIGINT before a node process is killed


def stop_node_processes(processes, timeout=NODE_PROCESS_STOP_TIMEOUT):
    """Stop node processes (``subprocess.Popen``): SIGINT (a normal stop for our mains), then
    kill what has not stopped within ``timeout`` [s]."""
    import signal
    import subprocess
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes:
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def shutdown_nodes(executor, nodes, context=None):
    """Stop ``executor``, close (if they can) and destroy ``nodes`` newest first, shut rclpy down."""
    executor.shutdown()
    for node in reversed(nodes):
        close = getattr(node, 'close', None)
        if close is not None:
            close()
        node.destroy_node()
    rclpy.try_shutdown(context=context)


def freeze_startup_heap():
    """Move every object alive now (modules, models, nodes) out of the garbage collector's view.

    A full collection scans every tracked object: with the FDI nodes built that is 60 000
    objects and 20–28 ms on the 2-core dev machine, several times that on the youBot's Atom,
    a stall of the 100 Hz stream. Start-up objects live as long as the process, so after
    construction they are frozen (:func:`gc.freeze`) and collections see only what spinning
    allocates. Call once, after the nodes exist and before spinning.
    """
    gc.collect()
    gc.freeze()


#: Environment variable choosing the executor of our node executables (:data:`EXECUTORS`).
EXECUTOR_VARIABLE = 'YOUBOT_FDI_EXECUTOR'
#: ``single``: rclpy's SingleThreadedExecutor (the default); ``events``: rclpy's experimental
#: EventsExecutor, which does not rebuild a wait set from every entity on every wake-up (about
#: half the CPU of our nodes, docs/nodes.md), opt-in: rclpy 7.1's has open crash reports.
EXECUTORS = ('single', 'events')
#: Longest wait for work before the spin loop looks at its stop flag [s]: the longest a stop
#: asked for by SIGINT or SIGTERM waits on an idle node.
STOP_POLL = 0.1
#: The signals that stop our node executables cleanly (exit 0).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def executor_kind():
    """The executor :data:`EXECUTOR_VARIABLE` asks for (``single`` when unset); ConfigError for
    an unknown one."""
    kind = os.environ.get(EXECUTOR_VARIABLE, 'single') or 'single'
    if kind not in EXECUTORS:
        msg = f'{EXECUTOR_VARIABLE}={kind!r}: choose one of {", ".join(EXECUTORS)}'
        raise ConfigError(msg)
    return kind


def make_executor(kind, context=None):
    """An executor of ``kind`` (:data:`EXECUTORS`)."""
    if kind == 'events':
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)


def stop_on_signals():
    """Install handlers that set, and return, a stop flag on :data:`STOP_SIGNALS`.

    Call before :func:`ros_init`, which installs no rclpy handlers. Under rclpy's own handlers
    (which shut the context down when the signal comes, and raise KeyboardInterrupt wherever the
    main thread is), ``take_message`` raised ``RuntimeError: Unable to convert call argument
    '0'`` as the demo's SIGINT came (2 of about 16 separate-layout runs under load;
    ros/joint_state_publisher#117): a traceback and exit 1, a crash to anyone reading the log,
    and SIGTERM exited 1 too. With a flag the executor finishes the callback it is in, and the
    nodes and the context are shut down in order by the main's ``finally``.
    """
    stop = threading.Event()
    for number in STOP_SIGNALS:
        signal.signal(number, lambda *_: stop.set())
    return stop


def spin_until_stopped(executor, stop):
    """Spin ``executor`` one callback at a time until ``stop`` (:func:`stop_on_signals`) is set;
    the wait for work is at most :data:`STOP_POLL`, so a signal on an idle node is seen in time.
    (The events executor's own ``spin`` does not return on SIGINT in rclpy 7.1: it spins a core.)"""
    while not stop.is_set():
        executor.spin_once(timeout_sec=STOP_POLL)


def ros_init(args=None, context=None):
    """``rclpy.init`` without rclpy's signal handlers (:func:`stop_on_signals` stops the spin)."""
    from rclpy.signals import SignalHandlerOptions
    rclpy.init(args=args, context=context, signal_handler_options=SignalHandlerOptions.NO)


def node_module(factory):
    """The module of a node factory (a Node class or a partial of one): ``python -m`` runs it as
    its own process."""
    return getattr(factory, 'func', factory).__module__


#: Arguments asking for the usage text instead of a node (before ``--ros-args``).
HELP_FLAGS = ('-h', '--help')
NODE_USAGE = f"""\
Usage: ros2 run youbot_fdi {{executable}} [--ros-args -p NAME:=VALUE ... --params-file FILE]

Parameters: the defaults and the reasoning behind them are in config/ (docs/nodes.md lists which
file each node reads); on a running node `ros2 param list` and `ros2 param describe` show them.
Environment: {EXECUTOR_VARIABLE}={'|'.join(EXECUTORS)} picks the executor (default single).
Stop with Ctrl-C (SIGINT) or SIGTERM."""


def asks_for_help(args):
    """Whether the command line ``args`` (``sys.argv`` when None) asks for the usage text: a
    :data:`HELP_FLAGS` argument before ``--ros-args`` (what follows it is rclpy's)."""
    args = sys.argv if args is None else args
    own = args[1:args.index('--ros-args')] if '--ros-args' in args else args[1:]
    return any(arg in HELP_FLAGS for arg in own)


def node_help(factories, executable, description=None):
    """The usage text of an executable running ``factories``: its ``description`` (several nodes
    in one process), each node module's description (its docstring), then how parameters and the
    environment are given."""
    modules = dict.fromkeys(node_module(factory) for factory in factories)
    parts = [description] if description else []
    parts += [sys.modules[module].__doc__.strip() for module in modules]
    return '\n\n'.join(parts + [NODE_USAGE.format(executable=executable)])


def spin_nodes(factories, args=None, description=None):
    """Create nodes with ``factories`` (callables -> Node) and spin them in one executor (of the
    kind :data:`EXECUTOR_VARIABLE` names).

    The canonical Jazzy main: try/finally, SIGINT or SIGTERM is a normal stop (exit 0,
    :func:`stop_on_signals`), ExternalShutdownException (the context shut down by someone else)
    exits 1, a configuration error exits 2 with a one-line reason.
    ``-h``/``--help`` prints :func:`node_help` (with ``description``) and exits 0 without
    starting ROS.
    """
    if asks_for_help(args):
        argv = sys.argv if args is None else args
        print(node_help(factories, os.path.basename(argv[0]), description))
        return 0
    try:
        kind = executor_kind()
    except ConfigError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    stop = stop_on_signals()
    ros_init(args=args)
    nodes = []
    executor = make_executor(kind)
    status = 0
    try:
        for factory in factories:
            nodes.append(factory())
            executor.add_node(nodes[-1])
        freeze_startup_heap()
        spin_until_stopped(executor, stop)
    except ExternalShutdownException:
        status = 1
    except (ConfigError, FdiError) as err:
        print(f'error: {err}', file=sys.stderr)
        status = 2
    finally:
        shutdown_nodes(executor, nodes)
    return status
