"""TMCL and process-data codecs: reference vectors, round trips and garbage (hypothesis)."""
from hypothesis import given, strategies as st
import pytest

from youbot_fdi.tmcm.process_data import (MotorCommand, MotorStatus, ProcessDataIds, StatusAssembler,
                                          StatusPart)
from youbot_fdi.tmcm.tmcl import (decode_reply_can, decode_reply_serial, decode_request_can,
                                  decode_request_serial, TmclDecodeError, TmclReply, TmclRequest)

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute

bytes_ = st.integers(0, 255)
int32 = st.integers(-(2 ** 31), 2 ** 31 - 1)
requests = st.builds(TmclRequest, bytes_, bytes_, bytes_, bytes_, int32)
replies = st.builds(TmclReply, bytes_, bytes_, bytes_, bytes_, int32)


def test_trinamic_manual_worked_example():
    """TMCM-1211 manual p. 82: CALCV request and its reply, checksums included."""
    request = TmclRequest(module=1, command=45, type=1, motor=0x1B, value=5000)
    assert request.to_serial() == bytes.fromhex('012D011B00001388E5')
    reply = decode_reply_serial(bytes.fromhex('0201642D000013882F'))
    assert reply == TmclReply(host=2, module=1, status=100, command=45, value=5000)
    assert reply.ok


@given(requests)
def test_request_round_trips(request):
    assert decode_request_serial(request.to_serial()) == request
    can_id, payload = request.to_can()
    assert can_id == request.module and len(payload) == 7
    assert decode_request_can(can_id, payload) == request
    can_id, payload = request.to_can(with_checksum=True)  # PyTrinamic's 8-byte form
    assert len(payload) == 8 and decode_request_can(can_id, payload) == request


@given(replies)
def test_reply_round_trips(reply):
    assert decode_reply_serial(reply.to_serial()) == reply
    assert decode_reply_can(*reply.to_can()) == reply


def test_negative_values_are_twos_complement_msb_first():
    frame = TmclRequest(1, 5, 2, 0, -1).to_serial()
    assert frame[4:8] == b'\xff\xff\xff\xff'


@given(requests, st.integers(0, 8), bytes_)
def test_any_corruption_of_a_serial_frame_is_caught(request, position, flip):
    frame = bytearray(request.to_serial())
    if flip == 0:
        return
    frame[position] ^= flip
    with pytest.raises(TmclDecodeError, match='checksum'):
        decode_request_serial(bytes(frame))


@given(st.integers(0, 0x7FF), st.binary(max_size=12))
def test_garbage_never_raises_anything_but_decode_errors(can_id, payload):
    for decode in (decode_request_can, decode_reply_can):
        try:
            decode(can_id, payload)
        except TmclDecodeError:
            pass
    for decode in (decode_request_serial, decode_reply_serial):
        try:
            decode(payload)
        except TmclDecodeError:
            pass


def test_bad_frames_name_the_problem():
    with pytest.raises(TmclDecodeError, match='7 or 8 data bytes, got 3'):
        decode_request_can(0x11, b'\x01\x02\x03')
    good = TmclRequest(0x11, 6, 3, 0, 0).to_can(with_checksum=True)[1]
    with pytest.raises(TmclDecodeError, match='bad checksum'):
        decode_request_can(0x11, good[:7] + bytes([good[7] ^ 1]))
    with pytest.raises(ValueError, match='signed 32-bit'):
        TmclRequest(1, 5, 0, 0, 2 ** 31)
    with pytest.raises(ValueError, match='byte'):
        TmclRequest(256, 5, 0, 0, 0)


@given(st.integers(0, 7), int32, st.integers(0, 255))
def test_process_data_command_round_trips(mode, value, cycle):
    command = MotorCommand(mode, value, cycle)
    assert MotorCommand.decode(command.encode()) == command


@given(int32, int32, int32, st.integers(0, 2 ** 32 - 1), int32, st.integers(0, 7), st.integers(0, 255))
def test_process_data_status_round_trips(position, velocity, current, flags, target, mode, cycle):
    status = MotorStatus(position, velocity, current, flags, target, mode, cycle)
    assembler = StatusAssembler()
    parts = status.encode()
    assert assembler.add(0x11, StatusPart.MOTION, parts[0]) is None
    assert assembler.add(0x11, StatusPart.ELECTRICAL, parts[1]) is None
    assert assembler.add(0x11, StatusPart.SETPOINT, parts[2]) == status


def test_incomplete_samples_are_counted_not_delivered():
    assembler = StatusAssembler()
    parts = MotorStatus(1, 2, 3, 4, 5, 2, 9).encode()
    assert assembler.add(0x12, StatusPart.MOTION, parts[0]) is None
    assert assembler.add(0x12, StatusPart.SETPOINT, parts[2]) is None  # ELECTRICAL was lost
    assert assembler.incomplete == 1
    with pytest.raises(TmclDecodeError, match='has 8 bytes, got 3'):
        assembler.add(0x12, StatusPart.MOTION, b'abc')


def test_process_data_ids_do_not_collide_with_tmcl_ids():
    ids = ProcessDataIds()
    assert ids.command_id(0x11) == 0x211
    assert ids.status_ids(0x14) == (0x194, 0x294, 0x394)
    assert ids.classify(0x211) == ('command', 0x11)
    assert ids.classify(0x292) == ('status', 0x12, StatusPart.ELECTRICAL)
    for tmcl_id in (0x02, 0x11, 0x12, 0x13, 0x14):
        assert ids.classify(tmcl_id) is None
    with pytest.raises(ValueError):
        ids.command_id(0x80)
