"""A virtual youBot base: four simulated TMCM modules on one CAN bus, running on the dynamic model.

Each module answers TMCL requests on its CAN id exactly as the manuals define (so PyTrinamic or any
TMCL tool can read and set parameters and drive it: ROR/ROL/MST/MVP/SAP/GAP/STAP/RSAP/SGP/GGP),
and exchanges cyclic process data (:mod:`youbot_fdi.tmcm.process_data`). Behind them one
:class:`~youbot_fdi.model.simulation.BaseSimulator` runs the firmware modes (stop, position,
velocity, current) on the exactly discretised wheel dynamics.

Firmware behaviour emulated:

- controller timeout (GP 90): once process data has been received, a module that gets none for
  longer than the timeout sets flag 0x10000 and stops its motor, and stays stopped until the flag
  is cleared (SAP 158, or CLE). TMCL motion commands (ROR/ROL/MST/MVP, SAP 0/2/155) take the
  module out of process-data control, disarming the watchdog until the next process-data frame;
- over-current (0x1) while the current is at its limit; I²t (0x20000) when the filtered I² exceeds
  the nominal current squared, sticky until SAP 29; motor halted (0x10); mode flags;
- values in motor units and the driver sign convention: ticks, rpm, mA.

Faults (CONTRACT.md vocabulary) can be injected while it runs: ``runaway`` (keeps the drive it had),
``torque_loss``, ``stuck``, ``friction``, ``encoder_freeze`` (reported and fed-back position and
speed freeze), ``comm_loss`` (the module stops answering and, hearing nothing, times out).

Time is simulated time: :meth:`VirtualYoubot.advance` steps it; :meth:`VirtualYoubot.start` runs a
thread that keeps it in step with the wall clock. Following the wall clock, a module lives on bus
time, as a real one does, however late this process reads the frames (the GIL, a busy host): it
answers a process-data command with its state at the moment the frame was on the bus (its CAN
timestamp; one cycle's answers are not spread over the time it took to read them), and the
simulation waits up to ``FRAME_LOOKBACK`` for frames before a module times out (GP 90): a frame
still unread is not a silent host.
"""
from collections import deque
from dataclasses import dataclass
import threading
import time

import numpy as np

from youbot_fdi.errors import ConfigError
from youbot_fdi.faults import FaultKind, INJECTABLE
from youbot_fdi.model.firmware import ControlMode
from youbot_fdi.model.simulation import BaseSimulator
from youbot_fdi.tmcm.parameters import AxisParameter, ErrorFlag, GlobalParameter
from youbot_fdi.tmcm.process_data import (MotorCommand, MotorStatus, ProcessDataIds,
                                          SAMPLE_TIME_MODULO)
from youbot_fdi.tmcm.tmcl import (CAN_PAYLOAD_LENGTH, TmclCommand, TmclDecodeError, TmclReply,
                                  TmclStatus, decode_request_can)
from youbot_fdi.tmcm.transport import CanTransport

MILLISECONDS = 1000.0
FIRMWARE_ID = b'1632V200'  # TMCM-1632, firmware 2.00 (type 0 reply)
FIRMWARE_BINARY = (1632 << 16) | 200  # type 1 reply value
MODULE_TYPE_VOLTAGE = 2400  # GAP 151: 24.00 V in 0.01 V
NO_FAULT = 'none'
#: How late a command frame may be read and still count at its bus time [s] (answered with the
#: state of then; the simulation waits this long for it before a module times out): the modules'
#: default controller timeout, the longest a host may be late before a module must stop.
FRAME_LOOKBACK = 0.1
MOTION_COMMANDS = (TmclCommand.ROR, TmclCommand.ROL, TmclCommand.MST, TmclCommand.MVP)
READ_ONLY = (AxisParameter.ACTUAL_VELOCITY, AxisParameter.ACTUAL_CURRENT, AxisParameter.ERROR_FLAGS,
             AxisParameter.I2T_SUM, AxisParameter.SUPPLY_VOLTAGE, AxisParameter.INITIALIZED)


