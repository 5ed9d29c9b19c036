"""Composed mode: several nodes in one process and one executor (cheaper on a weak robot PC).

``ros2 run youbot_fdi youbot_sim`` runs the virtual youBot and the driver shim together, which is
also the only way python-can's ``virtual`` bus connects them (it does not cross processes).
``ros2 run youbot_fdi youbot_fdi_suite`` runs the FDI nodes together beside a real driver.
"""
import sys

from youbot_fdi.nodes.common import spin_nodes
from youbot_fdi.nodes.decision import DecisionNode
from youbot_fdi.nodes.driver_shim import DriverShimNode
from youbot_fdi.nodes.kinematics_bridge import KinematicsBridgeNode
from youbot_fdi.nodes.observer import ObserverNode
from youbot_fdi.nodes.virtual_youbot import VirtualYoubotNode

FDI_NODES = (KinematicsBridgeNode, ObserverNode, DecisionNode)


def sim_main(args=None):
    """Virtual youBot + driver shim in one process."""
    return spin_nodes([VirtualYoubotNode, DriverShimNode], args=args)


def fdi_main(args=None):
    """The FDI suite (kinematics bridge, observer, decision) in one process, beside a driver."""
    return spin_nodes(list(FDI_NODES), args=args)


if __name__ == '__main__':
    sys.exit(sim_main())
