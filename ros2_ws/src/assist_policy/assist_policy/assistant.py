"""The deployed assistant: the actor's action through the non-learned stages to the command V, in one order.

policy_node (through ``policy_core.PolicyCore``), the training/evaluation env (``env.LandingAssistEnv``) and
``replay_assist`` all run this chain; nothing else chains the stages. Each rule's module implements its stage
(``stage.Stage``: ``damper.DamperStage``, ``override.OverrideStage``, ...); each stage sees the same
``StepContext`` and the ``Decision`` so far, and returns a new ``Decision`` when it acts (None when it
does not). The order, and so who wins:

1. ``oscillation_damper`` (``damper.OscillationDamper``): while the pilot's held keys keep reversing across
   a mapped pad, a_xy = -gain v_xy. A later action stage replaces its result.
2. ``pilot_override`` (``override.PilotOverride``): a held key, a persistent or long push, a held climb
   passes instead of a. Wins over the damper and the recall (its Decision is ``final``: the recall leaves it).
3. ``pad_recall`` (``recall.PadRecall``): maps every depth frame (also when it then does not act); steers a
   descent over bare floor back to a mapped pad (recall, scout) or centres on the pad below (touchdown).
4. blending (``blending.blend``): V = (u + a) / 2 if |a| > threshold else u. The action history the
   actor observes records a as it stands here (zero when the actor did not run).
5. ``floor_guard`` (``safety.FloorGuard``): low over bare floor (or straddling a pad edge), a descent in V is
   replaced by a small climb (a' = (a_xy, 2 climb - u_z)). Acts on whatever the stages above produced.
6. ``wall_guard`` (``walls.WallGuard``, same settings and switch as the floor guard): the part of V heading
   for a wall seen within reach is removed, the pilot's too (a' = 2 V' - u).
7. speed clamp (``blending.clamp_velocity``): V within max_speed (horizontal) and max_vertical_speed.

When the actor did not run (stale inputs, a non-finite action: ``agent`` None), the action stages 1-3 are
skipped and V = u goes through 5-7: the guards protect an unassisted pilot as well.

Everything a stage remembers (pad and wall maps, landing spots, held keys, reversals, the last pad under the
legs) belongs to one flight: ``Assistant.reset`` forgets it (``flight.FlightMonitor`` decides when).
"""
from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from assist_common.settings import check_named, setting

from .blending import DEFAULT_THRESHOLD, MAX_SPEED_MPS, MAX_VERTICAL_MPS, MIN_SPEED_LIMIT_MPS, blend, clamp_velocity
from .damper import DamperConfig, DamperStage, OscillationDamper
from .override import OverrideConfig, OverrideStage, PilotOverride
from .recall import PadRecall, RecallConfig, RecallStage
from .rules import RULES, switched
from .safety import FloorGuard, GuardStage, SafetyConfig
from .stage import Decision, Stage, StepContext
from .walls import WallGuard, WallStage


@dataclass
class AssistantConfig:
    """Settings of the chain (blending and speed limits here; each stage's in its own config)."""

    blend_threshold: float = setting(DEFAULT_THRESHOLD, ge=0)
    max_speed_mps: float = setting(MAX_SPEED_MPS, ge=MIN_SPEED_LIMIT_MPS)       # horizontal limit of V
    max_vertical_mps: float = setting(MAX_VERTICAL_MPS, ge=MIN_SPEED_LIMIT_MPS)  # vertical limit of V
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    override: OverrideConfig = field(default_factory=OverrideConfig)
    recall: RecallConfig = field(default_factory=RecallConfig)
    damper: DamperConfig = field(default_factory=DamperConfig)

    def __post_init__(self) -> None:
        """Reject a threshold or limits that would suppress or invent motion (SettingsError, one line)."""
        check_named(self, type(self).__name__)


def rules_off(cfg: AssistantConfig | None = None) -> AssistantConfig:
    """A copy of `cfg` (default settings: None) with every non-learned rule switched off: the bare actor."""
    cfg = cfg or AssistantConfig()
    return dataclasses.replace(cfg, **{r.field: switched(r, False, getattr(cfg, r.field)) for r in RULES})


