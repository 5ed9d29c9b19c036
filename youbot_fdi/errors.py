"""Errors raised by youbot_fdi.

::

    FdiError
     +-- ConfigError      a parameter or model file is missing, malformed or out of range (also ValueError)
     +-- ModelError       a model cannot be built or used as asked (also ValueError)

Every message names what was rejected (a file and key, an argument and its shape).
"""


class FdiError(Exception):
    """Base of every error youbot_fdi raises on purpose."""


class ConfigError(FdiError, ValueError):
    """A parameter file or configuration value is missing, malformed or out of range."""


class ModelError(FdiError, ValueError):
    """A model cannot be built from the given geometry or parameters, or is used wrongly."""
