"""Structural models: equations as the sets of variables they relate, plus where faults enter.

Only structure matters here (which variable appears in which equation), as in the report's
chapter 4 and Blanke et al. A model is declared as data: a YAML file (``config/structure/``) or a
mapping generated from a platform's geometry (:mod:`youbot_fdi.structure.generate`).
"""
from dataclasses import dataclass, field

import numpy as np
import yaml

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ConfigError
from youbot_fdi.yamlio import load_yaml


@dataclass(frozen=True)
class Equation:
    """One constraint: its name, the variables it relates and an optional readable form."""

    name: str
    variables: tuple
    expression: str = ''


@dataclass(frozen=True)
class StructuralModel:
    """Equations over known and unknown variables, with faults attached to equations.

    Attributes
    ----------
    name : str
    equations : tuple of Equation
        In order; every matrix below follows this order.
    unknown, known : tuple of str
    faults : dict
        Fault name -> name of the equation it violates.
    reference : dict
        What a source printed about this model (for comparison), free-form.
    """

    name: str
    equations: tuple
    unknown: tuple
    known: tuple
    faults: dict
    description: str = ''
    reference: dict = field(default_factory=dict)

    def __post_init__(self):
        names = [e.name for e in self.equations]
        if len(set(names)) != len(names):
            msg = f'structural model {self.name!r}: equation names must be unique'
            raise ConfigError(msg)
        declared = set(self.unknown) | set(self.known)
        if len(declared) != len(self.unknown) + len(self.known):
            msg = f'structural model {self.name!r}: a variable is declared twice'
            raise ConfigError(msg)
        for equation in self.equations:
            undeclared = set(equation.variables) - declared
            if undeclared:
                msg = (f'structural model {self.name!r}: equation {equation.name} uses undeclared '
                       f'variables {sorted(undeclared)}')
                raise ConfigError(msg)
        for fault, equation in self.faults.items():
            if equation not in names:
                msg = (f'structural model {self.name!r}: fault {fault} enters unknown equation '
                       f'{equation!r}')
                raise ConfigError(msg)

    @property
    def equation_names(self):
        """Equation names in order."""
        return tuple(e.name for e in self.equations)

    @property
    def fault_names(self):
        """Fault names in declaration order."""
        return tuple(self.faults)

    def incidence(self, variables):
        """Boolean incidence matrix, shape (n_equations, len(variables))."""
        index = {v: j for j, v in enumerate(variables)}
        matrix = np.zeros((len(self.equations), len(variables)), dtype=bool)
        for i, equation in enumerate(self.equations):
            for v in equation.variables:
                if v in index:
                    matrix[i, index[v]] = True
        return matrix

    def fault_equation_index(self):
        """For each fault (declaration order), the index of the equation it enters."""
        position = {name: i for i, name in enumerate(self.equation_names)}
        return np.array([position[self.faults[f]] for f in self.faults], dtype=int)

    def with_sensors(self, sensors):
        """A copy with extra measurement equations.

        Parameters
        ----------
        sensors : iterable of (name, measured unknown variable)
            Each adds a known variable ``<name>`` and an equation ``<name>: <name> = <variable>``
            with its own fault ``<name>`` (a new sensor can fail too).
        """
        equations, known, faults = list(self.equations), list(self.known), dict(self.faults)
        for name, variable in sensors:
            if variable not in self.unknown:
                msg = f'sensor {name!r} measures {variable!r}, which is not an unknown variable'
                raise ConfigError(msg)
            known.append(name)
            equations.append(Equation(name, (name, variable), f'{name} = {variable}'))
            faults[name] = name
        return StructuralModel(f'{self.name}+sensors', tuple(equations), self.unknown, tuple(known),
                               faults, self.description, self.reference)


def model_from_mapping(data, source='<model>'):
    """Build a :class:`StructuralModel` from a mapping as in ``config/structure/*.yaml``."""
    try:
        equations = tuple(Equation(str(e['name']), tuple(e['vars']), str(e.get('expression', '')))
                          for e in data['equations'])
        return StructuralModel(
            name=str(data['name']), equations=equations,
            unknown=tuple(data['variables']['unknown']), known=tuple(data['variables']['known']),
            faults={str(k): str(v) for k, v in (data.get('faults') or {}).items()},
            description=str(data.get('description', '')), reference=data.get('reference') or {})
    except (KeyError, TypeError) as err:
        msg = f'{source}: not a structural model ({type(err).__name__}: {err})'
        raise ConfigError(msg) from err


def load_structural_model_file(path):
    """Load a structural model YAML file."""
    try:
        data = load_yaml(open(path).read())
    except (OSError, yaml.YAMLError) as err:
        msg = f'{path}: cannot read structural model: {err}'
        raise ConfigError(msg) from err
    return model_from_mapping(data, str(path))


def shipped_structure_files():
    """Structural models shipped as data in ``config/structure``: name -> path."""
    return {p.stem: p for p in sorted((config_dir() / 'structure').glob('*.yaml'))}
