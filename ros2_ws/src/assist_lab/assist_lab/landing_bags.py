"""Record one simulated landing of the training/evaluation env as a bag with the graph's topics and types.

evaluate runs without ROS, so `EpisodeRecorder` writes what the graph would have carried: camera
frames as rendered (clean depth, as sim_node publishes it and as the floor guard, pad recall and pilot
override read it), /odom (twist in base_link, REP-105), /pilot/cmd_vel (u),
/assist/latent, /assist/agent_cmd (a) and /cmd_vel (V) at every control step (a and V as the env
applied them: after the pilot override and the floor guard, as policy_node publishes; with the cues shown, the
assistant's intent: /assist/goal_estimate and /assist/descent_ok), /sim/goal and
/sim/scene at the start and the /sim/landing JSON at the end. Times are the episode's sim time
(0 at the start pose). The bag's custom_data records that the assistant observed world-frame
velocity (as the env does) and, in the latent condition with the simulated depth sensor noise, the
noise's seeds (``DEPTH_NOISE_KEY``: base seed, landing seed), so replay_assist re-encodes each frame with
the same noise the encoder saw; replay_assist honours both. (Bags recorded before November 2026 hold
the noisy depth instead and no seeds: replay encodes them as they are.)
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np

from assist_sim.core.scene_markers import scene_markers

from assist_policy.observation import Condition
from assist_bags import msgs
from assist_bags.bagio import CONTRACT_TOPICS, DEPTH_NOISE_KEY, VELOCITY_FRAME_KEY, BagWriter

EPISODE_TOPICS = ('/camera/color/image_raw', '/camera/depth/image_raw', '/odom', '/pilot/cmd_vel', '/assist/latent',
                  '/assist/agent_cmd', '/cmd_vel', '/sim/goal', '/sim/scene', '/sim/landing')
INTENT_TOPICS = ('/assist/goal_estimate', '/assist/descent_ok')    # recorded when the pilots see the cues


def ns(t: float) -> int:
    """Episode seconds -> bag nanoseconds."""
    return int(round(float(t) * 1e9))


class EpisodeRecorder:
    """Wraps an evaluate policy; `policy` records each step, `finish` writes the landing and closes the bag."""

    def __init__(self, env: Any, policy: Callable | None, path: str | Path, storage: str = 'mcap',
                 custom: dict[str, str] | None = None):
        self.env = env
        self._policy = policy
        self.writer = BagWriter(path, storage=storage, atomic=True)
        self._intent = bool(env.cfg.cues) and not env.unassisted
        for topic in EPISODE_TOPICS + (INTENT_TOPICS if self._intent else ()):
            if topic == '/assist/latent' and env.condition is not Condition.LATENT:
                continue
            self.writer.add_topic(topic, *CONTRACT_TOPICS[topic])
        self.writer.custom_data = {VELOCITY_FRAME_KEY: 'odom', **(custom or {})}
        self._t0: float | None = None
        self._pending: int | None = None       # bag time of the step whose applied command is not written yet
        self._latent_fn = getattr(env, 'latent_fn', None)
        self._last_mu: np.ndarray | None = None
        if self._latent_fn is not None:
            env.latent_fn = self._capture_latent()

    def _capture_latent(self) -> Callable:
        """env.latent_fn while recording: the wrapped fn, keeping each mu; forwards the fn's reset and records the
        landing's depth noise seeds (custom_data ``DEPTH_NOISE_KEY``) when the fn adds noise."""
        inner = self._latent_fn

        def capture(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
            mu = inner(rgb, depth)
            self._last_mu = np.asarray(mu, dtype=float)
            return mu
        inner_reset = getattr(inner, 'reset', None)
        if inner_reset is not None:
            def reset(episode_seed: int | None) -> None:
                inner_reset(episode_seed)
                if getattr(inner, 'depth_noise', False) and episode_seed is not None:
                    self.writer.custom_data[DEPTH_NOISE_KEY] = f'{int(inner.seed)},{int(episode_seed)}'
            capture.reset = reset
        else:
            capture.reset = None
        return capture

    def _t(self) -> float:
        return self.env.world.state.time - self._t0

    def policy(self, obs: np.ndarray) -> np.ndarray:
        """The wrapped policy's raw action for `obs`; records the step's inputs and outputs first."""
        self._flush()           # the previous step's command, now that the env has flown it
        env, w = self.env, self.writer
        st = env.world.state
        if self._t0 is None:     # first step of the episode: the start pose, goal and scene
            self._t0 = st.time
            w.write_msg('/sim/goal', 0, msgs.point_stamped(0, env.world.goal_position))
            w.write_msg('/sim/scene', 0, msgs.scene_markers(0, scene_markers(env.world.scene, env.world.goal_index)))
        t = ns(st.time - self._t0)
        raw = np.zeros(3) if self._policy is None else np.asarray(self._policy(obs), dtype=float)
        frame = env.camera_frame()        # the encoder's frame before its noise (the env's rules read it too)
        w.write_msg('/camera/color/image_raw', t, msgs.image(t, frame.rgb))
        w.write_msg('/camera/depth/image_raw', t, msgs.image(t, frame.depth))
        w.write_msg('/odom', t, msgs.odometry(t, st.position, st.quaternion, st.velocity))
        u = env.pilot_action
        w.write_msg('/pilot/cmd_vel', t, msgs.twist_stamped(t, u))
        if self._last_mu is not None:
            w.write_msg('/assist/latent', t, msgs.float_array(self._last_mu))
        self._pending = t
        return raw

    def _flush(self) -> None:
        """Write the command the env applied in the last step (after the pilot override and the floor guard)."""
        if self._pending is None or self.env.last_command is None:
            return
        t, (a, v) = self._pending, self.env.last_command
        if not self.env.unassisted:
            self.writer.write_msg('/assist/agent_cmd', t, msgs.twist_stamped(t, a))
        self.writer.write_msg('/cmd_vel', t, msgs.twist_stamped(t, v))
        intent = self.env.loop.intent.last
        if self._intent and intent.goal is not None:
            self.writer.write_msg('/assist/goal_estimate', t,
                                  msgs.pose_with_covariance(t, intent.goal, intent.pose_covariance()))
        if self._intent and intent.descent_ok is not None:
            self.writer.write_msg('/assist/descent_ok', t, msgs.boolean(intent.descent_ok))
        self._pending = None

    def finish(self, row: dict) -> Path:
        """Write the last command, the final pose and the /sim/landing JSON, close the bag; returns its path."""
        self._flush()
        st = self.env.world.state
        t = ns(st.time - (self._t0 if self._t0 is not None else st.time))
        self.writer.write_msg('/odom', t, msgs.odometry(t, st.position, st.quaternion, st.velocity))
        landing = {'episode': int(row.get('seed', 0)), 'goal_index': row['goal_index'],
                   'landed_index': row['landed_index'], 'nearest_index': row['nearest_index'],
                   'error_m': row['error_m'], 'nearest_error_m': row['nearest_error_m'],
                   'success': bool(row['success']), 'crash': bool(row['crash']), 'duration_s': row['duration_s'],
                   'assisted': not self.env.unassisted, 'outcome': row.get('outcome')}
        self.writer.write_msg('/sim/landing', t, msgs.string(json.dumps(landing)))
        if self._latent_fn is not None:
            self.env.latent_fn = self._latent_fn
        return self.writer.close()

    def abort(self) -> None:
        """Drop the unfinished bag and restore the env."""
        if self._latent_fn is not None:
            self.env.latent_fn = self._latent_fn
        self.writer.abort()


def landing_bag_name(condition: str, beta: float, seed: int) -> str:
    """Directory name of a landing's bag under --record-dir (one per landings.csv row)."""
    return f'{condition}_beta{float(beta):.2f}_seed{int(seed)}'


def record_landing(run_landing: Callable, env: Any, policy: Callable | None, seed: int, beta: float,
                   condition: str, record_dir: str | Path) -> dict:
    """evaluate's run_landing with the landing saved as <record_dir>/<condition>_beta<b>_seed<s>/ (a bag)."""
    path = Path(record_dir) / landing_bag_name(condition, beta, seed)
    rec = EpisodeRecorder(env, policy, path, custom={'assist.condition': condition, 'assist.beta': str(beta),
                                                      'assist.seed': str(seed)})
    try:
        row = run_landing(env, rec.policy, seed, beta)
    except BaseException:
        rec.abort()
        raise
    rec.finish(row)
    return row
