"""Composed mode: several nodes in one process and one executor (cheaper on a weak robot PC).

``ros2 run youbot_fdi youbot_sim`` runs the virtual youBot and the driver shim together, which is
also the only way python-can's ``virtual`` bus connects them (it does not cross processes).
"""
import sys

from youbot_fdi.nodes.common import spin_nodes
from youbot_fdi.nodes.driver_shim import DriverShimNode
from youbot_fdi.nodes.virtual_youbot import VirtualYoubotNode


def sim_main(args=None):
    """Virtual youBot + driver shim in one process."""
    return spin_nodes([VirtualYoubotNode, DriverShimNode], args=args)


if __name__ == '__main__':
    sys.exit(sim_main())
