"""policy_node: runs the TD3 actor at a fixed rate and publishes /assist/agent_cmd and blended /cmd_vel.

Thin rclpy shell over ``policy_core.PolicyCore`` (inputs, staleness, blending, NaN rejection).
"""
from __future__ import annotations

import sys
import threading

import numpy as np
import torch
from geometry_msgs.msg import PointStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Float32MultiArray

from assist_sim.ros_common import (LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, Diagnostics, Param, StartupError,
                                   declare_parameters, fill_twist, run_node, twist_to_array)

from .blending import DEFAULT_THRESHOLD
from .policy_core import PolicyCore, PolicyCoreConfig, default_model_path

PARAMS = {
    'model_path': Param('', 'TD3 actor file; empty: the shipped models/td3_<mode>_actor.pt.'),
    'mode': Param('latent', 'Assistant input: latent (CM-VAE /assist/latent), oracle (/sim/goal, sim only), '
                            'end_to_end (raw RGB-D images).'),
    'rate_hz': Param(20.0, 'Actor rate (the training control rate is 20 Hz).'),
    'blend_threshold': Param(DEFAULT_THRESHOLD, 'Agent actions with |a| at or below this (m/s) are ignored: V = u.'),
    'pilot_timeout_s': Param(0.5, 'Pilot command older than this counts as absent (u = 0).'),
    'latent_timeout_s': Param(0.5, 'Latent (or image) older than this: the assistant relinquishes (V = u).'),
    'odom_timeout_s': Param(0.5, 'Odometry older than this: the assistant relinquishes (V = u).'),
    'max_speed': Param(1.5, 'Horizontal speed limit of the published /cmd_vel (m/s).'),
    'max_vertical_speed': Param(1.0, 'Vertical speed limit of the published /cmd_vel (m/s).'),
    'max_input_speed': Param(5.0, 'Pilot commands faster than this are rejected as out of range (m/s).'),
    'frame_id': Param('base_link', 'frame_id of the published commands.'),
    'torch_threads': Param(1, 'Intra-op CPU threads for the actor (1 is fastest for this small network).'),
    'step_on_latent': Param(True, 'latent mode: run the actor as soon as a new latent arrives (camera-to-command '
                                  'latency = one inference, /cmd_vel stamped with the frame\'s sim time); the '
                                  'rate_hz timer then runs only while latents are missing.'),
}


