"""Pure policy core behind policy_node: inputs with timestamps -> agent action a and blended V.

Safety rules (ARCHITECTURE.md, "Timing and safety rules"):
* every input is range-checked where it enters (finite, plausible magnitude, right size, right
  frame); a bad one raises ``InputRejected`` (a ValueError with a short reason key), is counted in
  ``rejections`` and never replaces the last good value;
* no pilot command arrived within pilot_timeout_s (or none ever) -> u = 0; a command that arrives late (stamped
  up to pilot_max_latency_s before its arrival) is still the pilot's latest and is flown (counted in late_pilot);
* scene feature (latent / goal / image) or odometry stale or absent -> relinquish: no a, V = u;
* non-finite actor output is rejected (counted, V = u), never reaches V;
* any exception inside a step relinquishes (V = u, reason key ``step_error``), never escapes;
* the actor's action goes through the assistant's non-learned stages in their one order (``assistant.Assistant``:
  oscillation damper, pilot override, pad recall, blending, floor guard, wall rule, speed clamp; the env and
  replay_assist run the same chain); the depth-reading stages need a depth image (``set_depth``) no older
  than feature_timeout_s; the guards also act when the actor did not run (V = u);
* flights (``flight.FlightMonitor``): the vehicle's landed state (``set_landed_state``, it wins where known), an
  odometry jump, a landing or a take-off after one ends the flight, and ``reset`` does explicitly
  (``request_reset``: at most one per flight_reset_min_interval_s): the action history, every stage's memory
  and the odometry poses are dropped (counted in ``flight_resets`` by reason, the why in ``last_reset_detail``).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from assist_common.frames import quat_to_matrix
from assist_common.shipped import shipped_model_path

from .actions import scale_action
from .assistant import Assistant, AssistantConfig
from .stage import DepthFrame
from .blending import DEFAULT_THRESHOLD, MAX_SPEED_MPS, MAX_VERTICAL_MPS, MIN_SPEED_LIMIT_MPS, clamp_velocity
from .flight import FlightConfig, FlightMonitor, surface_clearance
from .intent import NO_INTENT, Intent, IntentConfig, LearnedGoal
from .loop import AssistLoop
from .observation import Condition, ObservationBuilder, image_feature, oracle_feature
from .poses import PoseHistory
from .rules import RULES, all_settings, changed, rule_fields
from .actor_runtime import image_size, load_actor_runtime
from .settings import nested, node_param
from assist_common.settings import check_named, setting

log = logging.getLogger(__name__)

POSE_HISTORY_S = 1.0  # odometry poses kept for pairing depth frames by stamp (s)
MAX_DEPTH_M = 100.0   # depth beyond this (or negative / non-finite) is a hole (0), as the sim and drivers mark them


def default_model_path(mode: str) -> Path:
    """Shipped actor for a mode, td3_<mode>_actor.pt: $ASSIST_MODELS_DIR, share/assist_policy/models or the
    repo's models/."""
    return shipped_model_path('assist_policy', f'td3_{Condition(mode).value}_actor.pt')


