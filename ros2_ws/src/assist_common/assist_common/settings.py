"""Command lines from settings dataclasses: every field is a --flag, `--config file.yaml` sets many.

Precedence: dataclass default < YAML file (`--config`) < explicit --flags.

One builder for every command line of the project: `add_dataclass_args` turns each field into a --flag
(defaults from the class, help from a table), `parse_dataclass_args` parses and checks; `parse_settings`
adds `--config file.yaml` on top of the same two.

Settings rules: a field declared with `setting(default, ge=..., choices=..., ...)` carries a `Rule` in its
metadata, and `check_settings` checks every field of a settings object against its type (an int
is an int, a float is a finite number, a string holds no NUL, a tuple holds items of its type)
and its Rule, then the object's own `check_relations()` (rules between fields) if it has one. The
command lines run it before doing any work: a bad value is one `error:` line and exit status 2, as
argparse reports a malformed flag.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import logging
import math
import sys
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

_T = TypeVar('_T')
RULE_KEY = 'settings_rule'


class SettingsError(ValueError):
    """A settings value breaks its field's type or rule; the message is one line naming the --flag."""


@dataclass(frozen=True)
class Rule:
    """Allowed values of one settings field (numbers: bounds; strings: choices, non-empty, a file name)."""

    ge: float | None = None          # value (or each tuple item) >= ge
    gt: float | None = None          # ... > gt
    le: float | None = None          # ... <= le
    lt: float | None = None          # ... < lt
    choices: tuple[Any, ...] = ()    # value (or each tuple item) is one of these
    min_len: int = 0                 # tuple fields: number of items
    max_len: int | None = None
    nonempty: bool = False           # strings: not ''
    max_chars: int | None = None     # strings: at most this many characters
    file_name: bool = False          # strings: one path component (no '/', not '.' or '..')

    def problem(self, value: Any) -> str | None:
        """Why one scalar value breaks this rule (None when it follows it)."""
        if self.choices and value not in self.choices:
            return 'must be one of ' + ', '.join(str(c) for c in self.choices)
        if isinstance(value, str):
            if (self.nonempty or self.file_name) and not value.strip():
                return 'must not be empty'
            if self.max_chars is not None and len(value) > self.max_chars:
                return f'must be at most {self.max_chars} characters'
            if self.file_name and ('/' in value or '\\' in value or value in ('.', '..')):
                return "must be a plain name (no '/', not '.' or '..')"
            return None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            bounds = (('ge', '>=', lambda b: value >= b), ('gt', '>', lambda b: value > b),
                      ('le', '<=', lambda b: value <= b), ('lt', '<', lambda b: value < b))
            for attr, word, ok in bounds:
                bound = getattr(self, attr)
                if bound is not None and not ok(bound):
                    return f'must be {word} {bound:g}'
        return None


def setting(default: Any, **rule: Any) -> Any:
    """A dataclass field with `default` whose values must follow `Rule(**rule)` (see `check_settings`)."""
    return dataclasses.field(default=default, metadata={RULE_KEY: Rule(**rule)})


def flag(name: str) -> str:
    """The --flag of a settings field name."""
    return '--' + name.replace('_', '-')


def _type_problem(hint: Any, value: Any) -> str | None:
    """Why `value` is not of type `hint` (int, float, str, bool, optional bool, tuples of those)."""
    if hint is bool:
        return None if isinstance(value, bool) else 'must be true or false'
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else 'must be an integer'
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return 'must be a number'
        return None if math.isfinite(value) else 'must be a finite number'
    if hint is str:
        if not isinstance(value, str):
            return 'must be a string'
        return 'must not contain a NUL character' if '\0' in value else None
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _type_problem(inner[0], value) if len(inner) == 1 else None
    if origin in (tuple, list):
        if not isinstance(value, (tuple, list)):
            return 'must be a list of values'
        item_types = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(item_types) != len(value):
            return f'must hold {len(item_types)} values'
        for item, item_hint in zip(value, item_types):
            why = _type_problem(item_hint, item)
            if why:
                return f'items {why}'
    return None


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + '...'


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """typing.get_type_hints of a settings class, once per class (it compiles every string annotation anew, and
    some settings objects are made per camera frame)."""
    return typing.get_type_hints(cls)