def _image_to_array(msg: Image) -> np.ndarray:
    """sensor_msgs/Image (rgb8, 32FC1, 16UC1) -> numpy (uint8 HxWx3 or float32 metres HxW)."""
    h, w = msg.height, msg.width
    if msg.encoding == 'rgb8':
        return np.frombuffer(bytes(msg.data), np.uint8).reshape(h, msg.step)[:, :w * 3].reshape(h, w, 3)
    if msg.encoding == '32FC1':
        return np.frombuffer(bytes(msg.data), np.float32).reshape(h, msg.step // 4)[:, :w].copy()
    if msg.encoding == '16UC1':
        return np.frombuffer(bytes(msg.data), np.uint16).reshape(h, msg.step // 2)[:, :w].astype(np.float32) / 1000.0
    raise ValueError(f'unsupported image encoding {msg.encoding!r}')


class PolicyNode(Node):
    """Subscribes latent/odom/pilot (+goal in oracle mode), publishes agent_cmd and cmd_vel."""

    def __init__(self, **kwargs):
        super().__init__('policy_node', **kwargs)
        self.p = declare_parameters(self, PARAMS)
        self.diag = Diagnostics(self)
        mode = self.p['mode']
        if mode not in ('latent', 'oracle', 'end_to_end'):
            raise StartupError(f"policy_node: mode must be latent, oracle or end_to_end, got '{mode}'")
        if not self.p['rate_hz'] > 0:
            raise StartupError('policy_node: rate_hz must be > 0')
        if int(self.p['torch_threads']) < 1:
            raise StartupError('policy_node: torch_threads must be >= 1')
        # a 256x256 MLP gains nothing from intra-op threads; spinning OpenMP workers would starve
        # the sim and the other nodes on a small machine
        torch.set_num_threads(int(self.p['torch_threads']))
        path = self.p['model_path'] or str(default_model_path(mode))
        cfg = PolicyCoreConfig(mode=mode, blend_threshold=float(self.p['blend_threshold']),
                               pilot_timeout_s=float(self.p['pilot_timeout_s']),
                               feature_timeout_s=float(self.p['latent_timeout_s']),
                               odom_timeout_s=float(self.p['odom_timeout_s']),
                               max_speed_mps=float(self.p['max_speed']),
                               max_vertical_mps=float(self.p['max_vertical_speed']))
        try:
            self.core = PolicyCore(path, cfg)
        except ValueError as exc:
            raise StartupError(f'policy_node: {exc}') from exc
        self._lock = threading.Lock()
        inputs = MutuallyExclusiveCallbackGroup()
        self.pub_agent = self.create_publisher(TwistStamped, '/assist/agent_cmd', RELIABLE_QOS)
        self.pub_cmd = self.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
        self.create_subscription(Odometry, '/odom', self._on_odom, SENSOR_QOS, callback_group=inputs)
        self.create_subscription(TwistStamped, '/pilot/cmd_vel', self._on_pilot, RELIABLE_QOS,
                                 callback_group=inputs)
        if mode == 'latent':
            self.create_subscription(Float32MultiArray, '/assist/latent', self._on_latent, SENSOR_QOS,
                                     callback_group=inputs)
        elif mode == 'oracle':
            self.create_subscription(PointStamped, '/sim/goal', self._on_goal, LATCHED_QOS,
                                     callback_group=inputs)
        else:
            self._rgb = None
            self.create_subscription(Image, '/camera/color/image_raw', self._on_rgb, SENSOR_QOS,
                                     callback_group=inputs)
            self.create_subscription(Image, '/camera/depth/image_raw', self._on_depth, SENSOR_QOS,
                                     callback_group=inputs)
        self._on_latent_steps = mode == 'latent' and bool(self.p['step_on_latent'])
        self._last_latent_step = -1e9           # node-clock time of the last latent-driven step
        self.create_timer(1.0 / float(self.p['rate_hz']), self._on_timer,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.diag.set('model_path', path)
        self.diag.set('mode', mode)
        self.get_logger().info(f'policy_node: {mode} actor {path} at {self.p["rate_hz"]} Hz')

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _reject(self, what: str, exc: Exception) -> None:
        self.diag.count(f'rejected_{what}')
        self.get_logger().warning(f'rejected {what}: {exc}', throttle_duration_sec=2.0)

    def _on_odom(self, msg: Odometry) -> None:
        p, v = msg.pose.pose.position, msg.twist.twist.linear
        try:
            with self._lock:
                self.core.set_odom(self._now(), [p.x, p.y, p.z], [v.x, v.y, v.z])
        except ValueError as exc:
            self._reject('odom', exc)

    def _on_pilot(self, msg: TwistStamped) -> None:
        u = twist_to_array(msg)
        try:
            if np.all(np.isfinite(u)) and np.abs(u).max() > float(self.p['max_input_speed']):
                raise ValueError(f'pilot command {u.tolist()} out of range')
            with self._lock:
                self.core.set_pilot(self._now(), u)
        except ValueError as exc:
            self._reject('pilot', exc)

    def _on_latent(self, msg: Float32MultiArray) -> None:
        try:
            with self._lock:
                self.core.set_latent(self._now(), np.asarray(msg.data, dtype=float))
        except ValueError as exc:
            self._reject('latent', exc)
            return
        if self._on_latent_steps:
            self._last_latent_step = self._now()
            self._tick()

    def _on_timer(self) -> None:
        # with latent-driven steps the timer only covers gaps in the latent stream
        if not 0.0 <= self._now() - self._last_latent_step <= 1.5 / float(self.p['rate_hz']):
            self._tick()

    def _on_goal(self, msg: PointStamped) -> None:
        try:
            with self._lock:
                self.core.set_goal([msg.point.x, msg.point.y, msg.point.z])
                self.core.reset()
        except ValueError as exc:
            self._reject('goal', exc)

    def _on_rgb(self, msg: Image) -> None:
        try:
            self._rgb = _image_to_array(msg)
        except ValueError as exc:
            self._reject('image', exc)

    def _on_depth(self, msg: Image) -> None:
        try:
            if self._rgb is None:
                return
            depth = _image_to_array(msg)
            with self._lock:
                self.core.set_image(self._now(), self._rgb, depth)
        except ValueError as exc:
            self._reject('image', exc)

    def _tick(self) -> None:
        now = self._now()
        with self._lock:
            out = self.core.step(now)
            rejected = self.core.rejected
        stamp = self.get_clock().now().to_msg()
        frame = self.p['frame_id']
        if out.agent is not None:
            msg = TwistStamped()
            msg.header.stamp, msg.header.frame_id = stamp, frame
            self.pub_agent.publish(fill_twist(msg, out.agent))
            self.diag.count('agent_cmds')
        if not np.all(np.isfinite(out.velocity)):  # defence in depth: never reaches an actuator
            self.diag.count('rejected_velocity')
            return
        cmd = TwistStamped()
        cmd.header.stamp, cmd.header.frame_id = stamp, frame
        self.pub_cmd.publish(fill_twist(cmd, out.velocity))
        self.diag.set('state', out.reason)
        self.diag.set('rejected_actor_outputs', rejected)


def main(args=None):
    """Console entry point."""
    sys.exit(run_node(lambda: PolicyNode(), args))


if __name__ == '__main__':
    main()
