"""policy_node: runs the TD3 actor at a fixed rate and publishes /assist/agent_cmd and blended /cmd_vel.

Thin rclpy shell over ``policy_core.PolicyCore`` (input range checks, staleness, blending, NaN rejection).
pilot_override, pad_recall and oscillation_damper default to true, false in mode oracle (``params_for_mode``:
the assistant knows the goal there). Run-time parameters (``ros2 param set``): blend_threshold, the three
timeouts, depth_pose_match_s, max_speed,
max_vertical_speed, max_input_speed, the floor_guard*, pilot_override*, pad_recall* and
oscillation_damper* parameters; every other parameter is read-only. The floor guard
(assist_policy.safety) and the pad recall (assist_policy.recall, which maps pads with the /odom pose and
orientation) read /camera/depth/image_raw in every mode; /diagnostics shows floor_guard (on/off) and
floor_guard_engaged (steps it replaced a descent), wall_guard_engaged (steps its wall rule, assist_policy.walls,
removed a command's approach to a wall), pilot_override (on/off) and pilot_override_engaged
(steps the pilot override, assist_policy.override, replaced the actor's action) and
pilot_override_persistent_engaged, pilot_override_climb_engaged and pilot_override_long_engaged (of
those, steps for a persistent push, a held climb, a long push), pilot_override_spot_kept (steps a push back to,
or a climb off, a spot the pilot tried to land on stayed with the actor), pad_recall (on/off),
pad_recall_engaged (steps it steered to a mapped pad), pad_recall_touchdown and pad_recall_scout (of those,
steps it centred on the pad below for touchdown, it looked beyond for a nearer pad before steering back to one
behind), pad_recall_pads (pads in its map), depth_pose_unmatched (depth frames mapped from the latest odometry
because no /odom header stamp lay within depth_pose_match_s of theirs; the recall maps each frame from the pose
at its header stamp), oscillation_damper (on/off) and oscillation_damper_engaged (steps the oscillation damper,
assist_policy.damper, replaced the actor's horizontal action).
"""
from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, Float32MultiArray, UInt8
from std_srvs.srv import Trigger

from assist_common.images import decode_color, decode_depth
from assist_common.ros_io import (LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, STAMP_TOLERANCE_S, Diagnostics,
                                  stamp_problem, fill_twist, twist_to_array)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import executor_param, exit_process, realtime_priority_param, run_node

from . import settings
from .flight import REASONS as FLIGHT_REASONS, LandedState
from .actor_runtime import BACKENDS
from .policy_core import InputRejected, PolicyCore, PolicyCoreConfig, PolicyOutput, default_model_path
from .poses import header_seconds
from .rules import RULES

# policy_node's own parameters; the assistant's (blending, limits, timeouts, every rule, flight boundaries) are
# declared on its config dataclasses (settings.node_param) and derived from them below
NODE_PARAMS = {
    'model_path': Param('', 'TD3 actor file; empty: the shipped models/td3_<mode>_actor.pt.'),
    'mode': Param('latent', 'Assistant input: latent (CM-VAE /assist/latent), oracle (/sim/goal, sim only), '
                            'end_to_end (raw RGB-D images).', choices=('latent', 'oracle', 'end_to_end')),
    'rate_hz': Param(20.0, 'Actor rate (the training control rate is 20 Hz).', min=0.0, max=200.0,
                     min_exclusive=True),
    'actor_backend': Param('auto', 'What runs the actor: onnxruntime (an export of the actor file, cached by its '
                                   'hash: no torch at start-up), torch (as evaluate and training), or auto '
                                   '(onnxruntime when installed).', choices=BACKENDS),
    'torch_threads': Param(1, 'Intra-op CPU threads for the actor, on either backend (1 is fastest for this small '
                              'network).', min=1, max=64),
    'error_after_faults': Param(20, 'Consecutive failed steps (exceptions or non-finite actor output) after which '
                                    'diagnostics report ERROR (20 = 1 s at 20 Hz).', min=1, max=100_000),
    'warn_period_s': Param(2.0, 'Minimum seconds between repeated warnings of the same reason.', min=0.0,
                           max=3600.0),
    'step_on_latent': Param(True, 'latent mode: run the actor as soon as a new latent arrives (camera-to-command '
                                  'latency = one inference, /cmd_vel stamped with the frame\'s sim time); the '
                                  'rate_hz timer then runs only while latents are missing.'),
    'stamp_tolerance_s': Param(STAMP_TOLERANCE_S, 'An input stamped further ahead of the node\'s clock than this '
                               '(s) is rejected and counted (rejected_<input>_future_stamp); one older than its '
                               'timeout is rejected as stale. Inputs are dated by their header stamp (unset: '
                               'arrival).', min=0.0, max=10.0, dynamic=True),
    'assist_enabled': Param(True, 'false: pass the pilot through (V = u, clamped to the speed limits; no '
                                  '/assist/agent_cmd), e.g. a user study\'s unassisted block, switched by the '
                                  'station at run time.', dynamic=True),
    'executor': executor_param('events'),
    'realtime_priority': realtime_priority_param(0),
}
CORE_PARAMS = settings.parameters(PolicyCoreConfig)      # parameter name -> config path, default, rule
PARAMS = {**NODE_PARAMS, **{name: Param(f.default, f.spec.description, f.spec.min, f.spec.max, f.spec.min_exclusive,
                                        f.spec.choices, f.spec.dynamic) for name, f in CORE_PARAMS.items()}}