def check_settings(obj: Any) -> None:
    """SettingsError (one line, naming the --flag) unless every field of dataclass `obj` fits its type and Rule.

    Then runs `obj.check_relations()` when the class defines it (rules between fields; it raises
    SettingsError itself).
    """
    cls = type(obj)
    hints = _type_hints(cls)
    for f in dataclasses.fields(cls):
        value = getattr(obj, f.name)
        why = _type_problem(hints.get(f.name, Any), value)
        rule: Rule | None = f.metadata.get(RULE_KEY)
        if why is None and rule is not None:
            if isinstance(value, (tuple, list)):
                if len(value) < rule.min_len:
                    why = f'needs at least {rule.min_len} value(s)'
                elif rule.max_len is not None and len(value) > rule.max_len:
                    why = f'takes at most {rule.max_len} value(s)'
                else:
                    why = next((f'items {w}' for w in map(rule.problem, value) if w), None)
            else:
                why = rule.problem(value)
        if why:
            raise SettingsError(f'{flag(f.name)} {why}, got {_shown(value)}')
    relations = getattr(obj, 'check_relations', None)
    if callable(relations):
        relations()


def check_named(obj: Any, section: str = '') -> None:
    """`check_settings` naming the field as code and config files do, not as a --flag: SettingsError
    `field why` (e.g. `max_speed_x_mps must be <= 20, got 99.0`), or `section.field why` for a settings object
    nested in a config file (`arducopter.accel_xy_mps2 must be <= 10, got 99.0`); a relation between
    fields (check_relations, naming its first field) likewise."""
    try:
        check_settings(obj)
    except ValueError as exc:       # SettingsError, or a relation between fields
        name, _, why = str(exc).partition(' ')
        name = name.removeprefix('--').replace('-', '_')
        raise SettingsError(f"{section + '.' if section else ''}{name} {why}") from None


def exit_error(prog: str, problem: BaseException | str, status: int) -> typing.NoReturn:
    """Write one `<prog>: error: ...` line to stderr and exit with `status` (2: bad arguments, 1: the run failed)."""
    text = str(problem).strip()
    line = text.splitlines()[0] if text else type(problem).__name__
    if isinstance(problem, OSError) and problem.filename is not None and str(problem.filename) not in line:
        line = f'{problem.filename}: {line}'
    sys.stderr.write(f'{prog}: error: {line}\n')
    raise SystemExit(status)


def parse_bool(text: str) -> bool:
    """argparse type: true/false, 1/0, yes/no, on/off (any case); anything else is refused, quoted."""
    low = text.strip().lower()
    if low in ('1', 'true', 'yes', 'on'):
        return True
    if low in ('0', 'false', 'no', 'off'):
        return False
    raise argparse.ArgumentTypeError(f'expected true/false, got {text!r}')


def finite_float(text: str) -> float:
    """argparse type: a finite float (nan and inf are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not a number: {text!r}') from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'not a finite number: {text!r}')
    return value


_UNSET = object()     # marks a flag the command line did not give


def _default(f: dataclasses.Field) -> Any:
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()


def add_dataclass_args(parser: argparse.ArgumentParser, cls: type, help_text: dict[str, str] | None = None) -> None:
    """Add one --flag per field of dataclass `cls` (defaults from the class, help from `help_text`).

    bool fields take true/false (alone: true); tuple and list fields take several values; floats refuse nan/inf.
    """
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        default = _default(f)
        hint = hints[f.name]
        doc = ((help_text or {}).get(f.name, '') + f' (default: {default})').strip()
        origin = typing.get_origin(hint)
        if hint is bool or hint == (bool | None):       # an optional bool: left unset, None
            parser.add_argument(flag(f.name), type=parse_bool, nargs='?', const=True, default=default, help=doc)
        elif origin in (tuple, list):
            inner = typing.get_args(hint)[0]
            parser.add_argument(flag(f.name), type=finite_float if inner is float else inner, nargs='*',
                                default=default, help=doc)
        else:
            if origin in (typing.Union, types.UnionType):      # X | None: the flag gives an X
                hint = next(a for a in typing.get_args(hint) if a is not type(None))
            parser.add_argument(flag(f.name), type=finite_float if hint is float else hint, default=default,
                                help=doc)


def _parse_values(parser: argparse.ArgumentParser, cls: type, argv: list[str] | None,
                  base: dict[str, Any] | None = None) -> tuple[Any, frozenset[str], argparse.Namespace]:
    names = [f.name for f in dataclasses.fields(cls)]
    ns = parser.parse_args(argv, namespace=argparse.Namespace(**{n: _UNSET for n in names}))
    given = frozenset(n for n in names if getattr(ns, n) is not _UNSET)
    values = dict(base or {})
    for f in dataclasses.fields(cls):
        v = getattr(ns, f.name)
        if v is not _UNSET:
            values[f.name] = tuple(v) if isinstance(v, list) else v
        elif f.name not in values:
            values[f.name] = _default(f)
        setattr(ns, f.name, values[f.name])
    obj = cls(**values)
    try:
        check_settings(obj)
    except SettingsError as exc:
        parser.error(str(exc))
    return obj, given, ns


def parse_dataclass_args(parser: argparse.ArgumentParser, cls: type,
                         argv: list[str] | None = None) -> tuple[Any, frozenset[str]]:
    """(checked `cls` instance, names of the fields given on the command line) from `argv`.

    `parser` must hold `add_dataclass_args(parser, cls, ...)`. A value that breaks its field's type or
    rule (``check_settings``) ends the program like a malformed flag: one `error:` line, status 2.
    """
    obj, given, _ = _parse_values(parser, cls, argv)
    return obj, given


def load_yaml_settings(cls: type[_T], path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping of `cls` fields; unknown keys raise ValueError."""
    with open(path, encoding='utf-8') as fh:
        data = yaml.safe_load(fh) or {}
    if not isinstance(data, dict):
        raise ValueError(f'{path}: expected a mapping of {cls.__name__} fields')
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f'{path}: unknown {cls.__name__} setting(s) {sorted(map(str, unknown))}')
    return data


