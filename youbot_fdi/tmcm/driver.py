"""The base driver behind the ``driver_shim`` node: wheel commands in, wheel samples out, over CAN.

Plain Python (python-can, no rclpy), so tests and tools can drive a base without ROS. Per cycle it
sends every module its process-data command; the modules' status frames come back asynchronously,
each echoing the cycle it answers, and are assembled **per cycle** into one :class:`BaseSample` in
wheel units (rad, rad/s, N·m), driver convention: every wheel's readings from that cycle, stamped
with the cycle's time, as one EtherCAT frame reads every slave. A sample is complete once every
module has answered its cycle. A module that has not answered gets NaN for its entries (counted per
wheel as ``missed_cycles``), never its previous value, which would read as a frozen encoder, once
its silence is certain: it answered a later cycle (a module answers its cycles in order on the bus,
so the older answer will not come), it is missing already (it let a cycle's ``answer_timeout``
pass and answered nothing since: a module that fell silent holds up no cycle but the first it
missed), or ``answer_timeout`` passed since the cycle was sent, plus as far as this host is
behind in reading the bus (the delay of the latest answer read, up to another ``answer_timeout``:
answers not read yet are not silence). A cycle is
never closed merely because the next one started: on a busy host the receive thread reads answers
that were on the bus in time a cycle late, and those are data, not silence. An answer that comes
after its cycle was closed is counted (``late_answers``) and dropped. Modules whose sample times lie
more than half a period apart (the host was preempted between sending their commands) are
separate samples of the cycle, each with its own time (``split_cycles``). ``on_sample`` is called with each
sample as it is closed.

Safety: a **command watchdog** turns a command older than ``command_timeout`` into zero speed (the
original youBot driver keeps sending the last command forever). ``motors_off`` commands 0 mA in
current mode, as the youBot driver's switchOffMotors does. A module that stopped on its own
**controller timeout** (GP 90: no process data for ``controller_timeout``, the host's cycle was
late) is cleared (SAP 158) once the host commands it again, at most once per ``command_timeout``,
and counted (``timeout_recoveries``); the original driver only logs the flag, which left a wheel
stopped for good (youbot_driver issue #10, whose workaround was this). ``recover_controller_timeout:
false`` keeps it stopped until ``motors_on``.
"""
from collections import deque
from dataclasses import dataclass
import enum
import itertools
import threading
import time

import numpy as np

from youbot_fdi.errors import ConfigError
from youbot_fdi.model.firmware import ControlMode
from youbot_fdi.tmcm.parameters import AxisParameter, describe_flags, ERROR_FLAGS, ErrorFlag
from youbot_fdi.tmcm.process_data import (CYCLE_MODULO, MotorCommand, ProcessDataIds,
                                          SAMPLE_TIME_MODULO, StatusAssembler)
from youbot_fdi.tmcm.tmcl import decode_reply_can, TmclCommand, TmclRequest
from youbot_fdi.tmcm.transport import CanTransport
from youbot_fdi.timing import CycleTiming, parse_cores


#: Fraction of the clock-offset error corrected per sample (a slow tracking filter).
CLOCK_TRACKING = 0.01
MAX_REALTIME_PRIORITY = 99  # SCHED_FIFO priorities are 1..99 on Linux
#: Modules of one cycle whose sample times lie within this share of a period sampled one instant
#: (the module clocks count whole milliseconds); further apart, separate samples [-].
SAME_INSTANT_SHARE = 0.5
#: Closed cycle numbers remembered, so that a late answer is told from a new cycle's first one.
CLOSED_CYCLES_KEPT = 16
#: The modules' sticky flags a switch-on clears (SAP value 1): the controller timeout and I²t.
STICKY_FLAG_CLEARS = (AxisParameter.CLEAR_TIMEOUT_FLAG, AxisParameter.CLEAR_I2T_FLAG)


