"""Platform models: geometry, kinematics, Lagrangian dynamics, drive train and firmware emulation.

Plain numpy/scipy; never imports rclpy, python-can or rosbags.
"""
from youbot_fdi.model.drive import DriveTrain
from youbot_fdi.model.dynamics import (DiscreteWheelModel, DynamicParameters, WheelDynamics,
                                       mass_matrix, zoh_discretize)
from youbot_fdi.model.firmware import (ControlMode, FirmwareParameters, LoopKind,
                                       sampled_loop_spectral_radius)
from youbot_fdi.model.geometry import Platform, Wheel, mecanum4
from youbot_fdi.model.kinematics import integrate_pose, Kinematics, Odometry
from youbot_fdi.model.profile import (available_profiles, load_model, load_profile, ModelProfile,
                                      parse_profile, PlatformModel)
from youbot_fdi.model.simulation import BaseSimulator, SimulationStep

__all__ = [
    'available_profiles', 'BaseSimulator', 'ControlMode', 'DiscreteWheelModel', 'DriveTrain',
    'DynamicParameters', 'FirmwareParameters', 'integrate_pose', 'Kinematics', 'load_model',
    'load_profile', 'LoopKind', 'mass_matrix', 'mecanum4', 'ModelProfile', 'Odometry',
    'parse_profile', 'Platform', 'PlatformModel', 'sampled_loop_spectral_radius',
    'SimulationStep', 'Wheel', 'WheelDynamics', 'zoh_discretize',
]
