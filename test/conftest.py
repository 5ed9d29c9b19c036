"""Test-wide settings: keep ROS 2 discovery on loopback, a per-run domain, checked message fields."""
import os
import random
import tempfile

import pytest

# Fast DDS multicasts discovery out of every interface unless told otherwise; nothing may leave
# loopback. Make sets these too; this covers a bare `pytest` run.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(1, 100)))
os.environ.setdefault('ROS_PYTHON_CHECK_FIELDS', '1')
os.environ.setdefault('MPLBACKEND', 'Agg')
# The decision node keeps incident recordings under $ROS_HOME by default: not in the user's.
os.environ.setdefault('ROS_HOME', tempfile.mkdtemp(prefix='youbot-fdi-test-ros-home-'))


def pytest_collection_modifyitems(items):
    """A module with ``FAST_EXCEPT`` (test names) is in ``make check`` (marker fast) but for those."""
    for item in items:
        slow = getattr(item.module, 'FAST_EXCEPT', None)
        if slow is not None and getattr(item, 'originalname', item.name) not in slow:
            item.add_marker(pytest.mark.fast)