@dataclass(frozen=True)
class MailboxOutcome:
    """What a module answered to a TMCL request sent without waiting (:meth:`BaseDriver.motor_off`,
    :meth:`BaseDriver.motors_on`)."""

    wheel: str
    command: TmclCommand
    answered: bool  # a reply came within ``tmcl_timeout``
    ok: bool  # and its status was success


class CommandKind(str, enum.Enum):
    """What ``/wheel_commands`` carries."""

    VELOCITY = 'velocity'  # [rad/s]
    EFFORT = 'effort'  # [N·m]


class Level(enum.IntEnum):
    """Diagnostic levels (REP-107 / diagnostic_msgs values)."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True)
class DriverSettings:
    """Settings of the driver shim (``config/driver_shim.yaml``)."""

    profile: str = 'youbot'
    can_interface: str = 'virtual'
    can_channel: str = 'youbot'
    module_ids: tuple = (0x11, 0x12, 0x13, 0x14)
    host_id: int = 0x02
    cycle_rate: float = 100.0  # process-data cycles per second [Hz]
    command_timeout: float = 0.25  # command watchdog [s]
    stale_cycles: int = 10  # a module silent this many cycles is lost
    #: how long a cycle waits for a module that answered nothing since [s]: an answer takes under a
    #: millisecond on the wire, what delays it is the host reading it. As long as a module waits
    #: for its command (the controller timeout's default): a host later than that has stopped the
    #: modules anyway.
    answer_timeout: float = 0.1
    tmcl_timeout: float = 0.2  # wait for a TMCL reply [s]
    controller_timeout: float = 0.1  # written to every module's GP 90 at start [s]
    recover_controller_timeout: bool = True  # clear a tripped GP 90 once commands are fresh again
    diagnostics_rate: float = 1.0  # [Hz]
    realtime_priority: int = 0  # SCHED_FIFO priority 1..99 where permitted; 0: default scheduler
    cpu_cores: str = ''  # CPU affinity, e.g. '1' or '0,1'; empty: any core

    def validate(self, source='<settings>'):
        """Raise ConfigError on unusable values."""
        problems = []
        for name in ('cycle_rate', 'command_timeout', 'tmcl_timeout', 'diagnostics_rate',
                     'answer_timeout'):
            if getattr(self, name) <= 0:
                problems.append(f'{name} must be > 0')
        if self.stale_cycles < 1:
            problems.append('stale_cycles must be >= 1')
        if self.controller_timeout < 0:
            problems.append('controller_timeout must be >= 0')
        if not 0 <= self.realtime_priority <= MAX_REALTIME_PRIORITY:
            problems.append(f'realtime_priority must be 0..{MAX_REALTIME_PRIORITY}')
        try:
            parse_cores(self.cpu_cores)
        except ValueError as err:
            problems.append(str(err))
        if len(set(self.module_ids)) != len(self.module_ids) or self.host_id in self.module_ids:
            problems.append('module_ids must be distinct and differ from host_id')
        if problems:
            msg = f'{source}: ' + '; '.join(problems)
            raise ConfigError(msg)


@dataclass(frozen=True)
class BaseSample:
    """Every wheel's reading from one process-data cycle (driver convention); arrays of shape
    (n,), NaN for a wheel whose module did not answer that cycle."""

    stamp: float  # the cycle's time on the driver clock: when its modules sampled [s]
    position: np.ndarray  # [rad]
    velocity: np.ndarray  # [rad/s]
    effort: np.ndarray  # from the measured motor current [N·m]
    error_flags: np.ndarray  # int (0 where the module did not answer)
    age: np.ndarray  # time since each wheel's module last answered, at closing [s]; inf if never
    cycle: int = 0  # the process-data cycle counter (0..255)

    @property
    def answered(self):
        """Wheels (n,) bool whose module answered this cycle."""
        return np.isfinite(self.position)


class _CycleSlot:
    """The answers of one process-data cycle as they arrive (NaN until a module answers)."""

    def __init__(self, cycle, sent_at, n):
        self.cycle = cycle
        self.sent_at = sent_at  # driver clock [s]
        self.position = np.full(n, np.nan)
        self.velocity = np.full(n, np.nan)
        self.effort = np.full(n, np.nan)
        self.flags = np.zeros(n, dtype=np.int64)
        self.stamps = np.full(n, np.nan)  # each module's sample time on the driver clock [s]
        self.passed = np.zeros(n, dtype=bool)  # modules that answered a later cycle instead

    def settled(self, missing):
        """Every module answered or will not: it answered a later cycle, or is ``missing`` (n,)
        bool: it let a cycle's deadline pass and has answered nothing since."""
        return bool(np.all(np.isfinite(self.stamps) | self.passed | missing))


