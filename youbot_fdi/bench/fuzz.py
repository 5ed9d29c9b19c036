"""Fuzzing every CAN decoding entry point with generated frames (issue 17).

Frames are random ids and payloads, and mutations of well-formed frames (bit flips, truncation,
extension, another id): the codecs (TMCL requests and replies over CAN and serial, process-data
commands and status parts), the status assembler, the virtual youBot's frame handler and the
driver's receive path. The contract each entry point keeps:

- a malformed frame raises :class:`~youbot_fdi.tmcm.tmcl.TmclDecodeError` (the transport counts
  it as ``malformed``) or is ignored; nothing else escapes;
- a malformed frame changes no motor's state (mode, target, parameters, flags) and no sample.

:func:`fuzz_frames` runs the contract over many frames (the benchmark: 100,000);
:func:`check_frame` over one (the hypothesis test in ``make test``).
"""
from dataclasses import dataclass, field
import uuid

import numpy as np

FRAME_BYTES = 8  # a classic CAN frame's payload limit
ID_BITS = 11
MAX_EXTENSION = 3  # bytes a mutation appends at most


@dataclass
class FuzzReport:
    """Counts of a fuzz run."""

    frames: int = 0
    entry_points: int = 0  # how many decoding entry points each frame went through
    malformed: int = 0  # rejected with TmclDecodeError
    violations: list = field(default_factory=list)  # (entry point, id, payload, what went wrong)

    def describe(self):
        return (f'{self.frames} frames into {self.entry_points} entry points: '
                f'{self.malformed} rejected as malformed, {len(self.violations)} violations')


class FuzzTargets:
    """One virtual youBot and one driver (each on its own virtual bus) to feed frames to."""

    def __init__(self, profile='youbot'):
        import can

        from youbot_fdi.model.profile import load_model
        from youbot_fdi.tmcm.driver import BaseDriver
        from youbot_fdi.tmcm.virtual_base import VirtualYoubot
        model = load_model(profile)
        self._buses = [can.Bus(interface='virtual', channel=f'fuzz-{uuid.uuid4()}')
                       for _ in range(2)]
        self.base = VirtualYoubot(model, self._buses[0])
        self.driver = BaseDriver(model, self._buses[1])

    def valid_frames(self):
        """Well-formed frames of every kind, the seeds of mutations: (id, payload)."""
        from youbot_fdi.tmcm.process_data import MotorCommand, MotorStatus
        from youbot_fdi.tmcm.tmcl import TmclCommand, TmclReply, TmclRequest
        ids, frames = self.base.ids, []
        for module in self.base.settings.module_ids:
            for command in (TmclCommand.ROR, TmclCommand.SAP, TmclCommand.GAP, TmclCommand.MVP):
                frames.append(TmclRequest(module, command, 0, 0, 1000).to_can())
            frames.append(TmclReply(self.driver.settings.host_id, module, 100, TmclCommand.GAP, 5).to_can())
            frames.append((ids.command_id(module), MotorCommand(2, 500, 7).encode()))
            status = MotorStatus(1000, 50, 300, 0, 500, 2, 7, 123)
            frames += list(zip(ids.status_ids(module), status.encode()))
        return [(int(i), bytes(p)) for i, p in frames]

    def state(self):
        """Everything a frame may not change unless it is well formed."""
        base = tuple((m.mode, m.target, tuple(sorted(m.parameters.items())), m.sticky_flags,
                      m.encoder_offset, m.process_data_control) for m in self.base.modules)
        driver = self.driver
        cycles = tuple((cycle, *(a.tobytes() for a in (slot.position, slot.velocity, slot.effort,
                                                      slot.flags)))
                       for cycle, slot in sorted(driver._open.items()))
        latest = driver.sample()
        readings = None if latest is None else tuple(
            a.tobytes() for a in (latest.position, latest.velocity, latest.effort))
        return (base, cycles, readings, driver._flags.tobytes(), tuple(sorted(driver._replies)))

    def close(self):
        self.base.close()
        self.driver.close()
        for bus in self._buses:
            bus.shutdown()