# The goal-agnostic rules (rules.RULES) are off by default in mode oracle, where the assistant knows the goal: letting
# the pilot's keys through, steering to the nearest pad or damping the pilot only cost it (evaluate, 110 paper-pilot
# landings: oracle + floor guard 99.1 % on the goal pad / 0 % crashes, with all three rules too 76.4 % / 8.2 %).
RULE_SWITCHES = tuple(r.switch for r in RULES)          # on/off in /diagnostics


def params_for_mode(mode: str) -> dict[str, Param]:
    """PARAMS with the defaults of `mode` (oracle: the goal-agnostic rules off unless set)."""
    return {**PARAMS, **{r.switch: dataclasses.replace(PARAMS[r.switch], default=False)
                         for r in RULES if not r.default_on(mode)}}


# step outcomes that are normal operation (diagnostics OK; also every stage's key); everything else is a WARN
OK_KEYS = ('assisting', 'small_action', 'switched_off')
FAULT_KEYS = ('actor_nonfinite', 'step_error')


class ReasonThrottle:
    """Per-reason rate limit for warnings: distinct faults are each logged, repeats of one are not."""

    def __init__(self, period_s: float, clock=time.monotonic):
        self.period_s = float(period_s)
        self._clock = clock
        self._last: dict[str, float] = {}

    def ready(self, reason: str) -> bool:
        """True (and remember the time) when `reason` was not logged within the last period."""
        now = self._clock()
        last = self._last.get(reason)
        if last is not None and now - last < self.period_s:
            return False
        self._last[reason] = now
        return True