@dataclass(frozen=True)
class Health:
    """One diagnostic status: a wheel's module or the bus."""

    name: str
    level: Level
    message: str
    values: dict


class BaseDriver:
    """Drives the modules of a base over a python-can bus.

    Parameters
    ----------
    model : PlatformModel
        Wheel names and the drive train (unit conversions).
    bus : can.BusABC
    settings : DriverSettings
    clock : callable
        Returns the current time [s] (the node passes ROS time, so sim time works).
    on_sample : callable, optional
        Called with each :class:`BaseSample` as its cycle closes, in cycle order: from the CAN
        receive thread when its last module answers (or answers a later cycle), or from
        :meth:`cycle` once ``answer_timeout`` passed with modules still silent.
    """

    def __init__(self, model, bus, settings=DriverSettings(), ids=ProcessDataIds(),
                 clock=time.monotonic, owns_bus=False, on_sample=None):
        settings.validate()
        n = model.kinematics.n_wheels
        if len(settings.module_ids) != n:
            msg = f'{len(settings.module_ids)} module ids for {n} wheels'
            raise ConfigError(msg)
        self.model, self.settings, self.ids, self.clock = model, settings, ids, clock
        self.drive = model.drive
        self.wheel_names = model.wheel_names
        self.n_wheels = n
        self._lock = threading.Lock()
        self._reply_ready = threading.Condition(self._lock)
        self._replies = {}
        self._assembler = StatusAssembler()
        self._module_index = {m: k for k, m in enumerate(settings.module_ids)}
        self._status_ids = {}
        for k, module in enumerate(settings.module_ids):
            for part, can_id in enumerate(ids.status_ids(module)):
                self._status_ids[can_id] = (k, part)
        self._flags = np.zeros(n, dtype=np.int64)  # each module's latest flags (health)
        self._received = np.full(n, -np.inf)
        self._missing = np.zeros(n, dtype=bool)  # modules that let a cycle's deadline pass since
        self._read_lag = 0.0  # from sending a cycle to reading its answer, the latest [s]
        self.on_sample = on_sample
        self._open = {}  # cycle counter -> _CycleSlot still waiting for answers
        self._closed = deque(maxlen=CLOSED_CYCLES_KEPT)
        self._ready = deque()  # closed samples not yet handed to on_sample
        self._deliver_lock = threading.Lock()
        self._latest = None  # the last closed BaseSample
        self._last_stamp = -np.inf
        #: per wheel: cycles closed without its module's answer
        self.missed_cycles = np.zeros(n, dtype=np.int64)
        self.late_answers = 0  # answers that came after their cycle was closed
        self.silent_cycles = 0  # cycles closed with no answer at all (no sample)
        self.split_cycles = 0  # cycles whose modules sampled at instants apart (several samples)
        self.samples_closed = 0
        period = 1.0 / settings.cycle_rate
        #: the host's cycle: period and lateness; late past the modules' controller timeout
        self.timing = CycleTiming(period, late_after=settings.controller_timeout - period
                                  if settings.controller_timeout > period else period)
        self._command_kind = CommandKind.VELOCITY
        self._command = np.zeros(n)
        self._command_stamp = -np.inf
        self.motors_enabled = True
        self.motors_off_wheels = set()  # wheel indices switched off one by one (motor_off)
        #: (wheel index, TmclCommand) -> driver-clock time an unwaited request went out [s]
        self._unanswered = {}
        self.cycle_count = 0
        self._sent_at = {}  # cycle counter -> driver-clock time its commands went out
        self._clock_offset = None  # driver clock - module clock [s], tracked slowly
        self._module_time = None  # unwrapped module clock of the last sample [s]
        self._offset_samples = 0
        #: controller-timeout flags cleared while commands were fresh, and when each wheel's last was
        self.timeout_recoveries = 0
        self._recovered_at = np.full(n, -np.inf)
        self.rejected_commands = 0
        self.last_rejection = ''
        self.transport = CanTransport(bus, self._on_frame, owns_bus=owns_bus)

    # ------------------------------------------------------------------ commands
    def set_command(self, kind, values, stamp=None):
        """Store a wheel command (driver convention): speeds [rad/s] or efforts [N·m].

        Raises ValueError (and counts it) for a wrong length or a non-finite value; the previous
        command stays in force and the watchdog keeps running.
        """
        kind = CommandKind(kind)
        values = np.asarray(values, dtype=float)
        if values.shape != (self.n_wheels,) or not np.all(np.isfinite(values)):
            self.rejected_commands += 1
            self.last_rejection = f'{kind.value} command {values.tolist()} rejected: need {self.n_wheels} finite values'
            raise ValueError(self.last_rejection)
        with self._lock:
            self._command_kind = kind
            self._command = values.copy()
            self._command_stamp = self.clock() if stamp is None else stamp

    def command_is_stale(self, now=None):
        """True when the last command is older than the watchdog timeout (or there is none)."""
        now = self.clock() if now is None else now
        return now - self._command_stamp > self.settings.command_timeout

    def _module_commands(self, now):
        """The (mode, value) per module this cycle, in motor units (0 mA for a wheel switched
        off)."""
        if not self.motors_enabled:
            return [(ControlMode.CURRENT, 0)] * self.n_wheels
        if self.command_is_stale(now):
            commands = [(ControlMode.VELOCITY, 0)] * self.n_wheels
        elif self._command_kind is CommandKind.VELOCITY:
            rpm = np.rint(self.drive.wheel_speed_to_rpm(self._command)).astype(int)
            commands = [(ControlMode.VELOCITY, int(v)) for v in rpm]
        else:
            milliamps = np.rint(self.drive.torque_to_milliamps(self._command)).astype(int)
            commands = [(ControlMode.CURRENT, int(v)) for v in milliamps]
        return [(ControlMode.CURRENT, 0) if k in self.motors_off_wheels else command
                for k, command in enumerate(commands)]

    def cycle(self, now=None):
        """Close the cycles past their deadline or settled (their silent modules get NaN), then
        send one process-data command to every module; returns how many went out."""
        now = self.clock() if now is None else now
        with self._lock:
            self.timing.tick(now)
            timeout = self.settings.answer_timeout
            due = now - timeout - min(self._read_lag, timeout)
            for slot in list(self._open.values()):  # in cycle order: a deadline marks missing
                if slot.sent_at <= due or slot.settled(self._missing):
                    self._close(slot)
            commands = self._module_commands(now)
            self.cycle_count = (self.cycle_count + 1) % CYCLE_MODULO
            cycle = self.cycle_count
            self._sent_at[cycle] = now
            if cycle in self._closed:
                self._closed.remove(cycle)  # the counter wrapped: a new cycle, not a late one
            self._open[cycle] = _CycleSlot(cycle, now, self.n_wheels)
            recover = self._timeouts_to_clear(now)
        self._deliver()
        sent = 0
        for module, (mode, value) in zip(self.settings.module_ids, commands):
            sent += self.transport.send(self.ids.command_id(module),
                                        MotorCommand(int(mode), value, cycle).encode())
        for index in recover:  # not waited for: the cycle goes on; the next status shows it
            self.transport.send(*TmclRequest(self.settings.module_ids[index], int(TmclCommand.SAP),
                                             int(AxisParameter.CLEAR_TIMEOUT_FLAG), 0, 1).to_can())
        return sent

    def _timeouts_to_clear(self, now):
        """Wheels whose module reports its controller timeout while the host commands it (fresh
        command, motors on): a late cycle stopped it, not a lost host. Each at most once per
        ``command_timeout`` (the next status frames still carry the flag). Call with the lock."""
        if not self.settings.recover_controller_timeout or not self.motors_enabled \
                or self.command_is_stale(now):
            return []
        tripped = [k for k in range(self.n_wheels)
                   if int(self._flags[k]) & ErrorFlag.TIMEOUT and k not in self.motors_off_wheels
                   and now - self._recovered_at[k] >= self.settings.command_timeout]
        for k in tripped:
            self._recovered_at[k] = now
        self.timeout_recoveries += len(tripped)
        return tripped

    # ------------------------------------------------------------------ receiving
    def _on_frame(self, arbitration_id, data, _timestamp):
        if arbitration_id == self.settings.host_id:
            reply = decode_reply_can(arbitration_id, data[:7]) if len(data) == 7 else None
            with self._reply_ready:
                if reply is not None and reply.module in self._module_index:
                    self._replies[(reply.module, reply.command)] = reply
                    self._reply_ready.notify_all()
            return
        where = self._status_ids.get(arbitration_id)
        if where is None:
            return
        index, part = where
        with self._lock:
            status = self._assembler.add(self.settings.module_ids[index], part, data)
            if status is None:
                return
            self._flags[index] = status.error_flags
            self._received[index] = self.clock()
            self._missing[index] = False  # it answers (if late): cycles wait for it again
            if status.cycle in self._sent_at:  # a module answers at once: the rest is this host
                self._read_lag = max(0.0, self._received[index] - self._sent_at[status.cycle])
            slot = self._open.get(status.cycle)
            if slot is None:
                if status.cycle in self._closed:  # its cycle was closed without it
                    self.late_answers += 1
                    return
                # a cycle this driver did not send (another master, or a restart): take it as is
                slot = self._open[status.cycle] = _CycleSlot(
                    status.cycle, self._sent_at.get(status.cycle, self.clock()), self.n_wheels)
            slot.stamps[index] = self._sample_stamp(status)
            slot.position[index] = float(self.drive.ticks_to_wheel_angle(status.position))
            slot.velocity[index] = float(self.drive.rpm_to_wheel_speed(status.velocity))
            slot.effort[index] = float(self.drive.milliamps_to_torque(status.current))
            slot.flags[index] = status.error_flags
            older = list(itertools.takewhile(lambda c: c is not slot, self._open.values()))
            for waiting in older:  # this module answers in order: it skipped those cycles
                waiting.passed[index] = True
            for done in [c for c in older + [slot] if c.settled(self._missing)]:  # in cycle order
                self._close(done)
        self._deliver()

    def restart_counters(self):
        """Start the cycle timing and the missing-answer counters afresh (e.g. when a drive
        begins, so that start-up does not count)."""
        with self._lock:
            self.timing = CycleTiming(self.timing.nominal_period, self.timing.late_after)
            self.missed_cycles[:] = 0
            self.late_answers = self.silent_cycles = self.samples_closed = self.split_cycles = 0

    def close_cycles(self):
        """Close every open cycle now (its deadline has passed: e.g. a lockstep rig that has
        seen every frame handled); the modules that did not answer get NaN."""
        with self._lock:
            self._close_open()
        self._deliver()

    def _close_open(self):
        for slot in list(self._open.values()):
            self._close(slot)

    def _close(self, slot):
        """Close ``slot``'s cycle: one :class:`BaseSample` (NaN for the modules that did not
        answer), queued for :meth:`_deliver`. Call with the lock."""
        del self._open[slot.cycle]
        self._closed.append(slot.cycle)
        answered = np.isfinite(slot.stamps)
        self._missing |= ~answered & ~slot.passed  # let its deadline pass: no cycle waits for it
        self.missed_cycles += ~answered
        if not answered.any():
            self.silent_cycles += 1
            return
        now = self.clock()
        instants = self._instants(slot.stamps)
        self.split_cycles += len(instants) > 1
        for together in instants:
            # Its time: when its modules sampled (their clocks, mapped to the driver's); a later
            # estimate of the clock offset never steps back before the last sample's stamp.
            stamp = max(float(np.mean(slot.stamps[together])), self._last_stamp)
            self._last_stamp = stamp
            sample = BaseSample(stamp, *(np.where(together, values, np.nan) for values in
                                         (slot.position, slot.velocity, slot.effort)),
                                np.where(together, slot.flags, 0), now - self._received, slot.cycle)
            self._latest = sample
            self.samples_closed += 1
            self._ready.append(sample)

    def _instants(self, stamps):
        """The modules (masks (n,), in time order) that sampled one instant of a cycle, from their
        sample ``stamps`` (n,) [s] (NaN: no answer). Modules sample when their command arrives: a
        host preempted between sending them spreads one cycle over several instants, and one
        stamp for all would misplace some wheels' readings by that much (a wheel read 30 ms
        early under a common stamp turned too little: a frozen encoder). Sample times more than
        ``SAME_INSTANT_SHARE`` of a period apart are separate samples."""
        order = np.argsort(stamps)[:int(np.count_nonzero(np.isfinite(stamps)))]
        gap = SAME_INSTANT_SHARE / self.settings.cycle_rate
        breaks = np.flatnonzero(np.diff(stamps[order]) > gap) + 1
        masks = []
        for members in np.split(order, breaks):
            mask = np.zeros(len(stamps), dtype=bool)
            mask[members] = True
            masks.append(mask)
        return masks

    def _deliver(self):
        """Hand the closed samples to ``on_sample`` in cycle order (outside the driver's lock; one
        caller at a time, whichever thread closed them)."""
        with self._deliver_lock:
            while True:
                with self._lock:
                    if not self._ready:
                        return
                    sample = self._ready.popleft()
                if self.on_sample is not None:
                    self.on_sample(sample)

    def _sample_stamp(self, status):
        """When the module sampled this state, on the driver's clock.

        With a module sample time (like EtherCAT's distributed clocks): the module clock, unwrapped,
        plus an offset to the driver clock that follows drift slowly and ignores bus and scheduling
        jitter. Without one: the time the command this sample answers went out.
        """
        sent = self._sent_at.get(status.cycle, self.clock())
        if not status.sample_time:
            return sent
        raw = status.sample_time / 1000.0
        if self._module_time is None:
            module_time = raw
        else:
            wrap = SAMPLE_TIME_MODULO / 1000.0
            module_time = self._module_time + ((raw - self._module_time) % wrap)
            if module_time - self._module_time > wrap / 2:  # an older sample of another module
                module_time -= wrap
        self._module_time = max(module_time, self._module_time or module_time)
        self._offset_samples += 1
        if self._clock_offset is None:
            self._clock_offset = sent - module_time
        else:  # a running mean at first, then slow tracking
            gain = max(CLOCK_TRACKING, 1.0 / self._offset_samples)
            self._clock_offset += gain * ((sent - module_time) - self._clock_offset)
        return module_time + self._clock_offset

    def sample(self):
        """The sample of the last closed cycle (:class:`BaseSample`), or None before one."""
        with self._lock:
            return self._latest

    # ------------------------------------------------------------------ TMCL client
    def _send_request(self, index, command, type_, value=0, motor=0):
        """Send wheel ``index``'s module a TMCL request, any older reply to the same command
        dropped first (what comes now answers this one); returns the reply's key. Call without
        the lock."""
        module = self.settings.module_ids[index]
        key = (module, int(command))
        with self._reply_ready:
            self._replies.pop(key, None)
        self.transport.send(*TmclRequest(module, int(command), int(type_), motor, int(value)).to_can())
        return key

    def request(self, wheel, command, type_, value=0, motor=0):
        """Send a TMCL request to one wheel's module and wait for the reply (or None on timeout)."""
        index = wheel if isinstance(wheel, int) else self.wheel_names.index(wheel)
        key = self._send_request(index, command, type_, value, motor)
        with self._reply_ready:
            arrived = self._reply_ready.wait_for(lambda: key in self._replies,
                                                 self.settings.tmcl_timeout)
            return self._replies.pop(key) if arrived else None

    def clear_flags(self):
        """Clear the timeout and I²t flags of every module; returns the wheels that did not answer."""
        silent = []
        for index, name in enumerate(self.wheel_names):
            for parameter in STICKY_FLAG_CLEARS:
                reply = self.request(index, TmclCommand.SAP, parameter, 1)
                if reply is None or not reply.ok:
                    silent.append(name)
                    break
        return silent

    def configure_modules(self):
        """Write the controller timeout (GP 90) and clear flags; returns the wheels that failed."""
        failed = []
        milliseconds = int(round(self.settings.controller_timeout * 1000))
        for index, name in enumerate(self.wheel_names):
            reply = self.request(index, TmclCommand.SGP, 90, milliseconds)
            if reply is None or not reply.ok:
                failed.append(name)
        return sorted(set(failed) | set(self.clear_flags()))

    def motors_on(self):
        """Enable motion commands (every wheel) and clear the modules' sticky flags (timeout and
        I²t), not waited for (as :meth:`motor_off`); :meth:`mailbox_outcomes` reports a module
        that did not answer."""
        self.motors_enabled = True
        self.motors_off_wheels.clear()
        for index in range(self.n_wheels):
            for parameter in STICKY_FLAG_CLEARS:
                self._send_unwaited(index, TmclCommand.SAP, parameter, 1)

    def motor_off(self, wheel):
        """Switch one wheel's motor off (a fault reaction): TMCL MST over the mailbox, the path
        that still reaches the motor when the module's cyclic set-point misbehaves (a runaway),
        and 0 mA from the next cycle on until :meth:`motors_on`; the reply is not waited for
        (:meth:`_send_unwaited`)."""
        index = wheel if isinstance(wheel, int) else self.wheel_names.index(wheel)
        with self._lock:
            self.motors_off_wheels.add(index)
        self._send_unwaited(index, TmclCommand.MST, 0, 0)

    def _send_unwaited(self, index, command, type_, value):
        """Send wheel ``index``'s module a TMCL request without waiting for its reply, which
        :meth:`mailbox_outcomes` reports.

        Why: the mailbox and the process data are separate channels, and a caller on the cycle's
        thread (the shim's service callbacks share its executor) waiting up to ``tmcl_timeout``
        per request would hold the cycle: /joint_states would pause (the base's ``comm_loss``
        to the FDI) and the modules' controller timeout would trip, just as a fault is handled
        or the motors come back. The cycle's own controller-timeout clears go out unwaited too."""
        self._send_request(index, command, type_, value)
        with self._lock:  # after the stale reply was dropped: what comes now answers this one
            self._unanswered[(index, TmclCommand(command))] = self.clock()

    def mailbox_outcomes(self, now=None):
        """The unwaited requests (:meth:`_send_unwaited`) settled since the last call, as
        :class:`MailboxOutcome` records: answered (ok or not), or not within ``tmcl_timeout``."""
        if not self._unanswered:  # nearly every cycle: nothing sent, no lock, no clock read
            return []
        now = self.clock() if now is None else now
        settled = []
        with self._lock:
            for (index, command), sent_at in list(self._unanswered.items()):
                reply = self._replies.pop((self.settings.module_ids[index], int(command)), None)
                if reply is not None or now - sent_at > self.settings.tmcl_timeout:
                    del self._unanswered[(index, command)]
                    settled.append(MailboxOutcome(self.wheel_names[index], command,
                                                  reply is not None, reply is not None and reply.ok))
        return settled

    def motors_off(self):
        """Command 0 mA in current mode from the next cycle on (the wheels coast)."""
        self.motors_enabled = False

    # ------------------------------------------------------------------ health
    def health(self, now=None):
        """Per-wheel module health and the bus health, as :class:`Health` records."""
        now = self.clock() if now is None else now
        period = 1.0 / self.settings.cycle_rate
        stale_after = self.settings.stale_cycles * period
        with self._lock:
            received, flags = self._received.copy(), self._flags.copy()
            incomplete = self._assembler.incomplete
            missed = self.missed_cycles.copy()
            timing = self.timing.summary()
        records = []
        for index, name in enumerate(self.wheel_names):
            age = now - received[index]
            names = describe_flags(int(flags[index]))
            values = {'age_s': f'{age:.3f}', 'error_flags': f'0x{int(flags[index]):05X}',
                      'flags': ' '.join(names) or 'none', 'missed_cycles': str(int(missed[index]))}
            if not np.isfinite(received[index]):
                records.append(Health(name, Level.STALE, 'no data from the module yet', values))
            elif age > stale_after:
                records.append(Health(name, Level.ERROR, f'no data for {age:.2f} s (comm_loss)', values))
            elif int(flags[index]) & ERROR_FLAGS & ~ErrorFlag.OVER_CURRENT:
                bad = describe_flags(int(flags[index]) & ERROR_FLAGS & ~ErrorFlag.OVER_CURRENT)
                records.append(Health(name, Level.ERROR, 'module reports ' + ', '.join(bad), values))
            elif int(flags[index]) & ErrorFlag.OVER_CURRENT:
                records.append(Health(name, Level.WARN, 'current at its limit', values))
            else:
                records.append(Health(name, Level.OK, 'ok', values))
        counters, last_error = self.transport.snapshot()
        values = {key: str(value) for key, value in sorted(counters.items())}
        values.update({'incomplete_samples': str(incomplete), 'rejected_commands': str(self.rejected_commands),
                       'command_watchdog': 'tripped' if self.command_is_stale(now) else 'ok',
                       'motors': 'on' if self.motors_enabled else 'off',
                       'controller_timeouts_cleared': str(self.timeout_recoveries),
                       'samples': str(self.samples_closed),
                       'incomplete_cycles': str(int(missed.sum())),
                       'late_answers': str(self.late_answers),
                       'split_cycles': str(self.split_cycles),
                       'silent_cycles': str(self.silent_cycles),
                       # A cycle later than this stops the modules (their GP 90 timeout).
                       'controller_timeout_ms': f'{1000.0 * self.settings.controller_timeout:g}',
                       **timing.values('cycle_'),
                       'last_error': last_error
                       or self.last_rejection})
        problems = sum(counters.get(k, 0) for k in ('malformed', 'send_errors', 'error_frames',
                                                    'handler_errors')) + incomplete + self.rejected_commands
        if all(r.level in (Level.STALE, Level.ERROR) and 'no data' in r.message for r in records):
            level, message = Level.ERROR, 'no module answers'
        elif problems:
            level, message = Level.WARN, f'{problems} bad frames or commands so far'
        else:
            level, message = Level.OK, 'ok'
        records.append(Health('bus', level, message, values))
        return records

    def close(self):
        """Stop the transport (and the bus if owned)."""
        self.transport.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
