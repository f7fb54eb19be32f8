"""MAVLink bridge to ArduPilot (pymavlink) and keyboard teleop."""