# ----------------------------------------------------------------------------------------------- chain
@dataclass
class StepResult:
    """One step of the chain: the command to fly and what decided it."""

    agent: np.ndarray | None            # a as flown (None: the actor did not run and no stage acted)
    velocity: np.ndarray                # V, within the speed limits
    applied: np.ndarray                 # a as it stood at blending (the action history records it)
    key: str                            # the last stage that acted, else assisting / small_action / the input's
    reason: str
    acted: tuple[str, ...] = ()         # every stage that acted on what flew this step, in order


class Assistant:
    """The ordered stages around the actor (see the module docstring); one per flight memory."""

    def __init__(self, cfg: AssistantConfig | None = None):
        self.cfg = cfg or AssistantConfig()
        c = self.cfg
        self.guard = FloorGuard(c.safety)
        self.walls = WallGuard(c.safety)                 # the same settings object: one switch for both
        self.override = PilotOverride(c.override)
        self.recall = PadRecall(c.recall, self.guard)
        self.damper = OscillationDamper(c.damper)
        threshold = lambda: self.cfg.blend_threshold    # noqa: E731 - read at each step (changeable at run time)
        self.action_stages: tuple[Stage, ...] = (DamperStage(self.damper, self.recall),
                                                 OverrideStage(self.override, self.guard),
                                                 RecallStage(self.recall))
        self.command_stages: tuple[Stage, ...] = (GuardStage(self.guard, threshold),
                                                  WallStage(self.walls, threshold))
        self.engaged: Counter[str] = Counter()           # steps each stage acted (stage key)
        self.modes: Counter[str] = Counter()             # ... of those, per mode (e.g. 'pilot_override:climb')

    @property
    def stages(self) -> tuple[Stage, ...]:
        """Every stage, in order."""
        return self.action_stages + self.command_stages

    def reset(self) -> None:
        """Forget the flight: every stage's memory."""
        for s in self.stages:
            s.reset()

    def configure(self, **changes) -> None:
        """Change blend_threshold / max_speed_mps / max_vertical_mps at run time (ValueError: nothing changed)."""
        new = dataclasses.replace(self.cfg, **changes)
        for name in changes:
            setattr(self.cfg, name, getattr(new, name))

    def step(self, ctx: StepContext, agent: np.ndarray | None, key: str = '', reason: str = '') -> StepResult:
        """The command for this step from the actor's action `agent` (m/s, base_link; None: it did not run, then
        `key`/`reason` say why)."""
        c = self.cfg
        d = Decision(None if agent is None else np.asarray(agent, dtype=float).reshape(3), None, key, reason)
        acted: list[str] = []
        if d.agent is not None:
            for stage in self.action_stages:
                new = stage.apply(ctx, d)
                if new is not None:
                    d = new
                    acted.append(stage.key)
        if DamperStage.key in acted and (OverrideStage.key in acted or RecallStage.key in acted):
            acted.remove(DamperStage.key)       # its action was replaced: it did not act on what flew
        applied = np.zeros(3) if d.agent is None else d.agent
        d.velocity = blend(ctx.u, applied, c.blend_threshold)
        if d.agent is not None and not d.key:
            big = float(np.linalg.norm(d.agent)) > c.blend_threshold
            d.key, d.reason = ('assisting', 'assisting') if big else ('small_action', 'relinquished')
        for stage in self.command_stages:
            new = stage.apply(ctx, d)
            if new is not None:
                d = new
                acted.append(stage.key)
        for k in acted:
            self.engaged[k] += 1
        if OverrideStage.key in acted and self.override.mode:
            self.modes[f'{OverrideStage.key}:{self.override.mode}'] += 1
        elif RecallStage.key in acted and self.recall.mode:
            self.modes[f'{RecallStage.key}:{self.recall.mode}'] += 1
        if agent is not None and self.override.kept:      # a landing spot kept the actor's action
            self.modes[f'{OverrideStage.key}:spot_kept'] += 1
        v = clamp_velocity(d.velocity, c.max_speed_mps, c.max_vertical_mps)
        return StepResult(d.agent, v, applied, d.key, d.reason, tuple(acted))
