"""Base-station side: the browser pilot station (human interface); never imports pybullet."""
