"""The configuration a pipeline runs with: ``config/fdi.yaml``, an ``identify`` parameter file,
and the runtime residual set of the structural analysis."""
from pathlib import Path

import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.fdi.pipeline import FdiPipeline
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model.profile import load_model, load_profile, PlatformModel
from youbot_fdi.naming import wheel_suffix
from youbot_fdi.settings import load_settings, settings_from_mapping
from youbot_fdi.yamlio import load_yaml

DEFAULT_RESIDUAL_MODEL = 'youbot'


def configure(settings, params_path=None):
    """The model and settings to run with: an ``identify`` parameter file overrides the profile
    and the noise floors of ``settings``."""
    if not params_path:
        return load_model(settings.profile), settings
    profile = load_profile(params_path)
    if profile.fdi:
        settings = settings_from_mapping(FdiSettings, {**settings.__dict__, **profile.fdi},
                                         source=str(params_path))
    return PlatformModel(profile), settings


def residual_data_for(model, settings):
    """The residual set ``settings`` names (``residual_file``), else the shipped one for ``model``."""
    return load_residual_data(settings.residual_file or None, model.wheel_names)


def build_pipeline(params_path=None, fdi_config=None, keep_frames=False):
    """The model and pipeline a replay (and a benchmark) uses: ``config/fdi.yaml`` (or
    ``fdi_config``), overridden by an ``identify`` parameter file."""
    model, settings = configure(load_settings(FdiSettings, 'fdi', fdi_config), params_path)
    return model, FdiPipeline(model, settings, residual_data_for(model, settings),
                              keep_frames=keep_frames)


def load_residual_data(path=None, wheel_names=None):
    """The runtime residual set written by ``youbot-fdi structure --write-residuals``: ``path``,
    or the shipped set (``config/residuals/``) whose faults cover every wheel of ``wheel_names``
    (the youBot's first)."""
    if not path:
        shipped = sorted((config_dir() / 'residuals').glob('*.yaml'),
                         key=lambda p: p.stem != DEFAULT_RESIDUAL_MODEL)
        path = shipped[0] if shipped else config_dir() / 'residuals' / f'{DEFAULT_RESIDUAL_MODEL}.yaml'
        for candidate in shipped if wheel_names else ():
            faults = set((_read_residual_file(candidate) or {}).get('faults', ()))
            if all(f'actuator_{wheel_suffix(w)}' in faults for w in wheel_names):
                path = candidate
                break
    data = _read_residual_file(Path(path))
    if not isinstance(data, dict) or 'residuals' not in data or 'faults' not in data:
        msg = f'{path}: not a residual set (needs faults and residuals)'
        raise ConfigError(msg)
    return data


def _read_residual_file(path):
    try:
        return load_yaml(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        msg = f'{path}: cannot read the residual set: {err}'
        raise ConfigError(msg) from err
