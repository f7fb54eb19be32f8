"""pilot_station: the browser pilot station as a ROS 2 node (thin shell over station_core + server).

Serves the page (chase view from /sim/scene + /odom, camera inset, assisted state, landing results,
the assistant's intent cues from /assist/goal_estimate, /assist/descent_ok and /cmd_vel) and publishes
the pilot's held keys as /pilot/cmd_vel (TwistStamped, base_link) at a fixed rate, and at once when
the command changes. No message on any topic stops the node: an unusable one is
rejected, counted on /diagnostics and logged once per reason.
"""
from __future__ import annotations

import functools
import math
import threading
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, String
from visualization_msgs.msg import Marker, MarkerArray

from assist_common.constants import BLEND_THRESHOLD_MPS
from assist_common.ros_io import (LANDING_QOS, LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, STAMP_TOLERANCE_S, Diagnostics,
                                  fill_twist, stamp_to_sec, twist_to_array)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import exit_process, run_node

from .server import ServerConfig, StationServer
from .access import allowed_hosts
from .station_core import (CUES, MODES, AssistMonitor, CommandGate, CueConfig, InputError, IntentCues, KeyState,
                           OncePerReason, StationConfig, StudyMessage, camera_payload, landing_feedback, parse_landing,
                           scene_from_boxes, short_repr)
from .study import StudyConfig, StudyError

