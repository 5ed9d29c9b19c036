"""Lagrangian wheel dynamics ``M*theta_ddot + D*theta_dot (+ Coulomb) = tau`` and its exact discretisation.

Derivation (report §3.2, generalised to any wheel layout): with the base twist written as the
least-squares function of the wheel speeds, ``V_O = F*theta_dot`` (F the forward-kinematics matrix),
the kinetic energy

    K = 1/2 * V_O^T diag(m, m, J_z) V_O + 1/2 * theta_dot^T diag(J_w) theta_dot

gives, through Lagrange's equation with the Rayleigh dissipation ``1/2 * theta_dot^T D theta_dot``,

    M = F^T diag(m, m, J_z) F + diag(J_w).

For the youBot this is the report's closed form with ``A = m R^2 / 8``, ``B = J_z R^2 / (16 (l+L)^2)``.
The state space is eq. 3.22: ``x = [theta; theta_dot]``, ``A = [[0, I], [0, -M^-1 D]]``,
``B = [[0], [M^-1]]``.

With the report's inertias (J_w = 1.35 kg·mm², J_z = 5.5 kg·mm²) M has a condition number of about
1e4 and two modes of about 40 µs; forward Euler at any practical step explodes. This module
discretises exactly: zero-order hold through the matrix exponential, valid for any step.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
import functools

import numpy as np
import scipy.linalg

from youbot_fdi.errors import ModelError

#: Explicitly held Coulomb friction is stable while dt * (F_c / v_scale) / lambda_min(M) stays below this.
COULOMB_STABILITY_LIMIT = 1.0
#: |cos(roller angle)| below this: the rollers run across the rolling direction (an omni wheel;
#: cos 90° is 6e-17 in floating point) and the motor feels none of their drag.
ACROSS_ROLLING = 1e-12


@dataclass(frozen=True)
class DynamicParameters:
    """Physical parameters of the base; per-wheel arrays follow the platform's wheel order."""

    mass: float  # m [kg]
    yaw_inertia: float  # J_z [kg·m²], base about its vertical axis
    wheel_inertia: tuple  # J_w [kg·m²] per wheel, including the rotor reflected through the gear
    viscous_friction: tuple  # D [N·m·s/rad] per wheel
    coulomb_friction: tuple  # F_c [N·m] per wheel
    coulomb_velocity_scale: float  # v_s [rad/s]: tanh smoothing width of the Coulomb term
    #: k [-]: the ratio of the contact's friction along the rollers to that along the rolling
    #: direction (the contact law, :meth:`WheelDynamics.coulomb_torque`); 0: per-wheel Coulomb
    #: friction (the report's model)
    roller_friction_ratio: float = 0.0
    #: D_r [N·m]: the torque each motor feels from its rollers' resistance to turning while the
    #: contact glides along them (:meth:`WheelDynamics.roller_drag_torque`); 0: none
    roller_drag: float = 0.0
    #: (m [kg], J_z [kg·m²], J_w [kg·m²]): the inertias the firmware's velocity loop moves where
    #: they are not these (``identify``: the prior's, where the torque readings come too seldom to
    #: see the wheels accelerate and the fitted inertias only relate those readings to the
    #: speeds); empty: the ones above
    loop_inertias: tuple = ()


def rolling_share(speed, slide, ratio):
    """The share [0, 1] of a contact's Coulomb friction the wheel's motor feels, ``|w| / sqrt(w² +
    (k u)²)``, for wheel speeds ``speed`` and roller slides ``slide`` [wheel rad/s] (same shape)
    and the roller friction ratio k; 0 where the contact stands."""
    speed = np.abs(speed)
    norm = np.sqrt(speed ** 2 + (ratio * np.asarray(slide, dtype=float)) ** 2)
    return np.divide(speed, norm, out=np.zeros_like(norm), where=norm > 0.0)


def mass_matrix(forward_matrix, mass, yaw_inertia, wheel_inertia):
    """Mass matrix M [kg·m²] of the wheel coordinates.

    Parameters
    ----------
    forward_matrix : array_like, shape (3, n)
        Forward kinematics F (base twist per wheel speed).
    mass : float
        Base mass m [kg].
    yaw_inertia : float
        J_z [kg·m²].
    wheel_inertia : array_like, shape (n,)
        J_w per wheel [kg·m²].

    Returns
    -------
    ndarray, shape (n, n)
        Symmetric positive definite M.
    """
    forward = np.asarray(forward_matrix, dtype=float)
    body_inertia = np.diag([mass, mass, yaw_inertia])
    return forward.T @ body_inertia @ forward + np.diag(np.asarray(wheel_inertia, dtype=float))


