"""Parameter profiles: platform geometry, drive train, dynamics and firmware from one YAML file.

A profile is named (``seed``, ``youbot``, ... in ``config/profiles/``) or given as a path. Every
value is validated on load; a missing, unknown, non-numeric, non-finite or out-of-range value raises
:class:`~youbot_fdi.errors.ConfigError` naming the file and the key (``dynamics.wheel_inertia``).

Schema (units in brackets)::

    name: str
    description: str                      # optional
    platform:
      wheels:                             # ordered; this order is every per-wheel array's order
        - {name: str, x: [m], y: [m], heading_deg: [deg], roller_angle_deg: [deg],
           radius: [m], drive_sign: +1|-1}
    drive:
      gear_ratio: [-]                     # wheel rev per motor rev
      torque_constant: [N·m/A]
      encoder_ticks_per_revolution: [ticks per motor rev]
      max_current: [A]
      signed_effort: true|false           # optional (true); false: effort is a magnitude only
    dynamics:
      mass: [kg]
      yaw_inertia: [kg·m²]
      wheel_inertia: [kg·m²]              # one value for all wheels, or a list per wheel
      viscous_friction: [N·m·s/rad]       # scalar or list
      coulomb_friction: [N·m]             # scalar or list, optional (0)
      coulomb_velocity_scale: [rad/s]     # optional (0.05)
      roller_friction_ratio: [-]          # optional (0): contact friction law, identify fits it
      roller_drag: [N·m]                  # optional (0): rollers' resistance the motors feel, identify fits it
      loop_inertias: {mass: [kg], yaw_inertia: [kg·m²], wheel_inertia: [kg·m²]}
                                          # optional: what the velocity loop moves, where not the above
    firmware:
      period: [s]
      velocity_kp: [A/(rad/s)]
      velocity_ki: [A/rad]
      loop: discrete|continuous           # optional (discrete)
    fdi: {...}                            # optional: FDI settings (config/fdi.yaml keys)
    identification: {...}                 # optional: how `identify` got these values
    learned: {torque: {...}}              # optional: learned corrections (youbot_fdi.fdi.learned)
"""
from dataclasses import dataclass
import math
from pathlib import Path

import yaml

from youbot_fdi.config_paths import available_profiles, config_dir, PROFILE_SUFFIX  # noqa: F401
from youbot_fdi.errors import ConfigError, ModelError
from youbot_fdi.model.drive import DriveTrain
from youbot_fdi.model.dynamics import DynamicParameters, WheelDynamics
from youbot_fdi.model.firmware import FirmwareParameters, LoopKind
from youbot_fdi.model.geometry import Platform, Wheel
from youbot_fdi.model.kinematics import Kinematics
from youbot_fdi.yamlio import load_yaml

DEFAULT_COULOMB_VELOCITY_SCALE = 0.05  # [rad/s]
LOOP_INERTIAS = 'loop_inertias'  # the dynamics key, and its names in DynamicParameters.loop_inertias order
LOOP_INERTIA_NAMES = ('mass', 'yaw_inertia', 'wheel_inertia')


class _Section:
    """Typed access to one mapping of a profile, remembering the key path for error messages."""

    def __init__(self, mapping, path, source):
        if not isinstance(mapping, dict):
            msg = f'{source}: {path or "the file"} must be a mapping, got {type(mapping).__name__}'
            raise ConfigError(msg)
        self.mapping = mapping
        self.path = path
        self.source = source
        self.used = set()

    def _key(self, key):
        return f'{self.path}.{key}' if self.path else key

    def fail(self, key, problem):
        msg = f'{self.source}: {self._key(key)} {problem}'
        raise ConfigError(msg)

    def raw(self, key, default=None, required=True):
        self.used.add(key)
        if key not in self.mapping:
            if required:
                self.fail(key, 'is missing')
            return default
        return self.mapping[key]

    def section(self, key):
        return _Section(self.raw(key), self._key(key), self.source)

    def number(self, key, minimum=None, strict=False, default=None):
        """A finite float; ``minimum`` with ``strict`` means value > minimum, else >= minimum."""
        value = self.raw(key, default=default, required=default is None)
        return self._check_number(key, value, minimum, strict)

    def _check_number(self, key, value, minimum, strict):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(key, f'must be a number, got {value!r}')
        value = float(value)
        if not math.isfinite(value):
            self.fail(key, f'must be finite, got {value!r}')
        if minimum is not None and (value <= minimum if strict else value < minimum):
            relation = '>' if strict else '>='
            self.fail(key, f'must be {relation} {minimum:g}, got {value:g}')
        return value

    def per_wheel(self, key, n_wheels, minimum=None, strict=False, default=None):
        """A scalar (same for every wheel) or a list of one number per wheel, as a tuple."""
        value = self.raw(key, default=default, required=default is None)
        values = value if isinstance(value, list) else [value] * n_wheels
        if len(values) != n_wheels:
            self.fail(key, f'must be one number or a list of {n_wheels}, got {len(values)} values')
        return tuple(self._check_number(f'{key}[{i}]', v, minimum, strict)
                     for i, v in enumerate(values))

    def flag(self, key, default=False):
        value = self.raw(key, default=default, required=False)
        if not isinstance(value, bool):
            self.fail(key, f'must be true or false, got {value!r}')
        return value

    def text(self, key, default=None):
        value = self.raw(key, default=default, required=default is None)
        if not isinstance(value, str):
            self.fail(key, f'must be a string, got {value!r}')
        return value

    def finish(self):
        unknown = sorted(set(self.mapping) - self.used)
        if unknown:
            self.fail(unknown[0], f'is not a known key (known: {sorted(self.used)})')


