"""The non-learned rules as every tool names them, and the one meaning of a rule's settings left out.

Each rule has one entry: the field that holds its settings (``AssistantConfig``, ``PolicyCoreConfig``,
``EnvConfig`` and the evaluation and replay options), the policy_node parameter that switches it (also its
stage key and its /diagnostics counter ``<switch>_engaged``), the flag evaluate adds to a condition's name
when it flies (and its ``<flag>_fraction`` column), its settings class (each has an ``enabled`` switch) and
whether it is goal-agnostic: such a rule is off by default for an assistant that knows the goal (mode
oracle) and never flies with the scripted references.

A rule's settings left out (None) are its settings class's defaults, everywhere; a rule is switched off by
its ``enabled`` field (``switched``), never by leaving it out.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from .damper import DamperConfig
from .observation import Condition
from .override import OverrideConfig
from .recall import RecallConfig
from .safety import SafetyConfig


@dataclass(frozen=True)
class Rule:
    """One non-learned rule: where its settings live and how each tool names it."""

    field: str              # settings field: 'safety'
    switch: str             # policy_node parameter, stage key, counter: 'floor_guard'
    flag: str               # evaluate's condition-name flag and fraction column: 'guard'
    config: type            # settings dataclass (with an `enabled` field)
    goal_agnostic: bool     # off by default when the assistant knows the goal

    def default_on(self, mode: str) -> bool:
        """Whether policy_node flies the rule by default in `mode` (latent, oracle, end_to_end)."""
        return not (self.goal_agnostic and Condition(mode).knows_goal)


RULES: tuple[Rule, ...] = (
    Rule('safety', 'floor_guard', 'guard', SafetyConfig, goal_agnostic=False),
    Rule('override', 'pilot_override', 'override', OverrideConfig, goal_agnostic=True),
    Rule('recall', 'pad_recall', 'recall', RecallConfig, goal_agnostic=True),
    Rule('damper', 'oscillation_damper', 'damper', DamperConfig, goal_agnostic=True),
)
GOAL_AGNOSTIC = tuple(r for r in RULES if r.goal_agnostic)


def rule(name: str) -> Rule:
    """The rule named `name` (its settings field, switch or flag); ValueError naming the rules otherwise."""
    for r in RULES:
        if name in (r.field, r.switch, r.flag):
            return r
    raise ValueError(f'no rule {name!r} (rules: {", ".join(r.switch for r in RULES)})')


def _check_registry(rules: tuple[Rule, ...]) -> None:
    """TypeError (one line) when two rules share a field, switch or flag, or a settings class has no switch."""
    for attr in ('field', 'switch', 'flag'):
        names = [getattr(r, attr) for r in rules]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise TypeError(f'rule {attr} {", ".join(map(repr, twice))} registered twice')
    for r in rules:
        if 'enabled' not in {f.name for f in dataclasses.fields(r.config)}:
            raise TypeError(f'rule {r.switch}: {r.config.__name__} has no `enabled` field')


_check_registry(RULES)


def settings(rule: Rule, value: Any = None) -> Any:
    """The rule's settings from `value`: None gives the defaults, a mapping the defaults with those fields
    changed (an unknown field is a ValueError naming it), a settings object is taken as it is."""
    if value is None:
        return rule.config()
    if isinstance(value, rule.config):
        return value
    if isinstance(value, Mapping):
        return changed(rule, rule.config(), value)
    raise TypeError(f'{rule.switch}: settings must be None, a mapping or a {rule.config.__name__}, '
                    f'got {type(value).__name__}')


def changed(rule: Rule, current: Any, changes: Mapping[str, Any]) -> Any:
    """A copy of the rule's settings `current` with `changes` (validated by the settings class; a field it does not
    have is a ValueError naming it)."""
    known = {f.name for f in dataclasses.fields(rule.config)}
    unknown = sorted(set(changes) - known)
    if unknown:
        raise ValueError(f'{rule.switch}: unknown setting{"s" if len(unknown) > 1 else ""} '
                         f'{", ".join(map(repr, unknown))} (known: {", ".join(sorted(known))})')
    return dataclasses.replace(current, **changes)


def switched(rule: Rule, on: bool, value: Any = None) -> Any:
    """The rule's settings (`value` as in `settings`) with its switch set to `on`."""
    return dataclasses.replace(settings(rule, value), enabled=bool(on))


def all_settings(obj: Any) -> dict[str, Any]:
    """Every rule's settings held by config `obj` (its fields named by the registry), None resolved to defaults."""
    return {r.field: settings(r, getattr(obj, r.field)) for r in RULES}
