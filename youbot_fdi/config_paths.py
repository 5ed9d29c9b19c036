"""Where the package's configuration files (``config/``) are found.

Search order: ``$YOUBOT_FDI_CONFIG_DIR``; the source checkout (``<repo>/config``, also what an
editable or ``colcon build --symlink-install`` install sees); the ament share directory
(``share/youbot_fdi/config`` of a colcon install or ROS package); ``<sys.prefix>/share/youbot_fdi/config``
(a plain ``pip install``).
"""
import os
from pathlib import Path
import sys

PACKAGE_NAME = 'youbot_fdi'
CONFIG_ENV = 'YOUBOT_FDI_CONFIG_DIR'


def _candidates():
    env = os.environ.get(CONFIG_ENV)
    if env:
        yield Path(env)
    yield Path(__file__).resolve().parent.parent / 'config'
    try:
        from ament_index_python.packages import get_package_share_directory
        yield Path(get_package_share_directory(PACKAGE_NAME)) / 'config'
    except Exception:  # noqa: BLE001 - no ament index, or the package is not in it
        pass
    yield Path(sys.prefix) / 'share' / PACKAGE_NAME / 'config'

PROFILE_SUFFIX = '.yaml'


def config_dir():
    """The first existing configuration directory (see the module docstring)."""
    tried = []
    for candidate in _candidates():
        if (candidate / 'profiles').is_dir():
            return candidate
        tried.append(str(candidate))
    msg = f'no youbot_fdi config directory found; tried {tried} (set ${CONFIG_ENV})'
    raise FileNotFoundError(msg)


def available_profiles():
    """Names of the profiles shipped in ``config/profiles``."""
    return sorted(p.stem for p in (config_dir() / 'profiles').glob('*' + PROFILE_SUFFIX))
