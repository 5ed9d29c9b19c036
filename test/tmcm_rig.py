"""Test helpers around :class:`youbot_fdi.tmcm.lockstep.LockstepBase`."""
import uuid

from youbot_fdi.model import load_model
from youbot_fdi.tmcm.lockstep import LockstepBase


def new_channel():
    return f'test-{uuid.uuid4()}'


#: Unit and sign checks compare to within a count of quantisation: no measurement noise.
NOISE_FREE = {'current_noise': 0.0, 'velocity_noise': 0.0}


def make_rig(profile='youbot', **base_settings):
    return LockstepBase(load_model(profile), **{**NOISE_FREE, **base_settings})


def forward_command(model, speed=0.3):
    """Driver-convention wheel speeds [rad/s] for driving forward at ``speed`` [m/s]."""
    kin = model.kinematics
    return kin.to_driver(kin.inverse((speed, 0.0, 0.0)))