PARAMS = {
    'host': Param('127.0.0.1', 'Address the HTTP/WebSocket server binds to (loopback by default). Requests '
                               'must name it (Host and Origin headers): 127.0.0.1, localhost or [::1] for a '
                               'loopback bind, also the machine\'s names for 0.0.0.0, else the address itself.'),
    'allowed_hosts': Param([], 'More host names (or name:port) the page may be reached by, e.g. a DNS name of '
                               'this machine; each is added to the Host/Origin allow-list.', item_type=str),
    'port': Param(8080, 'TCP port of the page (0: any free port; the printed URL says which).', min=0, max=65535),
    'mode': Param('practice', 'practice: goal marked, result after each landing; study: goal marked, no '
                              'feedback (the paper\'s study landings); free: no goal marker, result shown.',
                  choices=MODES),
    'rate_hz': Param(20.0, 'Fixed publish rate of /pilot/cmd_vel (Hz); key changes also publish at once.',
                     min=1.0, max=200.0),
    'speed': Param(StationConfig.speed, 'Horizontal speed of W/S/A/D (m/s).', min=0.0, max=5.0, min_exclusive=True),
    'speed_z': Param(StationConfig.speed_z, 'Vertical speed of ArrowUp/ArrowDown (m/s).', min=0.0, max=5.0,
                     min_exclusive=True),
    'key_timeout_s': Param(StationConfig.key_timeout_s, 'Held keys the page has not refreshed for this long '
                           'count as released (the page refreshes every 0.25 s).', min=0.3, max=10.0),
    'view_rate_hz': Param(30.0, 'Rate of pose/state updates sent to the page (Hz).', min=1.0, max=120.0),
    'camera_rate_hz': Param(15.0, 'Most camera inset frames per second sent to the page (0: no inset).',
                            min=0.0, max=60.0),
    'camera_max_width': Param(160, 'Camera inset frames wider or taller than this are subsampled (pixels).',
                              min=8, max=1280),
    'agent_timeout_s': Param(0.5, '/assist/agent_cmd older than this: the page shows "unassisted".',
                             min=0.0, max=10.0, min_exclusive=True),
    'assist_threshold': Param(BLEND_THRESHOLD_MPS, 'Agent actions above this norm (m/s) show as "assistant '
                              'acting" (the blending threshold).', min=0.0, max=5.0),
    'max_message_bytes': Param(1024, 'Page messages larger than this are rejected (bytes).', min=64, max=65536),
    'stall_timeout_s': Param(5.0, 'A page that stops reading for this long is disconnected (s).',
                             min=0.1, max=120.0),
    'max_connections': Param(16, 'Most WebSocket connections open at once; more are refused (503). The pilot '
                                 'page reconnecting with its session token is always let in.', min=1, max=10000),
    'pilot_grace_s': Param(10.0, 'After the pilot page\'s socket drops, the pilot role waits this long for that '
                                 'page to reconnect; other pages stay view only meanwhile (s).', min=0.0, max=600.0),
    'chase_back_m': Param(3.5, 'Chase camera distance behind the drone (m).', min=0.0, max=50.0),
    'chase_up_m': Param(2.0, 'Chase camera height above the drone (m).', min=0.0, max=50.0),
    'fov_deg': Param(60.0, 'Vertical field of view of the chase view (deg).', min=10.0, max=120.0),
    'camera_vfov_deg': Param(58.0, 'Vertical field of view of the downward camera (deg), to place the goal cue in '
                                   'the camera inset (image top = body forward, optical x = body -y).',
                             min=1.0, max=170.0),
    'camera_offset_m': Param(0.05, 'Optical centre of the downward camera below base_link, on the body z axis (m).',
                             min=0.0, max=2.0),
    'cue_goal': Param(True, 'Show the assistant\'s estimated goal pad (/assist/goal_estimate) in the chase view and '
                            'the camera inset (settable at run time; a study sets it: on only in its assisted_cues '
                            'landings).', dynamic=True),
    'cue_descent': Param(True, 'Show the assistant\'s descent light (/assist/descent_ok): green descend, red hold, '
                               'grey unknown (settable at run time; a study sets it: on only in its assisted_cues '
                               'landings).', dynamic=True),
    'cue_push': Param(True, 'Show the assistant\'s push, /cmd_vel minus the pilot\'s command, as an arrow from '
                            'the drone in the chase view (settable at run time; a study sets it: on only in its '
                            'assisted_cues landings).', dynamic=True),
    'cue_timeout_s': Param(CueConfig.timeout_s, 'A goal estimate or /cmd_vel stamped longer ago than this, or a '
                           '/assist/descent_ok not received for this long, shows as unknown (s, the node\'s clock: '
                           'sim time under use_sim_time).', min=0.0, max=10.0, min_exclusive=True),
    'cue_max_sigma_m': Param(CueConfig.max_sigma_m, 'A goal estimate whose sqrt(max(var x, var y)) exceeds this is '
                             'drawn as unsure (outlined, not filled) (m).', min=0.0, max=100.0, min_exclusive=True),
    'cue_pad_tolerance_m': Param(CueConfig.pad_tolerance_m, 'A goal estimate farther than this from the top centre '
                                 'of every pad of /sim/scene (horizontally or vertically) is an unknown pad: not '
                                 'drawn, counted (m).', min=0.0, max=10.0, min_exclusive=True),
    'frame_id': Param('base_link', 'frame_id of the published /pilot/cmd_vel.'),
    'study_config': Param('', 'User-study YAML file (see config/study.yaml); empty: no study. With one, the page '
                              'runs the protocol (participant ID, consent, practice, a block per condition, '
                              'questionnaires), the keys fly only while a landing is in flight, and results go '
                              'under study_dir.'),
    'study_dir': Param('study_data', 'Directory holding one directory per participant (created if missing).'),
    'study_sim_node': Param('/sim_node', 'sim_node whose scene_seed/goal_index/auto_reset the study sets.'),
    'study_policy_node': Param('/policy_node', 'policy_node whose assist_enabled the study switches per block.'),
    'study_encoder_node': Param('/encoder_node', 'encoder_node whose model_path the study checks (encoder_model).'),
}


def _finite(values) -> bool:
    return all(math.isfinite(float(x)) for x in values)


