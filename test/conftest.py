"""Test-wide settings: keep ROS 2 discovery on loopback, a per-run domain, checked message fields."""
import os
import random

# Fast DDS multicasts discovery out of every interface unless told otherwise; nothing may leave
# loopback. Make sets these too; this covers a bare `pytest` run.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(1, 100)))
os.environ.setdefault('ROS_PYTHON_CHECK_FIELDS', '1')
os.environ.setdefault('MPLBACKEND', 'Agg')
