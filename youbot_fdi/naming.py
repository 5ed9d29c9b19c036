"""Names shared by every layer: the wheel joints' naming convention."""

#: Wheel joints are named ``wheel_joint_<suffix>`` (the youBot's URDF: fl, fr, bl, br).
WHEEL_PREFIX = 'wheel_joint_'


def wheel_suffix(joint_name):
    """``wheel_joint_fl`` -> ``fl``; other names unchanged."""
    return joint_name[len(WHEEL_PREFIX):] if joint_name.startswith(WHEEL_PREFIX) else joint_name
