"""What every stage of the assistant's chain sees and returns, and how a rule declares itself (``Rule``).

Each non-learned rule lives in its own module with its settings class, its stages and its ``RULE`` (``damper``,
``override``, ``recall``, ``safety``); ``rules.RULES`` lists them. A stage (``damper.DamperStage``,
``override.OverrideStage``, ``recall.RecallStage``, ``safety.GuardStage``, ``walls.WallStage``) says where it sits
in the chain (``phase``: on the actor's action before blending, or on the command after it; ``position`` within
the phase); ``apply`` gets the step's ``StepContext`` and the ``Decision`` so far and returns a new ``Decision``
when it acts, None when it does not.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Hashable, Mapping

import numpy as np

from .observation import Condition

Pose = tuple[np.ndarray, 'np.ndarray | None']     # odom position, attitude quaternion (x, y, z, w) or None


class DepthFrame:
    """One depth image (metres, HxW) with the odometry pose it was taken from; both read at most once, when asked.

    `key` identifies the frame: the stages that map what the camera sees (pad map, wall map) add a frame once.
    """

    def __init__(self, key: Hashable, image: Callable[[], np.ndarray], pose: Callable[[], Pose]):
        self.key = key
        self._image = image
        self._pose = pose

    @functools.cached_property
    def image(self) -> np.ndarray:
        """The depth image (rendered or decoded on first use)."""
        return self._image()

    @functools.cached_property
    def pose(self) -> Pose:
        """(position, attitude) of the vehicle when the frame was taken."""
        return self._pose()


@dataclass
class StepContext:
    """What every stage sees in one control step (odom ENU positions, base_link velocities and commands)."""

    t: float                            # flight clock (s)
    u: np.ndarray                       # pilot command
    mean_u: np.ndarray                  # its mean over the observation window (the actor's input)
    position: np.ndarray                # vehicle position (odom)
    velocity: np.ndarray                # odometry twist (base_link)
    quaternion: np.ndarray | None       # attitude (None: level, heading 0)
    frame: DepthFrame | None            # a fresh depth frame, or None (the depth-reading stages then skip)
    max_speed: tuple[float, float, float]   # the actor's action limits (m/s per axis)


@dataclass
class Decision:
    """The step's result so far: agent action a (None: the actor did not run), command V (None before blending)."""

    agent: np.ndarray | None
    velocity: np.ndarray | None = None
    key: str = ''                       # which stage decided last ('' before any)
    reason: str = ''
    final: bool = False                 # the pilot's own correction: the later action stages leave it as it is


ACTION, COMMAND = 'action', 'command'      # a stage's phase: on the actor's action (before blending), on V (after)


class Stage:
    """One non-learned stage (each rule's module subclasses it): ``apply`` returns the new Decision when the stage
    acts, None when it does not."""

    key: str                 # its name in counters and /diagnostics (`<key>_engaged`)
    phase: str               # ACTION or COMMAND
    position: int            # order within the phase (lower first)

    def reset(self) -> None:
        """Forget this flight."""

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """Act on the decision so far, or return None."""
        raise NotImplementedError

    def modes(self, acted: bool, ran: bool) -> tuple[str, ...]:
        """What to count under `<key>:<mode>` after a step (`acted`: it acted on what flew; `ran`: the actor ran)."""
        return ()

    def diagnostics(self, modes: Mapping[str, int]) -> dict[str, int]:
        """Its own /diagnostics values beside `<key>_engaged`, from the chain's mode counts (`<key>:<mode>`)."""
        return {}


Parts = Mapping[str, Any]      # the rules' objects built so far, by name (Assistant.parts: 'guard', 'recall', ...)


@dataclass(frozen=True)
class Rule:
    """One non-learned rule: where its settings live, how each tool names it, and how it joins the chain.

    ``make(settings, parts, threshold)`` builds the rule from its settings (its config class; the object is kept,
    so run-time changes to it reach the rule), the parts of the rules registered before it and the blending
    threshold (read at each step), and returns its parts by name and its stages.
    """

    field: str              # settings field of every config that holds the rules: 'safety'
    switch: str             # policy_node parameter, stage key, counter: 'floor_guard'
    flag: str               # evaluate's condition-name flag and fraction column: 'guard'
    config: type            # settings dataclass (with an `enabled` field)
    goal_agnostic: bool     # off by default when the assistant knows the goal
    title: str              # as a person reads it: 'floor guard'
    make: Callable[[Any, Parts, Callable[[], float]], tuple[dict[str, Any], tuple[Stage, ...]]]

    @property
    def module(self) -> str:
        """The module that implements it (its settings class's): 'assist_policy.safety'."""
        return self.config.__module__

    def default_on(self, mode: str) -> bool:
        """Whether policy_node flies the rule by default in `mode` (latent, oracle, end_to_end)."""
        return not (self.goal_agnostic and Condition(mode).knows_goal)
