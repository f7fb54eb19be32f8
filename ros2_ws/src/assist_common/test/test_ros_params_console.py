"""run_node's --help and --version: answered from the parameter table, without rclpy.init or the node."""
from __future__ import annotations

import rclpy

from assist_common import ros_params
from assist_common.ros_params import Param, node_help, parameter_help
from assist_common.ros_run import run_node

PARAMS = {
    'rate_hz': Param(20.0, 'Loop rate.', min=0.0, max=100.0, min_exclusive=True, dynamic=True),
    'mode': Param('a', 'Mode.', choices=('a', 'b')),
    'topics': Param([], 'Topics.', item_type=str),
    'on': Param(True, 'Switch.'),
}


def _never_built():
    raise AssertionError('the node must not be built for --help or --version')


def test_help_and_version_never_start_rclpy(monkeypatch, capsys):
    def no_init(*args, **kwargs):
        raise AssertionError('rclpy.init must not run for --help or --version')
    monkeypatch.setattr(rclpy, 'init', no_init)
    assert run_node(_never_built, ['--help'], params=PARAMS) == 0
    text = capsys.readouterr().out
    assert text.startswith('usage: test_ros_params_console [-h] [--version]')
    assert '  rate_hz (double; default 20.0; > 0.0 and <= 100.0; run-time)\n      Loop rate.' in text
    assert "  mode (string; default 'a'; one of a, b; read-only)" in text
    assert '  topics (string[]; default []; read-only)' in text
    assert '  on (bool; default True; read-only)' in text
    assert run_node(_never_built, ['-h', '--ros-args', '-p', 'x:=1'], params=PARAMS) == 0
    assert capsys.readouterr().out == text
    assert run_node(_never_built, ['--version']) == 0
    assert capsys.readouterr().out.startswith('test_ros_params_console (')   # package: the test module's top level


def test_package_version_of_an_installed_package():
    assert ros_params.package_version('assist_common') == '0.1.0'
    assert ros_params.package_version('no_such_package_here') == 'unknown'


def test_help_without_a_table_still_answers():
    assert 'parameters: see `ros2 param describe`' in node_help('x', '', None)
    assert parameter_help({}) == ''
