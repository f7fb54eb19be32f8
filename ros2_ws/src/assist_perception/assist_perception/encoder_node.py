"""encoder_node: RGB-D frames -> CM-VAE latent mean, pad estimate and (on demand) denoised depth.

Thin rclpy shell over assist_perception.encoder_core. Colour and depth are paired by header stamp
(approximate sync, `sync_slop_s`); each pair goes into a latest-only slot and a worker thread runs
the inference, so a slow frame never queues up old ones and callbacks never block.

With `depth_noise` (simulation: the encoder was trained on noisy depth) each frame's noise is drawn
from `noise.frame_rng(noise_seed, the depth header stamp in ns)`, not from one running generator: the
noise a frame got then depends on the recorded data alone, not on which frames this node happened to
drop or skip. bag_record stores this node's parameters (depth_noise, noise_seed, level_camera,
model_path, ...) in the bag's metadata, so replay_assist re-encodes a recorded flight through the
same noise and reproduces the latents that flew. (The alternative, publishing the noisy depth, would
cost a second depth stream per frame in every recording and still not tell replay the settings.)
"""
from __future__ import annotations

import array
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float32MultiArray, MultiArrayDimension

from assist_common.ros_io import (SENSOR_QOS, STAMP_TOLERANCE_S, Diagnostics, forward_logging, stamp_problem,
                                  stamp_to_sec)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import executor_param, exit_process, realtime_priority_param, run_node

from .encoder_core import BadFrame, LatentEncoder, LatestOnly, StampPairer, decode_color, decode_depth
from .level import DEFAULT_MIN_TILT_DEG, AttitudeBuffer, level_frame, level_rotation, tilt_deg
from .errors import ModelLoadError
from .noise import apply_depth_noise, frame_rng
from .onnx_backend import BACKENDS

PARAMS = {
    'model_path': Param('', 'CM-VAE weights file; empty = the shipped models/cmvae.pt.'),
    'device': Param('cpu', 'torch device for inference (cpu, cuda, cuda:0, ...).'),
    'backend': Param('auto', 'CM-VAE inference for mu + pad XYZ: onnxruntime (CPU; same weights, exported '
                     'at start-up, ~3x less CPU per frame), torch, or auto (onnxruntime on CPU, torch on '
                     'a GPU).', choices=BACKENDS),
    'threads': Param(1, 'torch intra-op threads for inference (0 = torch default).', min=0, max=256),
    'color_topic': Param('/camera/color/image_raw', 'Colour image topic (rgb8/bgr8).'),
    'depth_topic': Param('/camera/depth/image_raw', 'Depth image topic (32FC1 m or 16UC1 mm), aligned to colour.'),
    'latent_topic': Param('/assist/latent', 'Output: encoder mean mu (Float32MultiArray).'),
    'pad_topic': Param('/assist/pad_estimate', 'Output: closest pad top-centre (PointStamped, optical frame).'),
    'denoised_topic': Param('/assist/depth_denoised', 'Output: 64x64 32FC1 denoised depth (only when subscribed).'),
    'frame_id': Param('camera_optical_frame', 'frame_id of outputs when the input image has none.'),
    'sync_slop_s': Param(0.02, 'Colour and depth stamps closer than this form one frame.', min=0.0, max=1.0),
    'min_valid_depth_fraction': Param(0.01, 'Frames with fewer valid depth pixels are skipped (settable at run '
                                            'time).', min=0.0, max=1.0, dynamic=True),
    'depth_noise': Param(False, 'Apply the D435i-like noise model to incoming depth (clean sim depth -> '
                                'training distribution); leave off for a real camera.'),
    'noise_seed': Param(0, 'Seed of the depth noise (depth_noise only): the noise of a frame is a function of this '
                           'seed and its header stamp.', min=0, max=2**31 - 1),
    'max_frame_age_s': Param(0.5, 'Frames whose depth header stamp is older than this on the node\'s clock (sim or '
                                  'wall) are skipped and counted (bad_stale_stamp): a latent is never made of an '
                                  'old frame (settable at run time).', min=0.0, max=60.0, min_exclusive=True,
                             dynamic=True),
    'stamp_tolerance_s': Param(STAMP_TOLERANCE_S, 'Frames stamped further ahead of the node\'s clock than this (s) '
                               'are skipped and counted (bad_future_stamp) (settable at run time).', min=0.0,
                               max=10.0, dynamic=True),
    'executor': executor_param('events'),
    'realtime_priority': realtime_priority_param(0),
    'level_camera': Param(False, 'Undo the camera tilt before encoding (camera rigidly mounted on an airframe '
                                 'that rolls and pitches: ArduPilot SITL/JSON physics, real vehicles): each frame '
                                 'is re-rendered as a level camera would see it, using the /odom attitude nearest '
                                 'its stamp and the colour camera_info. Frames without both are skipped.'),
    'attitude_topic': Param('/odom', 'Attitude source for level_camera (nav_msgs/Odometry, odom <- base_link).'),
    'camera_info_topic': Param('/camera/color/camera_info', 'Intrinsics for level_camera (sensor_msgs/CameraInfo).'),
    'attitude_max_offset_s': Param(0.1, 'level_camera: an attitude sample must be this close to the frame stamp.',
                                   min=0.0, max=5.0, min_exclusive=True),
    'level_min_tilt_deg': Param(DEFAULT_MIN_TILT_DEG, 'level_camera: frames tilted less than this pass unchanged.',
                                min=0.0, max=45.0),
    'warn_period_s': Param(5.0, 'Minimum seconds between repeated bad-frame warnings (settable at run time).',
                           min=0.0, max=3600.0, dynamic=True),
}
# Bad-frame reasons that are part of normal flight: counted in diagnostics, logged once (INFO).
EXPECTED_SKIPS = {'no_valid_depth': 'frames without enough valid depth are skipped and counted '
                                    '(bad_no_valid_depth): normal at touchdown, the camera is too close'}


