"""Node parameters (declared with a default, a description and a range, read-only unless run-time), their
--help text and table, and the start-up error every node reports in one line."""
from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from .console import HELP_FLAGS, VERSION_FLAG, own_arguments, package_version, version_text  # noqa: F401 - re-exported


class StartupError(RuntimeError):
    """A node cannot start (bad parameter, missing model, unreachable endpoint): one clear line."""


_NUMERIC = (int, float)


@dataclass(frozen=True)
class Param:
    """One declared node parameter: default, description, and the rule every value must pass.

    `min`/`max` bound numeric values (inclusive unless `min_exclusive`), `choices` lists the
    accepted strings, `dynamic` marks a parameter the node applies at run time (validated by the
    parameter callback); every other parameter is declared read-only, so `ros2 param set` is
    refused instead of accepted and ignored. A float parameter accepts an integer (`-p x:=2`).
    An array parameter has a list default and `item_type` (int, float or str): every item is
    checked against `min`/`max`/`choices` (rcl's parser wants one item type: write 0.0, not 0, in a
    float array).
    """

    default: Any
    description: str
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False
    choices: tuple[str, ...] | None = None
    dynamic: bool = False
    item_type: type | None = None

    def coerce(self, name: str, value: Any) -> Any:
        """Value converted to the parameter's type and checked; ValueError with a one-line reason."""
        if self.item_type is not None:
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"parameter '{name}' must be a list, got {value!r}")
            item = Param(self.item_type(), self.description, self.min, self.max, self.min_exclusive, self.choices)
            return [item.coerce(f'{name}[{i}]', v) for i, v in enumerate(value)]
        kind = type(self.default)
        if kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"parameter '{name}' must be true or false, got {value!r}")
            return value
        if kind in _NUMERIC:
            if isinstance(value, bool) or not isinstance(value, _NUMERIC):
                raise ValueError(f"parameter '{name}' must be a number, got {value!r}")
            if kind is int:
                if isinstance(value, float):
                    if not (math.isfinite(value) and value.is_integer()):
                        raise ValueError(f"parameter '{name}' must be an integer, got {value!r}")
                    value = int(value)
            else:
                value = float(value)
                if not math.isfinite(value):
                    raise ValueError(f"parameter '{name}' must be finite, got {value!r}")
            self._check_range(name, value)
            return value
        if kind is str:
            if not isinstance(value, str):
                raise ValueError(f"parameter '{name}' must be a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise ValueError(f"parameter '{name}' must be one of {', '.join(self.choices)}; got {value!r}")
            return value
        if isinstance(self.default, (list, tuple)):
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"parameter '{name}' must be a list, got {value!r}")
            return list(value)
        return value

    def rule(self) -> str:
        """The accepted values in words ('> 0.0 and <= 10.0', 'one of a, b'); empty when unrestricted."""
        if self.choices is not None:
            return 'one of ' + ', '.join(self.choices)
        lo, hi = self.min, self.max
        lo_s = '' if lo is None else (f'> {lo}' if self.min_exclusive else f'>= {lo}')
        hi_s = '' if hi is None else f'<= {hi}'
        return ' and '.join(x for x in (lo_s, hi_s) if x)

    def _check_range(self, name: str, value: float) -> None:
        lo, hi = self.min, self.max
        below = lo is not None and (value <= lo if self.min_exclusive else value < lo)
        above = hi is not None and value > hi
        if below or above:
            raise ValueError(f"parameter '{name}' must be {self.rule()}, got {value!r}")


_ARRAY_TYPES = {int: Parameter.Type.INTEGER_ARRAY, float: Parameter.Type.DOUBLE_ARRAY,
                str: Parameter.Type.STRING_ARRAY}


class ParamValues(dict):
    """The node's current (validated, coerced) parameter values; dynamic ones follow run-time sets."""


