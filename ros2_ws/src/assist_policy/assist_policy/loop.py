"""The step code around the actor, run by policy_node's core (``policy_core.PolicyCore``) and by the training and
evaluation env (``assist_lab.env.LandingAssistEnv``) alike.

Each control step: the actor's observation (``observation``), the context every stage sees (``context``), the
assistant's chain on the actor's action with the action history recording what was applied and the assistant's
intent following the command (``act``; a step
without the chain records no action: ``idle``), and at a flight boundary the flight's memories forgotten and
counted by reason (``forget``). What differs between the two is only where the inputs come from (messages or
the simulated world) and who runs the actor (the core, or the gymnasium agent).
"""
from __future__ import annotations

from collections import Counter

import numpy as np

from .assistant import Assistant, StepResult
from .stage import DepthFrame, StepContext
from .flight import FlightMonitor
from .intent import IntentConfig, IntentEstimator, LearnedGoal
from .observation import Condition, ObservationBuilder


class AssistLoop:
    """The observation builder, the assistant and the flight monitor of one vehicle, stepped together."""

    def __init__(self, condition: Condition, builder: ObservationBuilder, assistant: Assistant,
                 flight: FlightMonitor, intent: IntentConfig | None = None):
        self.condition = Condition(condition)
        self.builder = builder
        self.assistant = assistant
        self.flight = flight
        # the assistant's intent (goal estimate, descent flag) after each chain step (None: not estimated)
        self.intent = IntentEstimator(intent or IntentConfig(enabled=False), assistant.recall, assistant.guard)
        self.flight_resets: Counter[str] = Counter()    # flight boundaries, per reason (flight.REASONS)

    def observation(self, t: float, feature: np.ndarray, velocity: np.ndarray, position: np.ndarray,
                    u: np.ndarray) -> np.ndarray:
        """The actor's input at `t` (float32): the vector part from the builder (feature, velocity, height, u, the
        means, lags and displacement the actor declares); end_to_end: the image feature first, then that vector."""
        if self.condition is Condition.END_TO_END:
            vec = self.builder.build(t, np.zeros(0), velocity, position[2], u)
            return np.concatenate([feature, vec]).astype(np.float32)
        return self.builder.build(t, feature, velocity, position[2], u, position)

    def context(self, t: float, u: np.ndarray, position: np.ndarray, velocity: np.ndarray,
                quaternion: np.ndarray | None, frame: DepthFrame | None,
                max_speed: tuple[float, float, float]) -> StepContext:
        """What every stage sees this step (the pilot's mean command over the observation window included)."""
        return StepContext(t, u, self.builder.history.means(t)[0], position, velocity, quaternion, frame, max_speed)

    def act(self, ctx: StepContext, agent: np.ndarray | None, key: str = '', reason: str = '',
            known_goal: np.ndarray | None = None, learned_goal: LearnedGoal | None = None) -> StepResult:
        """The chain on the actor's action `agent` (None: it did not run; `key`/`reason` say why); the action
        history records a as it stood at blending, and the intent (``intent.last``) follows the command that flies
        (`known_goal`: the goal an oracle assistant is given; `learned_goal`: the actor's goal head's estimate)."""
        res = self.assistant.step(ctx, agent, key, reason)
        self.builder.record(ctx.t, ctx.u, res.applied)
        self.intent.update(ctx, res.velocity, known_goal, assisting=agent is not None, learned=learned_goal)
        return res

    def idle(self, t: float, u: np.ndarray) -> None:
        """A step without the chain (unassisted, no odometry): the history records u and no action; no intent."""
        self.builder.record(t, u, np.zeros(3))
        self.intent.clear()

    def forget(self, reason: str) -> None:
        """A flight boundary: the action history and every stage's memory go; counted under `reason`."""
        self.builder.reset()
        self.assistant.reset()
        self.intent.reset()
        self.flight_resets[reason] += 1

    def restart(self) -> None:
        """A new episode (the env's reset, not a boundary inside a flight): everything forgotten, nothing counted."""
        self.builder.reset()
        self.assistant.reset()
        self.intent.reset()
        self.flight.reset()