LOG_FORMAT = '%(asctime)s %(levelname)s %(name)s: %(message)s'


@dataclass(frozen=True)
class CommandLine:
    """A parsed command line: the checked settings, the fields given as flags, argparse's namespace (positional
    arguments too) and the parser (its `error` reports a bad combination found later)."""

    settings: Any
    given: frozenset[str]
    namespace: argparse.Namespace
    parser: argparse.ArgumentParser


def parse_command(cls: type, prog: str, description: str | None, help_text: dict[str, str] | None = None,
                  argv: list[str] | None = None, positional: dict[str, dict] | None = None,
                  log_level: int = logging.INFO) -> CommandLine:
    """The prologue of a command's main(): logging to stderr, a parser with one --flag per field of `cls`
    (plus `positional` arguments), parsed and checked (a bad value: one `error:` line, exit 2)."""
    logging.basicConfig(level=log_level, format=LOG_FORMAT)
    parser = argparse.ArgumentParser(prog=prog, description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, kw in (positional or {}).items():
        parser.add_argument(name, **kw)
    add_dataclass_args(parser, cls, help_text)
    obj, given, ns = _parse_values(parser, cls, argv)
    return CommandLine(obj, given, ns, parser)


def parse_settings(cls: type[_T], description: str, argv: list[str] | None = None,
                   extra: dict[str, dict] | None = None, prog: str | None = None) -> tuple[_T, argparse.Namespace]:
    """Build `cls` from --config YAML and --flags, checked (`check_settings`); returns (settings, namespace).

    Precedence: the dataclass default < the YAML file < the flags given. A bad flag, an unreadable or wrong
    --config file or a value that breaks its rule exits with status 2 and one `error:` line (argparse's
    `error`) before the caller does any work.
    """
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument('--config', help=f'YAML file of {cls.__name__} fields')
    add_dataclass_args(ap, cls)
    for name, kw in (extra or {}).items():
        ap.add_argument(name, **kw)
    pre, _ = ap.parse_known_args(argv)
    values: dict[str, Any] = {}
    if pre.config:
        try:
            values = load_yaml_settings(cls, pre.config)
        except ValueError as exc:               # not a mapping, unknown settings (the message names the file)
            ap.error(f'--config: {exc}')
        except (OSError, yaml.YAMLError) as exc:
            reason = getattr(exc, 'strerror', None) or (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            ap.error(f'--config {pre.config}: {reason}')
        hints = typing.get_type_hints(cls)
        for name, v in values.items():
            if hints[name] is float and isinstance(v, str):
                try:                        # YAML 1.1 reads 1e-3 (no dot) as a string
                    values[name] = float(v)
                except ValueError:
                    pass                    # check_settings names it
    cfg, _, args = _parse_values(ap, cls, argv, values)
    return cfg, args
