"""A black box for every alarm: the seconds around it kept as a replayable recording.

The live suite keeps a ring buffer of the raw (serialized) messages of the FDI's inputs and
outputs (:data:`RECORDED_TOPICS`). When a new alarm episode is confirmed, an *incident* opens: a
rosbag2 MCAP recording, written by rosbags in a background thread, of everything from
``incident_before`` seconds ahead of the alarm to ``incident_after`` seconds past it, and beside it
a sidecar ``incident.yaml`` (the event, the freeze-frame of the decision: residuals, bounds,
evidence, load factor; the software version, the parameter file and its hash) with copies of
the parameter file and the FDI settings in use, so ``youbot-fdi replay INCIDENT`` reproduces the
alarm with what the robot ran.

Live cost: the node takes what the recorded topics received every 0.1 s (no callback per
message) and appends references to the messages to a deque (and, while an incident is open,
hands the batch to the writer's queue); all file work happens in the writer thread, which writes
in slices and yields between them so a callback never waits long for the interpreter lock
(``youbot-fdi bench`` measures both: the recorder's CPU and the longest hold-up).

Durability: the sidecar is written first (``complete: false``), then the messages, with the
writer's chunk closed and flushed every ``FLUSH_INTERVAL`` of recorded time; on kill -9 only the
incident being written is cut, and it reads to its damage like any recording (docs/fdi.md).
Bounded: before an incident opens, the oldest incidents go until the folder holds fewer than
``incident_max_count`` and less than ``incident_max_megabytes`` (a log line for each).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import datetime
import hashlib
import json
import math
import os
from pathlib import Path
import queue
import shutil
import sys
import threading
import time
from collections.abc import Callable

import yaml

from youbot_fdi.errors import ConfigError
from youbot_fdi.faults import Level
from youbot_fdi.naming import wheel_suffix
from youbot_fdi.yamlio import load_yaml
from youbot_fdi.topics import CMD_VEL, DIAGNOSTICS, FAULTS, JOINT_STATES, REACTIONS, WHEEL_COMMANDS

JOINT_STATE = 'sensor_msgs/msg/JointState'
DIAGNOSTIC_ARRAY = 'diagnostic_msgs/msg/DiagnosticArray'
#: What an incident keeps: the FDI's inputs, then its outputs (topic -> message type).
RECORDED_TOPICS = {JOINT_STATES: JOINT_STATE, WHEEL_COMMANDS: JOINT_STATE,
                   CMD_VEL: 'geometry_msgs/msg/Twist', FAULTS: DIAGNOSTIC_ARRAY,
                   REACTIONS: DIAGNOSTIC_ARRAY, DIAGNOSTICS: DIAGNOSTIC_ARRAY}
SIDECAR = 'incident.yaml'
PARAMS_COPY = 'params.yaml'  # the identify parameter file the robot ran with (if any)
SETTINGS_COPY = 'fdi.yaml'  # the FDI settings the decision ran with (a ROS parameter file)
NANOSECONDS = 1_000_000_000
BYTES_PER_MEGABYTE = 1_000_000
#: The writer closes its chunk and flushes it to the operating system after this much recorded
#: time [s]: what a kill -9 can cut from the incident being written.
FLUSH_INTERVAL = 1.0
#: Messages the writer thread writes before it yields the interpreter lock (sleep(0)): about
#: 0.3 ms of work on the 2-core dev machine (rosbags writes one in 2.5 µs), so a callback
#: waiting for the lock waits about that long (measured: at most 0.4 ms, docs/fdi.md).
WRITE_SLICE = 128
#: How long closing waits for the writer to finish what is queued [s].
CLOSE_TIMEOUT = 10.0
BAG_VERSION = 9  # what Jazzy's rosbag2 writes


@dataclass(frozen=True)
class IncidentSettings:
    """The incident recorder's parameters (``config/incidents.yaml``, decision node)."""

    incidents_enabled: bool = True  # keep an incident recording for every alarm episode
    #: folder of the incidents ('' = $ROS_HOME/youbot_fdi/incidents, ROS_HOME defaults to ~/.ros)
    incident_dir: str = ''
    incident_before: float = 10.0  # recorded time kept ahead of the alarm [s], >= 0
    incident_after: float = 5.0  # recorded time past the alarm [s], >= 0
    incident_max_count: int = 20  # incidents kept in the folder (oldest first out), >= 1
    incident_max_megabytes: float = 200.0  # size of the folder (oldest first out) [MB], > 0

    def validate(self, source: str) -> None:
        for name in ('incident_before', 'incident_after'):
            if getattr(self, name) < 0.0:
                raise ConfigError(f'{source}: {name} must be >= 0 s, got {getattr(self, name)}')
        if self.incident_max_count < 1:
            raise ConfigError(f'{source}: incident_max_count must be >= 1, got {self.incident_max_count}')
        if self.incident_max_megabytes <= 0.0:
            raise ConfigError(f'{source}: incident_max_megabytes must be > 0, got '
                              f'{self.incident_max_megabytes}')

    def folder(self) -> Path:
        """Where incidents go: ``incident_dir``, else ``$ROS_HOME/youbot_fdi/incidents``."""
        if self.incident_dir:
            return Path(self.incident_dir).expanduser()
        ros_home = os.environ.get('ROS_HOME') or os.path.join('~', '.ros')
        return Path(ros_home).expanduser() / 'youbot_fdi' / 'incidents'