@dataclass(frozen=True)
class VirtualBaseSettings:
    """Settings of the virtual base (``config/virtual_youbot.yaml``); units as there."""

    profile: str = 'youbot'
    can_interface: str = 'virtual'
    can_channel: str = 'youbot'
    module_ids: tuple = (0x11, 0x12, 0x13, 0x14)
    host_id: int = 0x02
    controller_timeout: float = 0.1
    nominal_current: float = 2.32
    thermal_time_constant: float = 16.6
    halted_velocity: int = 5
    position_gain: float = 5.0
    max_positioning_velocity: int = 4000
    current_noise: float = 5.0
    velocity_noise: float = 1.0
    seed: int = 0
    measurement_delay: float = 0.0  # the reported state lags the true one by this much [s]
    realtime_step: float = 0.001
    fault: str = NO_FAULT
    fault_wheel: str = 'wheel_joint_fl'
    torque_loss_gain: float = 0.3
    friction_factor: float = 6.0
    stuck_friction: float = 1000.0

    def validate(self, source='<settings>'):
        """Raise ConfigError on values no base can run with."""
        problems = []
        if len(set(self.module_ids)) != len(self.module_ids):
            problems.append('module_ids must be distinct')
        if self.host_id in self.module_ids:
            problems.append('host_id must differ from every module id')
        for name in ('controller_timeout', 'current_noise', 'velocity_noise', 'measurement_delay'):
            if getattr(self, name) < 0:
                problems.append(f'{name} must be >= 0')
        if not 0.0 <= self.torque_loss_gain <= 1.0:
            problems.append('torque_loss_gain must be in [0, 1]')
        for name in ('nominal_current', 'thermal_time_constant', 'position_gain', 'realtime_step',
                     'friction_factor', 'stuck_friction'):
            if getattr(self, name) <= 0:
                problems.append(f'{name} must be > 0')
        if self.fault != NO_FAULT and self.fault not in [k.value for k in INJECTABLE]:
            problems.append(f'fault must be none or one of {[k.value for k in INJECTABLE]}')
        if problems:
            msg = f'{source}: ' + '; '.join(problems)
            raise ConfigError(msg)


class _Module:
    """The state of one simulated TMCM module (motor units, driver convention)."""

    def __init__(self, can_id, max_current_ma, encoder_resolution, pid_period_ms):
        self.can_id = can_id
        self.mode = ControlMode.MOTOR_STOP
        self.target = 0  # rpm, mA or ticks
        self.process_data_control = False
        self.last_command_time = 0.0
        self.sticky_flags = ErrorFlag.NONE
        self.encoder_offset = 0  # ticks subtracted from the true count (SAP 1, 0)
        self.cycle = 0
        self.i2t = 0.0  # filtered current squared [A²]
        self.parameters = {
            AxisParameter.MAX_CURRENT: max_current_ma,
            AxisParameter.ENCODER_RESOLUTION: encoder_resolution,
            AxisParameter.PID_CONTROL_TIME: pid_period_ms,
            AxisParameter.MAX_POSITIONING_VELOCITY: 4000,
            AxisParameter.ACCELERATION: 2000,
            AxisParameter.THERMAL_WINDING_TIME: 16600,
            AxisParameter.I2T_LIMIT: 134957,
            AxisParameter.MOTOR_POLES: 16,
        }
        self.eeprom = dict(self.parameters)