class InputRejected(ValueError):
    """An input the core refused; `reason` is a short key for diagnostics (e.g. ``pilot_frame``)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


@dataclass
@rule_fields(lambda r: nested(r.config))     # each rule's settings (rules.RULES; None: its defaults, as everywhere)
class PolicyCoreConfig:
    """Settings of the policy core (policy_node parameters map 1:1); validated on construction."""

    mode: str = 'latent'
    blend_threshold: float = node_param(DEFAULT_THRESHOLD, 'blend_threshold', 'Agent actions with |a| at or below '
                                        'this (m/s) are ignored: V = u.', min=0.0, max=10.0)
    pilot_timeout_s: float = node_param(0.5, 'pilot_timeout_s', 'No pilot command arrived for this long (s): the '
                                        'pilot counts as absent (u = 0).', min=0.0, max=10.0, min_exclusive=True)
    # a late pilot link (a starved CPU, a slow radio) still carries the pilot's latest command: flown, counted
    pilot_max_latency_s: float = node_param(2.0, 'pilot_max_latency_s', 'A pilot command that arrives up to this '
                                            'long after its header stamp (s) is still the pilot\'s latest command '
                                            '(flown, counted as late beyond pilot_timeout_s); an older one is '
                                            'rejected as stale.', min=0.0, max=10.0, min_exclusive=True)
    feature_timeout_s: float = node_param(0.5, 'latent_timeout_s', 'Latent (or image) older than this: the '
                                          'assistant relinquishes (V = u).', min=0.0, max=10.0, min_exclusive=True)
    odom_timeout_s: float = node_param(0.5, 'odom_timeout_s', 'Odometry older than this: the assistant relinquishes '
                                       '(V = u).', min=0.0, max=10.0, min_exclusive=True)
    max_speed_mps: float = node_param(MAX_SPEED_MPS, 'max_speed', 'Horizontal speed limit of the published /cmd_vel '
                                      '(m/s; not below 0.1: a tinier limit would silently stop the pilot too).',
                                      min=MIN_SPEED_LIMIT_MPS, max=20.0)
    max_vertical_mps: float = node_param(MAX_VERTICAL_MPS, 'max_vertical_speed', 'Vertical speed limit of the '
                                         'published /cmd_vel (m/s; not below 0.1).', min=MIN_SPEED_LIMIT_MPS,
                                         max=10.0)
    # pilot commands faster than this (norm) are rejected
    max_input_mps: float = node_param(5.0, 'max_input_speed', 'Pilot commands faster than this (speed, the norm) '
                                      'are rejected (m/s).', min=0.0, max=50.0, min_exclusive=True)
    # pilot commands must be in this frame (or carry no frame)
    body_frame: str = node_param('base_link', 'frame_id', 'Body frame: frame_id of the published commands; pilot '
                                 'commands must carry it (or none).', dynamic=False)
    max_odom_speed_mps: float = setting(50.0, gt=0)    # odometry faster than this is not a multirotor: rejected
    max_position_m: float = setting(1.0e4, gt=0)       # odometry / goal coordinates beyond this are rejected
    max_latent_abs: float = setting(1.0e3, gt=0)       # encoder means beyond this are rejected
    flight: FlightConfig | None = nested(FlightConfig)   # flight boundaries (None: FlightConfig() defaults)
    intent: IntentConfig | None = nested(IntentConfig)   # goal estimate and descent flag (None: the defaults)
    # velocity the actor sees: the odometry twist as given (base_link, policy_node) or rotated to odom with the
    # odometry attitude (as evaluate's env trains and flies it; replay_assist for evaluate's bags); the rules
    # (floor guard, override, damper) always read the twist
    actor_velocity: str = setting('twist', choices=('twist', 'odom'))
    # the pad recall maps a depth frame from the odometry pose at the frame's sensor stamp (interpolated) when
    # odometry stamps lie within this of it (s); else from the latest odometry (counted: depth_pose_unmatched)
    depth_pose_match_s: float = node_param(0.1, 'depth_pose_match_s', 'The pad recall maps a depth frame from the '
                                           "odometry pose at the frame's header stamp (interpolated) when /odom "
                                           'header stamps lie within this of it (s); else from the latest odometry '
                                           '(counted in /diagnostics depth_pose_unmatched: stamps never set, '
                                           'another clock).', min=0.0, max=1.0)

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line) and an unknown mode."""
        self.mode = Condition(self.mode).value
        check_named(self, type(self).__name__)


@dataclass
class PolicyOutput:
    """Result of one policy step: agent action (None when relinquished), blended V, why.

    `key` is a short stable reason for diagnostics: ``assisting``, ``small_action`` (the actor chose
    |a| <= threshold), ``odom_stale``, ``feature_stale``, ``goal_absent``, ``actor_nonfinite`` or
    ``step_error``, ``floor_guard`` (the floor guard replaced a descent), ``pilot_override`` (the pilot
    override replaced the actor's action), ``pad_recall`` (the pad recall steered back to a mapped pad) or
    ``oscillation_damper`` (the oscillation damper replaced the actor's horizontal action), ``switched_off``
    (pass_through: the node's assist_enabled is false);
    `reason` is the text.
    """

    agent: np.ndarray | None
    velocity: np.ndarray
    reason: str
    key: str = 'assisting'
    fault: str = ''           # exception type name when key is step_error
    intent: Intent = NO_INTENT   # the assistant's intent this step (intent.IntentEstimator; none when it did not run)

    @property
    def assisting(self) -> bool:
        """True when the agent's action is blended into V."""
        return self.key == 'assisting'


