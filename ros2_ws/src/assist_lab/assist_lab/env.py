"""Gymnasium environment: a simulated pilot lands in the LandingWorld, the agent's action is blended in.

One step = one control period of the world (1/control_hz s):
  1. the agent sees obs_t (scene feature, dynamics, pilot action u_t, 1 s means) and outputs raw
     action in [-1, 1]^3, scaled to a velocity a_t (``actions.scale_action``);
     the assistant's non-learned stages then act on it in their one order, the chain policy_node runs
     (``assistant.Assistant``: oscillation damper, pilot override, pad recall, blending, floor guard, wall
     rule, speed clamp); each rule (``assist_policy.rules.RULES``) is off unless EnvConfig switches it on;
     the flight monitor (``flight.FlightMonitor``) applies policy_node's flight boundaries (the odometry
     rules: the simulation reports no landed state, and its camera evidence is not read);
  2. the vehicle flies V_t, the chain's command (within policy_node's speed limits when assisted; the
     unassisted pilot flies u_t as it is), with the world's turbulence;
  3. the pilot updates its goal estimate with the applied assistance (a_t if |a_t| > threshold,
     else 0) and produces u_{t+1}.

Reward (paper, "TD3 implementation"), weights in ``RewardConfig``:
  (i)   at the end of the episode: -landing_weight * landing error (horizontal distance from the
        body to the goal pad centre, the judge's error_m), plus optional success/crash terms
        (0 by default: the paper names only the three terms);
  (ii)  each step: progress_weight * (d_t - d_{t+1}) when d_{t+1} < progress_radius_m, d = 3-D
        distance to the true goal's top centre;
  (iii) each step: -action_weight * |a_t| (m/s);
  (iv)  optional safety term (not in the paper, 0 by default): each step below floor_descent_height_m
        with no pad under the vehicle (privileged pad geometry, ``over_pad``), -floor_descent_weight *
        the flown descent speed (m/s), so descending over bare floor costs more than countering it;
  (v)   optional action-rate term (not in the paper, 0 by default): each step, -action_rate_weight *
        |a_t - a_{t-1}| (m/s), so an assistant that jerks between actions pays for it.

``privileged()`` is what an asymmetric critic sees besides the observation (never the actor): the true goal and
the pilot's own goal estimate relative to the vehicle, and the pilot's alpha and beta.
An episode cut at max_episode_s gets the landing term for where the vehicle is (so stalling a
landing never pays); trainers treat it as terminal.
"""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from assist_sim.core.arducopter import randomised
from assist_sim.core.config import WorldConfig
from assist_common.frames import nearest_xy, quat_to_matrix
from assist_sim.core.world import LandingWorld
from assist_sim.cues import Cue, CueConfig
from assist_sim.pilot import PilotConfig, SimulatedPilot
from assist_sim.pilots import make_pilot

from assist_policy.actions import DEFAULT_MAX_SPEED, scale_action
from assist_policy.assistant import Assistant, AssistantConfig
from assist_policy.stage import DepthFrame
from assist_policy.blending import DEFAULT_THRESHOLD, MAX_SPEED_MPS, MAX_VERTICAL_MPS
from assist_policy.flight import FlightConfig, FlightMonitor
from assist_policy.intent import Intent, IntentConfig, LearnedGoal
from assist_policy.loop import AssistLoop
from assist_policy.observation import IMAGE_SHAPE, Condition, ObservationBuilder, image_feature, oracle_feature
from assist_policy.rules import RULES, all_settings, rule_fields, switched
from .episodes_plan import landing_plan

log = logging.getLogger(__name__)

# privileged(): true goal offset (3), the pilot's goal estimate offset (3), alpha, beta
PRIVILEGED_DIM = 8


@dataclass
class RewardConfig:
    """Weights of the paper's three reward terms (and two optional extras, off by default)."""

    landing_weight: float = 10.0       # per metre of final landing error
    progress_weight: float = 1.0       # per metre of progress toward the goal near it
    progress_radius_m: float = 3.0     # progress counts only within this 3-D distance of the goal
    action_weight: float = 0.02        # per m/s of assistant action, every step
    success_bonus: float = 0.0         # extra terminal reward on success (not in the paper)
    crash_penalty: float = 0.0         # extra terminal penalty on a crash (not in the paper)
    floor_descent_weight: float = 0.0  # per m/s of flown descent over bare floor, every step (not in the paper)
    floor_descent_height_m: float = 1.5  # the safety term counts below this height above the floor
    floor_pad_margin_m: float = 0.15   # a pad footprint grown by this (the legs' reach) counts as under
    action_rate_weight: float = 0.0    # per m/s of change in the assistant action between steps (not in the paper)