def declare_parameters(node: Node, spec: Mapping[str, Param],
                       on_change: Callable[[dict[str, Any]], None] | None = None) -> ParamValues:
    """Declare every parameter in `spec`, validate the start-up values and return them (live).

    A bad start-up value raises StartupError (one line naming the node and parameter). Parameters
    with `dynamic=True` may be set at run time: each set is validated with the same rule and then
    passed to `on_change(changed)` (which may raise ValueError to refuse it); the others are
    read-only. The returned dict is updated in place when a set is accepted.
    """
    from rcl_interfaces.msg import SetParametersResult

    values = ParamValues()
    for name, p in spec.items():
        rule = p.rule()
        text = p.description + (f' Accepted: {rule}.' if rule else '') + ('' if p.dynamic else ' Read-only.')
        desc = ParameterDescriptor(description=text, read_only=not p.dynamic,
                                   dynamic_typing=(isinstance(p.default, (int, float))
                                                   and not isinstance(p.default, bool)))
        try:
            if p.item_type is not None:      # typed array (an empty default has no type of its own)
                desc.type = _ARRAY_TYPES[p.item_type].value
                raw = node.declare_parameter(name, _ARRAY_TYPES[p.item_type], desc).value
                raw = list(p.default) if raw is None else raw
            else:
                raw = node.declare_parameter(name, p.default, desc).value
        except Exception as exc:  # rclpy raises its own type errors for e.g. a string for a bool
            raise StartupError(f'{node.get_name()}: parameter {name!r}: {exc}') from exc
        try:
            values[name] = p.coerce(name, raw)
        except ValueError as exc:
            raise StartupError(f'{node.get_name()}: {exc}') from exc

    def _on_set(params) -> SetParametersResult:
        changed = {}
        for prm in params:
            p = spec.get(prm.name)
            if p is None:
                continue  # use_sim_time and other rclpy-owned parameters
            try:
                changed[prm.name] = p.coerce(prm.name, prm.value)
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        if changed:
            old = {k: values[k] for k in changed}
            values.update(changed)
            if on_change is not None:
                try:
                    on_change(changed)
                except ValueError as exc:
                    values.update(old)
                    return SetParametersResult(successful=False, reason=str(exc))
            node.get_logger().info('parameters set: ' + ', '.join(f'{k}={v!r}' for k, v in changed.items()))
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(_on_set)
    return values


def check_overrides(node: Node) -> None:
    """StartupError (one line) when the node was given a parameter it does not declare (a misspelt name in a
    parameter file or a ``-p``), naming the closest declared one: rclpy would otherwise ignore it silently."""
    import difflib
    given = node._parameter_overrides      # rclpy keeps a node's start-up overrides only here (no public getter)
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if not unknown:
        return
    declared = sorted(node._parameters)
    hints = []
    for name in unknown:
        close = difflib.get_close_matches(name, declared, n=1)
        hints.append(f'{name!r}' + (f' (did you mean {close[0]!r}?)' if close else ''))
    raise StartupError(f'{node.get_name()}: unknown parameter{"s" if len(unknown) > 1 else ""} {", ".join(hints)}; '
                       'its --help lists the parameters')





def _param_type(p: Param) -> str:
    """ROS type name of a parameter's values (bool, integer, double, string, or an array of one)."""
    names = {bool: 'bool', int: 'integer', float: 'double', str: 'string'}
    if p.item_type is not None:
        return names[p.item_type] + '[]'
    return names.get(type(p.default), type(p.default).__name__)


def parameter_help(params: Mapping[str, Param]) -> str:
    """One entry per parameter: name, type, default, accepted values, run-time or read-only, description."""
    lines = []
    for name, p in params.items():
        rule = p.rule()
        facts = [_param_type(p), f'default {p.default!r}'] + ([rule] if rule else [])
        facts.append('run-time' if p.dynamic else 'read-only')
        lines.append(f'  {name} ({"; ".join(facts)})')
        lines.append(f'      {p.description}')
    return '\n'.join(lines)


def parameter_table(params: Mapping[str, Param]) -> str:
    """The parameters as a Markdown table (name, type, default, accepted, run-time, description): docs/nodes.md."""
    def cell(text: str) -> str:
        return str(text).replace('|', '\\|').replace('\n', ' ')
    rows = ['| parameter | type | default | accepted | run-time | description |',
            '| --- | --- | --- | --- | --- | --- |']
    for name, p in params.items():
        rows.append(f'| `{name}` | {_param_type(p)} | `{p.default!r}` | {cell(p.rule() or "any")} | '
                    f'{"yes" if p.dynamic else "no"} | {cell(p.description)} |')
    return '\n'.join(rows)


def node_help(prog: str, summary: str, params: Mapping[str, Param] | None) -> str:
    """The --help text of node executable `prog`: usage, `summary`, and its parameter table."""
    text = [f'usage: {prog} [-h] [--version] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] ...]', '']
    if summary:
        text += [summary, '']
    if params:
        text += ['parameters (-p NAME:=VALUE; run-time ones also by `ros2 param set`):', parameter_help(params)]
    else:
        text += ['parameters: see `ros2 param describe` on the running node']
    return '\n'.join(text) + '\n'


def console_request(factory: Callable[[], Node], args: list[str] | None,
                    params: Mapping[str, Param] | None) -> str | None:
    """The text --help or --version asks for (flags before --ros-args only), else None: the node should start."""
    argv = sys.argv[1:] if args is None else list(args)
    own = own_arguments(argv)
    if not any(a in HELP_FLAGS or a == VERSION_FLAG for a in own):
        return None
    module = getattr(factory, '__module__', None) or __name__
    package, prog = module.split('.')[0], module.rsplit('.', 1)[-1]
    if any(a in HELP_FLAGS for a in own):
        doc = (getattr(sys.modules.get(module), '__doc__', None) or '').strip()
        return node_help(prog, doc.splitlines()[0] if doc else '', params)
    return version_text(prog, package)