class PolicyCore:
    """Holds the latest inputs, builds observations, runs the actor, applies the blending rule."""

    def __init__(self, actor_path: str | Path, cfg: PolicyCoreConfig | None = None, actor_backend: str = 'torch',
                 actor_threads: int = 1):
        self.cfg = cfg or PolicyCoreConfig()
        self.mode = Condition(self.cfg.mode)
        # metadata and weights validated there; 'torch' is the lab's path (actor_runtime.BACKENDS)
        self.actor = load_actor_runtime(actor_path, actor_backend, actor_threads)
        self.meta = self.actor.meta
        trained = self.meta.get('condition')
        if trained is not None and trained != self.mode.value:
            raise ValueError(f'{actor_path}: actor was trained for {trained!r}, not mode {self.mode.value!r}')
        self.max_speed = tuple(float(v) for v in self.meta['max_speed'])
        self.builder = ObservationBuilder.for_actor(self.mode, self.meta)
        if self.builder.dim != int(self.meta['vec_dim']):
            raise ValueError(f'{actor_path}: actor expects {self.meta["vec_dim"]} inputs, the {self.mode.value} '
                             f'observation has {self.builder.dim}')
        self._pilot: tuple[float, np.ndarray] | None = None   # (arrival, command)
        self._pilot_stamp: float | None = None      # header stamp of the held pilot command
        self.pilot_latency_s = 0.0                  # arrival - stamp of the latest accepted pilot command (s)
        self.late_pilot = 0                         # pilot commands accepted later than pilot_timeout_s after stamping
        self._odom: tuple[float, np.ndarray, np.ndarray] | None = None
        self._attitude: np.ndarray | None = None   # odom -> base_link quaternion (x, y, z, w); None: level, heading 0
        self._feature: tuple[float, np.ndarray] | None = None
        self._goal: np.ndarray | None = None
        self.rejected = 0                      # non-finite actor outputs
        self.rejections: Counter[str] = Counter()   # refused inputs, per reason key
        self.faults: Counter[str] = Counter()       # exceptions inside step(), per exception type
        c = self.cfg
        self.assistant = Assistant(AssistantConfig(c.blend_threshold, c.max_speed_mps, c.max_vertical_mps,
                                                   **all_settings(c)))
        self.flight = FlightMonitor(c.flight or FlightConfig())
        # the step code the training/evaluation env runs too: observation, chain, action history, forgetting
        self.loop = AssistLoop(self.mode, self.builder, self.assistant, self.flight, c.intent or IntentConfig())
        self.flight_resets = self.loop.flight_resets    # flight boundaries seen, per reason (flight.REASONS)
        self.last_reset: tuple[float, str] | None = None   # (odometry time, reason) of the latest
        self.last_reset_detail = ''                 # why the latest boundary (FlightMonitor.last_detail, or the caller)
        self._odom_stamp = -math.inf                # sensor stamp of the latest odometry
        self._flight_start: float | None = None     # sensor time of the latest boundary: older depth frames are refused
        self._last_vz = 0.0                         # vertical command flown in the last step (flight monitor)
        self._depth: tuple[float, np.ndarray] | None = None
        self._depth_stamp = 0.0                     # sensor stamp of the latest depth frame (s)
        self._frame: DepthFrame | None = None       # the latest depth frame as the stages read it (pose looked up once)
        self._poses = PoseHistory(POSE_HISTORY_S, self.cfg.depth_pose_match_s)   # odometry by sensor stamp
        # depth frames mapped from the latest odometry (no pose at their stamp)
        self.depth_pose_unmatched = 0

    def __getattr__(self, name: str) -> object:
        """A rule's object by name (``core.recall``, ``core.guard``: ``Assistant.parts``; their settings objects
        are the ones policy_node changes at run time)."""
        assistant = self.__dict__.get('assistant')
        if assistant is not None and name in assistant.parts:
            return assistant.parts[name]
        raise AttributeError(f'{type(self).__name__!r} object has no attribute {name!r}')

    @property
    def engaged(self) -> Counter[str]:
        """Steps each stage of the assistant acted, by stage key (assistant.Assistant.engaged)."""
        return self.assistant.engaged

    def configure(self, **changes) -> None:
        """Change settings at run time; ValueError (nothing changed) if any is invalid.

        Top-level fields by name (e.g. ``max_speed_mps=1.0``); a rule's by its config field (rules.RULES) and a dict
XX
        settings object changes in place (the floor guard's is shared with the wall rule and the recall's floor test).
        """
        rules = {r.field: r for r in RULES}
        live = {**{f: getattr(self.assistant.cfg, f) for f in rules}, 'flight': self.flight.cfg,
                'intent': self.loop.intent.cfg}
        nested_changes = {k: changes.pop(k) for k in list(changes) if k in live}
        checked = {k: changed(rules[k], live[k], v) if k in rules else dataclasses.replace(live[k], **v)
                   for k, v in nested_changes.items()}   # validates each
        cfg = dataclasses.replace(self.cfg, **changes)
        if cfg.mode != self.cfg.mode:
            raise ValueError('the mode of a running policy core cannot change')
        self.assistant.configure(blend_threshold=cfg.blend_threshold, max_speed_mps=cfg.max_speed_mps,
                                 max_vertical_mps=cfg.max_vertical_mps)
        for k, v in nested_changes.items():
            for name in v:
                setattr(live[k], name, getattr(checked[k], name))
        self.cfg = dataclasses.replace(cfg, **{k: live[k] for k in live})
        self._poses.match_s = cfg.depth_pose_match_s

    # ------------------------------------------------------------- inputs
    def _reject(self, reason: str, detail: str) -> InputRejected:
        self.rejections[reason] += 1
        return InputRejected(reason, detail)

    def _vector(self, what: str, values, size: int, limit: float) -> np.ndarray:
        """`values` as a float vector of `size` finite entries within +-limit, else InputRejected."""
        try:
            v = np.asarray(values, dtype=float).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise self._reject(f'{what}_malformed', f'{what}: not numbers ({exc})') from None
        if v.size != size:
            raise self._reject(f'{what}_size', f'{what} has {v.size} values, expected {size}')
        if not np.all(np.isfinite(v)):
            raise self._reject(f'{what}_nonfinite', f'{what} not finite: {v.tolist()}')
        if np.abs(v).max(initial=0.0) > limit:
            raise self._reject(f'{what}_range', f'{what} out of range (|x| > {limit:g}): {v.tolist()}')
        return v

    def _stamp(self, what: str, t: float) -> float:
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise self._reject(f'{what}_stamp', f'{what}: stamp {t!r} is not a number') from None
        if not math.isfinite(t):
            raise self._reject(f'{what}_stamp', f'{what}: stamp {t!r} is not finite')
        return t

    def set_pilot(self, t: float, u: np.ndarray, frame_id: str = '', stamp: float | None = None) -> None:
        """Latest pilot command (m/s, body frame) that arrived at `t`, stamped `stamp` (None: unstamped).

        The pilot counts as present while commands keep arriving (pilot_timeout_s from the latest arrival), however
        late each is: one stamped more than pilot_timeout_s before its arrival is flown and counted in
        ``late_pilot`` (a starved CPU or a slow link delays every command, and dropping them all would leave the
        vehicle with no pilot at all); one stamped more than pilot_max_latency_s before it, or before the command
        already held while that one is fresh (another publisher's older command), is rejected. InputRejected also
        when malformed, too fast or in another frame.
        """
        t = self._stamp('pilot', t)
        latency = 0.0
        if stamp is not None:
            stamp = self._stamp('pilot', stamp)
            latency = t - stamp
            if latency > self.cfg.pilot_max_latency_s:
                raise self._reject('pilot_stale_stamp', f'pilot command stamped {latency:.3f} s before it arrived '
                                                        f'(pilot_max_latency_s {self.cfg.pilot_max_latency_s:g} s)')
            held = self._pilot_stamp
            if (held is not None and stamp < held and self._pilot is not None
                    and self._fresh(self._pilot[0], t, self.cfg.pilot_timeout_s)):
                raise self._reject('pilot_out_of_order', f'pilot command stamped {held - stamp:.3f} s before the '
                                                         'one already held')
        if frame_id not in ('', self.cfg.body_frame):
            raise self._reject('pilot_frame', f'pilot command in frame {frame_id!r}, expected '
                                              f'{self.cfg.body_frame!r}')
        u = self._vector('pilot', u, 3, math.inf)
        speed = float(np.linalg.norm(u))
        if speed > self.cfg.max_input_mps:
            raise self._reject('pilot_range', f'pilot command {u.tolist()} ({speed:.3g} m/s) faster than '
                                              f'max_input_speed {self.cfg.max_input_mps:g} m/s')
        self._pilot = (t, u)
        self._pilot_stamp = stamp
        self.pilot_latency_s = latency
        if latency > self.cfg.pilot_timeout_s:
            self.late_pilot += 1

    def set_odom(self, t: float, position: np.ndarray, velocity: np.ndarray,
                 orientation: np.ndarray | None = None, stamp: float | None = None) -> None:
        """Latest odometry (odom ENU; orientation x, y, z, w, None or zeros = level); InputRejected when implausible.

        `t` is when it arrived (the clock of `step`); `stamp` when it was measured (header stamp, s; None: `t`),
        by which a depth frame's pose is looked up.
        """
        t = self._stamp('odom', t)
        stamp = t if stamp is None else self._stamp('odom', stamp)
        p = self._vector('odom_position', position, 3, self.cfg.max_position_m)
        v = self._vector('odom_velocity', velocity, 3, self.cfg.max_odom_speed_mps)
        q = None if orientation is None else self._vector('odom_orientation', orientation, 4, 2.0)
        if q is not None and not np.any(q):
            q = None                  # all zero: a source that fills no orientation (taken as level, heading 0)
        if q is not None:
            n = float(np.linalg.norm(q))
            if not 0.9 < n < 1.1:
                raise self._reject('odom_orientation', f'odometry orientation {q.tolist()} is not a unit quaternion')
            q = q / n
        self._odom_stamp = stamp
        steps = self.flight.clock_steps
        boundary = self.flight.update(stamp, p, v, self._last_vz, now=t)
        if self.flight.clock_steps != steps:
            self._flight_start = None   # the clock stepped back: the last boundary's time means nothing on it
        if boundary is not None:
            self._forget(stamp, boundary, self.flight.last_detail)
        self._odom, self._attitude = (t, p, v), q
        self._poses.add(stamp, p, q)

    def set_latent(self, t: float, mu: np.ndarray) -> None:
        """Latest encoder mean (latent mode); InputRejected on wrong size, non-finite or huge values."""
        t = self._stamp('latent', t)
        self._feature = (t, self._vector('latent', mu, self.builder.latent_dim, self.cfg.max_latent_abs))

    def set_goal(self, goal: np.ndarray) -> None:
        """True goal (oracle mode, simulation only); InputRejected when non-finite or implausible."""
        self._goal = self._vector('goal', goal, 3, self.cfg.max_position_m)

    def set_image(self, t: float, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Latest RGB-D frame (end-to-end mode): uint8 HxWx3 + metres HxW (holes: 0, NaN, negative)."""
        t = self._stamp('image', t)
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.dtype != np.uint8:
            raise self._reject('image_encoding', f'colour image must be uint8, got {rgb.dtype}')
        if not np.issubdtype(depth.dtype, np.number):
            raise self._reject('image_encoding', f'depth image must be numeric, got {depth.dtype}')
        depth = depth.astype(np.float32)
        depth = np.where(np.isfinite(depth) & (depth >= 0) & (depth <= MAX_DEPTH_M), depth, 0.0)
        try:
            feature = image_feature(rgb, depth).reshape(-1)
        except ValueError as exc:
            raise self._reject('image_size', str(exc)) from None
        if feature.size != image_size(self.meta):
            raise self._reject('image_size', f'image of {feature.size} values, the actor expects '
                                              f'{image_size(self.meta)}')
        self._feature = (t, feature)

    def set_depth(self, t: float, depth: np.ndarray, stamp: float | None = None) -> None:
        """Latest depth image for the floor guard: metres HxW (holes: 0, NaN, negative); InputRejected if not 2-D.

        `t` is when it arrived; `stamp` when it was taken (header stamp, s; None: `t`): the pad recall maps it
        from the odometry pose at that stamp.
        """
        t = self._stamp('depth', t)
        stamp = t if stamp is None else self._stamp('depth', stamp)
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.size == 0 or not np.issubdtype(depth.dtype, np.number):
            raise self._reject('depth_image', f'depth image must be a numeric HxW array, got {depth.dtype} '
                                              f'{depth.shape}')
        if self._flight_start is not None and stamp < self._flight_start:
            raise self._reject('depth_before_flight', f'depth frame stamped {stamp:.3f} s, before the flight began '
                                                      f'({self._flight_start:.3f} s)')
        depth = depth.astype(np.float32)
        depth = np.where(np.isfinite(depth) & (depth >= 0) & (depth <= MAX_DEPTH_M), depth, 0.0)
        self._depth = (t, depth)
        self._depth_stamp = stamp
        clearance = surface_clearance(depth, self.guard.cfg.camera_offset_m)
        if clearance is not None:               # the flight monitor's evidence of what lies below
            self.flight.observe_surface(stamp, clearance)

    def set_landed_state(self, t: float, state: int) -> None:
        """The vehicle's own MAV_LANDED_STATE (/uav/landed_state) at clock time `t` (the clock of `step`); it wins
        over the odometry rules while known; InputRejected when not 0-4."""
        t = self._stamp('landed_state', t)
        try:
            boundary = self.flight.vehicle_state(t, state)
        except ValueError as exc:
            raise self._reject('landed_state_range', str(exc)) from None
        if boundary is not None:
            self._forget(t, boundary, self.flight.last_detail)

    def request_reset(self, now: float) -> tuple[bool, str]:
        """policy_node's ~/reset at clock time `now`: (honoured, message); at most one per
        flight_reset_min_interval_s, sooner calls are refused (counted in ``flight.resets_refused``)."""
        refused = self.flight.request_reset(now)
        if refused is not None:
            return False, refused
        self.reset('service')
        return True, "assistant reset: the flight's memories are forgotten"

    def reset(self, reason: str = 'service') -> None:
        """Forget the flight (an explicit boundary: policy_node's ~/reset): action history, the stages' memories,
        the odometry poses; counted in `flight_resets` under `reason`."""
        self.flight.reset()
        self._forget(self._odom_stamp, reason, '~/reset' if reason == 'service' else reason)

    def _forget(self, t: float, reason: str, detail: str = '') -> None:
        """Drop everything that belongs to the current flight (flight boundary `reason` at odometry time `t`)."""
        self.loop.forget(reason)
        self._poses.clear()
        # what the camera showed before the boundary belongs to the last flight: a frame taken on the pad just
        # landed on, mapped from the next start pose 3 m up, is a 'wall' under the start (the assistant then
        # held the vehicle there); the next frame and latent arrive within a camera period
        self._frame = self._depth = None
        if not self.mode.knows_goal:
            self._feature = None
        self._flight_start = float(t)
        self.last_reset = (float(t), reason)
        self.last_reset_detail = detail
        log.info('assistant reset: %s (%s)', reason, detail)

    # ------------------------------------------------------------- step
    def _fresh(self, stamp: float | None, now: float, timeout: float) -> bool:
        return stamp is not None and abs(now - stamp) <= timeout

    def _clamp(self, v: np.ndarray) -> np.ndarray:
        return clamp_velocity(v, self.cfg.max_speed_mps, self.cfg.max_vertical_mps)

    def pilot_command(self, now: float) -> np.ndarray:
        """The pilot's u at `now`: the latest accepted command if fresh, else zero (never raises)."""
        p = self._pilot
        if p is not None and self._fresh(p[0], now, self.cfg.pilot_timeout_s):
            return p[1].copy()
        return np.zeros(3)

    def fallback(self, now: float) -> PolicyOutput:
        """What to fly when a step cannot run: V = u, clamped (finite by construction; never raises)."""
        try:
            v = self._clamp(self.pilot_command(now))
            if not np.all(np.isfinite(v)):
                v = np.zeros(3)
        except Exception:  # noqa: BLE001 - the last line of defence must not raise
            v = np.zeros(3)
        return PolicyOutput(None, v, 'step failed: relinquished', 'step_error')

    def pass_through(self, now: float) -> PolicyOutput:
        """The assistant switched off: V = u, clamped, no agent action (a study's unassisted block)."""
        out = self.fallback(now)
        return PolicyOutput(None, out.velocity, 'assistant switched off (assist_enabled false): V = u', 'switched_off')

    def step(self, now: float) -> PolicyOutput:
        """One control step at time `now` (seconds, same clock as the input stamps); never raises.

        Any exception inside the step (a bad observation, the actor, the history) relinquishes:
        V = u (clamped), reason key ``step_error``, counted in `faults` by exception type and logged.
        """
        try:
            now = float(now)
            if not math.isfinite(now):
                raise ValueError(f'clock reads {now!r}')
            out = self._step(now)
            self._last_vz = float(out.velocity[2])
            return out
        except Exception as exc:  # noqa: BLE001 - contract: no exception leaves a control step
            self.faults[type(exc).__name__] += 1
            log.debug('policy step failed (%s: %s): relinquishing', type(exc).__name__, exc)
            out = self.fallback(now)
            out.reason = f'step failed ({type(exc).__name__}: {exc}): relinquished'
            out.fault = type(exc).__name__
            return out

    def _frame_now(self, now: float) -> DepthFrame | None:
        """The latest depth frame if fresh (one DepthFrame per frame: its pose is looked up once), else None."""
        if self._depth is None or not self._fresh(self._depth[0], now, self.cfg.feature_timeout_s):
            return None
        t_depth, depth = self._depth
        if self._frame is None or self._frame.key != t_depth:
            self._frame = DepthFrame(t_depth, lambda: depth, self._pose_of_depth)
        return self._frame

    def _pose_of_depth(self) -> tuple[np.ndarray, np.ndarray | None]:
        """Odometry pose (position, attitude) at the latest depth frame's stamp; with no pose within
        depth_pose_match_s of it, the latest (counted in depth_pose_unmatched)."""
        pose = self._poses.at(self._depth_stamp)
        if pose is None:
            self.depth_pose_unmatched += 1
            pose = (self._odom[1], self._attitude)
        return pose

    def _step(self, now: float) -> PolicyOutput:
        c = self.cfg
        u = self.pilot_command(now)
        odom_ok = self._odom is not None and self._fresh(self._odom[0], now, c.odom_timeout_s)
        if not odom_ok:                          # nothing to place the vehicle by: V = u, no stage runs
            self.loop.idle(now, u)
            return PolicyOutput(None, self._clamp(u), 'odometry stale or absent', 'odom_stale')
        _, pos, vel = self._odom
        vel_actor = (quat_to_matrix(self._attitude) @ vel
                     if c.actor_velocity == 'odom' and self._attitude is not None else vel)
        ctx = self.loop.context(now, u, pos, vel, self._attitude, self._frame_now(now), self.max_speed)
        a, key, reason, learned = self._actor(now, u, pos, vel_actor)
        known = self._goal if self.mode is Condition.ORACLE else None
        res = self.loop.act(ctx, a, key, reason, known_goal=known, learned_goal=learned)
        return PolicyOutput(res.agent, res.velocity, res.reason, res.key, intent=self.loop.intent.last)

    def _actor(self, now: float, u: np.ndarray, pos: np.ndarray,
               vel: np.ndarray) -> tuple[np.ndarray | None, str, str, LearnedGoal | None]:
        """The actor's action a (m/s) and its goal head's estimate (None without one), or (None, key, reason,
        None) when it cannot run."""
        if self.mode is Condition.ORACLE:
            if self._goal is None:
                return None, 'goal_absent', 'goal absent', None
            feature = oracle_feature(self._goal, pos)
        else:
            if self._feature is None or not self._fresh(self._feature[0], now, self.cfg.feature_timeout_s):
                return None, 'feature_stale', f'{self.mode.value} input stale or absent', None
            feature = self._feature[1]
        obs = self.loop.observation(now, feature, vel, pos, u)
        raw, learned = self.actor(obs, pos)
        if not np.all(np.isfinite(raw)):
            self.rejected += 1
            return None, 'actor_nonfinite', 'actor output not finite (rejected)', None
        if learned is not None and not (np.all(np.isfinite(learned.mean)) and math.isfinite(learned.sigma_m)):
            learned = None                  # a non-finite estimate is not published; the action still flies
        return scale_action(raw, self.max_speed), '', '', learned
