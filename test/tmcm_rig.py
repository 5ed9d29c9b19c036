"""A virtual base and a driver on one private virtual CAN channel, stepped in lockstep."""
from dataclasses import dataclass, replace
import time
import uuid

import can
import numpy as np

from youbot_fdi.model import load_model
from youbot_fdi.tmcm.driver import BaseDriver, DriverSettings
from youbot_fdi.tmcm.virtual_base import VirtualBaseSettings, VirtualYoubot

CYCLE = 0.01  # [s]
SETTLE_TIMEOUT = 2.0  # [s] wall time for frames to cross the virtual bus


def new_channel():
    return f'test-{uuid.uuid4()}'


@dataclass
class Rig:
    model: object
    base: VirtualYoubot
    driver: BaseDriver
    channel: str

    def settle(self):
        """Wait until every frame sent either way has been handled."""
        deadline = time.monotonic() + SETTLE_TIMEOUT
        while time.monotonic() < deadline:
            base, _ = self.base.transport.snapshot()
            drv, _ = self.driver.transport.snapshot()
            if (base.get('received', 0) + base.get('ignored', 0) >= drv.get('sent', 0)
                    and drv.get('received', 0) >= base.get('sent', 0)):
                return
            time.sleep(0.0005)
        raise TimeoutError('frames did not cross the virtual bus in time')

    def run(self, seconds, kind=None, command=None):
        """Run ``seconds`` of lockstep cycles, re-sending ``command`` each cycle (if given)."""
        for _ in range(int(round(seconds / CYCLE))):
            if command is not None:
                self.driver.set_command(kind, command)
            self.driver.cycle()
            self.settle()
            self.base.advance(CYCLE)
        self.driver.cycle()
        self.settle()
        return self.driver.sample()

    def close(self):
        self.driver.close()
        self.base.close()


def make_rig(profile='youbot', **base_settings):
    channel = new_channel()
    model = load_model(profile)
    settings = replace(VirtualBaseSettings(), can_channel=channel, **base_settings)
    base = VirtualYoubot(model, can.Bus(interface='virtual', channel=channel), settings,
                         owns_bus=True)
    driver = BaseDriver(model, can.Bus(interface='virtual', channel=channel),
                        replace(DriverSettings(), can_channel=channel, cycle_rate=1 / CYCLE),
                        clock=lambda: base.time, owns_bus=True)
    return Rig(model, base, driver, channel)


def forward_command(model, speed=0.3):
    """Driver-convention wheel speeds [rad/s] for driving forward at ``speed`` [m/s]."""
    kin = model.kinematics
    return kin.to_driver(kin.inverse((speed, 0.0, 0.0)))


__all__ = ['CYCLE', 'forward_command', 'make_rig', 'new_channel', 'np', 'Rig']
