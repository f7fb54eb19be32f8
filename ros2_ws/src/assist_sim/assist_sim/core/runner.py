"""Episode runner shared by sim_node and scripts: command validation and staleness, camera
scheduling, landing reports and auto-reset. Pure Python (no rclpy)."""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .world import CameraFrame, LandingResult, LandingWorld, VehicleState

_LOG = logging.getLogger(__name__)


@dataclass
class RunnerConfig:
    """How the runner turns commands into episodes."""

    camera_rate_hz: float = 20.0      # 0 disables the camera
    auto_reset: bool = True           # start the next episode after a landing
    reset_delay_s: float = 1.0        # sim seconds between a landing and the next episode
    cmd_timeout_s: float = 0.5        # older commands count as absent (zero velocity)
    max_cmd_speed_mps: float = 5.0    # larger commands are rejected as out of range
    airborne_start: bool = True       # False: episodes start landed and disarmed (MAVLink vehicle)
    # scene seed of episode 0, 1, 2, ... (every reset starts the next); past the end, or empty: the world's sequence
    episode_seeds: tuple[int, ...] = ()
    scene_seed: int = -1              # >= 0: every episode starts in the scene of this seed (a user study's one scene)
    goal_index: int = -1              # >= 0: the goal pad of every episode started from now on; -1: drawn per episode


@dataclass
class StepOutput:
    """What one control step produced."""

    state: VehicleState
    frame: CameraFrame | None = None
    landing: LandingResult | None = None
    new_episode: bool = False


def validate_velocity(v, max_speed: float) -> tuple[np.ndarray | None, str | None]:
    """Check a velocity 3-vector: (array, None) if usable, else (None, reason)."""
    arr = np.asarray(v, dtype=float).reshape(-1)
    if arr.shape != (3,):
        return None, f'expected 3 components, got {arr.size}'
    if not np.all(np.isfinite(arr)):
        return None, 'non-finite component'
    speed = float(np.linalg.norm(arr))
    if speed > max_speed:
        return None, f'speed {speed:.2f} m/s above the {max_speed:.2f} m/s limit'
    return arr, None


class SimRunner:
    """Drives a LandingWorld one control step at a time with the contract's timing rules."""

    def __init__(self, world: LandingWorld, cfg: RunnerConfig | None = None):
        self.world = world
        self.cfg = cfg or RunnerConfig()
        self._cmd = np.zeros(3)
        self._cmd_time = -math.inf
        self._agent_seen = False
        self._next_frame_time = 0.0
        self._landed_at: float | None = None
        self.episodes_finished = 0
        self.episodes_started = 0
        self.commands_rejected = 0

    # -------------------------------------------------------------- inputs
    def set_command(self, v) -> str | None:
        """Accept a body-FLU velocity command now (sim time); returns a rejection reason or None."""
        arr, reason = validate_velocity(v, self.cfg.max_cmd_speed_mps)
        if arr is None:
            self.commands_rejected += 1
            return reason
        self._cmd = arr
        self._cmd_time = self.world.time
        return None

    def note_agent_command(self) -> None:
        """Record that the assistant was live during this episode."""
        self._agent_seen = True

    @property
    def command(self) -> np.ndarray:
        """The command the vehicle flies now: zero when absent or stale."""
        if self.world.time - self._cmd_time > self.cfg.cmd_timeout_s:
            return np.zeros(3)
        return self._cmd.copy()

    @property
    def command_stale(self) -> bool:
        """True when no fresh command is present."""
        return self.world.time - self._cmd_time > self.cfg.cmd_timeout_s

    # -------------------------------------------------------------- episodes
    def reset(self, seed: int | None = None) -> VehicleState:
        """Start a new episode now (scene `seed`, else cfg.scene_seed, else the next of cfg.episode_seeds, else the
        world's sequence; goal pad cfg.goal_index unless -1)."""
        if seed is None and self.cfg.scene_seed >= 0:
            seed = int(self.cfg.scene_seed)
        elif seed is None and self.episodes_started < len(self.cfg.episode_seeds):
            seed = int(self.cfg.episode_seeds[self.episodes_started])
        goal = int(self.cfg.goal_index) if self.cfg.goal_index >= 0 else None
        state = self.world.reset(seed, goal_index=goal, airborne=self.cfg.airborne_start)
        self.episodes_started += 1
        self._cmd = np.zeros(3)
        self._cmd_time = -math.inf
        self._agent_seen = False
        self._landed_at = None
        self._next_frame_time = self.world.time + 1.0 / self.world.cfg.control_hz
        return state

    def step(self, fly=None) -> StepOutput:
        """Advance one control period; `fly(dt)` overrides how the vehicle is flown (MAVLink)."""
        w = self.world
        dt = 1.0 / w.cfg.control_hz
        was_done = w.done
        if fly is None:
            state = w.step(self.command, dt)
        else:
            fly(dt)
            state = w.state
        out = StepOutput(state=state)
        if w.done and not was_done:
            w.result.assisted = self._agent_seen
            out.landing = w.result
            self.episodes_finished += 1
            self._landed_at = w.time
        # a reset before the camera: a frame of this step would show the last episode's scene and pose, stamped
        # with the time the new episode starts (a receiver would place it at the new start pose)
        if (self.cfg.auto_reset and self._landed_at is not None
                and w.time - self._landed_at >= self.cfg.reset_delay_s):
            out.state = self.reset()
            out.new_episode = True
        if self.cfg.camera_rate_hz > 0 and w.time + 1e-9 >= self._next_frame_time:
            out.frame = w.render()
            self._next_frame_time += 1.0 / self.cfg.camera_rate_hz
            if self._next_frame_time < w.time:  # fell behind: do not burst
                self._next_frame_time = w.time + 1.0 / self.cfg.camera_rate_hz
        return out
