"""Pure-Python simulation core (pybullet, numpy): no rclpy import anywhere below here."""
