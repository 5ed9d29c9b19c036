"""The physically corrected structural model, generated from a platform profile's geometry.

Per wheel ``<w>`` (the joint name without ``wheel_joint_``), with the report's torque restored
(Appendix A dropped it):

=============  =====================================================  ======================
equation       relation                                               fault
=============  =====================================================  ======================
``dyn_<w>``    sum_j M[w, j] ddtheta_j + D_w dtheta_w = tau_w         ``friction_<w>``
``act_<w>``    tau_w = k_t / gear * i_w                               ``actuator_<w>``
``sens_<w>``   y_w = dtheta_w (the measured wheel speed)              ``velocity_sensor_<w>``
``diff_<w>``   ddtheta_w = d(dtheta_w)/dt
``int_<w>``    dtheta_w = d(theta_w)/dt
=============  =====================================================  ======================

The runtime residuals are declared as templates (``reference['residuals']``), which the analysis
checks are MSO sets that together reach the model's full isolability:

- ``torque_<w>``: the torque balance of wheel w, ``(M a + D y - k_t/gear i)_w`` with the wheel
  accelerations a from the measured speeds y: sensitive to ``actuator_<w>``, ``friction_<w>`` and
  every speed sensor (M is dense);
- ``observer_<w>``: the wheel speeds predicted from the currents alone (the dynamic-model observer)
  against the measured speed of wheel w: sensitive to every actuator and friction fault and to
  ``velocity_sensor_<w>`` only.

plus the forward kinematics ``kin_vx``, ``kin_vy``, ``kin_wz`` (base twist from wheel speeds), so
that sensors on the base can be considered. Known: the motor currents ``i_<w>`` and measured
speeds ``y_<w>``. Which ``ddtheta_j`` enter ``dyn_<w>`` follows the non-zero pattern of the
platform's mass matrix M: dense for the youBot.
"""
from pathlib import Path

import numpy as np

from youbot_fdi.config_paths import available_profiles
from youbot_fdi.errors import ConfigError
from youbot_fdi.model.profile import load_model
from youbot_fdi.naming import wheel_suffix
from youbot_fdi.structure.model import (Equation, load_structural_model_file, model_from_mapping,
                                        shipped_structure_files, StructuralModel)
from youbot_fdi.yamlio import load_yaml

#: Entries of M or F below this fraction of the largest are structural zeros [-].
STRUCTURAL_ZERO = 1e-12
TWIST_NAMES = ('vx', 'vy', 'wz')


def _pattern(matrix):
    matrix = np.abs(np.asarray(matrix, dtype=float))
    return matrix > STRUCTURAL_ZERO * matrix.max()


def platform_structural_model(platform_model, name=None):
    """The corrected structural model of a :class:`~youbot_fdi.model.profile.PlatformModel`.

    Returns
    -------
    model : StructuralModel
        With ``reference['sensor_candidates']``: extra sensors worth considering, by group.
    """
    wheels = [wheel_suffix(n) for n in platform_model.wheel_names]
    mass_pattern = _pattern(platform_model.dynamics.mass_matrix)
    forward_pattern = _pattern(platform_model.kinematics.forward_matrix)
    equations, faults = [], {}
    for i, w in enumerate(wheels):
        coupled = [f'ddtheta_{wheels[j]}' for j in np.flatnonzero(mass_pattern[i])]
        equations += [
            Equation(f'dyn_{w}', (*coupled, f'dtheta_{w}', f'tau_{w}'),
                     f'sum_j M[{w},j] ddtheta_j + D_{w} dtheta_{w} = tau_{w}'),
            Equation(f'act_{w}', (f'tau_{w}', f'i_{w}'), f'tau_{w} = k_t / gear * i_{w}'),
            Equation(f'sens_{w}', (f'y_{w}', f'dtheta_{w}'), f'y_{w} = dtheta_{w}'),
            Equation(f'diff_{w}', (f'ddtheta_{w}', f'dtheta_{w}'), f'ddtheta_{w} = d(dtheta_{w})/dt'),
            Equation(f'int_{w}', (f'dtheta_{w}', f'theta_{w}'), f'dtheta_{w} = d(theta_{w})/dt'),
        ]
        faults[f'actuator_{w}'] = f'act_{w}'
        faults[f'friction_{w}'] = f'dyn_{w}'
        faults[f'velocity_sensor_{w}'] = f'sens_{w}'
    for k, twist in enumerate(TWIST_NAMES):
        speeds = [f'dtheta_{wheels[j]}' for j in np.flatnonzero(forward_pattern[k])]
        equations.append(Equation(f'kin_{twist}', (twist, *speeds),
                                  f'{twist} = forward kinematics row {k} of the wheel speeds'))
    # Faults in wheel order, grouped by kind, as CONTRACT.md lists them.
    ordered = {f'{kind}_{w}': faults[f'{kind}_{w}']
               for kind in ('actuator', 'friction', 'velocity_sensor') for w in wheels}
    unknown = tuple(f'{q}_{w}' for q in ('theta', 'dtheta', 'ddtheta', 'tau') for w in wheels)
    known = tuple(f'{q}_{w}' for q in ('i', 'y') for w in wheels)
    candidates = {
        'wheel_position': [(f'pos_{w}', f'theta_{w}') for w in wheels],
        'wheel_torque': [(f'torque_{w}', f'tau_{w}') for w in wheels],
        'gyro': [('gyro', 'wz')],
        'base_velocity': [('vel_x', 'vx'), ('vel_y', 'vy')],
    }
    all_of = lambda kind: [f'{kind}_{v}' for v in wheels]  # noqa: E731
    residuals = {}
    for w in wheels:
        residuals[f'torque_{w}'] = [f'dyn_{w}', f'act_{w}', *all_of('sens'), *all_of('diff')]
    for w in wheels:
        residuals[f'observer_{w}'] = [*all_of('dyn'), *all_of('act'), *all_of('diff'), f'sens_{w}']
    return StructuralModel(
        name=name or platform_model.profile.name,
        equations=tuple(equations), unknown=unknown + TWIST_NAMES, known=known, faults=ordered,
        description=(f'Corrected model of profile {platform_model.profile.name!r}: '
                     'M theta_ddot + D theta_dot = tau with tau = k_t/gear i, measured wheel speeds '
                     'and motor currents.'),
        reference={'sensor_candidates': candidates, 'residuals': residuals})


def resolve_model(name):
    """A structural model by name (shipped data file or parameter profile) or YAML path."""
    shipped = shipped_structure_files()
    if name in shipped:
        return load_structural_model_file(shipped[name])
    if name in available_profiles():
        return platform_structural_model(load_model(name))
    path = Path(name)
    if path.is_file():
        data = load_yaml(path.read_text())
        if isinstance(data, dict) and 'equations' in data:
            return model_from_mapping(data, str(path))
        return platform_structural_model(load_model(path))
    msg = (f'unknown model {name!r}; available: {sorted(set(shipped) | set(available_profiles()))} '
           'or a YAML path')
    raise ConfigError(msg)
