"""``virtual_youbot`` node: simulated TMCM modules of a youBot base on a python-can bus.

``ros2 run youbot_fdi virtual_youbot --ros-args --params-file config/virtual_youbot.yaml``

The modules speak TMCL and the cyclic process data on ``can_interface``/``can_channel`` and run the
dynamic model in real time. Faults are injected while it runs through parameters::

    ros2 param set /virtual_youbot fault_wheel wheel_joint_fr
    ros2 param set /virtual_youbot fault torque_loss      # none clears every fault

python-can's ``virtual`` interface only connects buses of one process: run it composed with the
driver shim (``youbot-fdi sim``) or use ``socketcan`` with a vcan device on Linux.
"""
import sys

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node

from youbot_fdi.errors import ConfigError
from youbot_fdi.model.profile import load_model
from youbot_fdi.nodes.common import declare_settings, spin_nodes
from youbot_fdi.tmcm.transport import open_bus
from youbot_fdi.tmcm.virtual_base import NO_FAULT, VirtualBaseSettings, VirtualYoubot

NODE_NAME = 'virtual_youbot'
RUNTIME_PARAMETERS = ('fault', 'fault_wheel')


class VirtualYoubotNode(Node):
    """Runs a :class:`~youbot_fdi.tmcm.virtual_base.VirtualYoubot` in real time."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        self.settings = declare_settings(self, VirtualBaseSettings, RUNTIME_PARAMETERS)
        model = load_model(self.settings.profile)
        bus = open_bus(self.settings.can_interface, self.settings.can_channel)
        self.base = VirtualYoubot(model, bus, self.settings, owns_bus=True)
        self._fault = (self.settings.fault, self.settings.fault_wheel)
        self.add_on_set_parameters_callback(self.on_set_parameters)
        self.base.start()
        self.get_logger().info(
            f'virtual youBot on {self.settings.can_interface}:{self.settings.can_channel}, modules '
            + ', '.join(f'0x{m:02x}' for m in self.settings.module_ids))

    def on_set_parameters(self, parameters):
        """Accept fault injection at run time; refuse changes that need a restart."""
        fault, wheel = self._fault
        for parameter in parameters:
            if parameter.name == 'fault':
                fault = parameter.value
            elif parameter.name == 'fault_wheel':
                wheel = parameter.value
            elif parameter.name != 'use_sim_time':
                return SetParametersResult(successful=False,
                                           reason=f'{parameter.name} needs a restart')
        try:
            self.base.wheel_index(wheel)
            self.base.clear_faults()
            if fault != NO_FAULT:
                self.base.inject(fault, wheel)
        except (ConfigError, ValueError) as err:
            return SetParametersResult(successful=False, reason=str(err))
        self._fault = (fault, wheel)
        self.get_logger().info(f'fault now: {fault} on {wheel}' if fault != NO_FAULT else 'no fault')
        return SetParametersResult(successful=True)

    def close(self):
        self.base.close()


def main(args=None):
    """Entry point of ``ros2 run youbot_fdi virtual_youbot``."""
    return spin_nodes([VirtualYoubotNode], args=args)


if __name__ == '__main__':
    sys.exit(main())
