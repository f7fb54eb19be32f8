"""Command lines from settings dataclasses: every field is a --flag, `--config file.yaml` sets many.

Precedence: dataclass default < YAML file (`--config`) < explicit --flags.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any, TypeVar

import yaml

_T = TypeVar('_T')
_TYPES = {'int': int, 'float': float, 'str': str, 'bool': bool}


def _bool(text: str) -> bool:
    low = text.strip().lower()
    if low in ('1', 'true', 'yes', 'on'):
        return True
    if low in ('0', 'false', 'no', 'off'):
        return False
    raise argparse.ArgumentTypeError(f'expected true/false, got {text!r}')


def load_yaml_settings(cls: type[_T], path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping of `cls` fields; unknown keys raise ValueError."""
    with open(path, encoding='utf-8') as fh:
        data = yaml.safe_load(fh) or {}
    if not isinstance(data, dict):
        raise ValueError(f'{path}: expected a mapping of {cls.__name__} fields')
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f'{path}: unknown {cls.__name__} setting(s) {sorted(unknown)}')
    return data


def parse_settings(cls: type[_T], description: str, argv: list[str] | None = None,
                   extra: dict[str, dict] | None = None) -> tuple[_T, argparse.Namespace]:
    """Build `cls` from --config YAML and --flags; returns (settings, namespace with `extra` flags)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument('--config', help=f'YAML file of {cls.__name__} fields')
    for f in dataclasses.fields(cls):
        typ = _TYPES[str(f.type)]
        flag = '--' + f.name.replace('_', '-')
        if typ is bool:
            ap.add_argument(flag, nargs='?', const=True, type=_bool, default=None,
                            help=f'(default {f.default})')
        else:
            ap.add_argument(flag, type=typ, default=None, help=f'(default {f.default})')
    for flag, kw in (extra or {}).items():
        ap.add_argument(flag, **kw)
    args = ap.parse_args(argv)
    values: dict[str, Any] = load_yaml_settings(cls, args.config) if args.config else {}
    for f in dataclasses.fields(cls):
        v = getattr(args, f.name)
        if v is not None:
            values[f.name] = v
    return cls(**values), args
