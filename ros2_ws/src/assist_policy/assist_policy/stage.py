"""What every stage of the assistant's chain sees and returns (``assistant.Assistant`` runs them in order).

Each non-learned rule implements ``Stage`` in its own module (``damper.DamperStage``, ``override.OverrideStage``,
``recall.RecallStage``, ``safety.GuardStage``, ``walls.WallStage``): ``apply`` gets the step's ``StepContext`` and
the ``Decision`` so far and returns a new ``Decision`` when it acts, None when it does not.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Protocol
from collections.abc import Callable, Hashable

import numpy as np

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


class Stage(Protocol):
    """One non-learned stage: ``apply`` returns the new Decision when the stage acts, None when it does not."""

    key: str

    def reset(self) -> None:
        """Forget this flight."""

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """Act on the decision so far, or return None."""
