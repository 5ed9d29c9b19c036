"""Package attributes imported from their sub-modules on first use (PEP 562).

A package's ``__init__`` lists which sub-module defines each public name; ``import package.sub``
then costs only what ``sub`` needs (the CLI's ``--help`` and the nodes stay light).
"""
import importlib


def lazy_exports(package, module_of):
    """``__getattr__`` for ``package`` (its ``__name__``) from ``{name: sub_module}``."""
    def __getattr__(name):
        module = module_of.get(name)
        if module is None:
            raise AttributeError(f'module {package!r} has no attribute {name!r}')
        return getattr(importlib.import_module(f'{package}.{module}'), name)
    return __getattr__