class PolicyNode(Node):
    """Subscribes latent/odom/pilot (+goal in oracle mode), publishes agent_cmd and cmd_vel.

    No exception in a callback may stop the node: bad inputs are rejected (counted per reason,
    warned once per reason per warn_period_s); a failed control step publishes V = u (clamped).
    """

    def __init__(self, **kwargs):
        super().__init__('policy_node', **kwargs)
        # mode first: the rules' defaults depend on it (params_for_mode)
        mode = declare_parameters(self, {'mode': PARAMS['mode']})['mode']
        self.p = declare_parameters(self, {k: v for k, v in params_for_mode(mode).items() if k != 'mode'},
                                    on_change=self._on_params)
        self.p['mode'] = mode
        self.diag = Diagnostics(self)
        self._warn_throttle = ReasonThrottle(self.p['warn_period_s'])
        path = self.p['model_path'] or str(default_model_path(mode))
        try:
            cfg = settings.config_from(PolicyCoreConfig, self.p, mode=mode)
            # a 256x256 MLP gains nothing from intra-op threads; spinning workers would starve the sim and the
            # other nodes on a small machine
            self.core = PolicyCore(path, cfg, self.p['actor_backend'], int(self.p['torch_threads']))
        except ValueError as exc:
            raise StartupError(f'policy_node: {exc}') from None
        self._lock = threading.Lock()
        self._consecutive_faults = 0
        self._reported_reset: tuple[float, str] | None = None
        inputs = MutuallyExclusiveCallbackGroup()
        self.pub_agent = self.create_publisher(TwistStamped, '/assist/agent_cmd', RELIABLE_QOS)
        self.pub_cmd = self.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
        # the assistant's intent (assist_policy.intent), for the pilot's cues
        self.pub_goal = self.create_publisher(PoseWithCovarianceStamped, '/assist/goal_estimate', RELIABLE_QOS)
        self.pub_descent = self.create_publisher(Bool, '/assist/descent_ok', RELIABLE_QOS)
        self.create_subscription(Odometry, '/odom', self._guard('odom', self._on_odom), SENSOR_QOS,
                                 callback_group=inputs)
        self.create_subscription(TwistStamped, '/pilot/cmd_vel', self._guard('pilot', self._on_pilot),
                                 RELIABLE_QOS, callback_group=inputs)
        if mode == 'latent':
            self.create_subscription(Float32MultiArray, '/assist/latent', self._guard('latent', self._on_latent),
                                     SENSOR_QOS, callback_group=inputs)
        elif mode == 'oracle':
            self.create_subscription(PointStamped, '/sim/goal', self._guard('goal', self._on_goal), LATCHED_QOS,
                                     callback_group=inputs)
        else:
            self.create_subscription(Image, '/camera/color/image_raw', self._guard('image', self._on_rgb),
                                     SENSOR_QOS, callback_group=inputs)
        self._rgb = None
        self._odom_frame = 'odom'
        # every mode: the floor guard reads the depth image (end_to_end also feeds it to the actor)
        self.create_subscription(Image, '/camera/depth/image_raw', self._guard('depth', self._on_depth),
                                 SENSOR_QOS, callback_group=inputs)
        # the vehicle's own landed state (the bridge's, from EXTENDED_SYS_STATE) wins over the odometry rules
        self.create_subscription(UInt8, '/uav/landed_state', self._guard('landed_state', self._on_landed_state),
                                 LATCHED_QOS, callback_group=inputs)
        self.create_service(Trigger, '~/reset', self._on_reset, callback_group=inputs)
        self._on_latent_steps = mode == 'latent' and bool(self.p['step_on_latent'])
        self._last_latent_step = -1e9           # node-clock time of the last latent-driven step
        self.create_timer(1.0 / float(self.p['rate_hz']), self._on_timer,
                          callback_group=MutuallyExclusiveCallbackGroup())
        self.diag.set('model_path', path)
        self.diag.set('mode', mode)
        self.diag.set('actor_backend', self.core.actor.backend)
        self.diag.set('assist_enabled', 'on' if self.p['assist_enabled'] else 'off')
        for switch in RULE_SWITCHES:
            self.diag.set(switch, 'on' if self.p[switch] else 'off')
        self.diag.status(DiagnosticStatus.WARN, 'relinquished: waiting for inputs')
        self.get_logger().info(f'policy_node: {mode} actor {path} on {self.core.actor.backend} '
                               f'at {self.p["rate_hz"]} Hz')

    # ------------------------------------------------------------- parameters
    def _on_params(self, changed: dict) -> None:
        """Apply run-time parameter changes to the core (ValueError refuses the whole set)."""
        changes = settings.changes_for(CORE_PARAMS, changed)
        if changes:
            top = changes.pop((), {})
            with self._lock:
                self.core.configure(**top, **{path[0]: fields for path, fields in changes.items()})
        for switch in RULE_SWITCHES:
            if switch in changed:
                self.diag.set(switch, 'on' if changed[switch] else 'off')
        if 'assist_enabled' in changed:
            self.diag.set('assist_enabled', 'on' if changed['assist_enabled'] else 'off')
            self.get_logger().info('assistant ' + ('switched on' if changed['assist_enabled'] else
                                                   'switched off: passing the pilot through (V = u)'))

    # ------------------------------------------------------------- inputs
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _warn(self, reason: str, text: str) -> None:
        if self._warn_throttle.ready(reason):
            self.get_logger().warning(text)

    def _reject(self, what: str, exc: Exception) -> None:
        reason = getattr(exc, 'reason', None) or f'{what}_{type(exc).__name__}'
        self.diag.count(f'rejected_{what}')
        self.diag.count(f'rejected_{reason}')
        self._warn(reason, f'rejected {what} ({reason}): {exc}')

    def _guard(self, what: str, callback):
        """Wrap an input callback: any exception rejects the message (counted, logged), never escapes."""
        def guarded(msg) -> None:
            try:
                callback(msg)
            except Exception as exc:  # noqa: BLE001 - contract: a bad message never kills the node
                self._reject(what, exc)
        return guarded

    def _dated(self, what: str, msg, max_age_s: float) -> tuple[float, float | None]:
        """(time the core dates the message by, its header stamp): the stamp against the node's clock (an unset
        stamp: the arrival); InputRejected when it lies in the future beyond stamp_tolerance_s or is older than
        `max_age_s` (the input's timeout: it would count as absent anyway, and must not replace a newer one)."""
        now, stamp = self._now(), header_seconds(msg)
        problem = stamp_problem(stamp, now, max_age_s, float(self.p['stamp_tolerance_s']))
        if problem is not None:
            raise InputRejected(f'{what}_{problem[0]}', f'{what}: {problem[1]}')
        return (now if stamp is None else min(stamp, now)), stamp

    def _on_odom(self, msg: Odometry) -> None:
        p, v, q = msg.pose.pose.position, msg.twist.twist.linear, msg.pose.pose.orientation
        with self._lock:
            t, stamp = self._dated('odom', msg, self.core.cfg.odom_timeout_s)
            self.core.set_odom(t, [p.x, p.y, p.z], [v.x, v.y, v.z], [q.x, q.y, q.z, q.w], stamp)
            self._odom_frame = msg.header.frame_id or 'odom'   # the goal estimate is in the odometry's frame

    def _on_pilot(self, msg: TwistStamped) -> None:
        # dated by its arrival: the pilot is present while commands keep coming, however late (policy_core.set_pilot)
        with self._lock:
            _, stamp = self._dated('pilot', msg, self.core.cfg.pilot_max_latency_s)
            late_before = self.core.late_pilot
            self.core.set_pilot(self._now(), twist_to_array(msg), msg.header.frame_id, stamp)
        if self.core.late_pilot > late_before:
            self.diag.count('pilot_late')
            self.diag.set('pilot_latency_s', round(self.core.pilot_latency_s, 3))
            self._warn('pilot_late', f'pilot commands arrive late ({self.core.pilot_latency_s:.2f} s after their '
                                     f'stamp, pilot_timeout_s {self.core.cfg.pilot_timeout_s:g} s): flown as the '
                                     'pilot\'s latest command')

    def _on_latent(self, msg: Float32MultiArray) -> None:
        with self._lock:
            self.core.set_latent(self._now(), np.asarray(msg.data, dtype=float))
        if self._on_latent_steps:               # a rejected latent raised above: no step for it
            self._last_latent_step = self._now()
            self._tick()

    def _on_timer(self) -> None:
        # with latent-driven steps the timer only covers gaps in the latent stream
        if not 0.0 <= self._now() - self._last_latent_step <= 1.5 / float(self.p['rate_hz']):
            self._tick()

    def _on_goal(self, msg: PointStamped) -> None:
        with self._lock:
            self.core.set_goal([msg.point.x, msg.point.y, msg.point.z])   # not a flight boundary

    def _on_landed_state(self, msg: UInt8) -> None:
        with self._lock:
            self.core.set_landed_state(self._now(), int(msg.data))

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """~/reset: forget the current flight (counted in /diagnostics flight_reset_service); at most one call per
        flight_reset_min_interval_s, sooner ones are answered success=false (counted: flight_reset_refused)."""
        with self._lock:
            response.success, response.message = self.core.request_reset(self._now())
        if not response.success:
            self.diag.set('flight_reset_refused', self.core.flight.resets_refused)
            self._warn('flight_reset_refused', f'~/reset {response.message}')
        return response

    def _on_rgb(self, msg: Image) -> None:
        self._rgb = decode_color(msg.data, msg.encoding, msg.height, msg.width, msg.step)

    def _on_depth(self, msg: Image) -> None:
        # encoding, step and byte order honoured (images.decode_depth); what it cannot read raises BadFrame (counted)
        depth = decode_depth(msg.data, msg.encoding, msg.height, msg.width, msg.step, bool(msg.is_bigendian))
        with self._lock:
            t, stamp = self._dated('depth', msg, self.core.cfg.feature_timeout_s)
            self.core.set_depth(t, depth, stamp)
            if self.core.mode.value == 'end_to_end' and self._rgb is not None:
                self.core.set_image(t, self._rgb, depth)

    # ------------------------------------------------------------- control step
    def _publish(self, out: PolicyOutput) -> None:
        stamp = self.get_clock().now().to_msg()
        frame = self.p['frame_id']
        cmd = TwistStamped()                    # /cmd_vel first: it is on the camera-to-command path
        cmd.header.stamp, cmd.header.frame_id = stamp, frame
        self.pub_cmd.publish(fill_twist(cmd, out.velocity))
        if out.agent is not None and np.all(np.isfinite(out.agent)):
            msg = TwistStamped()
            msg.header.stamp, msg.header.frame_id = stamp, frame
            self.pub_agent.publish(fill_twist(msg, out.agent))
            self.diag.count('agent_cmds')
        intent = out.intent
        if intent.goal is not None and np.all(np.isfinite(intent.goal)):
            goal = PoseWithCovarianceStamped()
            goal.header.stamp, goal.header.frame_id = stamp, self._odom_frame
            goal.pose.pose.position.x, goal.pose.pose.position.y, goal.pose.pose.position.z = (
                float(v) for v in intent.goal)
            goal.pose.pose.orientation.w = 1.0
            goal.pose.covariance = intent.pose_covariance()
            self.pub_goal.publish(goal)
            self.diag.count('goal_estimates')
        if intent.descent_ok is not None:
            self.pub_descent.publish(Bool(data=bool(intent.descent_ok)))

    def _tick(self) -> None:
        """One control step; any exception relinquishes (V = u, clamped), is counted and logged."""
        if not self.context.ok():
            return                              # shutting down (Ctrl-C): no context left to publish in
        try:
            with self._lock:
                out = self.core.step(self._now()) if self.p['assist_enabled'] else self.core.pass_through(self._now())
                if not np.all(np.isfinite(out.velocity)):   # defence in depth: never reaches an actuator
                    out = self.core.fallback(self._now())
                    out.reason = 'blended velocity not finite: relinquished'
            self._publish(out)
        except Exception as exc:  # noqa: BLE001 - contract: no exception kills a control step
            if not self.context.ok():           # the context went away during this step: shutdown, not a fault
                self.get_logger().debug(f'control step at shutdown: {type(exc).__name__}: {exc}')
                return
            out = self.core.fallback(self._now())
            out.reason = f'control step failed ({type(exc).__name__}: {exc}): relinquished'
            out.fault = type(exc).__name__
            try:
                self._publish(out)
            except Exception as exc2:  # noqa: BLE001 - publishing itself failed: count and go on
                self.diag.count('publish_errors')
                self._warn('publish_error', f'cannot publish /cmd_vel: {type(exc2).__name__}: {exc2}')
        self._report(out)

    def _report(self, out: PolicyOutput) -> None:
        """Counters, throttled warnings and the diagnostic level/message for this step's outcome."""
        self.diag.set('state', out.key)
        self.diag.set('rejected_actor_outputs', self.core.rejected)
        for name, value in self.core.assistant.diagnostics().items():     # <stage>_engaged and each stage's own
            self.diag.set(name, value)
        intent = out.intent
        self.diag.set('intent_confidence', round(intent.confidence, 3))
        self.diag.set('intent_candidates', intent.candidates)
        self.diag.set('descent_ok', 'unknown' if intent.descent_ok is None else str(intent.descent_ok).lower())
        self.diag.set('depth_pose_unmatched', self.core.depth_pose_unmatched)
        for reason in FLIGHT_REASONS:
            self.diag.set(f'flight_reset_{reason}', self.core.flight_resets[reason])
        last = self.core.last_reset
        why = self.core.last_reset_detail
        self.diag.set('last_flight_reset', 'none' if last is None else f'{last[1]} at {last[0]:.2f} s ({why})')
        self.diag.set('flight_reset_refused', self.core.flight.resets_refused)
        self.diag.set('flight_state', self.core.flight.phase.value)
        report = self.core.flight.vehicle_report
        self.diag.set('landed_state', 'none' if report is None else LandedState(report).name)
        if last is not None and last != self._reported_reset:
            self._reported_reset = last
            self.get_logger().info(f'assistant reset ({last[1]}: {why}): the flight\'s memories are forgotten')
        if out.key in FAULT_KEYS:
            self._consecutive_faults += 1
            self.diag.count(f'fault_{out.key}')
            if out.fault:
                self.diag.count(f'fault_{out.fault}')
            self._warn(f'{out.key}:{out.fault}', out.reason)
        else:
            self._consecutive_faults = 0
        stage_keys = {s.key for s in self.core.assistant.stages}
        if out.key not in OK_KEYS and out.key not in stage_keys:
            self.diag.count(f'relinquished_{out.key}')
        if self._consecutive_faults >= int(self.p['error_after_faults']):
            self.diag.status(DiagnosticStatus.ERROR, f'relinquished: {self._consecutive_faults} consecutive '
                                                     f'failed steps ({out.reason})')
        elif out.key == 'assisting':
            self.diag.status(DiagnosticStatus.OK, 'assisting')
        elif out.key in stage_keys or out.key == 'switched_off':
            self.diag.status(DiagnosticStatus.OK, out.reason)      # the stage's text (recall: which mode acted)
        elif out.key == 'small_action':
            self.diag.status(DiagnosticStatus.OK, 'relinquished: agent action at or below blend_threshold')
        else:
            self.diag.status(DiagnosticStatus.WARN, f'relinquished: {out.reason}')


def main(args=None):
    """Console entry point."""
    exit_process(run_node(lambda: PolicyNode(), args, params=PARAMS))


if __name__ == '__main__':
    main()
