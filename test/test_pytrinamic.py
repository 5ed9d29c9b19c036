"""Trinamic's own client (PyTrinamic) against the virtual youBot: what a user tries first.

PyTrinamic's ``CanTmclInterface`` with the one thing its SocketCAN subclass does differently: a
python-can ``virtual`` bus instead of ``socketcan``, with the same receive filter. Optional test
extra; skipped with a message where PyTrinamic is not installed.
"""
import can
import pytest

from tmcm_rig import make_rig
from youbot_fdi.tmcm.parameters import AxisParameter

pytrinamic = pytest.importorskip('pytrinamic', reason='PyTrinamic is not installed (pip install pytrinamic)')
from pytrinamic.connections.can_tmcl_interface import CanTmclInterface  # noqa: E402
from pytrinamic.tmcl import TMCLReplyStatusError  # noqa: E402

HOST_ID = 2
MODULES = {0x11: 'wheel_joint_fl', 0x12: 'wheel_joint_fr', 0x13: 'wheel_joint_bl',
           0x14: 'wheel_joint_br'}
VERSION = '1632V200'
TIMEOUT = 2.0  # [s] PyTrinamic's receive timeout
INVALID_COMMAND = 2  # TMCL status: the virtual module does not know the command


class VirtualCanTmclInterface(CanTmclInterface):
    """``SocketcanTmclInterface`` with a python-can virtual bus."""

    def __init__(self, channel, host_id=HOST_ID, module_id=1, timeout_s=TIMEOUT):
        super().__init__(channel, 1_000_000, host_id, module_id, timeout_s)
        self._connection = can.Bus(interface='virtual', channel=channel)
        self._connection.set_filters([{'can_id': host_id, 'can_mask': 0x7F}])


@pytest.fixture()
def client():
    rig = make_rig()
    interface = VirtualCanTmclInterface(rig.channel)
    yield rig, interface
    interface.close()
    rig.close()


@pytest.mark.parametrize('address', sorted(MODULES))
def test_pytrinamic_reads_sets_stores_and_restores_parameters(client, address):
    rig, tmcl = client
    assert tmcl.get_version_string(module_id=address) == VERSION
    index = int(AxisParameter.MAX_CURRENT)
    default = tmcl.get_axis_parameter(index, 0, module_id=address)
    tmcl.set_axis_parameter(index, 0, 2000, module_id=address)
    assert tmcl.get_axis_parameter(index, 0, module_id=address) == 2000
    tmcl.store_axis_parameter(index, 0, module_id=address)
    tmcl.set_axis_parameter(index, 0, 1500, module_id=address)
    tmcl.restore_axis_parameter(index, 0, module_id=address)
    assert tmcl.get_axis_parameter(index, 0, module_id=address) == 2000
    tmcl.set_axis_parameter(index, 0, default, module_id=address)
    with pytest.raises(TMCLReplyStatusError) as error:
        tmcl.send(99, 0, 0, 0, module_id=address)
    assert error.value.reply.status == INVALID_COMMAND


@pytest.mark.parametrize('address', sorted(MODULES))
def test_pytrinamic_drives_every_module(client, address):
    """ROR, ROL, MST and position moves (MVP relative and absolute) end where they should."""
    rig, tmcl = client
    wheel = MODULES[address]
    velocity = int(AxisParameter.ACTUAL_VELOCITY)
    position = int(AxisParameter.ACTUAL_POSITION)
    tmcl.rotate(0, 1000, module_id=address)
    rig.base.advance(1.0)
    assert tmcl.get_axis_parameter(velocity, 0, module_id=address, signed=True) == pytest.approx(1000, abs=3)
    tmcl.send(2, 0, 0, 500, module_id=address)  # ROL: PyTrinamic has no helper for it
    rig.base.advance(1.0)
    assert tmcl.get_axis_parameter(velocity, 0, module_id=address, signed=True) == pytest.approx(-500, abs=3)
    tmcl.stop(0, module_id=address)
    rig.base.advance(1.0)
    start = tmcl.get_axis_parameter(position, 0, module_id=address, signed=True)
    tmcl.move_by(0, 20000, module_id=address)
    rig.base.advance(3.0)
    reached = tmcl.get_axis_parameter(position, 0, module_id=address, signed=True)
    assert reached == pytest.approx(start + 20000, abs=20)
    assert rig.base.status(wheel).position == reached
    tmcl.move_to(0, start - 5000, module_id=address)
    rig.base.advance(3.0)
    assert tmcl.get_axis_parameter(position, 0, module_id=address, signed=True) == pytest.approx(start - 5000, abs=20)