class VirtualYoubot:
    """Simulated TMCM modules of a youBot base on a python-can bus.

    Parameters
    ----------
    model : PlatformModel
    bus : can.BusABC
        Any python-can bus; the transport does not shut it down unless ``owns_bus``.
    settings : VirtualBaseSettings
    ids : ProcessDataIds
    """

    def __init__(self, model, bus, settings=VirtualBaseSettings(), ids=ProcessDataIds(),
                 owns_bus=False):
        if len(settings.module_ids) != model.kinematics.n_wheels:
            msg = (f'{len(settings.module_ids)} module ids for {model.kinematics.n_wheels} wheels '
                   f'of profile {model.profile.name!r}')
            raise ConfigError(msg)
        settings.validate()
        self.model = model
        self.settings = settings
        self.ids = ids
        self.drive = model.drive
        self.signs = model.kinematics.drive_signs
        self.simulator = BaseSimulator(model)
        self.period = self.simulator.step_size
        self.nominal_friction = np.array(model.dynamics.parameters.viscous_friction, dtype=float)
        self.time = 0.0
        self._rng = np.random.default_rng(settings.seed)
        self._lock = threading.RLock()
        self._thread = None
        self._clock_origin = None  # (monotonic [s], epoch [s], simulated [s]) in real time
        self._running = threading.Event()
        self.modules = [_Module(i, int(round(model.drive.max_current * MILLISECONDS)),
                                int(model.drive.encoder_ticks_per_revolution),
                                int(round(model.firmware.period * MILLISECONDS)))
                        for i in settings.module_ids]
        self._module_index = {m: k for k, m in enumerate(settings.module_ids)}
        self.controller_timeout = settings.controller_timeout
        self._last_current = np.zeros(len(self.modules))
        self._delay_steps = int(round(settings.measurement_delay / self.period))
        self._lookback_steps = int(round(FRAME_LOOKBACK / self.period))
        self._history = deque(maxlen=self._delay_steps + self._lookback_steps + 1)
        self._record_history()
        self._faults = {}
        self._frozen = {}
        self._pending_faults = []  # (simulated time [s], FaultKind, wheel index), in time order
        self.transport = CanTransport(bus, self._on_frame, owns_bus=owns_bus)
        if settings.fault != NO_FAULT:
            self.inject(settings.fault, settings.fault_wheel)

    # ------------------------------------------------------------------ faults
    def wheel_index(self, wheel):
        """Index of a wheel given by joint name or index."""
        if isinstance(wheel, (int, np.integer)):
            if not 0 <= wheel < len(self.modules):
                raise ConfigError(f'wheel index {wheel} out of range')
            return int(wheel)
        try:
            return self.model.wheel_names.index(wheel)
        except ValueError:
            msg = f'unknown wheel {wheel!r}; one of {list(self.model.wheel_names)}'
            raise ConfigError(msg) from None

    def inject(self, kind, wheel):
        """Inject a fault on one wheel now (replacing any fault on that wheel). Following the wall
        clock, "now" is the wall clock's: a simulation still behind it (waiting for unread
        frames) takes the fault when it gets there, not earlier."""
        kind = FaultKind(kind)
        if kind not in INJECTABLE:
            msg = f'cannot inject {kind.value!r}'
            raise ConfigError(msg)
        index = self.wheel_index(wheel)
        with self._lock:
            at = self._simulated_time()
            if at is not None and at > self.time + self.period:
                self._pending_faults.append((at, kind, index))
            else:
                self._apply_fault(kind, index)

    def _apply_fault(self, kind, index):
        """Inject ``kind`` on wheel ``index`` at the simulation's time (call with the lock held)."""
        self._faults[index] = kind
        module = self.modules[index]
        if kind is FaultKind.RUNAWAY:
            self._frozen[index] = ('runaway', module.mode, module.target)
        elif kind is FaultKind.ENCODER_FREEZE:
            position, velocity, _ = self._reported()
            self._frozen[index] = ('encoder', position[index], velocity[index])
        self._apply_friction()

    def clear_faults(self):
        """Remove every injected fault."""
        with self._lock:
            self._pending_faults.clear()
            self._faults.clear()
            self._frozen.clear()
            self._apply_friction()

    @property
    def faults(self):
        """Injected faults: wheel name -> FaultKind."""
        with self._lock:
            return {self.model.wheel_names[i]: k for i, k in self._faults.items()}

    def _apply_friction(self):
        friction = self.nominal_friction.copy()
        for index, kind in self._faults.items():
            if kind is FaultKind.FRICTION:
                friction[index] *= self.settings.friction_factor
            elif kind is FaultKind.STUCK:
                friction[index] = self.settings.stuck_friction
        self.simulator.set_viscous_friction(friction)

    def _fault(self, index):
        return self._faults.get(index)

    # ------------------------------------------------------------------ bus side
    def _send_reply(self, module, status, command, value):
        reply = TmclReply(self.settings.host_id, module.can_id, int(status), command, int(value))
        self.transport.send(*reply.to_can())

    def _on_frame(self, arbitration_id, data, timestamp):
        with self._lock:
            index = self._module_index.get(arbitration_id)
            if index is not None:
                if self._fault(index) is FaultKind.COMM_LOSS:
                    return
                self._on_tmcl(self.modules[index], arbitration_id, data)
                return
            kind = self.ids.classify(arbitration_id)
            if kind is None or kind[0] != 'command':
                return
            index = self._module_index.get(kind[1])
            if index is None or self._fault(index) is FaultKind.COMM_LOSS:
                return
            command = MotorCommand.decode(data)
            self._on_process_data(index, command, timestamp)

    def _on_tmcl(self, module, arbitration_id, data):
        try:
            request = decode_request_can(arbitration_id, data)
        except TmclDecodeError:
            if len(data) > CAN_PAYLOAD_LENGTH:  # a PyTrinamic frame with a bad checksum byte
                self._send_reply(module, TmclStatus.WRONG_CHECKSUM, data[0], 0)
                return
            raise
        status, value = self._execute(module, request)
        if request.command == TmclCommand.FIRMWARE_VERSION and request.type == 0:
            self.transport.send(self.settings.host_id, FIRMWARE_ID)
            return
        self._send_reply(module, status, request.command, value)

    def _execute(self, module, request):
        """Run one TMCL request; returns (status, value)."""
        command, type_, value = request.command, request.type, request.value
        if command in (TmclCommand.SGP, TmclCommand.GGP, TmclCommand.STGP, TmclCommand.RSGP):
            return self._global_parameter(command, type_, value)
        if request.motor != 0:
            return TmclStatus.INVALID_VALUE, 0
        if command in MOTION_COMMANDS:
            module.process_data_control = False
        if command == TmclCommand.ROR:
            self._set_mode(module, ControlMode.VELOCITY, value)
        elif command == TmclCommand.ROL:
            self._set_mode(module, ControlMode.VELOCITY, -value)
        elif command == TmclCommand.MST:
            self._set_mode(module, ControlMode.MOTOR_STOP, 0)
            # A runaway is a fault of the cyclic set-point path: a motor stop over the mailbox
            # still reaches the motor driver and ends it (the wheel then obeys 0 mA and coasts).
            index = self.modules.index(module)
            if self._frozen.get(index, ('',))[0] == 'runaway':
                del self._frozen[index]
        elif command == TmclCommand.MVP:
            if type_ not in (0, 1):
                return TmclStatus.WRONG_TYPE, 0
            target = value if type_ == 0 else self._ticks(module) + value
            self._set_mode(module, ControlMode.POSITION, target)
        elif command == TmclCommand.SAP:
            return self._set_axis_parameter(module, type_, value)
        elif command == TmclCommand.GAP:
            return self._get_axis_parameter(module, type_)
        elif command == TmclCommand.STAP:
            if type_ not in module.parameters:
                return TmclStatus.WRONG_TYPE, 0
            module.eeprom[type_] = module.parameters[type_]
        elif command == TmclCommand.RSAP:
            if type_ not in module.eeprom:
                return TmclStatus.WRONG_TYPE, 0
            module.parameters[type_] = module.eeprom[type_]
        elif command == TmclCommand.CLE:
            module.sticky_flags = ErrorFlag.NONE
        elif command == TmclCommand.FIRMWARE_VERSION:
            if type_ not in (0, 1):
                return TmclStatus.WRONG_TYPE, 0
            return TmclStatus.SUCCESS, FIRMWARE_BINARY
        else:
            return TmclStatus.INVALID_COMMAND, 0
        return TmclStatus.SUCCESS, value

    def _global_parameter(self, command, type_, value):
        if type_ != GlobalParameter.MOTOR_CONTROLLER_TIMEOUT:
            return TmclStatus.WRONG_TYPE, 0
        if command == TmclCommand.SGP:
            if value < 0:
                return TmclStatus.INVALID_VALUE, 0
            self.controller_timeout = value / MILLISECONDS
        return TmclStatus.SUCCESS, int(round(self.controller_timeout * MILLISECONDS))

    def _set_axis_parameter(self, module, type_, value):
        if type_ in READ_ONLY:
            return TmclStatus.WRONG_TYPE, 0
        if type_ == AxisParameter.TARGET_VELOCITY:
            module.process_data_control = False
            self._set_mode(module, ControlMode.VELOCITY, value)
        elif type_ == AxisParameter.TARGET_CURRENT:
            module.process_data_control = False
            self._set_mode(module, ControlMode.CURRENT, value)
        elif type_ == AxisParameter.TARGET_POSITION:
            module.process_data_control = False
            self._set_mode(module, ControlMode.POSITION, value)
        elif type_ == AxisParameter.ACTUAL_POSITION:
            module.encoder_offset = self._ticks(module, raw=True) - value
        elif type_ == AxisParameter.CLEAR_TIMEOUT_FLAG:
            module.sticky_flags &= ~ErrorFlag.TIMEOUT
        elif type_ == AxisParameter.CLEAR_I2T_FLAG:
            module.sticky_flags &= ~ErrorFlag.I2T_EXCEEDED
        elif type_ == AxisParameter.MAX_CURRENT:
            if value <= 0:
                return TmclStatus.INVALID_VALUE, 0
            module.parameters[type_] = value
        elif type_ in module.parameters or type_ in AxisParameter.__members__.values():
            module.parameters[type_] = value
        else:
            return TmclStatus.WRONG_TYPE, 0
        return TmclStatus.SUCCESS, value

    def _get_axis_parameter(self, module, type_):
        index = self.modules.index(module)
        status = self._status(index)
        readings = {
            AxisParameter.TARGET_POSITION: module.target if module.mode == ControlMode.POSITION else 0,
            AxisParameter.ACTUAL_POSITION: status.position,
            AxisParameter.TARGET_VELOCITY: module.target if module.mode == ControlMode.VELOCITY else 0,
            AxisParameter.ACTUAL_VELOCITY: status.velocity,
            AxisParameter.TARGET_CURRENT: module.target if module.mode == ControlMode.CURRENT else 0,
            AxisParameter.ACTUAL_CURRENT: status.current,
            AxisParameter.ERROR_FLAGS: status.error_flags,
            AxisParameter.I2T_SUM: int(round(module.i2t * MILLISECONDS)),
            AxisParameter.SUPPLY_VOLTAGE: MODULE_TYPE_VOLTAGE,
            AxisParameter.INITIALIZED: 1,
        }
        if type_ in readings:
            return TmclStatus.SUCCESS, readings[type_]
        if type_ in module.parameters:
            return TmclStatus.SUCCESS, module.parameters[type_]
        return TmclStatus.WRONG_TYPE, 0

    def _set_mode(self, module, mode, target):
        module.mode = ControlMode(mode) if mode in ControlMode.__members__.values() else \
            ControlMode.MOTOR_STOP
        module.target = int(target)

    def _on_process_data(self, index, command, bus_time=None):
        """A module's process-data command, on the bus at ``bus_time`` (epoch [s]; None: now):
        the simulation is brought to that moment, and the module answers with its state then."""
        back = 0
        at = self._simulated_time(bus_time)
        if at is not None:
            self._advance_to(at)
            back = int(round((self.time - at) / self.period))
            back = max(0, min(back, self._lookback_steps, len(self._history) - 1 - self._delay_steps))
        module = self.modules[index]
        module.process_data_control = True
        module.last_command_time = self.time - back * self.period
        module.cycle = command.cycle
        if command.mode in (ControlMode.MOTOR_STOP, ControlMode.POSITION, ControlMode.VELOCITY,
                            ControlMode.NO_MORE_ACTION, ControlMode.CURRENT):
            self._set_mode(module, command.mode, command.value)
        status = self._status(index, back)
        for can_id, payload in zip(self.ids.status_ids(module.can_id), status.encode()):
            self.transport.send(can_id, payload)

    # ------------------------------------------------------------------ measurements
    def _record_history(self):
        self._history.append((self.simulator.position.copy(), self.simulator.velocity.copy(),
                              self._last_current.copy()))

    def _reported(self, back=0):
        """(position, velocity, current) as the modules report them: ``measurement_delay`` old,
        ``back`` firmware periods before now."""
        return self._history[max(0, len(self._history) - 1 - self._delay_steps - back)]

    def _ticks(self, module, raw=False, back=0):
        index = self.modules.index(module)
        angle = self._reported(back)[0][index]
        frozen = self._frozen.get(index)
        if frozen is not None and frozen[0] == 'encoder':
            angle = frozen[1]
        ticks = int(round(float(self.drive.wheel_angle_to_ticks(self.signs[index] * angle))))
        return ticks if raw else ticks - module.encoder_offset

    def _flags(self, index, speed_rpm):
        module = self.modules[index]
        flags = module.sticky_flags | ErrorFlag.MODULE_INITIALIZED
        flags |= {ControlMode.VELOCITY: ErrorFlag.VELOCITY_MODE,
                  ControlMode.POSITION: ErrorFlag.POSITION_MODE,
                  ControlMode.CURRENT: ErrorFlag.TORQUE_MODE}.get(module.mode, ErrorFlag.NONE)
        if abs(speed_rpm) < self.settings.halted_velocity:
            flags |= ErrorFlag.MOTOR_HALTED
        if abs(self._last_current[index]) >= module.parameters[AxisParameter.MAX_CURRENT] / MILLISECONDS:
            flags |= ErrorFlag.OVER_CURRENT
        return int(flags)

    def _status(self, index, back=0):
        """The module's sample ``back`` firmware periods ago (0: now) in motor units and driver
        convention."""
        module = self.modules[index]
        _, reported_speed, reported_current = self._reported(back)
        speed = reported_speed[index]
        frozen = self._frozen.get(index)
        if frozen is not None and frozen[0] == 'encoder':
            speed = frozen[2]
        rpm = float(self.drive.wheel_speed_to_rpm(self.signs[index] * speed))
        current_ma = self.signs[index] * reported_current[index] * MILLISECONDS
        if self.settings.velocity_noise > 0 and frozen is None:  # a frozen reading is frozen
            rpm += self._rng.normal(0.0, self.settings.velocity_noise)
        if self.settings.current_noise > 0:
            current_ma += self._rng.normal(0.0, self.settings.current_noise)
        sampled = self.time - self.settings.measurement_delay - back * self.period
        return MotorStatus(position=self._ticks(module, back=back), velocity=int(round(rpm)),
                           current=int(round(current_ma)), error_flags=self._flags(index, rpm),
                           target=module.target, mode=int(module.mode), cycle=module.cycle,
                           sample_time=int(round(sampled * MILLISECONDS)) % SAMPLE_TIME_MODULO or 1)

    def status(self, wheel):
        """The current sample of a wheel's module (:class:`MotorStatus`)."""
        with self._lock:
            return self._status(self.wheel_index(wheel))

    # ------------------------------------------------------------------ simulation
    def _setpoints(self):
        """Per wheel (kinematic convention, SI): setpoint array and ControlMode array."""
        n = len(self.modules)
        setpoints, modes = np.zeros(n), np.full(n, int(ControlMode.MOTOR_STOP))
        for index, module in enumerate(self.modules):
            mode, target = module.mode, module.target
            frozen = self._frozen.get(index)
            if frozen is not None and frozen[0] == 'runaway':
                mode, target = frozen[1], frozen[2]
            elif module.sticky_flags & ErrorFlag.TIMEOUT:
                mode, target = ControlMode.MOTOR_STOP, 0
            sign = self.signs[index]
            if mode == ControlMode.VELOCITY:
                setpoints[index] = sign * float(self.drive.rpm_to_wheel_speed(target))
            elif mode == ControlMode.CURRENT:
                limit = module.parameters[AxisParameter.MAX_CURRENT]
                setpoints[index] = sign * float(np.clip(target, -limit, limit)) / MILLISECONDS
            elif mode == ControlMode.POSITION:
                error = float(self.drive.ticks_to_wheel_angle(target + module.encoder_offset)) \
                    - sign * self.simulator.position[index]
                limit = float(self.drive.rpm_to_wheel_speed(self.settings.max_positioning_velocity))
                setpoints[index] = sign * float(np.clip(self.settings.position_gain * error, -limit, limit))
                mode = ControlMode.VELOCITY
            modes[index] = int(mode if mode in (ControlMode.VELOCITY, ControlMode.CURRENT)
                               else ControlMode.MOTOR_STOP)
        return setpoints, modes

    def _check_timeouts(self):
        if self.controller_timeout <= 0:
            return
        for index, module in enumerate(self.modules):
            silent = (self._fault(index) is FaultKind.COMM_LOSS
                      or self.time - module.last_command_time > self.controller_timeout)
            if module.process_data_control and silent and self._fault(index) is not FaultKind.RUNAWAY:
                module.sticky_flags |= ErrorFlag.TIMEOUT

    def _step(self):
        while self._pending_faults and self._pending_faults[0][0] <= self.time:
            self._apply_fault(*self._pending_faults.pop(0)[1:])
        self._check_timeouts()
        setpoints, modes = self._setpoints()
        gain = np.ones(len(self.modules))
        measured = self.simulator.velocity.copy()
        for index, kind in self._faults.items():
            if kind is FaultKind.TORQUE_LOSS:
                gain[index] = self.settings.torque_loss_gain
            elif kind is FaultKind.ENCODER_FREEZE:
                measured[index] = self._frozen[index][2]
        result = self.simulator.step(setpoints, modes, torque_gain=gain, measured_velocity=measured)
        self._last_current = result.current
        decay = self.period / self.settings.thermal_time_constant
        for index, module in enumerate(self.modules):
            module.i2t += (result.current[index] ** 2 - module.i2t) * decay
            if module.i2t > self.settings.nominal_current ** 2:
                module.sticky_flags |= ErrorFlag.I2T_EXCEEDED
        self.time += self.period
        self._record_history()

    def advance(self, duration):
        """Advance the simulation by ``duration`` [s] (rounded to whole firmware periods)."""
        steps = int(round(duration / self.period))
        for _ in range(steps):
            with self._lock:
                self._step()
        return self.time

    def wheel_state(self):
        """True wheel angles [rad] and speeds [rad/s] in the driver convention (for tests, plots)."""
        with self._lock:
            return (self.signs * self.simulator.position.copy(),
                    self.signs * self.simulator.velocity.copy())

    # ------------------------------------------------------------------ real time
    def follow_wall_clock(self):
        """From now on the simulated time follows the wall clock: every module answer first
        catches the simulation up to its frame's bus time (:meth:`start` also steps it in a thread
        of its own)."""
        with self._lock:
            self._clock_origin = (time.monotonic(), time.time(), self.time)

    def start(self):
        """Run the simulation in a thread that follows the wall clock."""
        if self._thread is not None:
            return
        self.follow_wall_clock()
        self._running.set()
        self._thread = threading.Thread(target=self._run, name='virtual_youbot', daemon=True)
        self._thread.start()

    def _simulated_time(self, bus_time=None):
        """The simulated time [s] of a bus timestamp (epoch [s]; None or 0: now), or None unless
        following the wall clock."""
        if self._clock_origin is None:
            return None
        monotonic, epoch, simulated = self._clock_origin
        if not bus_time:
            return simulated + time.monotonic() - monotonic
        return simulated + bus_time - epoch

    def _advance_to(self, simulated):
        """Step the simulation up to ``simulated`` [s] (call with the lock held). Real modules
        sample their encoders on their own hardware clock: a simulation thread starved of the
        CPU must not hand the driver the same position twice while time goes on, which reads as
        frozen encoders on every wheel."""
        for _ in range(int(round((simulated - self.time) / self.period))):
            self._step()

    def _realtime_target(self):
        """Where the real-time thread takes the simulation [s]: now, but not past the moment a
        module under process data would time out while its next frame may still be unread
        (until ``FRAME_LOOKBACK`` after it: then the host is silent). Call with the lock held."""
        now = self._simulated_time()
        if self.controller_timeout <= 0:
            return now
        waiting = [m.last_command_time for k, m in enumerate(self.modules)
                   if m.process_data_control and not m.sticky_flags & ErrorFlag.TIMEOUT
                   and self._fault(k) not in (FaultKind.COMM_LOSS, FaultKind.RUNAWAY)]
        if not waiting:
            return now
        hold = min(waiting) + self.controller_timeout - self.period
        return hold if hold < now < hold + FRAME_LOOKBACK else now

    def _run(self):
        step = self.settings.realtime_step
        while self._running.is_set():
            with self._lock:
                ahead = self._realtime_target() - self.time
            if ahead >= step:
                self.advance(step)
            else:
                time.sleep(step - max(ahead, 0.0))

    def close(self):
        """Stop the real-time thread and the transport."""
        self._running.clear()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self.transport.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
