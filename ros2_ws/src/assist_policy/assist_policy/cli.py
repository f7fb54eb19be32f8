"""Build an argparse parser from a dataclass (documented fields -> --flags) and back."""
from __future__ import annotations

import argparse
import dataclasses
import typing
from typing import Any


def _parse_bool(text: str) -> bool:
    if text.lower() in ('1', 'true', 'yes', 'on'):
        return True
    if text.lower() in ('0', 'false', 'no', 'off'):
        return False
    raise argparse.ArgumentTypeError(f'not a boolean: {text}')


def add_dataclass_args(parser: argparse.ArgumentParser, cls: type, help_text: dict[str, str]) -> None:
    """Add one --flag per field of dataclass `cls` (defaults from the class, help from `help_text`)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        hint = hints[f.name]
        flag = '--' + f.name.replace('_', '-')
        doc = help_text.get(f.name, '') + f' (default: {default})'
        origin = typing.get_origin(hint)
        if hint is bool or hint == (bool | None):       # an optional bool: left unset, None
            parser.add_argument(flag, type=_parse_bool, default=default, help=doc)
        elif origin in (tuple, list):
            inner = typing.get_args(hint)[0]
            parser.add_argument(flag, type=inner, nargs='*', default=default, help=doc)
        else:
            parser.add_argument(flag, type=hint, default=default, help=doc)


def dataclass_from_args(cls: type, ns: argparse.Namespace) -> Any:
    """Instantiate `cls` from parsed args (tuple fields converted back to tuples)."""
    kwargs = {}
    for f in dataclasses.fields(cls):
        value = getattr(ns, f.name)
        kwargs[f.name] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)
