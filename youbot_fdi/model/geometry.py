"""Platform geometry: where the wheels are and how each one rolls.

Frames follow REP-103: base frame x forward, y left, z up; yaw counter-clockwise positive.

A wheel is described by

- its contact point ``(x, y)`` [m] in the base frame,
- its ``heading`` [rad]: the direction its rim travels when the wheel turns positively
  (kinematic convention), measured from the base x axis,
- its ``roller_angle`` [rad]: the direction, measured from the heading, in which the free rollers
  let the contact point slide. Mecanum wheels use ±45°, plain omni wheels 90°,
- its ``radius`` [m],
- its ``drive_sign`` (±1): the sign between the kinematic convention (report eq. 3.8: all wheels
  positive when the base drives forward) and the driver convention that the motor controllers and
  every ROS topic carry. The youBot's left wheels are mounted mirrored, so theirs is -1.

The youBot (report Fig. 3.1, eq. 3.2) has wheel 1 = front left at ``(+L, +l)``, 2 = front right
at ``(+L, -l)``, 3 = back left at ``(-L, +l)``, 4 = back right at ``(-L, -l)``, all headings 0, roller
angles +45°, -45°, -45°, +45°.
"""
from dataclasses import dataclass
import math

from youbot_fdi.errors import ModelError

#: Smallest |sin(roller_angle)| for which a wheel still drives its contact point [-].
MIN_ROLLER_SINE = 1e-6


@dataclass(frozen=True)
class Wheel:
    """One wheel of the platform; see the module docstring for the conventions."""

    name: str
    x: float  # [m]
    y: float  # [m]
    heading: float  # [rad]
    roller_angle: float  # [rad]
    radius: float  # [m]
    drive_sign: float = 1.0  # [-], +1 or -1

    def __post_init__(self):
        if not self.name:
            raise ModelError('a wheel needs a non-empty name')
        for field in ('x', 'y', 'heading', 'roller_angle', 'radius', 'drive_sign'):
            value = getattr(self, field)
            if not math.isfinite(value):
                msg = f'wheel {self.name!r}: {field} must be finite, got {value!r}'
                raise ModelError(msg)
        if self.radius <= 0.0:
            msg = f'wheel {self.name!r}: radius must be > 0 m, got {self.radius!r}'
            raise ModelError(msg)
        if self.drive_sign not in (1.0, -1.0):
            msg = f'wheel {self.name!r}: drive_sign must be +1 or -1, got {self.drive_sign!r}'
            raise ModelError(msg)
        if abs(math.sin(self.roller_angle)) < MIN_ROLLER_SINE:
            msg = (f'wheel {self.name!r}: roller_angle {math.degrees(self.roller_angle):g} deg '
                   'lets the wheel slide along its own rolling direction; it cannot drive the base')
            raise ModelError(msg)


@dataclass(frozen=True)
class Platform:
    """An omnidirectional base: an ordered tuple of wheels (the order of every per-wheel array)."""

    wheels: tuple

    def __post_init__(self):
        object.__setattr__(self, 'wheels', tuple(self.wheels))
        if len(self.wheels) < 3:
            msg = f'a holonomic base needs at least 3 wheels, got {len(self.wheels)}'
            raise ModelError(msg)
        names = [w.name for w in self.wheels]
        if len(set(names)) != len(names):
            msg = f'wheel names must be unique, got {names}'
            raise ModelError(msg)

    @property
    def names(self):
        """Wheel (joint) names in platform order."""
        return tuple(w.name for w in self.wheels)

    @property
    def n_wheels(self):
        """Number of wheels."""
        return len(self.wheels)

    @property
    def drive_signs(self):
        """Per-wheel sign from kinematic to driver convention, as a tuple of ±1.0."""
        return tuple(w.drive_sign for w in self.wheels)


def mecanum4(names, half_length, half_track, radius, roller_angle=math.pi / 4,
             drive_signs=(1.0, 1.0, 1.0, 1.0)):
    """Build the report's four-mecanum-wheel layout (order fl, fr, bl, br).

    Parameters
    ----------
    names : sequence of 4 str
        Wheel names in the order front left, front right, back left, back right.
    half_length : float
        L [m], longitudinal distance of each wheel from the centre.
    half_track : float
        l [m], lateral distance of each wheel from the centre.
    radius : float
        Wheel radius R_W [m].
    roller_angle : float
        alpha [rad] (report: 45°).
    drive_signs : sequence of 4 float
        Kinematic-to-driver signs.
    """
    if len(names) != 4 or len(drive_signs) != 4:
        msg = f'mecanum4 needs 4 names and 4 drive signs, got {len(names)} and {len(drive_signs)}'
        raise ModelError(msg)
    layout = ((half_length, half_track, roller_angle), (half_length, -half_track, -roller_angle),
              (-half_length, half_track, -roller_angle), (-half_length, -half_track, roller_angle))
    return Platform(tuple(
        Wheel(name, x, y, 0.0, gamma, radius, float(sign))
        for name, (x, y, gamma), sign in zip(names, layout, drive_signs)))