@dataclass(frozen=True)
class RunContext:
    """What the robot ran with, for every incident's sidecar."""

    params_file: str = ''  # the identify parameter file ('' = the profile's defaults)
    settings: dict = field(default_factory=dict)  # the FDI settings in use (name -> value)
    profile: str = ''


def file_sha256(path) -> str:
    """The SHA-256 of a file's bytes (hex), '' when there is no file."""
    if not path:
        return ''
    digest = hashlib.sha256()
    with open(path, 'rb') as stream:
        for block in iter(lambda: stream.read(1 << 16), b''):
            digest.update(block)
    return digest.hexdigest()


def software_version() -> str:
    from youbot_fdi import __version__
    return __version__


class MessageRing:
    """The raw messages of the last ``span`` [s] of receive time: (topic, time [ns], bytes)."""

    def __init__(self, span: float) -> None:
        self.span_ns = int(span * NANOSECONDS)
        self.items: deque = deque()

    def add(self, item: tuple) -> None:
        items = self.items
        items.append(item)
        oldest = item[1] - self.span_ns
        while items[0][1] < oldest:
            items.popleft()

    def since(self, start_ns: int) -> list:
        """The messages received at ``start_ns`` or later, oldest first."""
        return [item for item in self.items if item[1] >= start_ns]


@dataclass
class _Incident:
    number: int
    path: Path
    end_ns: int


def incident_name(event: dict, time_ns: int) -> str:
    """A folder name that sorts by time: ``20261126T221530.123_fl_torque_loss`` (UTC of the
    receive time)."""
    moment = datetime.datetime.fromtimestamp(time_ns / NANOSECONDS, tz=datetime.UTC)
    wheel = wheel_suffix(event['wheel']) if event.get('wheel') else 'base'
    return f'{moment:%Y%m%dT%H%M%S}.{moment.microsecond // 1000:03d}_{wheel}_{event["fault"]}'


def folder_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob('*') if p.is_file())


def incident_folders(root: Path) -> list[Path]:
    """The incidents in ``root``, oldest first (by name: they start with their UTC time)."""
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and (p / SIDECAR).is_file())


def prune(root: Path, max_count: int, max_bytes: float, log: Callable[[str], None],
          room_count: int = 0, room_bytes: float = 0.0, keep: Path | None = None) -> list[Path]:
    """Remove the oldest incidents of ``root`` (never ``keep``) until, with room for
    ``room_count`` more of ``room_bytes``, they are at most ``max_count`` and ``max_bytes``;
    returns what was removed."""
    folders = [p for p in incident_folders(root) if p != keep]
    sizes = [folder_bytes(p) for p in folders]
    kept = (1, folder_bytes(keep)) if keep is not None and keep.is_dir() else (0, 0)
    removed = []
    while folders and (len(folders) + kept[0] + room_count > max_count
                       or sum(sizes) + kept[1] + room_bytes > max_bytes):
        oldest, size = folders.pop(0), sizes.pop(0)
        shutil.rmtree(oldest, ignore_errors=True)
        removed.append(oldest)
        log(f'incident budget ({max_count} incidents, {max_bytes / BYTES_PER_MEGABYTE:g} MB): '
            f'dropped the oldest, {oldest.name} ({size / BYTES_PER_MEGABYTE:.2f} MB)')
    return removed


def _write_yaml(path: Path, data: dict) -> None:
    """Write ``data`` as YAML atomically (a reader sees the old or the new file, whole)."""
    temporary = path.with_suffix('.tmp')
    temporary.write_text(yaml.safe_dump(data, sort_keys=False))
    os.replace(temporary, path)


