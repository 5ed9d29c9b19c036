"""Residual frames for the decision's unit tests: one wheel's torque score, every other residual
zero against unit bounds."""
import numpy as np

from youbot_fdi.fdi.residuals import FAMILIES, ResidualFrame


def torque_frame(model, stamp, torque_score, position_frozen=0, speed=2.0):
    """A :class:`~youbot_fdi.fdi.residuals.ResidualFrame` at ``stamp`` [s] whose first wheel's
    torque residual is ``torque_score`` bounds (every bound 1), its position frozen for
    ``position_frozen`` samples, every wheel turning at ``speed`` [rad/s] under 0.5 N·m."""
    n = len(model.wheel_names)
    values = {f: np.zeros(n) for f in FAMILIES}
    values['torque'] = np.array([torque_score] + [0.0] * (n - 1))
    return ResidualFrame(stamp=stamp, values=values, bounds={f: np.ones(n) for f in FAMILIES},
                         velocity=np.full(n, speed), torque=np.full(n, 0.5), velocity_mode=True,
                         command=np.full(n, 2.0), frozen=np.zeros(n, dtype=int),
                         effort_frozen=np.zeros(n, dtype=int),
                         position_frozen=np.array([position_frozen] + [0] * (n - 1)), silent=np.zeros(n))