@dataclass
# a field per non-learned rule (assist_policy.rules.RULES): off unless switched on (`rules.switched`); None: the
# settings class's defaults, as everywhere
@rule_fields(lambda r: field(default_factory=lambda: switched(r, False)))
class EnvConfig:
    """Everything that defines the training / evaluation task."""

    condition: str = 'oracle'                        # latent | oracle | end_to_end | none (unassisted)
    alpha: float = 0.5                               # pilot conformance
    beta_range: tuple[float, float] = (0.0, 1.0)     # pilot skill drawn uniformly per episode
    max_episode_s: float = 60.0                      # truncation (the world's own timeout is longer)
    blend_threshold: float = DEFAULT_THRESHOLD
    max_speed: tuple[float, float, float] = DEFAULT_MAX_SPEED
    # an assisted V is flown within policy_node's limits (max_speed, max_vertical_speed), as deployed (the
    # world's own clamp is 3 m/s); the unassisted pilot is not limited
    max_cmd_speed_mps: float = MAX_SPEED_MPS
    max_cmd_vertical_mps: float = MAX_VERTICAL_MPS
    window_s: float = 1.0
    feature_lags_s: tuple[float, ...] = ()           # feature memory (observation.FeatureMemory); () = none
    memory_displacement: bool = False                # + the displacement since each lagged feature
    history_s: float = 0.0                           # history window (observation.HistoryWindow); 0 = none
    history_step_s: float = 0.25                     # s between the window's rows
    latent_dim: int = 0                              # set from the encoder for the latent condition
    encoder_path: str = ''                           # CM-VAE weights (latent condition)
    pilot_family: str = 'paper'                      # assist_sim.pilots name: a family, 'mix' or 'train_mix'
    paper_share: float = 0.0                         # chance per landing of the paper pilot instead (training)
    # plant randomisation (training): chance per landing of the ArduCopter plant (else the world's own), its
    # dynamics scaled by uniform factors in [1 - spread, 1 + spread] (assist_sim.core.arducopter.randomised)
    arducopter_share: float = 0.0
    arducopter_spread: float = 0.0
    flight: FlightConfig = field(default_factory=FlightConfig)   # flight boundaries (flight.FlightMonitor)
    # the assistant's intent shown to the pilot (assist_policy.intent, as policy_node publishes it), and how the
    # pilots read it (assist_sim.cues; trust 0: they never look)
    cues: bool = False
    intent: IntentConfig = field(default_factory=IntentConfig)
    pilot_cues: CueConfig = field(default_factory=CueConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    pilot: PilotConfig = field(default_factory=PilotConfig)
    world: WorldConfig = field(default_factory=WorldConfig)


class LandingAssistEnv(gym.Env):
    """Shared-autonomy landing task with a simulated pilot (see module docstring)."""

    metadata = {'render_modes': []}

    def __init__(self, cfg: EnvConfig | None = None,
                 latent_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None):
        super().__init__()
        self.cfg = cfg or EnvConfig()
        cond = self.cfg.condition
        self.unassisted = cond == 'none'
        self.condition = Condition.ORACLE if self.unassisted else Condition(cond)
        if self.condition is Condition.LATENT and latent_fn is None:
            raise ValueError('latent condition needs latent_fn(rgb, depth) -> mu')
        self.latent_fn = latent_fn
        self.world = LandingWorld(self.cfg.world)
        self.builder = ObservationBuilder(self.condition, self.cfg.latent_dim, self.cfg.window_s,
                                          tuple(self.cfg.feature_lags_s), self.cfg.memory_displacement,
                                          self.cfg.history_s, self.cfg.history_step_s)
        self.dt = 1.0 / self.cfg.world.control_hz
        self.pilot_cfg = self.cfg.pilot
        self.pilot_cfg.control_hz = float(self.cfg.world.control_hz)
        vec = self.builder.dim
        self.image_size = int(np.prod(IMAGE_SHAPE)) if self.condition is Condition.END_TO_END else 0
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.image_size + vec,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.pilot: SimulatedPilot | None = None
        self.assistant = Assistant(assistant_config(self.cfg))     # the chain policy_node runs
        self.flight = FlightMonitor(self.cfg.flight)
        # the step code policy_node's core runs: observation, chain, action history, forgetting a flight
        intent = self.cfg.intent if self.cfg.cues else dataclasses.replace(self.cfg.intent, enabled=False)
        self.loop = AssistLoop(self.condition, self.builder, self.assistant, self.flight, intent)
        self.flight_resets = self.loop.flight_resets     # flight boundaries seen inside episodes, per reason
        self._frame = None
        self._u = np.zeros(3)
        self._steps = 0                                  # control steps since reset (the episode clock)
        self._dist = 0.0
        self.episode_return = 0.0
        self.path_m = 0.0                                # distance flown this episode (m, 3-D)
        self.last_command: tuple[np.ndarray, np.ndarray] | None = None   # (a, V) applied in the last step
        self._beta = 0.0                                 # this landing's pilot skill (privileged)
        self._last_a: np.ndarray | None = None           # the assistant action of the step before (action rate)
        # the goal head's estimate for the next step, set by whoever ran the actor (evaluate's GoalHeadPolicy) as
        # policy_node's core hands it to the loop; used by that step only
        self.learned_goal: LearnedGoal | None = None
        # per step with a learned goal: (episode time, whether the estimate is nearest the pilot's goal pad then)
        self.goal_trace: list[tuple[float, bool]] = []

    @property
    def pilot_action(self) -> np.ndarray:
        """The pilot's current command u_t (what the agent observes)."""
        return self._u.copy()

    @property
    def elapsed_s(self) -> float:
        """Episode time: control steps since reset x the control period.

        Counted, not read as world time - reset time: the world's clock runs on across episodes, and
        the rounding of that difference depends on how long it has run, so a landing's time limit
        fell one step later or earlier depending on the landings flown before it. Whole nanoseconds, as a
        landing's bag stamps it and replay reads it back (ns x 1e-9): the assistant's timers (a key held
        reversal_s ago, a window of persist_s) then compare the same numbers in the env and in replay, where
        steps x dt and the stamp differed in the last bit and a sample exactly on a window's edge fell on
        either side.
        """
        return round(self._steps * self.dt * 1e9) * 1e-9

    # -------------------------------------------------------------- helpers
    def _feature(self, pos: np.ndarray) -> np.ndarray:
        if self.condition is Condition.ORACLE:
            return oracle_feature(self.world.goal_position, pos)
        frame = self._frame = self.world.render()
        if self.condition is Condition.LATENT:
            if self.world.flight_controller is not None:    # the airframe leans: the encoder levels (as deployed)
                mu = self.latent_fn(frame.rgb, frame.depth, level=(frame.K, self.world.state.quaternion))
            else:
                mu = self.latent_fn(frame.rgb, frame.depth)
            return np.asarray(mu, dtype=float).reshape(-1)
        return image_feature(frame.rgb, frame.depth).reshape(-1)

    def _obs(self) -> np.ndarray:
        st = self.world.state
        self._frame = None
        t = self.elapsed_s
        return self.loop.observation(t, self._feature(st.position), st.velocity, st.position, self._u)

    def _goal_dist(self, pos: np.ndarray) -> float:
        return float(np.linalg.norm(self.world.goal_position - pos))

    # -------------------------------------------------------------- gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """New scene, goal, pilot (options: alpha, beta, scene_seed, goal_index, pilot = a pilots name)."""
        super().reset(seed=seed)
        options = options or {}
        rng = self.np_random
        plan = landing_plan(rng, options.get('beta'), options.get('pilot', self.cfg.pilot_family),
                            options.get('alpha', self.cfg.alpha), beta_range=self.cfg.beta_range,
                            paper_share=self.cfg.paper_share, scene_seed=options.get('scene_seed'),
                            pilot_named='pilot' in options)
        scene_seed, beta = plan.scene_seed, plan.beta
        self._beta = float(beta)
        st = self.world.reset(seed=scene_seed, goal_index=options.get('goal_index'))
        self.pilot = make_pilot(plan.pilot_family, plan.alpha, beta, self.pilot_cfg,
                                np.random.default_rng(plan.pilot_seed), pads=self.world.pad_top_centers,
                                cues=self.cfg.pilot_cues if self.cfg.cues else None)
        self.pilot.reset(self.world.goal_position, st.position)
        noise_seed = plan.noise_seed
        plant = self._draw_plant(rng)               # drawn after the plan: runs without it keep their landings
        latent_reset = getattr(self.latent_fn, 'reset', None)
        if latent_reset is not None:
            latent_reset(noise_seed)             # the camera noise of this landing depends on its seed only
        self.loop.restart()                        # a new episode is a new flight (the world teleports the vehicle)
        self.last_command = None
        self._last_a = None
        self.learned_goal = None
        self.goal_trace = []
        self._steps = 0
        self._u = self.pilot.act(st.position, None)
        self._dist = self._goal_dist(st.position)
        self.episode_return = 0.0
        self.path_m = 0.0
        return self._obs(), {'alpha': self.pilot.alpha, 'beta': beta, 'scene_seed': scene_seed,
                             'goal_index': self.world.goal_index, 'aimed_index': self.aimed_index(),
                             'pilot': self.pilot.name, 'pilot_params': dict(self.pilot.params), 'plant': plant}

    def _draw_plant(self, rng: np.random.Generator) -> str:
        """This landing's plant: the world's own unless `arducopter_share` draws the (randomised) ArduCopter one."""
        if self.cfg.arducopter_share <= 0.0:
            return 'arducopter' if self.world.flight_controller is not None else 'ideal'
        if rng.uniform() >= self.cfg.arducopter_share:
            self.world.set_flight_controller(self.cfg.world.flight_controller)
            return self.cfg.world.flight_controller
        cfg = self.cfg.world.arducopter
        if self.cfg.arducopter_spread > 0.0:
            cfg = randomised(cfg, rng, self.cfg.arducopter_spread)
        self.world.set_flight_controller('arducopter', cfg)
        return 'arducopter'

    def goal_label(self) -> np.ndarray:
        """The true goal relative to the vehicle now, as the oracle observes it (a goal head's training target)."""
        return oracle_feature(self.world.goal_position, self.world.state.position)

    def privileged(self) -> np.ndarray:
        """What an asymmetric critic sees besides the observation (PRIVILEGED_DIM values, float32): the true goal and
        the pilot's goal estimate relative to the vehicle (scaled as the oracle's feature), the pilot's alpha, beta."""
        pos = self.world.state.position
        return np.concatenate([oracle_feature(self.world.goal_position, pos),
                               oracle_feature(self.pilot.goal_estimate, pos),
                               [self.pilot.alpha, self._beta]]).astype(np.float32)

    def aimed_index(self) -> int:
        """Pad nearest (horizontally) to the pilot's current goal estimate: the pad it is heading for."""
        pads = self.world.pad_top_centers
        return nearest_xy(pads, self.pilot.goal_estimate)

    def step(self, action):
        """Blend, fly one control period, update the pilot, score (see module docstring)."""
        raw = np.asarray(action, dtype=float).reshape(3)
        if not np.all(np.isfinite(raw)):
            raise ValueError(f'non-finite action {raw.tolist()}')
        a = np.zeros(3) if self.unassisted else scale_action(raw, self.cfg.max_speed)
        t = self.elapsed_s
        st = self.world.state
        acted: tuple[str, ...] = ()
        if self.unassisted:
            v = self._u.copy()
            self.loop.idle(t, self._u)
        else:
            # the flight monitor policy_node's core runs (a landing, an odometry jump): the same rule here
            vz = 0.0 if self.last_command is None else float(self.last_command[1][2])
            boundary = self.flight.update(t, st.position, st.velocity, vz)
            if boundary is not None:
                self.loop.forget(boundary)
            v_body = quat_to_matrix(st.quaternion).T @ st.velocity   # odometry twist, base_link (REP-105)
            frame = DepthFrame(self._steps, lambda: self.camera_frame().depth, lambda: (st.position, st.quaternion))
            ctx = self.loop.context(t, self._u, st.position, v_body, st.quaternion, frame, self.cfg.max_speed)
            known = self.world.goal_position if self.condition is Condition.ORACLE else None
            res = self.loop.act(ctx, a, known_goal=known, learned_goal=self.learned_goal)
            a, v, acted = res.agent, res.velocity, res.acted
            if self.learned_goal is not None:
                nearest = nearest_xy(self.world.pad_top_centers, self.learned_goal.mean)
                self.goal_trace.append((t, nearest == self.world.goal_index))
        self.learned_goal = None
        self.pilot.see_cue(cue_of(self.loop.intent.last) if self.cfg.cues else None)
        active = float(np.linalg.norm(a)) > self.cfg.blend_threshold
        self.last_command = (a.copy(), np.array(v, dtype=float))    # what was flown (bags record it)
        before = st.position.copy()
        st = self.world.step(v)
        self.path_m += float(np.linalg.norm(st.position - before))
        self._steps += 1
        self._u = self.pilot.act(st.position, a if active else None)
        if self.pilot.new_goal_index is not None and self.pilot.new_goal_index != self.world.goal_index:
            self.world.change_goal(self.pilot.new_goal_index)     # the pilot changed its mind: judged on its new goal
            self._dist = self._goal_dist(st.position)              # progress counts toward the new goal from here
        r = self.cfg.reward
        d = self._goal_dist(st.position)
        reward = -r.action_weight * float(np.linalg.norm(a))
        if r.action_rate_weight > 0:
            before_a = np.zeros(3) if self._last_a is None else self._last_a
            reward -= r.action_rate_weight * float(np.linalg.norm(a - before_a))
        self._last_a = np.array(a, dtype=float)
        if d < r.progress_radius_m:
            reward += r.progress_weight * (self._dist - d)
        if (r.floor_descent_weight > 0 and v[2] < 0 and st.position[2] < r.floor_descent_height_m
                and not over_pad(self.world.scene.pads, st.position[:2], r.floor_pad_margin_m)):
            reward -= r.floor_descent_weight * float(-v[2])
        self._dist = d
        terminated = self.world.done
        truncated = (not terminated) and self.elapsed_s >= self.cfg.max_episode_s - 0.5 * self.dt
        info: dict[str, Any] = {'active': active, 'walls': 'wall_guard' in acted,
                                **{r.flag: r.switch in acted for r in RULES},      # guard, override, recall, damper
                                'goal_estimate': self.pilot.goal_estimate.copy()}
        if terminated:
            res = self.world.result
            res.assisted = not self.unassisted
            reward -= r.landing_weight * res.error_m
            reward += r.success_bonus * float(res.success) - r.crash_penalty * float(res.crash)
            info['result'] = res.to_dict()
        elif truncated:
            # time limit: scored like a landing where it is, so hovering forever never pays
            pos = st.position
            dists = np.linalg.norm(self.world.pad_top_centers[:, :2] - pos[:2], axis=1)
            info['result'] = {'goal_index': self.world.goal_index, 'landed_index': None,
                              'nearest_index': int(np.argmin(dists)),
                              'error_m': float(dists[self.world.goal_index]),
                              'nearest_error_m': float(dists.min()), 'success': False, 'crash': False,
                              'duration_s': self.elapsed_s, 'outcome': 'timeout',
                              'assisted': not self.unassisted}
            reward -= r.landing_weight * info['result']['error_m']
        self.episode_return += reward
        return self._obs(), float(reward), bool(terminated), bool(truncated), info

    def camera_frame(self):
        """This step's camera frame as rendered (clean depth): the encoder's, else rendered on first use
        (once a step)."""
        if self._frame is None:
            self._frame = self.world.render()
        return self._frame

    def close(self) -> None:
        """Release the pybullet client."""
        self.world.close()


def cue_of(intent: Intent) -> Cue:
    """What the station shows of the assistant's intent (the goal cue's xy standard deviation, the light)."""
    return Cue(intent.goal, intent.sigma_xy_m, intent.descent_ok)


def assistant_config(cfg: EnvConfig) -> AssistantConfig:
    """The assistant's settings for an env (its rules' settings as `cfg` holds them)."""
    return AssistantConfig(cfg.blend_threshold, cfg.max_cmd_speed_mps, cfg.max_cmd_vertical_mps, **all_settings(cfg))


def over_pad(pads, xy: np.ndarray, margin_m: float = 0.0) -> bool:
    """True if the horizontal point `xy` lies over a pad's yawed footprint grown by `margin_m` on each side."""
    return any(bool(pad.contains_xy(xy, margin=-margin_m)) for pad in pads)


def run_episode(env: LandingAssistEnv, policy, seed: int, options: dict | None = None) -> dict:
    """Roll out one landing with `policy(obs) -> raw action` (None = unassisted); returns a summary."""
    obs, info = env.reset(seed=seed, options=options)
    # step info key -> the summary's <name>_fraction: the assistant ran, the wall rule and each rule acted
    counted = {'active': 'active', 'walls': 'wall', **{r.flag: r.flag for r in RULES}}
    counts = dict.fromkeys(counted, 0)
    steps = 0
    while True:
        act = np.zeros(3) if policy is None else policy(obs)
        obs, _, term, trunc, step_info = env.step(act)
        steps += 1
        for key in counted:
            counts[key] += int(step_info.get(key, False))
        if term or trunc:
            break
    res = dict(step_info['result'])
    res.update(beta=info['beta'], alpha=info['alpha'], scene_seed=info['scene_seed'], steps=steps,
               aimed_index=info['aimed_index'], pilot=info['pilot'], episode_return=env.episode_return,
               path_m=env.path_m,
               **{f'{name}_fraction': counts[key] / steps for key, name in counted.items()})
    return res
