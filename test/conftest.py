"""Test-suite wide settings.

DDS safety: every ROS participant a test starts (in this process or in a subprocess,
which inherits os.environ) stays on this machine. This runs at conftest import time,
before any test module can import rclpy, so nobody can forget it.
"""
import os
import random

os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_STATIC_PEERS', None)
os.environ.pop('ROS_LOCALHOST_ONLY', None)  # deprecated in Jazzy; the range above rules.
# A test-local domain (0..101 are valid with default port mapping); parallel runs on one
# host do not see each other.
os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(30, 99))
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
os.environ.setdefault('PYTHONUNBUFFERED', '1')

import pytest  # noqa: E402


@pytest.fixture
def rclpy_context():
    """An isolated rclpy context for one test; shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)