def zoh_discretize(a_matrix, b_matrix, dt):
    """Exact zero-order-hold discretisation ``(A_d, B_d)`` of ``x_dot = A x + B u`` over ``dt`` [s].

    Uses the matrix exponential of the augmented matrix ``[[A, B], [0, 0]] * dt`` (scipy's
    scaling-and-squaring ``expm``), which is exact for stiff systems at any step.

    Returns
    -------
    a_d : ndarray, shape (n, n)
    b_d : ndarray, shape (n, p)
    """
    a_matrix = np.asarray(a_matrix, dtype=float)
    b_matrix = np.asarray(b_matrix, dtype=float)
    n, p = b_matrix.shape
    if a_matrix.shape != (n, n):
        msg = f'A must have shape ({n}, {n}) to match B {b_matrix.shape}, got {a_matrix.shape}'
        raise ValueError(msg)
    if not (dt > 0.0 and np.isfinite(dt)):
        msg = f'dt must be a finite step > 0 s, got {dt!r}'
        raise ValueError(msg)
    augmented = np.zeros((n + p, n + p))
    augmented[:n, :n] = a_matrix
    augmented[:n, n:] = b_matrix
    transition = scipy.linalg.expm(augmented * dt)
    return transition[:n, :n], transition[:n, n:]


