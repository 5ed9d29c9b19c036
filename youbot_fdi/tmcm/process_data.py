"""EtherCAT-style cyclic process data of the youBot's TMCM modules, carried over CAN frames.

On the youBot the master writes 5 bytes per slave and cycle (int32 value + uint8 controller mode)
and reads 32 bytes back (firmware 2.0). Over classic CAN (8 data bytes) we carry them as, for a
module with CAN id ``n`` (CANopen-style function code + node id; defaults, configurable):

=============  ===========  ===================================================================
id             direction    payload (little-endian, as EtherCAT)
=============  ===========  ===================================================================
0x200 + n      master->mod  int32 value (rpm | mA | ticks by mode), uint8 mode, uint8 cycle
0x180 + n      mod->master  int32 actual position [ticks], int32 actual velocity [rpm]
0x280 + n      mod->master  int32 actual current [mA], uint32 error flags
0x380 + n      mod->master  int32 target value in use, uint8 mode, uint8 cycle (echo),
                            uint16 sample time [ms, modulo 65536] (0 = not provided)
=============  ===========  ===================================================================

Each command frame is answered by the three status frames in that order; the last one closes the
sample and echoes the cycle counter of the command it answers, so the master can tell fresh data
from stale and count lost cycles. Module ids must be below 0x80 so that the ranges do not overlap.
"""
from dataclasses import dataclass
import enum
import struct

from youbot_fdi.tmcm.tmcl import TmclDecodeError

COMMAND_FORMAT = '<iBB'
STATUS_FORMATS = ('<ii', '<iI', '<iBBH')
CYCLE_MODULO = 256
SAMPLE_TIME_MODULO = 65536  # [ms]
MAX_NODE_ID = 0x7F


class StatusPart(enum.IntEnum):
    """The three status frames of a sample, in sending order."""

    MOTION = 0
    ELECTRICAL = 1
    SETPOINT = 2


@dataclass(frozen=True)
class ProcessDataIds:
    """CAN id bases of the process data (configurable)."""

    command_base: int = 0x200
    motion_base: int = 0x180
    electrical_base: int = 0x280
    setpoint_base: int = 0x380

    def command_id(self, module):
        """CAN id of the command frame to ``module``."""
        _check_node(module)
        return self.command_base + module

    def status_ids(self, module):
        """CAN ids of the three status frames of ``module``, in :class:`StatusPart` order."""
        _check_node(module)
        return (self.motion_base + module, self.electrical_base + module,
                self.setpoint_base + module)

    def classify(self, arbitration_id):
        """``('command', module)`` or ``('status', module, part)`` for a process-data id, else None."""
        for base, kind in ((self.command_base, None), (self.motion_base, StatusPart.MOTION),
                           (self.electrical_base, StatusPart.ELECTRICAL),
                           (self.setpoint_base, StatusPart.SETPOINT)):
            if base < arbitration_id <= base + MAX_NODE_ID:
                module = arbitration_id - base
                return ('command', module) if kind is None else ('status', module, kind)
        return None


def _check_node(module):
    if not 0 < module <= MAX_NODE_ID:
        msg = f'process-data module ids must be 1..0x{MAX_NODE_ID:X}, got 0x{module:X}'
        raise ValueError(msg)


@dataclass(frozen=True)
class MotorCommand:
    """Master -> module: the setpoint for one cycle."""

    mode: int  # ControlMode value
    value: int  # rpm, mA or ticks, by mode
    cycle: int  # 0..255, increments every cycle

    def encode(self):
        """Payload bytes."""
        return struct.pack(COMMAND_FORMAT, self.value, self.mode, self.cycle % CYCLE_MODULO)

    @classmethod
    def decode(cls, payload):
        """Parse a command payload; :class:`TmclDecodeError` if malformed."""
        size = struct.calcsize(COMMAND_FORMAT)
        if len(payload) != size:
            msg = f'a process-data command has {size} bytes, got {len(payload)}'
            raise TmclDecodeError(msg)
        value, mode, cycle = struct.unpack(COMMAND_FORMAT, bytes(payload))
        return cls(mode, value, cycle)


@dataclass(frozen=True)
class MotorStatus:
    """Module -> master: one complete sample."""

    position: int  # [ticks]
    velocity: int  # [rpm]
    current: int  # [mA]
    error_flags: int
    target: int  # setpoint in use (rpm, mA or ticks)
    mode: int
    cycle: int  # cycle counter of the command this sample answers
    sample_time: int = 0  # module clock when the state was sampled [ms modulo 65536]; 0 = none

    def encode(self):
        """The three payloads, in :class:`StatusPart` order."""
        return (struct.pack(STATUS_FORMATS[0], self.position, self.velocity),
                struct.pack(STATUS_FORMATS[1], self.current, self.error_flags & 0xFFFFFFFF),
                struct.pack(STATUS_FORMATS[2], self.target, self.mode, self.cycle % CYCLE_MODULO,
                            self.sample_time % SAMPLE_TIME_MODULO))


def decode_status_part(part, payload):
    """Values of one status frame as a tuple; :class:`TmclDecodeError` if malformed."""
    fmt = STATUS_FORMATS[part]
    if len(payload) != struct.calcsize(fmt):
        msg = f'status frame {StatusPart(part).name} has {struct.calcsize(fmt)} bytes, got {len(payload)}'
        raise TmclDecodeError(msg)
    return struct.unpack(fmt, bytes(payload))


class StatusAssembler:
    """Collects status frames per module into :class:`MotorStatus` samples.

    ``add`` returns a sample when the closing SETPOINT frame arrives after the other two;
    a closing frame without both others since the last sample is an incomplete sample
    (``incomplete`` counts them) and yields nothing.
    """

    def __init__(self):
        self._parts = {}
        self.incomplete = 0

    def add(self, module, part, payload):
        values = decode_status_part(part, payload)
        parts = self._parts.setdefault(module, {})
        if part != StatusPart.SETPOINT:
            parts[part] = values
            return None
        motion, electrical = parts.pop(StatusPart.MOTION, None), parts.pop(StatusPart.ELECTRICAL, None)
        if motion is None or electrical is None:
            self.incomplete += 1
            return None
        target, mode, cycle, sample_time = values
        return MotorStatus(motion[0], motion[1], electrical[0], electrical[1], target, mode, cycle,
                           sample_time)
