"""Wheel-speed allocation when wheels can no longer be relied on: the others carry the base.

Kinematic convention throughout (:class:`~youbot_fdi.model.kinematics.Kinematics`): wheel speeds
``w = J t`` for a base twist ``t = (v_x [m/s], v_y [m/s], w_z [rad/s])``, and the base twist that
odometry sees is ``F w`` with ``F`` the least-squares inverse of ``J``. With the wheels ``lost``
(unpowered, dragging, blocked), the healthy wheels ``h`` are solved for so that the twist of all
wheels (the lost ones at their measured speeds) is the set-point:

    F_h w_h = t* - F_l w_l        (minimum-norm w_h when more than three wheels are healthy)

A wheel that rolls freely (w_l = J_l t*) gives w_h = J_h t*; one that drags gets the others to make
up for it. The healthy wheels must determine the twist on their own (rank of ``J_h`` = 3): a
layout that loses rank is refused (:class:`AllocationError`), for any number of wheels.
"""
from dataclasses import dataclass

import numpy as np

from youbot_fdi.errors import FdiError
from youbot_fdi.model.kinematics import determines_twist

TWIST_DOF = 3  # v_x, v_y, w_z


class AllocationError(FdiError):
    """The healthy wheels cannot determine the base twist."""


@dataclass(frozen=True)
class Allocation:
    """Healthy-wheel speeds for the base twist, with the wheels in ``lost`` not relied on."""

    jacobian: np.ndarray  # (n, 3)
    lost: tuple  # wheel indices
    healthy: tuple
    solve: np.ndarray  # (len(healthy), 3): w_h = solve @ (t* - F_l w_l)
    forward_lost: np.ndarray  # (3, len(lost)): F_l
    estimate_lost: np.ndarray  # (len(lost), len(healthy)): w_l = J_l pinv(J_h) w_h

    @classmethod
    def for_lost(cls, jacobian, lost, wheel_names=None):
        """The allocation of ``jacobian`` (n, 3) without the wheels ``lost`` (indices);
        AllocationError naming them when the others lose rank."""
        jacobian = np.asarray(jacobian, dtype=float)
        n = len(jacobian)
        lost = tuple(sorted(set(int(k) for k in lost)))
        healthy = tuple(k for k in range(n) if k not in lost)
        names = wheel_names or [str(k) for k in range(n)]
        rows = jacobian[list(healthy)]
        if not determines_twist(rows):
            msg = (f'without {", ".join(names[k] for k in lost)} the other wheels do not determine '
                   f'the base twist (rank < {TWIST_DOF}): no degraded driving')
            raise AllocationError(msg)
        forward = np.linalg.pinv(jacobian)
        return cls(jacobian, lost, healthy, np.linalg.pinv(forward[:, list(healthy)]),
                   forward[:, list(lost)], jacobian[list(lost)] @ np.linalg.pinv(rows))

    def wheel_speeds(self, twist, lost_speeds=None):
        """Wheel speeds (n,) [rad/s]: the healthy ones solved for ``twist`` (3,) given the lost
        wheels' measured speeds ``lost_speeds`` (len(lost),; default: rolling freely, J_l t*);
        the lost ones at their rolling speed J_l t* (what they would turn at anyway)."""
        twist = np.asarray(twist, dtype=float)
        rolling = self.jacobian @ twist
        speeds = rolling.copy()
        if not self.lost:
            return speeds
        measured = rolling[list(self.lost)] if lost_speeds is None else np.asarray(lost_speeds, float)
        speeds[list(self.healthy)] = self.solve @ (twist - self.forward_lost @ measured)
        return speeds


    def substitute(self, speeds):
        """Wheel speeds (n,) (or increments) with the lost wheels' values replaced by their
        estimate from the others: the least-squares twist of the others mapped back through the
        Jacobian (a frozen encoder's reading for odometry and control)."""
        speeds = np.asarray(speeds, dtype=float).copy()
        if self.lost:
            speeds[list(self.lost)] = self.estimate_lost @ speeds[list(self.healthy)]
        return speeds


def substitute_readings(jacobian, speeds, replaced):
    """:meth:`Allocation.substitute` of the wheels ``replaced`` (indices) in one call;
    AllocationError when the others lose rank."""
    return Allocation.for_lost(jacobian, replaced).substitute(speeds)