class WheelDynamics:
    """Continuous-time wheel dynamics of a platform.

    Parameters
    ----------
    kinematics : Kinematics
        Supplies the forward-kinematics matrix and the number of wheels.
    parameters : DynamicParameters
    """

    def __init__(self, kinematics, parameters):
        self.kinematics = kinematics
        self.parameters = parameters
        n = kinematics.n_wheels
        self.n_wheels = n
        self.mass_matrix = mass_matrix(kinematics.forward_matrix, parameters.mass,
                                       parameters.yaw_inertia, parameters.wheel_inertia)
        self.friction_matrix = np.diag(np.asarray(parameters.viscous_friction, dtype=float))
        self.coulomb = np.asarray(parameters.coulomb_friction, dtype=float)
        self.mass_inverse = np.linalg.inv(self.mass_matrix)
        #: the contact law is on (``roller_friction_ratio`` > 0)
        self.contact_law = parameters.roller_friction_ratio > 0.0
        #: each wheel's share (n,) of its rollers' resistance the motor feels, -cos(roller angle):
        #: none for an omni wheel (rollers across the rolling direction), 0.71 in size for a
        #: mecanum one
        self.drag_projection = -np.cos([wheel.roller_angle for wheel in kinematics.platform.wheels])
        #: the size of that share (n,) [-], 0 where the rollers run across (an omni wheel)
        self.drag_share = np.where(np.abs(self.drag_projection) > ACROSS_ROLLING,
                                   np.abs(self.drag_projection), 0.0)
        #: the rollers' drag acts (``roller_drag`` > 0 on wheels whose motors feel it)
        self.has_drag = parameters.roller_drag > 0.0 and bool(self.drag_share.any())

    @functools.cached_property
    def loop(self) -> WheelDynamics:
        """The dynamics the firmware's velocity loop moves: these, with the parameters'
        ``loop_inertias`` where given."""
        inertias = self.parameters.loop_inertias
        if not inertias:
            return self
        mass, yaw_inertia, wheel_inertia = inertias
        return WheelDynamics(self.kinematics, replace(
            self.parameters, mass=mass, yaw_inertia=yaw_inertia,
            wheel_inertia=(wheel_inertia,) * self.n_wheels, loop_inertias=()))

    def state_space(self, friction_matrix=None):
        """Continuous state space of eq. 3.22.

        Returns
        -------
        a_matrix : ndarray, shape (2n, 2n)
        b_matrix : ndarray, shape (2n, n)
            Input: wheel torques [N·m]; state ``[theta [rad]; theta_dot [rad/s]]``.
        """
        n = self.n_wheels
        friction = self.friction_matrix if friction_matrix is None else friction_matrix
        a_matrix = np.zeros((2 * n, 2 * n))
        a_matrix[:n, n:] = np.eye(n)
        a_matrix[n:, n:] = -self.mass_inverse @ friction
        b_matrix = np.vstack([np.zeros((n, n)), self.mass_inverse])
        return a_matrix, b_matrix

    def coulomb_torque(self, velocity):
        """Smoothed Coulomb friction torque [N·m] opposing ``velocity`` [rad/s], shape (..., n)::

            F_c tanh(w / v_s) |w| / sqrt(w² + (k u)²)

        with u the contact point's slide along the rollers [wheel rad/s]
        (:meth:`~youbot_fdi.model.kinematics.Kinematics.roller_slide`) and k
        ``roller_friction_ratio``. With k = 0 it is per-wheel Coulomb friction (the report's model).
        With k > 0 it is the contact law of omni and mecanum wheels on a real floor: Coulomb
        friction at the contact point with an elliptic limit (maximum dissipation), k the ratio of
        the friction along the rollers to that along the rolling direction; the motor feels the
        rolling component, which depends on the direction the contact moves, not on the wheel's
        speed alone. A wheel turning slowly while its contact slides sideways needs only part of
        its Coulomb torque (the Robotino's currents follow this at every speed; docs/fdi.md).
        """
        felt = self.contact_share(velocity, self.coulomb_level(velocity))
        return felt + self.roller_drag_torque(velocity) if self.has_drag else felt

    def roller_drag_torque(self, velocity):
        """The torque [N·m] (..., n) the motors feel from the rollers' resistance to turning at
        wheel speeds ``velocity`` [rad/s]::

            -D_r cos(gamma) tanh(u / v_s)

        u the contact's slide along its rollers (:meth:`Kinematics.roller_slide`), gamma the
        roller angle, D_r ``roller_drag``. The floor holds a gliding roller back along its free
        direction; a mecanum roller's free direction has a part along the wheel's rolling
        direction, and the force there turns the wheel (it helps or brakes the motor with the
        direction the base moves, not with the wheel's own speed). It grows with the floor and
        the load, as the other contact friction does. 0 for an omni wheel."""
        velocity = np.asarray(velocity, dtype=float)
        if not self.has_drag:
            return np.zeros_like(velocity)
        return self.parameters.roller_drag * self.roller_drag_shape(velocity)

    def roller_drag_shape(self, velocity):
        """:meth:`roller_drag_torque` per unit ``roller_drag`` [-] (..., n), ``-cos(gamma)
        tanh(u / v_s)`` at wheel speeds ``velocity`` [rad/s], whatever ``roller_drag`` is
        (identify fits D_r on it)."""
        slide = self.kinematics.roller_slide(np.asarray(velocity, dtype=float))
        return self.drag_projection * np.tanh(slide / self.parameters.coulomb_velocity_scale)

    def coulomb_level(self, velocity):
        """The wheels' Coulomb friction torque as if their contacts only rolled, ``F_c tanh(w /
        v_s)`` [N·m], shape (..., n): :meth:`coulomb_torque` without the contact law."""
        return self.coulomb * np.tanh(np.asarray(velocity, dtype=float) / self.parameters.coulomb_velocity_scale)

    def coulomb_span(self, velocity, uncertainty):
        """How much [N·m] (..., n) the wheels' Coulomb friction may change without a fault at
        speeds read as ``velocity`` [rad/s] to within ``uncertainty`` [rad/s] (scalar or
        broadcast): ``F_c (tanh((|w| + d) / v_s) - tanh((|w| - d) / v_s))`` over the speeds the
        wheel may have, at least the tanh's own error ``F_c (1 - tanh(|w| / v_s))``, and ``2 F_c``
        where one of them is standing (``|w| <= d``).

        Why: the tanh is a model of a discontinuity. A standing wheel holds whatever the others
        and the floor ask of it up to its static friction, either way; one turning slower than
        the model's Coulomb step ``v_s`` is resolved meets friction anywhere between the levels
        of the speeds it may have (stick-slip, the Stribeck dip): there its friction changes
        with no change of the operating point the reading shows. And however exact the reading,
        a turning wheel meets the step's level ``F_c``, where the model says ``F_c tanh(|w| /
        v_s)``: the smoothing is the model's, not the wheel's (randomized plants whose readings
        showed no noise, ``speed_sigma`` 0, had a wheel creeping through zero at 0.02-0.04 rad/s
        alarm ``stuck`` on the torque shift, with no span allowed for it)."""
        speed = np.abs(np.asarray(velocity, dtype=float))
        scale = self.parameters.coulomb_velocity_scale
        within = np.tanh((speed + uncertainty) / scale) - np.tanh((speed - uncertainty) / scale)
        smoothing = 1.0 - np.tanh(speed / scale)  # the tanh against the step it stands for
        return self.coulomb * np.where(speed <= uncertainty, 2.0, np.maximum(within, smoothing))

    def contact_share(self, velocity, level):
        """The part of the Coulomb ``level`` (:meth:`coulomb_level` at ``velocity``) the motors
        feel under the contact law [N·m], shape (..., n); ``level`` itself without it."""
        if not self.contact_law:
            return level
        return level * self.rolling_shares(velocity)

    def rolling_shares(self, velocity):
        """The share [0, 1] of each wheel's Coulomb level its motor feels at wheel speeds
        ``velocity`` [rad/s], shape (..., n): :func:`rolling_share` of the contact law (all ones
        without it)."""
        velocity = np.asarray(velocity, dtype=float)
        if not self.contact_law:
            return np.ones_like(velocity)
        return rolling_share(velocity, self.kinematics.roller_slide(velocity),
                             self.parameters.roller_friction_ratio)

    def acceleration(self, velocity, torque):
        """Wheel accelerations [rad/s²] for wheel speeds [rad/s] and torques [N·m], shape (..., n)."""
        velocity = np.asarray(velocity, dtype=float)
        net = (np.asarray(torque, dtype=float) - velocity @ self.friction_matrix.T
               - self.coulomb_torque(velocity))
        return net @ self.mass_inverse.T

    def time_constants(self):
        """Time constants [s] of the free (torque-less, viscous) wheel-speed modes, ascending.

        The rates are the generalised eigenvalues of ``D v = lambda M v``. A mode with no
        friction has an infinite time constant.
        """
        rates = scipy.linalg.eigh(self.friction_matrix, self.mass_matrix, eigvals_only=True)
        with np.errstate(divide='ignore'):
            return np.sort(np.where(rates > 0.0, 1.0 / np.maximum(rates, 1e-300), np.inf))

    def discretize(self, dt):
        """The exactly discretised model for a fixed step ``dt`` [s]."""
        return DiscreteWheelModel(self, dt)