@dataclass(frozen=True)
class ModelProfile:
    """A validated parameter profile."""

    name: str
    description: str
    platform: Platform
    drive: DriveTrain
    dynamics: DynamicParameters
    firmware: FirmwareParameters
    source: str = ''
    fdi: dict = None  # optional FDI settings learned by `identify` (config/fdi.yaml keys)
    identification: dict = None  # optional record of how the parameters were identified
    learned: dict = None  # optional learned model corrections (youbot_fdi.fdi.learned), by family


class PlatformModel:
    """Kinematics, dynamics, drive train and firmware settings built from one profile."""

    def __init__(self, profile):
        self.profile = profile
        self.platform = profile.platform
        self.kinematics = Kinematics(profile.platform)
        self.dynamics = WheelDynamics(self.kinematics, profile.dynamics)
        self.drive = profile.drive
        self.firmware = profile.firmware

    @property
    def wheel_names(self):
        """Wheel (joint) names in model order."""
        return self.platform.names


def _parse_platform(section):
    wheels_raw = section.raw('wheels')
    if not isinstance(wheels_raw, list) or not wheels_raw:
        section.fail('wheels', 'must be a non-empty list of wheels')
    wheels = []
    for index, raw in enumerate(wheels_raw):
        wheel = _Section(raw, f'{section._key("wheels")}[{index}]', section.source)
        try:
            wheels.append(Wheel(
                name=wheel.text('name'),
                x=wheel.number('x'), y=wheel.number('y'),
                heading=math.radians(wheel.number('heading_deg', default=0.0)),
                roller_angle=math.radians(wheel.number('roller_angle_deg')),
                radius=wheel.number('radius', minimum=0.0, strict=True),
                drive_sign=wheel.number('drive_sign', default=1.0)))
        except ModelError as err:
            msg = f'{section.source}: {wheel.path}: {err}'
            raise ConfigError(msg) from err
        wheel.finish()
    section.finish()
    try:
        return Platform(tuple(wheels))
    except ModelError as err:
        msg = f'{section.source}: {section.path}: {err}'
        raise ConfigError(msg) from err


def _parse_drive(section):
    drive = DriveTrain(
        gear_ratio=section.number('gear_ratio', minimum=0.0, strict=True),
        torque_constant=section.number('torque_constant', minimum=0.0, strict=True),
        encoder_ticks_per_revolution=section.number('encoder_ticks_per_revolution', minimum=0.0,
                                                    strict=True),
        max_current=section.number('max_current', minimum=0.0, strict=True),
        signed_effort=section.flag('signed_effort', default=True))
    section.finish()
    return drive


def _parse_dynamics(section, n_wheels):
    dynamics = DynamicParameters(
        mass=section.number('mass', minimum=0.0, strict=True),
        yaw_inertia=section.number('yaw_inertia', minimum=0.0, strict=True),
        wheel_inertia=section.per_wheel('wheel_inertia', n_wheels, minimum=0.0, strict=True),
        viscous_friction=section.per_wheel('viscous_friction', n_wheels, minimum=0.0),
        coulomb_friction=section.per_wheel('coulomb_friction', n_wheels, minimum=0.0, default=0.0),
        coulomb_velocity_scale=section.number('coulomb_velocity_scale', minimum=0.0, strict=True,
                                              default=DEFAULT_COULOMB_VELOCITY_SCALE),
        roller_friction_ratio=section.number('roller_friction_ratio', minimum=0.0, default=0.0),
        roller_drag=section.number('roller_drag', minimum=0.0, default=0.0),
        loop_inertias=_parse_loop_inertias(section))
    section.finish()
    return dynamics


def _parse_loop_inertias(section):
    """``dynamics.loop_inertias`` (optional): {mass, yaw_inertia, wheel_inertia} the firmware's
    velocity loop moves, as (m, J_z, J_w); () where not given."""
    if section.raw(LOOP_INERTIAS, required=False) is None:
        return ()
    inertias = section.section(LOOP_INERTIAS)
    values = tuple(inertias.number(name, minimum=0.0, strict=True) for name in LOOP_INERTIA_NAMES)
    inertias.finish()
    return values


