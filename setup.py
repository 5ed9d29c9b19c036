"""ament_python package setup for youbot_fdi.

On a robot, ``colcon build`` installs the console scripts into ``lib/youbot_fdi`` (see setup.cfg)
so that ``ros2 run youbot_fdi <node>`` finds them; rclpy and the message packages come from the
apt ROS 2 install (package.xml). In a plain venv, the ``ros`` extra pulls the PyPI wheels.
"""
from glob import glob
import os

from setuptools import find_packages, setup

PACKAGE_NAME = 'youbot_fdi'

# The ROS 2 Jazzy wheels on PyPI, for a venv without an apt ROS install. Never in install_requires:
# on a robot these come from apt and a pip copy would shadow them.
ROS_WHEELS = ['ros-jazzy-rclpy[fastrtps]', 'ros-jazzy-common-interfaces']

EXTRAS = {
    'ros': ROS_WHEELS,
    'plot': ['matplotlib>=3.6'],
    # Cross-check of our own structural analysis; heavy (sympy, scikit-learn): never on the robot path.
    'structure': ['faultdiagnosistoolbox>=0.12'],
    # youbot-fdi fleet: a fleet's recordings on a local or remote Dask cluster; never on the robot.
    'fleet': ['dask[distributed]>=2024.1'],
    # pytrinamic: Trinamic's own TMCL client, driven against the virtual youBot in the tests.
    'test': ['pytest>=7', 'hypothesis>=6', 'ruff>=0.6', 'colcon-common-extensions', 'pytrinamic>=0.2.26'],
}
EXTRAS['all'] = sorted({req for reqs in EXTRAS.values() for req in reqs})


def config_data_files():
    """Every YAML under config/, installed to share/<package>/config/ with its sub-folder."""
    entries = {}
    for path in sorted(glob('config/**/*.yaml', recursive=True)):
        folder = os.path.join('share', PACKAGE_NAME, os.path.dirname(path))
        entries.setdefault(folder, []).append(path)
    return sorted(entries.items())


setup(
    name=PACKAGE_NAME,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE_NAME]),
        ('share/' + PACKAGE_NAME, ['package.xml', 'README.md']),
        ('share/' + PACKAGE_NAME + '/launch', glob('launch/*.launch.py')),
        *config_data_files(),
    ],
    python_requires='>=3.10',
    install_requires=['setuptools', 'numpy>=1.24', 'scipy>=1.10', 'pyyaml>=6', 'rosbags>=0.10',
                      'python-can>=4.3'],
    extras_require=EXTRAS,
    zip_safe=False,
    maintainer='youbot_fdi maintainers',
    maintainer_email='youbot-fdi@example.org',
    description='Fault detection and isolation for omnidirectional mecanum bases (KUKA youBot).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'youbot-fdi = youbot_fdi.cli.main:main',
            'driver_shim = youbot_fdi.nodes.driver_shim:main',
            'virtual_youbot = youbot_fdi.nodes.virtual_youbot:main',
            'youbot_sim = youbot_fdi.nodes.composed:sim_main',
            'kinematics_bridge = youbot_fdi.nodes.kinematics_bridge:main',
            'observer = youbot_fdi.nodes.observer:main',
            'residual_generator = youbot_fdi.nodes.residual_generator:main',
            'decision = youbot_fdi.nodes.decision:main',
            'youbot_fdi_suite = youbot_fdi.nodes.composed:fdi_main',
            'youbot_fdi_fused = youbot_fdi.nodes.composed:fused_main',
        ],
    },
)
