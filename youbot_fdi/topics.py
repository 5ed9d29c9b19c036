"""Topic names of CONTRACT.md (defaults; every one is remappable). Plain constants, no imports."""
JOINT_STATES = '/joint_states'  # sensor_msgs/JointState: measured wheel position, speed, effort
WHEEL_COMMANDS = '/wheel_commands'  # sensor_msgs/JointState: commanded wheel speed or effort
CMD_VEL = '/cmd_vel'  # geometry_msgs/Twist: body velocity set-point
ODOM = '/odom'  # nav_msgs/Odometry: wheel odometry
PREDICTED = '/youbot_fdi/predicted'  # sensor_msgs/JointState: what the model predicts
RESIDUALS = '/youbot_fdi/residuals'  # sensor_msgs/JointState: residuals and their bounds
FAULTS = '/youbot_fdi/faults'  # diagnostic_msgs/DiagnosticArray: fault states, latched
REACTIONS = '/youbot_fdi/reactions'  # diagnostic_msgs/DiagnosticArray: fault reactions, latched
DIAGNOSTICS = '/diagnostics'  # diagnostic_msgs/DiagnosticArray: node health
CLOCK = '/clock'  # rosgraph_msgs/Clock: replayed time