def _parse_firmware(section):
    loop_text = section.text('loop', default=LoopKind.DISCRETE.value)
    try:
        loop = LoopKind(loop_text)
    except ValueError:
        section.fail('loop', f'must be one of {[k.value for k in LoopKind]}, got {loop_text!r}')
    firmware = FirmwareParameters(
        period=section.number('period', minimum=0.0, strict=True),
        velocity_kp=section.number('velocity_kp', minimum=0.0),
        velocity_ki=section.number('velocity_ki', minimum=0.0),
        loop=loop)
    section.finish()
    return firmware


def _optional_mapping(section, key):
    value = section.raw(key, default={}, required=False)
    if not isinstance(value, dict):
        section.fail(key, 'must be a mapping')
    return value


def parse_profile(data, source='<profile>'):
    """Validate a profile mapping (as loaded from YAML) into a :class:`ModelProfile`."""
    top = _Section(data, '', source)
    platform = _parse_platform(top.section('platform'))
    profile = ModelProfile(
        name=top.text('name'),
        description=top.text('description', default=''),
        platform=platform,
        drive=_parse_drive(top.section('drive')),
        dynamics=_parse_dynamics(top.section('dynamics'), platform.n_wheels),
        firmware=_parse_firmware(top.section('firmware')),
        source=source,
        fdi=_optional_mapping(top, 'fdi'),
        identification=_optional_mapping(top, 'identification'),
        learned=_optional_mapping(top, 'learned'))
    top.finish()
    return profile


def profile_path(name_or_path):
    """Resolve a profile name (``youbot``) or a path to an existing file."""
    candidate = Path(name_or_path)
    if candidate.suffix in ('.yaml', '.yml') or candidate.exists():
        if not candidate.is_file():
            msg = f'profile file {str(candidate)!r} does not exist'
            raise ConfigError(msg)
        return candidate
    path = config_dir() / 'profiles' / (str(name_or_path) + PROFILE_SUFFIX)
    if not path.is_file():
        msg = f'unknown profile {name_or_path!r}; available: {available_profiles()} or a YAML path'
        raise ConfigError(msg)
    return path


def load_profile(name_or_path):
    """Load and validate a profile by name or path."""
    path = profile_path(name_or_path)
    try:
        data = load_yaml(path.read_text())
    except yaml.YAMLError as err:
        msg = f'{path}: not valid YAML: {err}'
        raise ConfigError(msg) from err
    return parse_profile(data, source=str(path))


def load_model(name_or_path):
    """Load a profile and build its :class:`PlatformModel`."""
    return PlatformModel(load_profile(name_or_path))


PARAMETER_FILE_HEADER = ('# Identified by `youbot-fdi identify`: a parameter profile (config/profiles schema) plus\n'
                         '# learned FDI noise floors (fdi), corrections (learned) and the fit record\n'
                         '# (identification). Use it with: youbot-fdi replay BAG --params THIS_FILE\n')


def save_profile(profile, path, header=PARAMETER_FILE_HEADER):
    """Write ``profile`` as a parameter file (YAML, :func:`profile_to_dict`); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(header + yaml.safe_dump(profile_to_dict(profile), sort_keys=False, width=100))
    return path


def profile_to_dict(profile):
    """The inverse of :func:`parse_profile`: a plain mapping ready for YAML."""
    wheels = [{'name': w.name, 'x': w.x, 'y': w.y, 'heading_deg': math.degrees(w.heading),
               'roller_angle_deg': math.degrees(w.roller_angle), 'radius': w.radius,
               'drive_sign': w.drive_sign} for w in profile.platform.wheels]
    dyn = profile.dynamics
    return {
        'name': profile.name,
        'description': profile.description,
        'platform': {'wheels': wheels},
        'drive': {'gear_ratio': profile.drive.gear_ratio,
                  'torque_constant': profile.drive.torque_constant,
                  'encoder_ticks_per_revolution': profile.drive.encoder_ticks_per_revolution,
                  'max_current': profile.drive.max_current,
                  'signed_effort': profile.drive.signed_effort},
        'dynamics': {'mass': dyn.mass, 'yaw_inertia': dyn.yaw_inertia,
                     'wheel_inertia': [float(v) for v in dyn.wheel_inertia],
                     'viscous_friction': [float(v) for v in dyn.viscous_friction],
                     'coulomb_friction': [float(v) for v in dyn.coulomb_friction],
                     'coulomb_velocity_scale': dyn.coulomb_velocity_scale,
                     'roller_friction_ratio': dyn.roller_friction_ratio,
                     'roller_drag': dyn.roller_drag,
                     **({LOOP_INERTIAS: dict(zip(LOOP_INERTIA_NAMES, map(float, dyn.loop_inertias)))}
                        if dyn.loop_inertias else {})},
        'firmware': {'period': profile.firmware.period,
                     'velocity_kp': profile.firmware.velocity_kp,
                     'velocity_ki': profile.firmware.velocity_ki,
                     'loop': profile.firmware.loop.value},
        **({'fdi': dict(profile.fdi)} if profile.fdi else {}),
        **({'identification': dict(profile.identification)} if profile.identification else {}),
        **({'learned': dict(profile.learned)} if profile.learned else {}),
    }

