"""A small CAN transport over python-can: send frames, hand received frames to one handler, count.

The transport depends on ``can.BusABC`` only: tests pass a ``virtual`` bus, robots ``socketcan``
(or any python-can interface). Nothing that arrives on the bus can raise into python-can's
receive thread: decoding errors and handler failures are counted and reported, never fatal.
"""
import collections
import logging
import threading

import can

from youbot_fdi.errors import ConfigError, FdiError
from youbot_fdi.tmcm.tmcl import TmclDecodeError

LOG = logging.getLogger(__name__)
#: How long the receive thread blocks before checking for shutdown [s].
NOTIFIER_TIMEOUT = 0.05
#: Interfaces that send frames off this machine by multicast: never used.
FORBIDDEN_INTERFACES = ('udp_multicast',)


class TransportError(FdiError):
    """The bus cannot be opened or used."""


def open_bus(interface, channel, **options):
    """Open a python-can bus, e.g. ``open_bus('virtual', 'youbot')`` or ``('socketcan', 'can0')``."""
    if interface in FORBIDDEN_INTERFACES:
        msg = f'CAN interface {interface!r} multicasts off this machine; use virtual or socketcan'
        raise ConfigError(msg)
    try:
        return can.Bus(interface=interface, channel=channel, **options)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as err:
        msg = f'cannot open CAN interface {interface!r} channel {channel!r}: {err}'
        raise TransportError(msg) from err


class CanTransport:
    """Sends frames and dispatches received ones to ``handler(arbitration_id, data, timestamp)``.

    Attributes
    ----------
    counters : collections.Counter
        ``sent``, ``received``, ``handled`` (received frames the handler has finished with,
        whatever the outcome), ``send_errors``, ``error_frames``, ``malformed`` (a
        :class:`TmclDecodeError` from the handler), ``ignored`` (extended/remote frames),
        ``handler_errors``.
    """

    def __init__(self, bus, handler, owns_bus=False):
        self.bus = bus
        self.handler = handler
        self.owns_bus = owns_bus
        self.counters = collections.Counter()
        self.last_error = ''
        self._lock = threading.Lock()
        self._closed = False
        self._notifier = can.Notifier(bus, [self._on_message], timeout=NOTIFIER_TIMEOUT)

    def _count(self, key, error=''):
        with self._lock:
            self.counters[key] += 1
            if error:
                self.last_error = error

    def _on_message(self, message):
        if message.is_error_frame:
            self._count('error_frames', 'error frame on the bus')
            return
        if message.is_extended_id or message.is_remote_frame:
            self._count('ignored')
            return
        self._count('received')
        try:
            self.handler(message.arbitration_id, bytes(message.data), message.timestamp)
        except TmclDecodeError as err:
            self._count('malformed', f'id 0x{message.arbitration_id:03X}: {err}')
        except Exception as err:  # noqa: BLE001 - the receive thread must survive anything
            LOG.exception('CAN frame handler failed')
            self._count('handler_errors', f'handler failed on id 0x{message.arbitration_id:03X}: {err}')
        finally:
            self._count('handled')

    def send(self, arbitration_id, data):
        """Send one standard frame; returns False (and counts) instead of raising on bus errors."""
        if self._closed:
            return False
        try:
            self.bus.send(can.Message(arbitration_id=arbitration_id, data=bytes(data),
                                      is_extended_id=False, check=True))
        except (can.CanError, ValueError, OSError) as err:
            self._count('send_errors', f'send on id 0x{arbitration_id:03X} failed: {err}')
            return False
        self._count('sent')
        return True

    def snapshot(self):
        """A copy of the counters and the last error message."""
        with self._lock:
            return dict(self.counters), self.last_error

    def close(self):
        """Stop receiving; shut the bus down if this transport owns it. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._notifier.stop()
        if self.owns_bus:
            self.bus.shutdown()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
