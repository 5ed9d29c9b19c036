"""TMCL codec: Trinamic's command protocol, as bytes <-> frozen dataclasses (no python-can here).

Serial (RS-232/485/USB) frames are 9 bytes:

- request ``[module address, command, type, motor/bank, value MSB..LSB (4), checksum]``
- reply ``[host address, module address, status, command, value MSB..LSB (4), checksum]``

with the checksum the 8-bit sum of the first 8 bytes. Over CAN the first byte becomes the
11-bit identifier and the checksum is dropped (CAN has a CRC): a request is 7 data bytes on the
module's id, a reply 7 data bytes on the host's id. PyTrinamic sends an 8th byte, the serial
checksum; it is accepted and verified. Values are signed 32-bit, big-endian (two's complement).
Sources: ../shared/reference/tmcm_youbot_facts.md §1.
"""
from dataclasses import dataclass
import enum
import struct

SERIAL_FRAME_LENGTH = 9
CAN_PAYLOAD_LENGTH = 7
CAN_PAYLOAD_WITH_CHECKSUM = 8
VALUE_FORMAT = '>i'
INT32_MIN, INT32_MAX = -(2 ** 31), 2 ** 31 - 1
BYTE_MAX = 0xFF
CAN_STANDARD_ID_MAX = 0x7FF


class TmclCommand(enum.IntEnum):
    """TMCL instruction numbers (youbot_driver ProtocolDefinitions.hpp, PyTrinamic tmcl.py)."""

    ROR = 1
    ROL = 2
    MST = 3
    MVP = 4
    SAP = 5
    GAP = 6
    STAP = 7
    RSAP = 8
    SGP = 9
    GGP = 10
    STGP = 11
    RSGP = 12
    CLE = 36
    FIRMWARE_VERSION = 136


class TmclStatus(enum.IntEnum):
    """Reply status codes."""

    SUCCESS = 100
    LOADED_INTO_EEPROM = 101
    WRONG_CHECKSUM = 1
    INVALID_COMMAND = 2
    WRONG_TYPE = 3
    INVALID_VALUE = 4
    EEPROM_LOCKED = 5
    COMMAND_NOT_AVAILABLE = 6
    WRITE_PROTECTED = 8


class TmclDecodeError(ValueError):
    """A frame is not a valid TMCL frame; the message says why."""


def checksum(data):
    """8-bit sum of ``data`` (bytes)."""
    return sum(data) & BYTE_MAX


def _check_byte(name, value):
    if not 0 <= value <= BYTE_MAX:
        msg = f'{name} must be a byte (0..255), got {value!r}'
        raise ValueError(msg)


def _check_value(value):
    if not INT32_MIN <= value <= INT32_MAX:
        msg = f'value must fit a signed 32-bit integer, got {value!r}'
        raise ValueError(msg)


@dataclass(frozen=True)
class TmclRequest:
    """A command to a module. ``command`` may be a number no enum knows (it is answered as invalid)."""

    module: int  # module address; over CAN the module's CAN id
    command: int
    type: int  # parameter number for SAP/GAP/SGP/GGP
    motor: int  # motor (axis) or bank number
    value: int  # signed 32-bit

    def __post_init__(self):
        for name in ('module', 'command', 'type', 'motor'):
            _check_byte(name, getattr(self, name))
        _check_value(self.value)

    def to_serial(self):
        """The 9-byte serial frame."""
        body = struct.pack('>BBBB', self.module, self.command, self.type, self.motor)
        body += struct.pack(VALUE_FORMAT, self.value)
        return body + bytes([checksum(body)])

    def to_can(self, with_checksum=False):
        """``(arbitration id, payload)``: 7 bytes, or PyTrinamic's 8 with the serial checksum."""
        if self.module > CAN_STANDARD_ID_MAX:
            msg = f'module {self.module} does not fit an 11-bit CAN id'
            raise ValueError(msg)
        frame = self.to_serial()
        return self.module, frame[1:8] + (frame[8:9] if with_checksum else b'')