class PilotStation(Node):
    """Web pilot station: page + WebSocket in, /pilot/cmd_vel out."""

    def __init__(self, **kwargs):
        super().__init__('pilot_station', **kwargs)
        self.p = declare_parameters(self, PARAMS)
        self.diag = Diagnostics(self)
        p = self.p
        study_cfg = None
        if p['study_config']:
            try:
                study_cfg = StudyConfig.load(p['study_config'])
            except StudyError as exc:
                raise StartupError(f'pilot_station: {exc}') from None
        key_cfg = StationConfig(speed=p['speed'], speed_z=p['speed_z'], key_timeout_s=p['key_timeout_s'])
        if study_cfg is not None:           # a study counts the pilot's key presses per landing
            from .study_station import CountingKeyState
            self.keys = CountingKeyState(key_cfg)
        else:
            self.keys = KeyState(key_cfg)
        self.assist = AssistMonitor(p['agent_timeout_s'], p['assist_threshold'])
        self.gate = CommandGate()
        self.cues = IntentCues(CueConfig(timeout_s=p['cue_timeout_s'], max_sigma_m=p['cue_max_sigma_m'],
                                         pad_tolerance_m=p['cue_pad_tolerance_m'],
                                         stamp_tolerance_s=STAMP_TOLERANCE_S), count=self.diag.count)
        self._first = OncePerReason()
        self._lock = threading.Lock()
        self._odom: dict | None = None
        self._odom_time = -math.inf
        self._last_camera = -math.inf
        self.pub_cmd = self.create_publisher(TwistStamped, '/pilot/cmd_vel', RELIABLE_QOS)
        guard = self._guarded
        self.create_subscription(Odometry, '/odom', guard('odom', self._on_odom), SENSOR_QOS)
        self.create_subscription(MarkerArray, '/sim/scene', guard('scene', self._on_scene), LATCHED_QOS)
        self.create_subscription(TwistStamped, '/assist/agent_cmd', guard('agent_cmd', self._on_agent), RELIABLE_QOS)
        self.create_subscription(String, '/sim/landing', guard('landing', self._on_landing), LANDING_QOS)
        self.create_subscription(PoseWithCovarianceStamped, '/assist/goal_estimate',
                                 guard('goal_estimate', self._on_goal_estimate), RELIABLE_QOS)
        self.create_subscription(Bool, '/assist/descent_ok', guard('descent_ok', self._on_descent_ok), RELIABLE_QOS)
        self.create_subscription(TwistStamped, '/cmd_vel', guard('cmd_vel', self._on_cmd_vel), RELIABLE_QOS)
        if p['camera_rate_hz'] > 0:
            self.create_subscription(Image, '/camera/color/image_raw', guard('camera', self._on_camera), SENSOR_QOS)
        self.study = None
        hello = {'mode': p['mode'], 'study': study_cfg is not None,      # a study always marks the goal pad
                 'show_goal': p['mode'] in ('practice', 'study') or study_cfg is not None,
                 'chase': {'back_m': p['chase_back_m'], 'up_m': p['chase_up_m'], 'fov_deg': p['fov_deg']},
                 'speed': p['speed'], 'speed_z': p['speed_z'], 'camera': p['camera_rate_hz'] > 0,
                 'camera_geom': {'vfov_deg': p['camera_vfov_deg'], 'offset_m': p['camera_offset_m']}}
        try:
            allowed_hosts(p['host'], 80, p['allowed_hosts'])
        except ValueError as exc:
            raise StartupError(f"pilot_station: parameter 'allowed_hosts': {exc}") from None
        self.server = StationServer(
            ServerConfig(host=p['host'], port=int(p['port']), max_message_bytes=int(p['max_message_bytes']),
                         view_rate_hz=p['view_rate_hz'], stall_timeout_s=p['stall_timeout_s'],
                         allowed_hosts=tuple(p['allowed_hosts']), max_connections=int(p['max_connections']),
                         pilot_grace_s=p['pilot_grace_s']),
            self.keys, self._state, hello, on_command=self._on_page_command, count=self.diag.count,
            on_study=self._on_study if study_cfg is not None else None, on_pilot_lost=self._on_pilot_lost)
        if study_cfg is not None:
            from .study_station import StudyDriver
            try:
                self.study = StudyDriver(self, study_cfg[0], study_cfg[1], Path(p['study_dir']),
                                         self.server.set_study, self.server.push_event,
                                         sim_node=p['study_sim_node'], policy_node=p['study_policy_node'],
                                         encoder_node=p['study_encoder_node'], key_counter=self.keys.counter)
            except OSError as exc:
                raise StartupError(f"pilot_station: cannot use study_dir {p['study_dir']}: {exc}") from None
            self.server.set_study(self.study.view())
            self.create_timer(0.1, guard('study', self.study.tick))
        try:
            url = self.server.start()
        except OSError as exc:
            raise StartupError(f"pilot_station: cannot serve on {p['host']}:{p['port']}: {exc}") from exc
        self.create_timer(1.0 / p['rate_hz'], guard('tick', self._tick))
        self.create_timer(1.0, guard('diagnostics', self._diag_values))
        if self.study is not None:
            self.get_logger().info(f"user study '{study_cfg[0].name}' ({study_cfg[0].landings_per_block} landings per "
                                   f"block): participants under {Path(p['study_dir']).resolve()}")
        print(f'pilot_station: open {url} in a browser', flush=True)
        self.get_logger().info(f"pilot station at {url} (mode {p['mode']}, /pilot/cmd_vel at {p['rate_hz']} Hz; "
                               f"serves the host names {self.server.policy.describe()})")

    def _guarded(self, name: str, fn: Callable[..., None]) -> Callable[..., None]:
        """`fn` as a callback that never raises: an exception is counted ({name}_errors) and logged once per kind."""
        @functools.wraps(fn)
        def call(*args: Any) -> None:
            try:
                fn(*args)
            except Exception as exc:  # noqa: BLE001 - no message may kill the node between pilot and vehicle
                self.diag.count(f'{name}_errors')
                if self._first(f'{name}:{type(exc).__name__}'):
                    self.get_logger().error(f'{name} callback failed, input dropped (further ones counted as '
                                            f'{name}_errors): {short_repr(exc, 200)}')
        return call

    def _rejected(self, counter: str, exc: InputError) -> None:
        """Count an unusable input and log it the first time its reason is seen."""
        self.diag.count(counter)
        if self._first(f'{counter}:{exc.reason}'):
            self.get_logger().warning(f'{exc} (further ones counted as {counter})')

    # ------------------------------------------------------------------ commands
    def _publish(self, v: np.ndarray) -> None:
        msg = TwistStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.p['frame_id']
        self.pub_cmd.publish(fill_twist(msg, v))
        self.cues.note_pilot(v)

    def _keys_fly(self) -> bool:
        """Whether the pilot's keys reach the vehicle now (always, except between a study's landings)."""
        return self.study is None or self.study.flying

    def _on_page_command(self, v: np.ndarray) -> None:
        """A command from the page: published at once when it changed (CommandGate), else left to the timer."""
        if not self._keys_fly():
            v = np.zeros(3)
        if self.gate.immediate(v, time.monotonic()):
            self._publish(v)

    def _on_study(self, msg: StudyMessage) -> None:
        """A study step from the pilot page (web server thread): handed to the study driver's queue."""
        self.study.submit(msg)

    def _on_pilot_lost(self) -> None:
        """The pilot page's socket went away (web server thread)."""
        if self.study is not None:
            self.study.page_lost()

    def _tick(self) -> None:
        v = self.keys.command(time.monotonic()) if self._keys_fly() else np.zeros(3)
        self.gate.sent(v)
        self._publish(v)

    # ------------------------------------------------------------------ inputs
    def _on_odom(self, msg: Odometry) -> None:
        pp, tw = msg.pose.pose, msg.twist.twist
        p = (pp.position.x, pp.position.y, pp.position.z)
        q = (pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w)
        v = (tw.linear.x, tw.linear.y, tw.linear.z)
        if not (_finite(p) and _finite(q) and _finite(v)) or sum(x * x for x in q) < 1e-6:
            self._rejected('odom_rejected', InputError('/odom rejected: non-finite pose/twist or zero quaternion'))
            return
        with self._lock:
            self._odom = {'p': [float(x) for x in p], 'q': [float(x) for x in q], 'v': [float(x) for x in v]}
            self._odom_time = time.monotonic()
        if self.study is not None:
            self.study.note_odom(np.array(p), self._stamp(msg))

    def _on_scene(self, msg: MarkerArray) -> None:
        boxes = []
        for m in msg.markers:
            if m.action == Marker.DELETEALL:
                boxes = []
                continue
            if m.type != Marker.CUBE or m.action != Marker.ADD or m.ns not in ('platforms', 'goal'):
                continue
            boxes.append({'ns': m.ns, 'id': m.id,
                          'p': (m.pose.position.x, m.pose.position.y, m.pose.position.z),
                          'q': (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                                m.pose.orientation.w),
                          's': (m.scale.x, m.scale.y, m.scale.z), 'c': (m.color.r, m.color.g, m.color.b)})
        try:
            scene = scene_from_boxes(boxes)
        except ValueError as exc:
            self._rejected('scene_rejected', InputError('/sim/scene rejected', short_repr(str(exc), 200)))
            return
        self.server.set_scene(scene)
        self.cues.set_scene(scene['platforms'])
        if self.study is not None:
            self.study.note_scene(boxes)
        self.get_logger().info(f"scene: {len(scene['platforms'])} platforms, goal {scene['goal']}")

    def _on_agent(self, msg: TwistStamped) -> None:
        if not self.assist.note(twist_to_array(msg), time.monotonic()):
            self._rejected('agent_cmd_rejected', InputError('/assist/agent_cmd rejected: not a finite 3-vector'))

    def _now_s(self) -> float:
        """The node's clock in seconds (sim time under use_sim_time)."""
        return self.get_clock().now().nanoseconds * 1e-9

    @staticmethod
    def _stamp(msg: Any) -> float | None:
        """A message's header stamp in seconds; None when unset (the message is then dated by its arrival)."""
        t = stamp_to_sec(msg.header.stamp)
        return t if t > 0 else None

    def _on_goal_estimate(self, msg: PoseWithCovarianceStamped) -> None:
        """The assistant's goal pad estimate: validated by the cue core, a rejected one counted by reason."""
        pp = msg.pose.pose
        try:
            self.cues.note_goal(msg.header.frame_id, self._stamp(msg), (pp.position.x, pp.position.y, pp.position.z),
                                (pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w),
                                msg.pose.covariance, self._now_s())
        except InputError as exc:
            self._rejected(f'goal_estimate_rejected_{exc.kind}', exc)

    def _on_descent_ok(self, msg: Bool) -> None:
        """The assistant's descent light (no header: dated by its arrival on the node's clock)."""
        self.cues.note_descent(bool(msg.data), self._now_s())

    def _on_cmd_vel(self, msg: TwistStamped) -> None:
        """The blended command V that flies: with the station's own u it gives the assistant's push."""
        try:
            self.cues.note_blended(msg.header.frame_id, self._stamp(msg), twist_to_array(msg), self._now_s())
        except InputError as exc:
            self._rejected(f'cmd_vel_rejected_{exc.kind}', exc)

    def _on_landing(self, msg: String) -> None:
        try:
            landing = parse_landing(msg.data)
        except InputError as exc:
            self._rejected('landing_rejected', exc)
            return
        if self.study is not None:       # the study driver records its landings and tells the page
            self.study.on_landing(landing)
            return
        self.server.push_event(landing_feedback(landing, self.p['mode']))

    def _on_camera(self, msg: Image) -> None:
        now = time.monotonic()
        if now - self._last_camera < 1.0 / self.p['camera_rate_hz'] or not self.server.n_clients:
            return
        try:
            w, h, rgb = camera_payload(msg.width, msg.height, msg.encoding, msg.step, msg.data,
                                       int(self.p['camera_max_width']))
            self.server.set_camera(w, h, rgb)
        except InputError as exc:
            self._rejected('camera_rejected', InputError(f'/camera/color/image_raw rejected: {exc.reason}', exc.detail))
            return
        self._last_camera = now

    # ------------------------------------------------------------------ view state
    def _state(self) -> dict:
        now = time.monotonic()
        with self._lock:
            odom, age = self._odom, now - self._odom_time
        assist = self.assist.state(now)
        cues = self.cues.view(self._now_s(), assist != 'off', {k: bool(self.p[f'cue_{k}']) for k in CUES})
        return {'pose': odom, 'odom_age_s': round(age, 3) if math.isfinite(age) else None,
                'assist': assist, 'cues': cues, 'keys': list(self.keys.held(now)),
                'stopped': self.keys.stopped(now),
                'cmd': [round(float(x), 3) for x in self.keys.command(now)]}

    def _diag_values(self) -> None:
        self.diag.set('url', self.server.url)
        self.diag.set('pilot_connected', self.server.pilot_connected)
        self.diag.set('clients', self.server.n_clients)

    def close(self) -> None:
        """Stop the web server (every socket closed), close a study landing's bag, send one zero command."""
        self.server.stop()
        if self.study is not None:
            self.study.close()
        try:
            self._publish(np.zeros(3))
        except Exception as exc:  # noqa: BLE001 - the context may already be gone at shutdown
            self.get_logger().debug(f'final zero command not sent: {exc!r}')


def main(args=None):
    """Entry point of `ros2 run assist_station pilot_station`."""
    exit_process(run_node(PilotStation, args, params=PARAMS))


if __name__ == '__main__':
    main()
