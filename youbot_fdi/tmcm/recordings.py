"""Make rosbag2 recordings of simulated drives, with or without an injected fault.

The drive goes the whole way a robot's would: wheel commands -> driver shim core -> CAN process
data -> virtual TMCM modules on the dynamic model -> status frames -> /joint_states, so the
recording carries the shim's quantisation (ticks, rpm, mA), delays and sign conventions.
"""
from dataclasses import dataclass
import math

import numpy as np

from youbot_fdi.bag.writer import RecordingWriter
from youbot_fdi.faults import FaultKind
from youbot_fdi.tmcm.lockstep import LockstepBase

#: Recordings start at this wall-clock-like stamp [s] so stamps look like a robot's.
DEFAULT_START_STAMP = 1_700_000_000.0


@dataclass(frozen=True)
class GroundTruth:
    """What was injected in a simulated recording."""

    path: str
    mode: str  # 'velocity' or 'effort'
    duration: float  # [s]
    fault: object  # FaultKind or None
    wheel: object  # joint name or None
    onset: float  # header stamp of the injection [s] (nan without a fault)


def effort_for(model, wheel_speed):
    """Open-loop efforts [N·m] that hold ``wheel_speed`` [rad/s] against viscous friction."""
    friction = np.array(model.dynamics.parameters.viscous_friction)
    return friction * np.asarray(wheel_speed)


def record_drive(path, model, script, mode='velocity', fault=None, wheel=None, fault_time=None,
                 storage='sqlite3', cycle=0.01, start_stamp=DEFAULT_START_STAMP, more_faults=(),
                 **base_settings):
    """Drive ``script`` on a virtual base and record it.

    Parameters
    ----------
    path : str or Path
        The new recording directory.
    model : PlatformModel
    script : DriveScript
    mode : str
        ``velocity`` (wheel speeds commanded) or ``effort`` (open-loop wheel torques).
    fault, wheel, fault_time : optional
        A FaultKind to inject on ``wheel`` at ``fault_time`` seconds into the drive.
    more_faults : sequence of (fault, wheel, fault_time)
        Further faults, injected likewise (a fault of None clears every injected fault); not in
        the returned ground truth.
    base_settings
        Overrides of the virtual base's settings (noise, fault magnitudes, ...).

    Returns
    -------
    GroundTruth
    """
    kin = model.kinematics
    names = model.wheel_names
    onset = math.nan
    steps = int(round(script.duration / cycle))
    times = np.arange(steps) * cycle
    twists = script.twists(times)
    pending = sorted(more_faults, key=lambda f: f[2])
    with LockstepBase(model, cycle, **base_settings) as rig, \
            RecordingWriter(path, names, storage) as writer:
        for k in range(steps):
            target = kin.inverse(twists[k])
            command = kin.to_driver(target if mode == 'velocity' else effort_for(model, target))
            if fault is not None and math.isnan(onset) and times[k] >= fault_time:
                rig.base.inject(fault, wheel)
                onset = start_stamp + rig.base.time
            while pending and times[k] >= pending[0][2]:
                kind, faulty, _ = pending.pop(0)
                if kind is None:
                    rig.base.clear_faults()
                else:
                    rig.base.inject(kind, faulty)
            writer.wheel_command(start_stamp + rig.base.time, mode, command)
            sample = rig.step(mode, command)
            if sample is not None:
                writer.joint_state(start_stamp + sample.stamp, sample.position, sample.velocity,
                                   sample.effort)
    return GroundTruth(str(path), mode, script.duration, FaultKind(fault) if fault else None,
                       wheel, onset)
