"""Shared plumbing of the assisted-landing packages (no pybullet, no torch): see the package README."""
