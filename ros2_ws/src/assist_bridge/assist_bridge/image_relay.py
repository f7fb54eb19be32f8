"""image_relay (on the vehicle): the camera pair, compressed at the encoder's size and rate, for a radio link.

Subscribes the raw colour and depth topics (a RealSense driver's, remapped to the contract, or the sim's),
keeps only the newest frame of each, and on a timer at `rate_hz` publishes the newest pair not sent yet as
sensor_msgs/CompressedImage on `<colour topic>/compressed` (JPEG) and `<depth topic>/compressedDepth`
(16-bit PNG, millimetres), each with its source frame's header (stamp and frame_id), so the base station
judges the frame's age as if it had the camera. Best-effort, depth-1 QoS on both sides: over a slow link
an old frame is dropped, never queued. Frames it cannot read are counted on /diagnostics by reason.
Payload format and shrinking: assist_bridge.image_link. Its partner on the base station: image_decoder.
"""
from __future__ import annotations

import threading

from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image

from assist_common.images import BadFrame, decode_color, decode_depth
from assist_common.ros_io import Diagnostics, stamp_to_sec
from assist_common.ros_params import Param, declare_parameters
from assist_common.ros_run import exit_process, run_node

from .image_link import COLOR_FORMAT, COLOR_SUFFIX, DEPTH_FORMAT, DEPTH_SUFFIX, LinkConfig, LinkError, pack_pair

# Over a radio link: the newest frame only, never a queue of old ones; lost frames are not resent.
LINK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT, history=HistoryPolicy.KEEP_LAST)
_D = LinkConfig()
PARAMS = {
    'color_topic': Param('/camera/color/image_raw', 'Raw colour input (rgb8/bgr8/rgba8/bgra8).'),
    'depth_topic': Param('/camera/depth/image_raw', 'Raw depth input (32FC1 metres or 16UC1 millimetres).'),
    'rate_hz': Param(20.0, 'Pairs sent per second at most (the encoder\'s rate); newer frames replace unsent ones.',
                     min=0.5, max=100.0),
    'width': Param(_D.width, 'Width of the sent frames (the encoder\'s input).', min=8, max=1280),
    'height': Param(_D.height, 'Height of the sent frames (the encoder\'s input).', min=8, max=960),
    'jpeg_quality': Param(_D.jpeg_quality, 'JPEG quality of the colour frames (settable at run time).', min=10,
                          max=100, dynamic=True),
    'png_level': Param(_D.png_level, 'PNG (zlib) effort for the depth frames, 0-9.', min=0, max=9),
    'max_pair_gap_s': Param(0.1, 'A colour and a depth frame whose stamps differ more than this are not a pair.',
                            min=0.0, max=5.0, min_exclusive=True),
}


class ImageRelay(Node):
    """Newest raw pair -> compressed pair at `rate_hz`."""

    def __init__(self, **kwargs):
        super().__init__('image_relay', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        self.cfg = LinkConfig(width=self.p['width'], height=self.p['height'], jpeg_quality=self.p['jpeg_quality'],
                              png_level=self.p['png_level'])
        self.diag = Diagnostics(self)
        self.lock = threading.Lock()
        self.color: Image | None = None
        self.depth: Image | None = None
        self.sent_stamp: float | None = None
        self.bytes_sent = 0
        color_out, depth_out = self.p['color_topic'] + COLOR_SUFFIX, self.p['depth_topic'] + DEPTH_SUFFIX
        self.pub_color = self.create_publisher(CompressedImage, color_out, LINK_QOS)
        self.pub_depth = self.create_publisher(CompressedImage, depth_out, LINK_QOS)
        self.create_subscription(Image, self.p['color_topic'], self._on_color, LINK_QOS)
        self.create_subscription(Image, self.p['depth_topic'], self._on_depth, LINK_QOS)
        self.create_timer(1.0 / self.p['rate_hz'], self._send)
        self.create_timer(1.0, self._report)
        self.get_logger().info(f'image_relay: {self.p["color_topic"]} + {self.p["depth_topic"]} -> {color_out} + '
                               f'{depth_out} at {self.cfg.width}x{self.cfg.height}, <= {self.p["rate_hz"]} Hz, '
                               f'JPEG {self.cfg.jpeg_quality}')

    def _on_params(self, changed: dict) -> None:
        if 'jpeg_quality' in changed:
            with self.lock:
                self.cfg.jpeg_quality = int(changed['jpeg_quality'])

    def _on_color(self, msg: Image) -> None:
        self.diag.count('color_in')
        with self.lock:
            self.color = msg

    def _on_depth(self, msg: Image) -> None:
        self.diag.count('depth_in')
        with self.lock:
            self.depth = msg

    def _send(self) -> None:
        with self.lock:
            color, depth, cfg = self.color, self.depth, LinkConfig(**vars(self.cfg))
        if color is None or depth is None:
            return
        stamp = stamp_to_sec(depth.header.stamp)
        if stamp == self.sent_stamp:
            return                                   # nothing new since the last pair
        if abs(stamp_to_sec(color.header.stamp) - stamp) > self.p['max_pair_gap_s']:
            self.diag.count('unpaired')
            return
        try:
            rgb = decode_color(color.data, color.encoding, color.height, color.width, color.step)
            dm = decode_depth(depth.data, depth.encoding, depth.height, depth.width, depth.step,
                              bool(depth.is_bigendian))
            jpeg, png = pack_pair(rgb, dm, cfg)
        except (BadFrame, LinkError) as exc:
            self.diag.count(f'rejected_{exc.reason}')
            self.sent_stamp = stamp
            return
        self.sent_stamp = stamp
        for pub, src, fmt, payload in ((self.pub_color, color, COLOR_FORMAT, jpeg),
                                       (self.pub_depth, depth, DEPTH_FORMAT, png)):
            out = CompressedImage()
            out.header = src.header
            out.format = fmt
            out.data = payload
            pub.publish(out)
        self.bytes_sent += len(jpeg) + len(png)
        self.diag.count('pairs_sent')

    def _report(self) -> None:
        self.diag.set('bytes_sent', self.bytes_sent)
        sent = self.diag.get('pairs_sent')
        self.diag.status(DiagnosticStatus.OK if sent else DiagnosticStatus.WARN,
                         'sending' if sent else 'no camera pair received yet')


def main(args=None):
    """Console entry point."""
    exit_process(run_node(lambda: ImageRelay(), args, params=PARAMS))


if __name__ == '__main__':
    main()

