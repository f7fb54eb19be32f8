"""The deployed assistant: the actor's action through the non-learned stages to the command V, in one order.

policy_node (through ``policy_core.PolicyCore``), the training/evaluation env (``env.LandingAssistEnv``) and
``replay_assist`` all run this chain; nothing else chains the stages. The rules are ``rules.RULES``; each rule's
module builds its stages (``stage.Stage``: ``damper.DamperStage``, ``override.OverrideStage``, ...), and each stage
says where it sits (``phase``: on the actor's action or on V; ``position``). Each stage sees the same
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
from .rules import RULES, rule_fields, settings, switched
from .stage import ACTION, COMMAND, Decision, Stage, StepContext


@dataclass
@rule_fields(lambda r: field(default_factory=r.config), lambda r: r.config)    # each rule's settings
class AssistantConfig:
    """Settings of the chain (blending and speed limits here; each rule's in its own config, a field per rule)."""

    blend_threshold: float = setting(DEFAULT_THRESHOLD, ge=0)
    max_speed_mps: float = setting(MAX_SPEED_MPS, ge=MIN_SPEED_LIMIT_MPS)       # horizontal limit of V
    max_vertical_mps: float = setting(MAX_VERTICAL_MPS, ge=MIN_SPEED_LIMIT_MPS)  # vertical limit of V

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
        threshold = lambda: self.cfg.blend_threshold    # noqa: E731 - read at each step (changeable at run time)
        self.parts: dict[str, object] = {}              # the rules' objects by name: guard, walls, override, ...
        stages: list[Stage] = []
        for r in RULES:           # each rule's settings object is kept: run-time changes reach the rule
            cfg = settings(r, getattr(self.cfg, r.field))
            setattr(self.cfg, r.field, cfg)
            parts, own = r.make(cfg, self.parts, threshold)
            self.parts.update(parts)
            stages += own
        keys = [s.key for s in stages]
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:
            raise TypeError(f'stage {", ".join(map(repr, twice))} registered twice')
        ordered = sorted(stages, key=lambda s: s.position)
        self.action_stages: tuple[Stage, ...] = tuple(s for s in ordered if s.phase == ACTION)
        self.command_stages: tuple[Stage, ...] = tuple(s for s in ordered if s.phase == COMMAND)
        self.engaged: Counter[str] = Counter()           # steps each stage acted (stage key)
        self.modes: Counter[str] = Counter()             # ... per mode (e.g. 'pilot_override:climb')

    def __getattr__(self, name: str) -> object:
        """A rule's object by name (``assistant.recall``, ``assistant.guard``: ``parts``)."""
        parts = self.__dict__.get('parts', {})
        if name in parts:
            return parts[name]
        raise AttributeError(f'{type(self).__name__!r} object has no attribute {name!r}')

    @property
    def stages(self) -> tuple[Stage, ...]:
        """Every stage, in order."""
        return self.action_stages + self.command_stages

    def diagnostics(self) -> dict[str, int]:
        """Every stage's ``<key>_engaged`` count and its own /diagnostics values."""
        out: dict[str, int] = {}
        for s in self.stages:
            out[f'{s.key}_engaged'] = self.engaged[s.key]
            out.update(s.diagnostics(self.modes))
        return out

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
            for stage in self.action_stages:    # each new action replaces the one before: only the last acted on
                new = stage.apply(ctx, d)       # what flies
                if new is not None:
                    d = new
                    acted[:] = [stage.key]
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
        for stage in self.stages:
            for mode in stage.modes(stage.key in acted, agent is not None):
                self.modes[f'{stage.key}:{mode}'] += 1
        v = clamp_velocity(d.velocity, c.max_speed_mps, c.max_vertical_mps)
        return StepResult(d.agent, v, applied, d.key, d.reason, tuple(acted))