class DiscreteWheelModel:
    """Zero-order-hold wheel dynamics for a fixed step; the torque is held over each step.

    Coulomb friction, if any, is evaluated at the start of the step and held with the torque.
    That is stable only while the step is short against the smoothed Coulomb slope; a step
    where it is not raises :class:`ModelError` rather than diverging.
    """

    def __init__(self, dynamics, dt):
        self.dynamics = dynamics
        self.dt = float(dt)
        n = dynamics.n_wheels
        a_matrix, b_matrix = dynamics.state_space()
        self.a_d, self.b_d = zoh_discretize(a_matrix, b_matrix, self.dt)
        self.n_wheels = n
        # the rollers' drag is held the same way; a roller slides at most about as fast as its
        # wheel turns (Kinematics.roller_slide), so its slope adds at most D_r / v_s
        drag = dynamics.parameters.roller_drag if dynamics.has_drag else 0.0
        coulomb_slope = ((np.max(dynamics.coulomb, initial=0.0) + drag)
                         / dynamics.parameters.coulomb_velocity_scale)
        smallest_inertia = np.linalg.eigvalsh(dynamics.mass_matrix)[0]
        if self.dt * coulomb_slope / smallest_inertia > COULOMB_STABILITY_LIMIT:
            msg = (f'Coulomb friction {np.max(dynamics.coulomb):g} N·m over a smoothing width of '
                   f'{dynamics.parameters.coulomb_velocity_scale:g} rad/s is too stiff to hold over '
                   f'dt = {self.dt:g} s with a smallest inertia of {smallest_inertia:.3g} kg·m²; '
                   'use a shorter step, a wider coulomb_velocity_scale or no Coulomb term')
            raise ModelError(msg)

    def step(self, position, velocity, torque):
        """Advance one step.

        Parameters
        ----------
        position, velocity : ndarray, shape (n,)
            Wheel angles [rad] and speeds [rad/s] at the start of the step.
        torque : ndarray, shape (n,)
            Wheel torques [N·m] held over the step.

        Returns
        -------
        position, velocity : ndarray, shape (n,)
            At the end of the step.
        """
        n = self.n_wheels
        net_torque = np.asarray(torque, dtype=float) - self.dynamics.coulomb_torque(velocity)
        state = self.a_d @ np.concatenate([position, velocity]) + self.b_d @ net_torque
        return state[:n], state[n:]
