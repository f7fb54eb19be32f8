"""Config dataclasses as the one source of node parameters: a field declares its parameter beside its default.

A field made with ``node_param(default, 'name', 'description', min=..., max=..., dynamic=...)`` is a policy_node
parameter of that name, with that description, range and run-time rule (``dynamic`` True: applied by
``ros2 param set``; False: read-only). A field made with ``nested(Cls)`` holds a config of class ``Cls`` whose own
parameter fields belong to the node too. ``parameters(PolicyCoreConfig)`` lists them all, ``config_from``
builds the config from parameter values, and ``changes_for`` turns a run-time set into per-config changes.
Pure Python (no rclpy): policy_node turns each ``NodeParam`` into its ``Param``, and a test holds
``config/assist.yaml`` to the same names and defaults. A node parameter's range is its field's settings rule
too, and the other fields declare theirs with ``assist_common.settings.setting``: a config's ``__post_init__``
checks every field with ``check_named`` (ranges declared once, where the field is).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from assist_common.settings import RULE_KEY, Rule

PARAM_KEY = 'node_param'
NESTED_KEY = 'nested_config'


@dataclass(frozen=True)
class NodeParam:
    """A config field's node parameter: name, description, range, whether it changes at run time."""

    name: str
    description: str
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False
    dynamic: bool = True
    choices: tuple[str, ...] | None = None

    def settings_rule(self) -> Rule:
        """The same range as a settings rule (one declaration for the node parameter and the config field)."""
        return Rule(ge=None if self.min_exclusive else self.min, gt=self.min if self.min_exclusive else None,
                    le=self.max, choices=tuple(self.choices or ()))


@dataclass(frozen=True)
class ParamField:
    """Where a node parameter lives: the config path (('safety', 'enabled')), its default and NodeParam."""

    path: tuple[str, ...]
    default: Any
    spec: NodeParam


def node_param(default: Any, name: str, description: str, **rule: Any) -> Any:
    """A dataclass field with `default` that is the node parameter `name` (rule: NodeParam's min, max, ...); its
    range is also the field's settings rule (``assist_common.settings.check_named`` checks the config with it)."""
    spec = NodeParam(name, description, **rule)
    return dataclasses.field(default=default, metadata={PARAM_KEY: spec, RULE_KEY: spec.settings_rule()})


def nested(cls: type, default: Any = None) -> Any:
    """A dataclass field holding a config of class `cls` (None: `cls()` defaults) whose parameters are the node's."""
    return dataclasses.field(default=default, metadata={NESTED_KEY: cls})


def parameters(cls: type, prefix: tuple[str, ...] = ()) -> dict[str, ParamField]:
    """Every node parameter of config class `cls` and its nested configs, by parameter name, in field order."""
    out: dict[str, ParamField] = {}
    for f in dataclasses.fields(cls):
        if NESTED_KEY in f.metadata:
            inner = parameters(f.metadata[NESTED_KEY], prefix + (f.name,))
        elif PARAM_KEY in f.metadata:
            spec = f.metadata[PARAM_KEY]
            inner = {spec.name: ParamField(prefix + (f.name,), f.default, spec)}
        else:
            continue
        clash = set(inner) & set(out)
        if clash:
            raise TypeError(f'{cls.__name__}: node parameter(s) {sorted(clash)} declared twice')
        out.update(inner)
    return out


def config_from(cls: type, values: dict[str, Any], **fixed: Any) -> Any:
    """A `cls` config built from node parameter `values` (others keep their defaults) and `fixed` fields."""
    kwargs: dict[str, Any] = dict(fixed)
    for f in dataclasses.fields(cls):
        if f.name in fixed:
            continue
        if NESTED_KEY in f.metadata:
            kwargs[f.name] = config_from(f.metadata[NESTED_KEY], values)
        elif PARAM_KEY in f.metadata and f.metadata[PARAM_KEY].name in values:
            kwargs[f.name] = _typed(f.default, values[f.metadata[PARAM_KEY].name])
    return cls(**kwargs)


def changes_for(fields: dict[str, ParamField], changed: dict[str, Any]) -> dict[tuple[str, ...], dict[str, Any]]:
    """Run-time parameter sets as {config path of the owning config: {field: value}} ((): the top-level config)."""
    out: dict[tuple[str, ...], dict[str, Any]] = {}
    for name, value in changed.items():
        pf = fields.get(name)
        if pf is not None:
            out.setdefault(pf.path[:-1], {})[pf.path[-1]] = _typed(pf.default, value)
    return out


def _typed(default: Any, value: Any) -> Any:
    """`value` as the type of the field's default (a float field accepts an integer parameter)."""
    if isinstance(default, bool) or default is None:
        return value
    if isinstance(default, float):
        return float(value)
    if isinstance(default, int):
        return int(value)
    return value
