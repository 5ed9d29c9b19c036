"""Composed mode: several nodes in one process and one executor (cheaper on a weak robot PC).

``ros2 run youbot_fdi youbot_sim`` runs the virtual youBot and the driver shim together, which is
also the only way python-can's ``virtual`` bus connects them (it does not cross processes).
``ros2 run youbot_fdi youbot_fdi_suite`` runs the FDI nodes (kinematics bridge, observer,
residual generator, decision) together beside a real driver; ``youbot_fdi_fused`` runs the observer
fused with the residual generator (one node fewer, one message fewer per sample: the weakest PCs).
"""
from functools import partial
import sys

from youbot_fdi.nodes.common import node_module, spin_nodes
from youbot_fdi.nodes.decision import DecisionNode
from youbot_fdi.nodes.driver_shim import DriverShimNode
from youbot_fdi.nodes.kinematics_bridge import KinematicsBridgeNode
from youbot_fdi.nodes.observer import ObserverNode
from youbot_fdi.nodes.residual_generator import ResidualGeneratorNode
from youbot_fdi.nodes.virtual_youbot import VirtualYoubotNode

#: The FDI nodes of each layout, in data-flow order: node factories (``context=`` etc. as kwargs).
LAYOUTS = {
    'separate': (KinematicsBridgeNode, ObserverNode, ResidualGeneratorNode, DecisionNode),
    'fused': (KinematicsBridgeNode, partial(ObserverNode, fused=True), DecisionNode),
}
FDI_NODES = LAYOUTS['separate']


def node_name(factory):
    """The ROS node name a factory's node takes (its module's ``NODE_NAME``)."""
    return sys.modules[node_module(factory)].NODE_NAME


def sim_main(args=None):
    """Virtual youBot + driver shim in one process."""
    return spin_nodes([VirtualYoubotNode, DriverShimNode], args=args, description=sim_main.__doc__)


def fdi_main(args=None):
    """The FDI nodes (kinematics bridge, observer, residual generator, decision) in one process."""
    return spin_nodes(list(LAYOUTS['separate']), args=args, description=fdi_main.__doc__)


def fused_main(args=None):
    """The FDI nodes with the observer fused with the residual generator, in one process."""
    return spin_nodes(list(LAYOUTS['fused']), args=args, description=fused_main.__doc__)


if __name__ == '__main__':
    sys.exit(sim_main())
