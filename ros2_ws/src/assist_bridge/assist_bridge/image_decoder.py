"""image_decoder (on the base station): image_relay's compressed pair back into the contract's raw topics.

Subscribes `<colour topic>/compressed` (JPEG) and `<depth topic>/compressedDepth` (16-bit PNG) and
publishes sensor_msgs/Image rgb8 on the colour topic and 16UC1 (millimetres) on the depth topic, each with
the header it came with (the camera's stamp and frame_id), so encoder_node and policy_node judge a frame's
age from the camera, radio delay included. Only the codec the `format` declares is decoded, and only after
its header is read (image_link.decode_color / decode_depth). A payload it refuses is counted on /diagnostics
as `rejected_<color|depth>_<reason>` and logged once per reason; the node keeps going. Reasons: `bad_format`
(the `format` is not image_transport's for that topic, or names another codec or encoding), `codec_mismatch`
(the data is not the declared codec: a TIFF, BMP or WebP labelled PNG, a PNG labelled JPEG), `too_large`
(over 8 MiB compressed), `bad_size` (its header announces more than 4096 px a side) and `bad_payload`
(a header or image data that cannot be read, a depth image that is not 16-bit greyscale).
"""
from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from sensor_msgs.msg import CompressedImage, Image

from assist_common.ros_io import Diagnostics
from assist_common.ros_params import Param, declare_parameters
from assist_common.ros_run import exit_process, run_node

from .image_link import COLOR_SUFFIX, DEPTH_SUFFIX, LinkError, decode_color, decode_depth
from .image_relay import LINK_QOS

PARAMS = {
    'color_topic': Param('/camera/color/image_raw', 'Raw colour output (rgb8); the input is this + /compressed.'),
    'depth_topic': Param('/camera/depth/image_raw', 'Raw depth output (16UC1 mm); the input is this + '
                                                    '/compressedDepth.'),
}


class ImageDecoder(Node):
    """Compressed pair -> raw pair, headers kept."""

    def __init__(self, **kwargs):
        super().__init__('image_decoder', **kwargs)
        self.p = declare_parameters(self, PARAMS)
        self.diag = Diagnostics(self)
        self.warned: set[str] = set()
        self.pub_color = self.create_publisher(Image, self.p['color_topic'], LINK_QOS)
        self.pub_depth = self.create_publisher(Image, self.p['depth_topic'], LINK_QOS)
        self.create_subscription(CompressedImage, self.p['color_topic'] + COLOR_SUFFIX, self._on_color, LINK_QOS)
        self.create_subscription(CompressedImage, self.p['depth_topic'] + DEPTH_SUFFIX, self._on_depth, LINK_QOS)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'image_decoder: {self.p["color_topic"]}{COLOR_SUFFIX} + '
                               f'{self.p["depth_topic"]}{DEPTH_SUFFIX} -> raw')

    def _refused(self, what: str, exc: LinkError) -> None:
        self.diag.count(f'rejected_{what}_{exc.reason}')
        if exc.reason not in self.warned:
            self.warned.add(exc.reason)
            self.get_logger().warning(f'image_decoder: {what} frame refused ({exc}); further ones are counted')

    def _publish(self, pub, msg: CompressedImage, img: np.ndarray, encoding: str) -> None:
        out = Image()
        out.header = msg.header
        out.height, out.width = int(img.shape[0]), int(img.shape[1])
        out.encoding = encoding
        out.is_bigendian = 0
        out.step = int(img.strides[0])
        out.data = np.ascontiguousarray(img).tobytes()
        pub.publish(out)

    def _on_color(self, msg: CompressedImage) -> None:
        try:
            rgb = decode_color(msg.data, msg.format)
        except LinkError as exc:
            self._refused('color', exc)
            return
        self._publish(self.pub_color, msg, rgb, 'rgb8')
        self.diag.count('color_out')

    def _on_depth(self, msg: CompressedImage) -> None:
        try:
            mm = decode_depth(msg.data, msg.format)
        except LinkError as exc:
            self._refused('depth', exc)
            return
        self._publish(self.pub_depth, msg, mm.astype('<u2', copy=False), '16UC1')
        self.diag.count('depth_out')

    def _report(self) -> None:
        out = self.diag.get('depth_out')
        self.diag.status(DiagnosticStatus.OK if out else DiagnosticStatus.WARN,
                         'decoding' if out else 'no compressed frame received yet')


def main(args=None):
    """Console entry point."""
    exit_process(run_node(lambda: ImageDecoder(), args, params=PARAMS))


if __name__ == '__main__':
    main()
