"""Block decoding of ``sensor_msgs/msg/JointState`` CDR messages that share one byte layout.

rosbags deserialises a JointState in about 9 µs of Python. In a recording nearly every message of
a topic has the same layout: the same frame_id, joint names and array lengths; only the stamp and
the doubles differ. :class:`JointStateLayout` learns the layout from one message, recognises the
others by their length and their non-numeric bytes, and decodes a whole block of them with numpy
views. Anything else (big-endian CDR, trailing bytes, another layout) is the caller's to hand to
rosbags.

CDR (XCDR1, little-endian, the ROS 2 default): a 4-byte encapsulation header ``00 01 00 00``, then
the fields, each aligned to its size counted from the end of that header.
"""
from dataclasses import dataclass
import struct

import numpy as np

ENCAPSULATION_SIZE = 4
CDR_LITTLE_ENDIAN = b'\x00\x01'
STAMP_END = ENCAPSULATION_SIZE + 8  # int32 sec, uint32 nanosec
ARRAY_FIELDS = ('position', 'velocity', 'effort')
DOUBLE = 8
UINT32 = struct.Struct('<I')
NANOSECONDS = 1e9


def _align(offset, size):
    body = offset - ENCAPSULATION_SIZE
    return ENCAPSULATION_SIZE + (body + size - 1) // size * size


def _string(raw, offset, length):
    """A CDR string at ``offset``: its uint32 length counts the terminating NUL."""
    if length == 0 or offset + 4 + length > len(raw):
        raise struct.error('bad string length')
    return raw[offset + 4:offset + 3 + length].decode()


@dataclass(frozen=True)
class JointStateLayout:
    """The byte layout of a family of JointState messages.

    ``fixed`` lists the (start, stop, bytes) ranges that every message of the layout repeats
    (frame_id, names, array lengths); ``arrays`` the (offset, count) of position, velocity, effort.
    """

    size: int
    frame_id: str
    names: tuple
    arrays: tuple
    fixed: tuple

    @classmethod
    def parse(cls, raw):
        """The layout of one serialised message, or None when this decoder cannot handle it."""
        raw = bytes(raw)
        if len(raw) < STAMP_END or raw[:2] != CDR_LITTLE_ENDIAN:
            return None
        try:
            offset = STAMP_END
            length, = UINT32.unpack_from(raw, offset)
            frame_id = _string(raw, offset, length)
            offset = _align(offset + 4 + length, 4)
            count, = UINT32.unpack_from(raw, offset)
            offset += 4
            names = []
            for _ in range(count):
                offset = _align(offset, 4)
                length, = UINT32.unpack_from(raw, offset)
                names.append(_string(raw, offset, length))
                offset += 4 + length
            arrays, fixed, fixed_start = [], [], STAMP_END
            for _ in ARRAY_FIELDS:
                offset = _align(offset, 4)
                count, = UINT32.unpack_from(raw, offset)
                offset = _align(offset + 4, DOUBLE) if count else offset + 4
                fixed.append((fixed_start, offset, raw[fixed_start:offset]))
                arrays.append((offset, count))
                offset += DOUBLE * count
                fixed_start = offset
        except (struct.error, UnicodeDecodeError):
            return None
        if offset != len(raw):
            return None
        return cls(len(raw), frame_id, tuple(names), tuple(arrays), tuple(fixed))

    def matches(self, raw):
        """True when ``raw`` has this layout (its stamp and doubles may differ)."""
        if len(raw) != self.size:
            return False
        for start, stop, expected in self.fixed:
            if raw[start:stop] != expected:
                return False
        return True

    def decode(self, raws):
        """Stamps (N,) [s] and the position, velocity, effort arrays (N, count) of messages of this
        layout."""
        block = np.frombuffer(b''.join(raws), dtype=np.uint8).reshape(len(raws), self.size)
        seconds = block[:, ENCAPSULATION_SIZE:ENCAPSULATION_SIZE + 4].copy().view('<i4')[:, 0]
        nanoseconds = block[:, ENCAPSULATION_SIZE + 4:STAMP_END].copy().view('<u4')[:, 0]
        stamp = seconds + nanoseconds / NANOSECONDS
        arrays = [block[:, offset:offset + DOUBLE * count].copy().view('<f8')
                  for offset, count in self.arrays]
        return stamp, arrays
