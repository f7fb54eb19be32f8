"""Stand-in for realsense2_camera's realsense2_camera_node (Jazzy) without a camera (tests only).

Publishes what the driver publishes with `align_depth.enable: true` at its default 640x480 / 30 Hz profile,
on the driver's own node-relative names (so `ros2 launch` must remap them to the interface contract, as
onboard.launch.py does): `~/color/image_raw` (rgb8), `~/aligned_depth_to_color/image_raw` (16UC1, mm,
0 = no return), `~/color/camera_info`; one stamp per colour/depth pair. The scene: a floor 1.5 m below with
a raised square pad in the middle and a band of missing returns. Parameters given on the command line are
accepted as the driver's (automatically declared). Ctrl-C exits 0.
"""
from __future__ import annotations

import sys

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

WIDTH, HEIGHT, RATE_HZ = 640, 480, 30.0
FX = FY = 615.0                      # a D435i colour stream's focal length at 640x480, pixels


def _frames() -> tuple[np.ndarray, np.ndarray]:
    rgb = np.full((HEIGHT, WIDTH, 3), (90, 90, 90), np.uint8)
    depth = np.full((HEIGHT, WIDTH), 1500, np.uint16)
    rows, cols = slice(HEIGHT // 2 - 80, HEIGHT // 2 + 80), slice(WIDTH // 2 - 80, WIDTH // 2 + 80)
    rgb[rows, cols] = (200, 40, 40)
    depth[rows, cols] = 1400
    depth[:, :24] = 0                                  # the left band a D435i's stereo pair does not see
    return rgb, depth


class RealsenseStandIn(Node):
    """The driver's topics, from a fixed scene."""

    def __init__(self) -> None:
        super().__init__('camera', automatically_declare_parameters_from_overrides=True)
        self.rgb, self.depth = _frames()
        self.color_pub = self.create_publisher(Image, '~/color/image_raw', 10)
        self.depth_pub = self.create_publisher(Image, '~/aligned_depth_to_color/image_raw', 10)
        self.info_pub = self.create_publisher(CameraInfo, '~/color/camera_info', 10)
        self.create_timer(1.0 / RATE_HZ, self._tick)

    def _image(self, stamp, encoding: str, data: np.ndarray) -> Image:
        msg = Image()
        msg.header.stamp = stamp
        msg.header.frame_id = 'camera_color_optical_frame'
        msg.height, msg.width = data.shape[:2]
        msg.encoding = encoding
        msg.is_bigendian = 0
        msg.step = data.strides[0]
        msg.data = data.tobytes()
        return msg

    def _tick(self) -> None:
        stamp = self.get_clock().now().to_msg()
        self.color_pub.publish(self._image(stamp, 'rgb8', self.rgb))
        self.depth_pub.publish(self._image(stamp, '16UC1', self.depth))
        info = CameraInfo()
        info.header.stamp = stamp
        info.header.frame_id = 'camera_color_optical_frame'
        info.height, info.width = HEIGHT, WIDTH
        info.k = [FX, 0.0, WIDTH / 2, 0.0, FY, HEIGHT / 2, 0.0, 0.0, 1.0]
        self.info_pub.publish(info)


def main() -> int:
    """Run until Ctrl-C."""
    rclpy.init(args=sys.argv)
    node = RealsenseStandIn()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