class IncidentRecorder:
    """The ring buffer and the background writer of the incidents (one per alarm episode).

    ``record_batch(items)`` with what the recorded topics received, (topic, receive time [ns],
    raw CDR bytes) each, oldest first (``record`` for one); ``open(event, time_ns,
    freeze_frame)`` when a new alarm episode is published; ``poll(time_ns)`` now and then (closes incidents whose time is up when no
    message comes); ``close()`` at shutdown (what is open is closed with what it has).
    """

    def __init__(self, settings: IncidentSettings, context: RunContext,
                 topics: dict[str, str] | None = None, log: Callable[[str], None] = print) -> None:
        self.settings = settings
        self.context = context
        self.topics = dict(RECORDED_TOPICS if topics is None else topics)
        self.root = settings.folder()
        self.log = log
        self.ring = MessageRing(settings.incident_before)
        self._active: list[_Incident] = []
        self._next_end = None  # the earliest end [ns] of an open incident
        self.opened = 0  # incidents opened (each one's number in the writer's jobs)
        self.dropped = 0  # incidents removed by the budget
        self.writer_cpu = 0.0  # CPU time the writer thread spent on its jobs [s]
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        # rosbags and its message types are loaded now, at start-up, not at the first alarm:
        # loading them takes about 0.1 s of interpreter time on the dev machine (the writer
        # thread would hold the lock from the callbacks in 5 ms turns meanwhile), and loaded
        # here they are part of the start-up heap the nodes move out of the garbage
        # collector's view (gc.freeze), not tens of thousands of objects every full collection
        # scans after.
        self.typestore = load_typestore()
        self._thread = threading.Thread(target=self._run, name='incident-writer', daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- the callbacks' side
    def record(self, topic: str, time_ns: int, data: bytes) -> None:
        """A message of ``topic`` received at ``time_ns``: into the ring, and into every open
        incident (the writer's queue)."""
        self.record_batch([(topic, time_ns, data)])

    def record_batch(self, items: list) -> None:
        """Messages (topic, receive time [ns], bytes), oldest first: into the ring, and into every
        open incident in one hand-over to the writer (a thread switch per message would cost
        more than the writing)."""
        if not items:
            return
        add = self.ring.add
        for item in items:
            add(item)
        if self._active:
            for incident in self._active:
                self._queue.put(('messages', incident.number,
                                 [item for item in items if item[1] <= incident.end_ns]))
            if items[-1][1] > self._next_end:
                self.poll(items[-1][1])

    def poll(self, time_ns: int) -> None:
        """Close the incidents whose ``incident_after`` has passed at ``time_ns``."""
        if not self._active:
            return
        still = []
        for incident in self._active:
            if time_ns > incident.end_ns:
                self._queue.put(('close', incident.number, 'after'))
            else:
                still.append(incident)
        self._active = still
        self._next_end = min((i.end_ns for i in still), default=None)

    def open(self, event: dict, time_ns: int, freeze_frame: dict) -> Path:
        """Start the incident of a new alarm ``event`` (a fault event as a dict) confirmed at
        ``time_ns`` with the decision's ``freeze_frame``; returns its folder."""
        self.opened += 1
        end_ns = time_ns + int(self.settings.incident_after * NANOSECONDS)
        name = incident_name(event, time_ns)
        path = self.root / name
        suffix = 1
        while path.exists() or any(i.path == path for i in self._active):
            suffix += 1
            path = self.root / f'{name}_{suffix}'
        incident = _Incident(self.opened, path, end_ns)
        event = json.loads(json.dumps(event))  # plain YAML types (levels are str enums)
        sidecar = {'event': event, 'alarm_time_ns': time_ns,
                   'window': {'before_s': self.settings.incident_before,
                              'after_s': self.settings.incident_after},
                   'freeze_frame': freeze_frame,
                   'software': {'youbot_fdi': software_version(),
                                'python': sys.version.split()[0]},
                   'parameters': {'profile': self.context.profile,
                                  'params_file': self.context.params_file,
                                  'params_sha256': file_sha256(self.context.params_file),
                                  'settings': SETTINGS_COPY},
                   'complete': False}
        start_ns = time_ns - int(self.settings.incident_before * NANOSECONDS)
        before = self.ring.since(start_ns)
        # What the ring held ahead of the alarm [s]: less than incident_before right after the
        # node started (a replay then has less time to settle before the alarm).
        sidecar['window']['recorded_before_s'] = round((time_ns - before[0][1]) / NANOSECONDS, 3) \
            if before else 0.0
        self._queue.put(('open', incident.number, (path, sidecar, before)))
        self._active.append(incident)
        self._next_end = min(i.end_ns for i in self._active)
        return path

    def close(self, timeout: float = CLOSE_TIMEOUT) -> None:
        """Close every open incident with what it has and stop the writer (waits up to
        ``timeout`` [s] for it to finish)."""
        for incident in self._active:
            self._queue.put(('close', incident.number, 'shutdown'))
        self._active = []
        self._queue.put(None)
        self._thread.join(timeout)

    def flush(self, timeout: float = CLOSE_TIMEOUT) -> bool:
        """Wait until the writer has done everything queued so far (tests, benchmarks)."""
        done = threading.Event()
        self._queue.put(('done', 0, done))
        return done.wait(timeout)

    # ---------------------------------------------------------------- the writer thread
    def _expected_bytes(self, before: list) -> float:
        """The size an incident is expected to take [bytes]: its messages ahead of the alarm,
        ``before``, at the same rate over the whole window."""
        if len(before) < 2:
            return 0.0
        span = (before[-1][1] - before[0][1]) / NANOSECONDS
        window = self.settings.incident_before + self.settings.incident_after
        return sum(len(item[2]) for item in before) * window / max(span, 1.0 / NANOSECONDS)

    def _hold_budget(self, **room) -> None:
        """:func:`prune` the folder to the settings' budget (``room``: its room and keep)."""
        self.dropped += len(prune(self.root, self.settings.incident_max_count,
                                  self.settings.incident_max_megabytes * BYTES_PER_MEGABYTE,
                                  self.log, **room))

    def _run(self) -> None:
        writers: dict[int, _IncidentWriter] = {}
        while True:
            job = self._queue.get()
            if job is None:
                break
            kind, number, payload = job
            started = time.thread_time()
            try:
                if kind == 'messages':
                    if number in writers:
                        writers[number].write(payload)
                elif kind == 'open':
                    path, sidecar, messages = payload
                    self._hold_budget(room_count=1, room_bytes=self._expected_bytes(messages))
                    writers[number] = _IncidentWriter(path, sidecar, self.topics, self.context,
                                                      self.typestore)
                    writers[number].write(messages)
                    self.log(f'incident: {path} (alarm {sidecar["event"]["fault"]} on '
                             f'{sidecar["event"]["wheel"] or "base"})')
                elif kind == 'close':
                    writer = writers.pop(number, None)
                    if writer is not None:
                        writer.close(payload)
                        # The estimate at its start may have been short (the sidecar, the
                        # recording's index): the budget is held again now it is whole.
                        self._hold_budget(keep=writer.path)
                elif kind == 'done':
                    payload.set()
            except Exception as err:  # noqa: BLE001 - a full disk must not stop the FDI
                self.log(f'incident recorder: {kind} failed: {err}')
                if kind in ('open', 'messages') and number in writers:
                    writers.pop(number).abort()
            self.writer_cpu += time.thread_time() - started
        for writer in writers.values():
            writer.close('shutdown')


def load_typestore():
    """rosbags' ROS 2 Jazzy type store (and its writer's modules)."""
    import rosbags.rosbag2  # noqa: F401 - loaded with the types (see IncidentRecorder)
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


class _IncidentWriter:
    """One incident being written (writer thread only)."""

    def __init__(self, path: Path, sidecar: dict, topics: dict[str, str], context: RunContext,
                 typestore):
        from rosbags.rosbag2 import StoragePlugin, Writer
        self.path = path
        self.sidecar = sidecar
        path.parent.mkdir(parents=True, exist_ok=True)
        self.writer = Writer(path, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        try:
            self.connections = {topic: self.writer.add_connection(topic, msgtype, typestore=typestore)
                                for topic, msgtype in topics.items()}
            self.counts = dict.fromkeys(topics, 0)
            if context.params_file and Path(context.params_file).is_file():
                shutil.copyfile(context.params_file, path / PARAMS_COPY)
            _write_yaml(path / SETTINGS_COPY, {'/**': {'ros__parameters': dict(context.settings)}})
            _write_yaml(path / SIDECAR, sidecar)
        except Exception:
            self.abort()
            shutil.rmtree(path, ignore_errors=True)  # an incident without its sidecar is no use
            raise
        self._flushed_ns = None

    def write(self, messages: list) -> None:
        for index, (topic, time_ns, data) in enumerate(messages):
            connection = self.connections.get(topic)
            if connection is None:
                continue
            self.writer.write(connection, time_ns, data)
            self.counts[topic] += 1
            if self._flushed_ns is None:
                self._flushed_ns = time_ns
            elif time_ns - self._flushed_ns >= FLUSH_INTERVAL * NANOSECONDS:
                self._flush()
                self._flushed_ns = time_ns
            if index % WRITE_SLICE == WRITE_SLICE - 1:
                time.sleep(0)  # let a waiting callback have the interpreter lock

    def _flush(self):
        """Put the messages so far on disk: rosbags' MCAP writer keeps a chunk in memory up to
        1 MiB (about 30 s of this recording); closing it each ``FLUSH_INTERVAL`` bounds what a
        kill -9 cuts."""
        storage = getattr(self.writer, 'storage', None)
        close_chunk = getattr(storage, 'close_chunk', None)
        bio = getattr(storage, 'bio', None)
        if close_chunk is None or bio is None:
            return
        if storage.chunk.bio.tell():
            close_chunk()
        bio.flush()

    def close(self, why: str):
        """Finish the recording: ``why`` 'after' (its time past the alarm is up) or 'shutdown'
        (the node stopped first: the recording ends there)."""
        self.writer.close()
        self.sidecar['complete'] = True
        self.sidecar['ended'] = why
        self.sidecar['messages'] = {topic: count for topic, count in self.counts.items() if count}
        _write_yaml(self.path / SIDECAR, self.sidecar)

    def abort(self):
        try:
            self.writer.close()
        except Exception:  # noqa: BLE001, S110 - what was written stays readable by salvage
            pass


@dataclass(frozen=True)
class IncidentSummary:
    """One incident of a folder, for listings."""

    path: Path
    time: str  # the alarm's UTC time (ISO)
    wheel: str
    fault: str
    detail: str
    size_bytes: int
    complete: bool
    stamp: float  # the alarm event's header stamp [s]
    #: why the sidecar could not be read ('' when it could): the folder is listed with it, the
    #: others as usual (one damaged incident does not hide the rest)
    problem: str = ''


def read_sidecar(path) -> dict:
    """An incident's sidecar (``incident.yaml``) as a mapping; ConfigError if unreadable."""
    sidecar = Path(path) / SIDECAR
    try:
        data = load_yaml(sidecar.read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f'{sidecar}: cannot read the incident sidecar: {err}'
        raise ConfigError(msg) from err
    if not isinstance(data, dict) or not isinstance(data.get('event'), dict):
        msg = f'{sidecar}: not an incident sidecar (no event)'
        raise ConfigError(msg)
    return data


def replays_alarm(sidecar: dict, events) -> bool:
    """True when the replayed ``events`` hold the incident's alarm: an ERROR of its fault on its
    wheel."""
    alarm = sidecar['event']
    return any(e.level == Level.ERROR and e.wheel == alarm.get('wheel') and e.fault == alarm.get('fault')
               for e in events)


def is_incident(path) -> bool:
    return (Path(path) / SIDECAR).is_file()


def incident_parameters(path) -> tuple[str | None, str | None]:
    """(parameter file, FDI settings file) to replay the incident at ``path`` with what the robot
    ran (None where the incident has none)."""
    path = Path(path)
    params = path / PARAMS_COPY
    settings = path / SETTINGS_COPY
    return (str(params) if params.is_file() else None,
            str(settings) if settings.is_file() else None)


def list_incidents(root) -> list[IncidentSummary]:
    """The incidents below ``root`` (or ``root`` itself when it is one), oldest first."""
    root = Path(root)
    folders = [root] if is_incident(root) else sorted(
        (p.parent for p in root.rglob(SIDECAR)), key=lambda p: p.name)
    found = []
    for folder in folders:
        try:
            data = read_sidecar(folder)
        except ConfigError as err:
            found.append(IncidentSummary(folder, '?', '?', '?', '', folder_bytes(folder), False,
                                         math.nan, problem=str(err)))
            continue
        event = data['event']
        moment = datetime.datetime.fromtimestamp(int(data.get('alarm_time_ns', 0)) / NANOSECONDS,
                                                 tz=datetime.UTC)
        found.append(IncidentSummary(folder, moment.isoformat(timespec='milliseconds'),
                                     str(event.get('wheel') or 'base'), str(event.get('fault')),
                                     str(event.get('detail', '')), folder_bytes(folder),
                                     bool(data.get('complete')), float(event.get('stamp', 0.0))))
    return found