class EncoderNode(Node):
    """Subscribes colour + depth, publishes latent mu, pad estimate and denoised depth."""

    def __init__(self, **kwargs):
        super().__init__('encoder_node', **kwargs)
        forward_logging(self)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        try:
            self.encoder = LatentEncoder(self.p['model_path'] or None, self.p['device'],
                                         int(self.p['threads']), float(self.p['min_valid_depth_fraction']),
                                         backend=str(self.p['backend']))
        except ModelLoadError as exc:
            raise StartupError(f'encoder_node: {exc}') from exc
        except ValueError as exc:   # an unknown or unavailable torch device
            raise StartupError(f'encoder_node: {exc}') from exc
        self.diag = Diagnostics(self)
        self.diag.set('model_path', str(self.encoder.model_path))
        self.diag.set('latent_dim', self.encoder.latent_dim)
        self.pairer = StampPairer(float(self.p['sync_slop_s']))
        self.slot: LatestOnly[tuple[Image, Image]] = LatestOnly()
        self._last_warn: dict[str, float] = {}
        self._stopping = threading.Event()

        n = self.encoder.latent_dim
        self._latent_msg = Float32MultiArray()
        self._latent_msg.layout.dim = [MultiArrayDimension(label='latent', size=n, stride=n)]
        self.pub_latent = self.create_publisher(Float32MultiArray, self.p['latent_topic'], SENSOR_QOS)
        self.pub_pad = self.create_publisher(PointStamped, self.p['pad_topic'], SENSOR_QOS)
        self.pub_depth = self.create_publisher(Image, self.p['denoised_topic'], SENSOR_QOS)
        group = ReentrantCallbackGroup()
        self.create_subscription(Image, self.p['color_topic'], lambda m: self._on_image('color', m),
                                 SENSOR_QOS, callback_group=group)
        self.create_subscription(Image, self.p['depth_topic'], lambda m: self._on_image('depth', m),
                                 SENSOR_QOS, callback_group=group)
        self.attitude = AttitudeBuffer()
        self._K: tuple[int, int, np.ndarray] | None = None
        if self.p['level_camera']:
            self.create_subscription(Odometry, self.p['attitude_topic'], self._on_attitude, SENSOR_QOS,
                                     callback_group=group)
            self.create_subscription(CameraInfo, self.p['camera_info_topic'], self._on_camera_info, SENSOR_QOS,
                                     callback_group=group)
        self._worker = threading.Thread(target=self._work, name='cmvae_inference', daemon=True)
        self._worker.start()
        self.get_logger().info(f'CM-VAE {self.encoder.model_path} (latent {self.encoder.latent_dim}) '
                               f"on {self.p['device']}, {self.encoder.backend}")

    def _on_params(self, changed: dict) -> None:
        """Run-time sets of min_valid_depth_fraction and warn_period_s."""
        if 'min_valid_depth_fraction' in changed:
            self.encoder.min_valid_fraction = float(changed['min_valid_depth_fraction'])

    # ------------------------------------------------------------------ callbacks (cheap)
    def _on_image(self, stream: str, msg: Image) -> None:
        if self._stopping.is_set():
            return
        self.diag.count(f'{stream}_received')
        pair = self.pairer.add(stream, stamp_to_sec(msg.header.stamp), msg)
        self.diag.set('unpaired_images', self.pairer.unpaired)
        if pair is not None:
            self.diag.count('pairs')
            self.slot.put(pair)

    def _on_attitude(self, msg: Odometry) -> None:
        q = msg.pose.pose.orientation
        try:
            self.attitude.add(stamp_to_sec(msg.header.stamp), (q.x, q.y, q.z, q.w))
        except ValueError as exc:
            self._bad('attitude', f'{self.p["attitude_topic"]}: {exc}')

    def _on_camera_info(self, msg: CameraInfo) -> None:
        K = np.array(msg.k, dtype=float).reshape(3, 3)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and msg.width > 0 and msg.height > 0):
            self._bad('camera_info', f'{self.p["camera_info_topic"]}: unusable intrinsics {msg.k.tolist()}')
            return
        self._K = (int(msg.height), int(msg.width), K)

    def _level(self, rgb: np.ndarray, dep: np.ndarray, stamp: float) -> tuple[np.ndarray, np.ndarray]:
        """The frame as a level camera would see it (BadFrame when attitude or intrinsics are missing)."""
        if self._K is None:
            raise BadFrame('no_camera_info', f'level_camera: nothing on {self.p["camera_info_topic"]} yet')
        h, w, K = self._K
        if (h, w) != dep.shape or rgb.shape[:2] != dep.shape:
            raise BadFrame('camera_info_mismatch', f'level_camera: camera_info is {w}x{h}, frames '
                                                   f'{dep.shape[1]}x{dep.shape[0]}')
        q = self.attitude.nearest(stamp, float(self.p['attitude_max_offset_s']))
        if q is None:
            raise BadFrame('no_attitude', f'level_camera: no {self.p["attitude_topic"]} attitude within '
                                          f'{self.p["attitude_max_offset_s"]} s of the frame')
        r = level_rotation(q)
        tilt = tilt_deg(r)
        self.diag.set('tilt_deg', f'{tilt:.1f}')
        if tilt < float(self.p['level_min_tilt_deg']):
            return rgb, dep
        self.diag.count('frames_levelled')
        return level_frame(rgb, dep, K, r)

    # ------------------------------------------------------------------ worker thread
    def _work(self) -> None:
        while not self.slot.closed:
            pair = self.slot.take(timeout=0.5)
            if pair is None:
                continue
            try:
                self._process(*pair)
            except BadFrame as exc:
                self._bad(exc.reason, str(exc))
            except Exception as exc:  # noqa: BLE001 - keep the worker alive; log and count anything unexpected
                if self._stopping.is_set() or not self.context.ok():
                    break             # shutting down: the publishers' context is going away
                self._bad('inference_error', f'{type(exc).__name__}: {exc}')

    def _bad(self, reason: str, text: str) -> None:
        self.diag.count(f'bad_{reason}')
        self.diag.count('bad_frames')
        self.diag.status(DiagnosticStatus.WARN, f'skipping bad frames ({reason})')
        if reason in EXPECTED_SKIPS:
            if reason not in self._last_warn:
                self._last_warn[reason] = time.monotonic()
                self.get_logger().info(EXPECTED_SKIPS[reason])
            return
        now = time.monotonic()
        if now - self._last_warn.get(reason, -1e9) >= float(self.p['warn_period_s']):
            self._last_warn[reason] = now
            self.get_logger().warning(f'skipping frame: {text}')

    def _publish(self, pub, msg) -> bool:
        """Publish unless the node is stopping (then False: the context may already be gone)."""
        if self._stopping.is_set() or not self.context.ok():
            return False
        pub.publish(msg)
        return True

    def _process(self, color: Image, depth: Image) -> None:
        # a frame is dated by its header stamp against this node's clock (sim or wall): stale or from the future,
        # it is skipped and counted (bad_stale_stamp / bad_future_stamp), never encoded as the present
        stamp = stamp_to_sec(depth.header.stamp)
        problem = stamp_problem(stamp if stamp > 0 else None, self.get_clock().now().nanoseconds * 1e-9,
                                float(self.p['max_frame_age_s']), float(self.p['stamp_tolerance_s']))
        if problem is not None:
            raise BadFrame(*problem)
        rgb = decode_color(color.data, color.encoding, color.height, color.width, color.step)
        dep = decode_depth(depth.data, depth.encoding, depth.height, depth.width, depth.step,
                           bool(depth.is_bigendian))
        if self.p['depth_noise']:
            stamp_ns = depth.header.stamp.sec * 1_000_000_000 + depth.header.stamp.nanosec
            if stamp_ns < 0:
                raise BadFrame('bad_stamp', f'depth stamp {stamp_ns} ns is before the epoch')
            dep = apply_depth_noise(dep, frame_rng(int(self.p['noise_seed']), stamp_ns),
                                    rgb=rgb if rgb.shape[:2] == dep.shape else None)
        if self.p['level_camera']:             # after the noise: the sensor sees the tilted scene
            rgb, dep = self._level(rgb, dep, stamp_to_sec(depth.header.stamp))
        t0 = time.perf_counter()
        out = self.encoder.encode(rgb, dep, want_depth=False)   # mu first: the policy waits for it
        self.diag.set('inference_ms', f'{1000 * (time.perf_counter() - t0):.2f}')
        header = depth.header
        if not header.frame_id:
            header.frame_id = self.p['frame_id']
        lat = self._latent_msg             # reused: publish() serialises before it returns
        lat.data = array.array('f', out.mu.astype(np.float32, copy=False).tobytes())
        if not self._publish(self.pub_latent, lat):
            return
        pt = PointStamped()
        pt.header = header
        pt.point.x, pt.point.y, pt.point.z = (float(v) for v in out.pad_xyz)
        self._publish(self.pub_pad, pt)
        if self.pub_depth.get_subscription_count() > 0:      # the depth decoder only on demand
            denoised = self.encoder.decode_depth(out.mu)
            img = Image()
            img.header = header
            img.height, img.width = denoised.shape
            img.encoding = '32FC1'
            img.is_bigendian = 0
            img.step = 4 * img.width
            img.data = np.ascontiguousarray(denoised, dtype='<f4').tobytes()
            self._publish(self.pub_depth, img)
        self.diag.count('frames_encoded')
        self.diag.set('superseded_pairs', self.slot.replaced)
        self.diag.status(DiagnosticStatus.OK, 'encoding')

    def close(self) -> None:
        """Stop taking frames and the worker thread (before the node and its publishers go)."""
        self._stopping.set()
        self.slot.close()
        self._worker.join(timeout=2.0)
        self.diag.set('superseded_pairs', self.slot.replaced)


def main(args=None):
    """Console entry point `encoder_node`."""
    exit_process(run_node(lambda: EncoderNode(), args, params=PARAMS))


if __name__ == '__main__':
    main()
