"""Node settings: frozen dataclasses filled from ROS-style parameter YAML (``ros__parameters``).

One spec serves both faces: a node declares its ROS parameters from the dataclass fields (name,
default, type) and the offline tools and tests read the same YAML through :func:`load_settings`.
"""
import dataclasses
import math
from pathlib import Path

import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.yamlio import load_yaml

ROS_PARAMETERS = 'ros__parameters'
WILDCARD = '/**'
#: Field metadata of a float setting for which +inf is a value ("no limit", YAML ``.inf``).
UNBOUNDED = 'unbounded'


def unbounded(default):
    """A float setting that may be ``.inf`` (no limit): ``x: float = unbounded(math.inf)``."""
    return dataclasses.field(default=default, metadata={UNBOUNDED: True})


def node_parameters(data, node_name, source='<parameters>'):
    """The ``ros__parameters`` of ``node_name`` (merged over ``/**``) from a parameter mapping."""
    if not isinstance(data, dict):
        msg = f'{source}: a ROS parameter file must be a mapping'
        raise ConfigError(msg)
    merged = {}
    for key in (WILDCARD, node_name, '/' + node_name):
        section = data.get(key)
        if section is not None:
            if not isinstance(section, dict) or not isinstance(section.get(ROS_PARAMETERS), dict):
                msg = f'{source}: {key} must hold a {ROS_PARAMETERS} mapping'
                raise ConfigError(msg)
            merged.update(section[ROS_PARAMETERS])
    return merged


def finite_number(value, where):
    """``value`` as a float, or ConfigError naming ``where`` unless it is a finite int or float
    (a bool is not a number here)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f'{where} must be a finite number, got {value!r}')
    return float(value)


def _coerce(field, value, source):
    default = field.default
    where = f'{source}: parameter {field.name}'
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f'{where} must be true or false, got {value!r}')
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f'{where} must be an integer, got {value!r}')
        return value
    if isinstance(default, float):
        if field.metadata.get(UNBOUNDED) and isinstance(value, float) and value == math.inf:
            return value
        return finite_number(value, where)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f'{where} must be a string, got {value!r}')
        return value
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f'{where} must be a list, got {value!r}')
        kinds = {type(v) for v in default}
        if kinds and not all(isinstance(v, tuple(kinds)) and not isinstance(v, bool) for v in value):
            raise ConfigError(f'{where} must be a list of {sorted(k.__name__ for k in kinds)}, '
                              f'got {value!r}')
        return tuple(value)
    return value


def settings_from_mapping(cls, mapping, source='<parameters>'):
    """Fill dataclass ``cls`` from ``mapping``; unknown keys and wrong types raise ConfigError."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(mapping) - set(fields) - {'use_sim_time'})
    if unknown:
        msg = f'{source}: unknown parameter {unknown[0]!r} (known: {sorted(fields)})'
        raise ConfigError(msg)
    values = {name: _coerce(fields[name], value, source) for name, value in mapping.items()
              if name in fields}
    settings = cls(**values)
    validate = getattr(settings, 'validate', None)
    if validate is not None:
        validate(source)
    return settings


def default_parameter_file(node_name):
    """``config/<node_name>.yaml``."""
    return config_dir() / f'{node_name}.yaml'


def load_settings(cls, node_name, path=None):
    """Settings of ``node_name`` from ``path`` (default ``config/<node_name>.yaml``)."""
    path = Path(path) if path else default_parameter_file(node_name)
    try:
        data = load_yaml(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f'{path}: cannot read parameters: {err}'
        raise ConfigError(msg) from err
    return settings_from_mapping(cls, node_parameters(data, node_name, str(path)), str(path))
