"""launch.substitutions stand-in (PythonExpression deliberately absent: launch arguments are never code here)."""
from __future__ import annotations

import math
import os

from ._impl import (Substitution, SubstitutionFailure, TextSubstitution,  # noqa: F401
                    normalize_to_list_of_substitutions, perform_substitutions)


class LaunchConfiguration(Substitution):
    """The value of a launch configuration (a declared argument); `default` when unset, else an error."""

    def __init__(self, variable_name, *, default=None) -> None:
        self.variable_name = normalize_to_list_of_substitutions(variable_name)
        self.default = None if default is None else normalize_to_list_of_substitutions(
            str(default) if isinstance(default, (int, float)) else default)

    def perform(self, context) -> str:
        name = perform_substitutions(context, self.variable_name)
        if name in context.launch_configurations:
            return context.launch_configurations[name]
        if self.default is not None:
            return perform_substitutions(context, self.default)
        raise SubstitutionFailure(f"launch configuration '{name}' does not exist")


def _text(value) -> list[Substitution]:
    if value is None:
        value = ''
    elif isinstance(value, bool):
        value = str(value).lower()
    elif isinstance(value, (int, float)):
        value = str(value)
    return normalize_to_list_of_substitutions(value)


def _is_bool(s: str) -> bool:
    return s.lower() in ('true', 'false', '1', '0')


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


class EqualsSubstitution(Substitution):
    """'true' when both sides perform to equal text (booleans and numbers compared as such), else 'false'."""

    def __init__(self, left, right) -> None:
        self.left, self.right = _text(left), _text(right)

    def perform(self, context) -> str:
        left = perform_substitutions(context, self.left)
        right = perform_substitutions(context, self.right)
        if _is_bool(left) and _is_bool(right):
            return str((left.lower() in ('true', '1')) == (right.lower() in ('true', '1'))).lower()
        if _is_float(left) and _is_float(right):
            return str(math.isclose(float(left), float(right))).lower()
        return str(left == right).lower()


class NotEqualsSubstitution(EqualsSubstitution):
    """The negation of EqualsSubstitution."""

    def perform(self, context) -> str:
        return 'false' if super().perform(context) == 'true' else 'true'


class PathJoinSubstitution(Substitution):
    """os.path.join of the performed parts (each part one str or Substitution, as in Jazzy)."""

    def __init__(self, substitutions) -> None:
        self.parts = normalize_to_list_of_substitutions(substitutions)

    def perform(self, context) -> str:
        return os.path.join(*[context.perform_substitution(p) for p in self.parts])


class EnvironmentVariable(Substitution):
    """The value of an environment variable (`default_value` when unset)."""

    def __init__(self, name, *, default_value='') -> None:
        self.name = normalize_to_list_of_substitutions(name)
        self.default_value = normalize_to_list_of_substitutions(default_value)

    def perform(self, context) -> str:
        name = perform_substitutions(context, self.name)
        return os.environ.get(name, perform_substitutions(context, self.default_value))


def _as_bool(context, subs) -> bool:
    """perform_typed_substitution(..., bool): true/1 or false/0 (any case), else a SubstitutionFailure."""
    text = perform_substitutions(context, subs).strip().lower()
    if text in ('true', '1'):
        return True
    if text in ('false', '0'):
        return False
    raise SubstitutionFailure(f"'{text}' is not a boolean (true/false/1/0)")


class NotSubstitution(Substitution):
    """'true' when the value is false."""

    def __init__(self, value) -> None:
        self.value = normalize_to_list_of_substitutions(value)

    def perform(self, context) -> str:
        return str(not _as_bool(context, self.value)).lower()


class AndSubstitution(Substitution):
    """'true' when both sides are true (each must be a boolean)."""

    def __init__(self, left, right) -> None:
        self.left, self.right = normalize_to_list_of_substitutions(left), normalize_to_list_of_substitutions(right)

    def perform(self, context) -> str:
        left, right = _as_bool(context, self.left), _as_bool(context, self.right)
        return str(left and right).lower()


class OrSubstitution(AndSubstitution):
    """'true' when either side is true (each must be a boolean)."""

    def perform(self, context) -> str:
        left, right = _as_bool(context, self.left), _as_bool(context, self.right)
        return str(left or right).lower()