@dataclass(frozen=True)
class TmclReply:
    """A module's answer."""

    host: int  # reply (host) address; over CAN the host's CAN id
    module: int
    status: int
    command: int
    value: int

    def __post_init__(self):
        for name in ('host', 'module', 'status', 'command'):
            _check_byte(name, getattr(self, name))
        _check_value(self.value)

    @property
    def ok(self):
        """True for status 100 or 101."""
        return self.status in (TmclStatus.SUCCESS, TmclStatus.LOADED_INTO_EEPROM)

    def to_serial(self):
        """The 9-byte serial frame."""
        body = struct.pack('>BBBB', self.host, self.module, self.status, self.command)
        body += struct.pack(VALUE_FORMAT, self.value)
        return body + bytes([checksum(body)])

    def to_can(self):
        """``(arbitration id, 7-byte payload)``."""
        return self.host, self.to_serial()[1:8]


def _as_bytes(data, what):
    try:
        return bytes(data)
    except (TypeError, ValueError) as err:
        msg = f'{what} must be bytes, got {type(data).__name__}'
        raise TmclDecodeError(msg) from err


def _checked_serial_frame(frame, what):
    """``frame`` as bytes after the length and checksum checks of a 9-byte serial frame."""
    frame = _as_bytes(frame, f'a serial {what}')
    if len(frame) != SERIAL_FRAME_LENGTH:
        msg = f'a serial TMCL {what} has {SERIAL_FRAME_LENGTH} bytes, got {len(frame)}'
        raise TmclDecodeError(msg)
    if checksum(frame[:8]) != frame[8]:
        msg = f'bad checksum 0x{frame[8]:02X}, expected 0x{checksum(frame[:8]):02X}'
        raise TmclDecodeError(msg)
    return frame


def decode_request_serial(frame):
    """Parse a 9-byte serial request; raises :class:`TmclDecodeError` on length or checksum."""
    frame = _checked_serial_frame(frame, 'request')
    module, command, type_, motor = frame[:4]
    return TmclRequest(module, command, type_, motor, struct.unpack(VALUE_FORMAT, frame[4:8])[0])


def decode_reply_serial(frame):
    """Parse a 9-byte serial reply; raises :class:`TmclDecodeError` on length or checksum."""
    frame = _checked_serial_frame(frame, 'reply')
    host, module, status, command = frame[:4]
    return TmclReply(host, module, status, command, struct.unpack(VALUE_FORMAT, frame[4:8])[0])


def decode_request_can(arbitration_id, payload):
    """Parse a request received on a module's CAN id (7 bytes, or 8 with PyTrinamic's checksum)."""
    payload = _as_bytes(payload, 'a CAN payload')
    if len(payload) not in (CAN_PAYLOAD_LENGTH, CAN_PAYLOAD_WITH_CHECKSUM):
        msg = (f'a TMCL request over CAN has {CAN_PAYLOAD_LENGTH} or {CAN_PAYLOAD_WITH_CHECKSUM} '
               f'data bytes, got {len(payload)}')
        raise TmclDecodeError(msg)
    if not 0 <= arbitration_id <= BYTE_MAX:
        msg = f'module id 0x{arbitration_id:X} does not fit a TMCL module address'
        raise TmclDecodeError(msg)
    frame = bytes([arbitration_id]) + payload[:CAN_PAYLOAD_LENGTH]
    if len(payload) == CAN_PAYLOAD_WITH_CHECKSUM and checksum(frame) != payload[-1]:
        msg = f'bad checksum 0x{payload[-1]:02X}, expected 0x{checksum(frame):02X}'
        raise TmclDecodeError(msg)
    return decode_request_serial(frame + bytes([checksum(frame)]))


def decode_reply_can(arbitration_id, payload):
    """Parse a reply received on the host's CAN id (7 data bytes)."""
    payload = _as_bytes(payload, 'a CAN payload')
    if len(payload) != CAN_PAYLOAD_LENGTH:
        msg = f'a TMCL reply over CAN has {CAN_PAYLOAD_LENGTH} data bytes, got {len(payload)}'
        raise TmclDecodeError(msg)
    if not 0 <= arbitration_id <= BYTE_MAX:
        msg = f'host id 0x{arbitration_id:X} does not fit a TMCL address'
        raise TmclDecodeError(msg)
    frame = bytes([arbitration_id]) + payload
    return decode_reply_serial(frame + bytes([checksum(frame)]))
