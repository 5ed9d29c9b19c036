"""youbot_fdi: fault detection and isolation for omnidirectional mecanum bases (KUKA youBot).

Layout: ``model`` (kinematics, dynamics, firmware; numpy/scipy only), ``cli`` (the ``youbot-fdi``
command). Nothing outside ``nodes`` imports rclpy.
"""
__version__ = '0.1.0'
