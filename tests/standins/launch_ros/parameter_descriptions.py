"""launch_ros.parameter_descriptions stand-in: ParameterValue, ParameterFile."""
from __future__ import annotations

import yaml
from launch._impl import Substitution, normalize_to_list_of_substitutions, perform_substitutions


class ParameterValue:
    """A parameter value from substitutions: `value_type` str keeps the text, else it is read as YAML."""

    def __init__(self, value, *, value_type=None) -> None:
        self.value = value
        self.value_type = value_type

    def evaluate(self, context):
        """The typed value."""
        if isinstance(self.value, (bool, int, float)) and not isinstance(self.value, str):
            return self.value
        text = perform_substitutions(context, normalize_to_list_of_substitutions(self.value))
        if self.value_type is str:
            return text
        value = yaml.safe_load(text) if text else ''
        if self.value_type is not None and not isinstance(value, self.value_type):
            raise TypeError(f'parameter value {text!r} is not of type {self.value_type.__name__}')
        return value


class ParameterFile:
    """A parameter file path (substitutions allowed)."""

    def __init__(self, param_file, *, allow_substs: bool = False) -> None:
        self.param_file = normalize_to_list_of_substitutions(param_file) \
            if isinstance(param_file, (str, Substitution, list, tuple)) else [str(param_file)]

    def evaluate(self, context) -> str:
        """The path."""
        return perform_substitutions(context, self.param_file)
