"""A virtual base and a driver on a private in-process virtual CAN channel, stepped in lockstep.

Deterministic: every cycle the driver sends its commands, both sides handle every frame, the
driver closes the cycle (a module that did not answer gets NaN), then the base simulates one cycle. Used to make recordings, by the benchmark and by the tests.
"""
from dataclasses import replace
import time
import uuid

import can

from youbot_fdi.tmcm.driver import BaseDriver, DriverSettings
from youbot_fdi.tmcm.virtual_base import VirtualBaseSettings, VirtualYoubot

SETTLE_TIMEOUT = 2.0  # wall time for frames to cross the virtual bus [s]


class LockstepBase:
    """:class:`VirtualYoubot` + :class:`BaseDriver` on one private virtual channel.

    Parameters
    ----------
    model : PlatformModel
    cycle : float
        Process-data cycle [s].
    base_settings : dict
        Overrides of :class:`VirtualBaseSettings` fields (noise, fault magnitudes, ...).
    """

    def __init__(self, model, cycle=0.01, **base_settings):
        self.model = model
        self.cycle_time = cycle
        self.channel = f'lockstep-{uuid.uuid4()}'
        settings = replace(VirtualBaseSettings(), can_channel=self.channel, **base_settings)
        self.base = VirtualYoubot(model, can.Bus(interface='virtual', channel=self.channel),
                                  settings, owns_bus=True)
        self.driver = BaseDriver(model, can.Bus(interface='virtual', channel=self.channel),
                                 replace(DriverSettings(), can_channel=self.channel,
                                         cycle_rate=1.0 / cycle),
                                 clock=lambda: self.base.time, owns_bus=True)

    def settle(self):
        """Wait until every frame sent either way has been handled: its handler has returned
        (a frame counted as received may still be in its handler, in the bus's receive thread,
        and its reply not yet sent)."""
        deadline = time.monotonic() + SETTLE_TIMEOUT
        while time.monotonic() < deadline:
            base, _ = self.base.transport.snapshot()
            drv, _ = self.driver.transport.snapshot()
            if (base.get('handled', 0) + base.get('ignored', 0) >= drv.get('sent', 0)
                    and drv.get('handled', 0) >= base.get('sent', 0)):
                return
            time.sleep(0)
        raise TimeoutError('frames did not cross the virtual bus in time')

    def step(self, kind=None, command=None):
        """One cycle: (optionally) command, exchange frames, simulate; returns the driver's sample."""
        if command is not None:
            self.driver.set_command(kind, command)
        self.driver.cycle()
        self.settle()
        self.driver.close_cycles()  # every answer is in: a silent module gets NaN this cycle
        self.base.advance(self.cycle_time)
        return self.driver.sample()

    def run(self, seconds, kind=None, command=None):
        """``seconds`` of cycles with the same command; returns the sample after a final exchange."""
        for _ in range(int(round(seconds / self.cycle_time))):
            self.step(kind, command)
        self.driver.cycle()
        self.settle()
        self.driver.close_cycles()
        return self.driver.sample()

    def close(self):
        self.driver.close()
        self.base.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
