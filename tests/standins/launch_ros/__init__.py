"""Test-only stand-in for ROS 2 `launch_ros` (Node, ParameterValue, FindPackageShare); never installed."""
from . import actions, parameter_descriptions, substitutions  # noqa: F401
