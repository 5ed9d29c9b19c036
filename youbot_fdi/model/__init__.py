"""Platform models: geometry, kinematics, Lagrangian dynamics, drive train and firmware emulation.

Plain numpy/scipy; never imports rclpy, python-can or rosbags. The names below are imported from
their sub-modules on first use (PEP 562), so ``import youbot_fdi.model.profile`` costs only what
that module needs.
"""
from youbot_fdi.lazy import lazy_exports

_SOURCES = {
    'drive': ('DriveTrain',),
    'dynamics': ('DiscreteWheelModel', 'DynamicParameters', 'WheelDynamics', 'mass_matrix',
                 'zoh_discretize'),
    'firmware': ('ControlMode', 'FirmwareParameters', 'LoopKind', 'response_time_constant',
                 'sampled_loop_spectral_radius', 'slowest_time_constant'),
    'geometry': ('Platform', 'Wheel', 'mecanum4'),
    'kinematics': ('integrate_pose', 'Kinematics', 'Odometry'),
    'profile': ('available_profiles', 'load_model', 'load_profile', 'ModelProfile', 'parse_profile',
                'PlatformModel'),
    'simulation': ('BaseSimulator', 'SimulationStep'),
}
_MODULE_OF = {name: module for module, names in _SOURCES.items() for name in names}

__all__ = sorted(_MODULE_OF, key=str.lower)

__getattr__ = lazy_exports(__name__, _MODULE_OF)