def _entry_points():
    from youbot_fdi.tmcm import process_data, tmcl

    def serial(decode):
        return lambda targets, can_id, data: decode(bytes([can_id & 0xFF]) + data)
    return {
        'tmcl request (CAN)': lambda targets, can_id, data: tmcl.decode_request_can(can_id, data),
        'tmcl reply (CAN)': lambda targets, can_id, data: tmcl.decode_reply_can(can_id, data),
        'tmcl request (serial)': serial(tmcl.decode_request_serial),
        'tmcl reply (serial)': serial(tmcl.decode_reply_serial),
        'process-data command': lambda targets, can_id, data: process_data.MotorCommand.decode(data),
        'status part': lambda targets, can_id, data: process_data.decode_status_part(can_id % 3, data),
        'virtual youBot': lambda targets, can_id, data: targets.base._on_frame(can_id, data, 0.0),
        'driver receive': lambda targets, can_id, data: targets.driver._on_frame(can_id, data, 0.0),
    }


def check_frame(targets, can_id, data, report=None, entry_points=None):
    """Feed one frame to every entry point and check the contract; returns the report."""
    from youbot_fdi.tmcm.tmcl import TmclDecodeError
    report = report if report is not None else FuzzReport()
    entry_points = entry_points or _entry_points()
    report.entry_points = len(entry_points)
    for name, entry in entry_points.items():
        before = targets.state()
        try:
            entry(targets, can_id, data)
        except TmclDecodeError:
            report.malformed += 1
            if targets.state() != before:
                report.violations.append((name, can_id, data.hex(), 'a malformed frame changed state'))
        except Exception as err:  # noqa: BLE001 - exactly what the fuzz looks for
            report.violations.append((name, can_id, data.hex(), f'{type(err).__name__}: {err}'))
    report.frames += 1
    return report


def generated_frames(count, seeds, seed=0):
    """``count`` frames: a third random, two thirds mutations of the ``seeds`` frames."""
    rng = np.random.default_rng(seed)
    ids = np.array([i for i, _ in seeds])
    for k in range(count):
        kind = k % 3
        if kind == 0:
            can_id = int(rng.integers(0, 1 << ID_BITS))
            data = rng.integers(0, 256, int(rng.integers(0, FRAME_BYTES + 1)), dtype=np.uint8).tobytes()
        else:
            can_id, data = seeds[int(rng.integers(len(seeds)))]
            payload = bytearray(data)
            action = int(rng.integers(4))
            if action == 0 and payload:  # flip bits
                for _ in range(int(rng.integers(1, 4))):
                    payload[int(rng.integers(len(payload)))] ^= 1 << int(rng.integers(8))
            elif action == 1:  # truncate
                payload = payload[:int(rng.integers(0, len(payload) + 1))]
            elif action == 2:  # extend (past 8 bytes too: the decoders check lengths themselves)
                payload += rng.integers(0, 256, int(rng.integers(1, MAX_EXTENSION + 1)),
                                        dtype=np.uint8).tobytes()
            else:  # a valid payload on another kind's id
                can_id = int(ids[int(rng.integers(len(ids)))])
            data = bytes(payload)
        yield can_id, data


def fuzz_frames(count, seed=0, progress=None):
    """Run the contract over ``count`` generated frames; returns a :class:`FuzzReport`."""
    targets = FuzzTargets()
    report, entry_points = FuzzReport(), _entry_points()
    try:
        for k, (can_id, data) in enumerate(generated_frames(count, targets.valid_frames(), seed)):
            check_frame(targets, can_id, data, report, entry_points)
            if progress is not None and (k + 1) % 20000 == 0:
                progress(f'  fuzz: {k + 1}/{count} frames')
    finally:
        targets.close()
    return report
