"""Build an argparse parser from a dataclass (documented fields -> --flags) and back, with checked values.

The value rules are the project's one settings mechanism (``assist_common.settings``): a field
declared with ``setting(default, ge=..., choices=...)`` carries its rule, ``check_settings`` checks
types (an int is an int, a float is finite, ...), rules and the class's ``check_relations()``.
``parse_dataclass_args`` parses, checks and exits with status 2 and one ``error:`` line (argparse's
``error``) before the command does any work. Float flags refuse nan and inf while parsing.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import typing
from typing import Any

from assist_common.settings import (Rule, SettingsError, check_settings, exit_error, flag,  # noqa: F401
                                    parse_bool, setting)

_UNSET = object()     # marks a flag the command line did not give


def finite_float(text: str) -> float:
    """argparse type: a finite float (nan and inf are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'not a number: {text!r}') from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f'not a finite number: {text!r}')
    return value


def add_dataclass_args(parser: argparse.ArgumentParser, cls: type, help_text: dict[str, str]) -> None:
    """Add one --flag per field of dataclass `cls` (defaults from the class, help from `help_text`)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        hint = hints[f.name]
        doc = help_text.get(f.name, '') + f' (default: {default})'
        origin = typing.get_origin(hint)
        if hint is bool or hint == (bool | None):       # an optional bool: left unset, None
            parser.add_argument(flag(f.name), type=parse_bool, default=default, help=doc)
        elif origin in (tuple, list):
            inner = typing.get_args(hint)[0]
            parser.add_argument(flag(f.name), type=finite_float if inner is float else inner, nargs='*',
                                default=default, help=doc)
        else:
            parser.add_argument(flag(f.name), type=finite_float if hint is float else hint, default=default,
                                help=doc)


def dataclass_from_args(cls: type, ns: argparse.Namespace) -> Any:
    """Instantiate `cls` from parsed args (tuple fields converted back to tuples)."""
    kwargs = {}
    for f in dataclasses.fields(cls):
        value = getattr(ns, f.name)
        kwargs[f.name] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)


def parse_dataclass_args(parser: argparse.ArgumentParser, cls: type,
                         argv: list[str] | None = None) -> tuple[Any, frozenset[str]]:
    """(checked `cls` instance, names of the fields given on the command line) from `argv`.

    `parser` must hold `add_dataclass_args(parser, cls, ...)`. A value that breaks its field's type or
    rule (``check_settings``) ends the program like a malformed flag: one `error:` line, status 2.
    """
    names = [f.name for f in dataclasses.fields(cls)]
    ns = parser.parse_args(argv, namespace=argparse.Namespace(**{n: _UNSET for n in names}))
    given = frozenset(n for n in names if getattr(ns, n) is not _UNSET)
    for f in dataclasses.fields(cls):
        if getattr(ns, f.name) is _UNSET:
            setattr(ns, f.name, f.default if f.default is not dataclasses.MISSING else f.default_factory())
    obj = dataclass_from_args(cls, ns)
    try:
        check_settings(obj)
    except SettingsError as exc:
        parser.error(str(exc))
    return obj, given
