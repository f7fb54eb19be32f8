"""The non-learned rules as every tool names them, and the one meaning of a rule's settings left out.

Each rule's module declares it (``stage.Rule``): the field that holds its settings, the policy_node parameter that
switches it (also its stage key and its /diagnostics counter ``<switch>_engaged``), the flag evaluate adds to a
condition's name when it flies (and its ``<flag>_fraction`` column), its settings class (each has an ``enabled``
switch), whether it is goal-agnostic (off by default for an assistant that knows the goal, mode oracle, and never
flown with the scripted references), and how it builds its stages. Everything else reads ``RULES``: the
assistant's chain, the configs that hold the rules' settings (``rule_fields``: ``AssistantConfig``,
``PolicyCoreConfig`` and so policy_node's parameters, ``EnvConfig``), evaluate's and evaluate_graph's options,
condition names and columns, and replay_assist's options. Adding a rule is its module (settings, stages, ``RULE``)
and its line in ``RULES``.

A rule's settings left out (None) are its settings class's defaults, everywhere; a rule is switched off by
its ``enabled`` field (``switched``), never by leaving it out.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

from . import damper, override, recall, safety
from .stage import Rule


# In the order they are built (a rule's parts may use those of the rules before it); the chain's order is the
# stages' own (Stage.phase, Stage.position).
RULES: tuple[Rule, ...] = (safety.RULE, override.RULE, recall.RULE, damper.RULE)
GOAL_AGNOSTIC = tuple(r for r in RULES if r.goal_agnostic)


def rule(name: str) -> Rule:
    """The rule named `name` (its settings field, switch or flag); ValueError naming the rules otherwise."""
    for r in RULES:
        if name in (r.field, r.switch, r.flag):
            return r
    raise ValueError(f'no rule {name!r} (rules: {", ".join(r.switch for r in RULES)})')


def rule_fields(field_for: Callable[[Rule], dataclasses.Field], annotation: Callable[[Rule], Any] | None = None):
    """A class decorator, applied before ``@dataclass``: one field per registered rule, named by its settings field
    (``field_for(rule)`` gives the field, ``annotation(rule)`` its type; default: the settings class or None), after
    the class's own fields."""
    def add(cls: type) -> type:
        notes = cls.__dict__.get('__annotations__', {})
        for r in RULES:
            if r.field in notes:
                raise TypeError(f'{cls.__name__}.{r.field} is a rule\'s field: rules.rule_fields adds it')
            notes[r.field] = annotation(r) if annotation else (r.config | None)
            setattr(cls, r.field, field_for(r))
        cls.__annotations__ = notes
        return cls
    return add


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
