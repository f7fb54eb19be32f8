"""launch_ros.actions stand-in: Node (an ExecuteProcess of <prefix>/lib/<package>/<executable>)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import yaml
from ament_index_python.packages import get_package_prefix
from launch._impl import ExecuteProcess, Substitution, normalize_to_list_of_substitutions, perform_substitutions

from .parameter_descriptions import ParameterFile, ParameterValue


def _evaluate_value(context, name, value):
    """launch_ros rules: substitution values are read as YAML ('' stays ''), plain values kept."""
    if isinstance(value, ParameterValue):
        return value.evaluate(context)
    if isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, str):
        return value
    if isinstance(value, Substitution) or (isinstance(value, (list, tuple)) and value
                                           and any(isinstance(v, Substitution) for v in value)):
        text = perform_substitutions(context, normalize_to_list_of_substitutions(value))
        out = yaml.safe_load(text if text else "''")
        if not isinstance(out, (bool, int, float, str, bytes, list)):
            raise TypeError(f'Allowed value types are bytes, bool, int, float, str, Sequence[...]. '
                            f'Got {type(out)} for "{name}"')
        return out
    if isinstance(value, (list, tuple)):
        return list(value)
    raise TypeError(f'Unexpected type for parameter value {value!r}')


def _flatten(params: dict, prefix: str = '') -> dict:
    out = {}
    for k, v in params.items():
        key = f'{prefix}.{k}' if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten(v, key))
        else:
            out[key] = v
    return out


class Node(ExecuteProcess):
    """A ROS 2 node from an installed package; parameters, remappings and name go on its --ros-args."""

    def __init__(self, *, executable, package=None, name=None, namespace=None, exec_name=None,
                 parameters=None, remappings=None, ros_arguments=None, arguments=None, **kwargs) -> None:
        self.package, self.executable = package, executable
        self.node_name, self.namespace = name, namespace
        self.parameters = list(parameters or [])
        self.remappings = list(remappings or [])
        self.ros_arguments = list(ros_arguments or [])
        self.arguments = list(arguments or [])
        super().__init__(cmd=[], name=exec_name, **kwargs)

    def _prepare(self, context) -> list[str]:
        exe = perform_substitutions(context, normalize_to_list_of_substitutions(self.executable))
        if self.package is not None:
            pkg = perform_substitutions(context, normalize_to_list_of_substitutions(self.package))
            libexec = Path(get_package_prefix(pkg)) / 'lib' / pkg
            path = libexec / exe
            if not (path.is_file() and os.access(path, os.X_OK)):
                raise RuntimeError(f"executable '{exe}' not found on the libexec directory '{libexec}'")
            exe = str(path)
        cmd = [exe] + [perform_substitutions(context, normalize_to_list_of_substitutions(a))
                       for a in self.arguments]
        if self.ros_arguments:
            cmd += ['--ros-args'] + [perform_substitutions(context, normalize_to_list_of_substitutions(a))
                                     for a in self.ros_arguments]
        cmd += ['--ros-args']
        name = None
        if self.node_name is not None:
            name = perform_substitutions(context, normalize_to_list_of_substitutions(self.node_name))
            cmd += ['-r', f'__node:={name}']
        if self.namespace is not None:
            ns = perform_substitutions(context, normalize_to_list_of_substitutions(self.namespace))
            cmd += ['-r', f'__ns:={ns if ns.startswith("/") else "/" + ns}']
        for p in self.parameters:
            if isinstance(p, dict):
                values = {k: _evaluate_value(context, k, v) for k, v in _flatten(p).items()}
                with tempfile.NamedTemporaryFile('w', prefix='launch_params_', suffix='.yaml',
                                                 delete=False) as fh:
                    yaml.safe_dump({'/**': {'ros__parameters': values}}, fh, default_flow_style=False)
                cmd += ['--params-file', fh.name]
            else:
                path = p.evaluate(context) if isinstance(p, ParameterFile) else \
                    perform_substitutions(context, normalize_to_list_of_substitutions(p))
                if not os.path.isfile(path):
                    print(f'[WARNING] [launch_ros.actions.node]: Parameter file path is not a file: {path}',
                          flush=True)
                    continue
                cmd += ['--params-file', path]
        for src, dst in self.remappings:
            cmd += ['-r', perform_substitutions(context, normalize_to_list_of_substitutions(src)) + ':=' +
                    perform_substitutions(context, normalize_to_list_of_substitutions(dst))]
        return cmd
