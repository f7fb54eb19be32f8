"""Param rules: integers for floats, range checks at start-up, run-time sets validated or refused."""
import math

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from assist_common.ros_params import Param, StartupError, declare_parameters

SPEC = {
    'rate_hz': Param(20.0, 'rate', min=0.0, min_exclusive=True, dynamic=True),
    'count': Param(1, 'count', min=0, max=10),
    'mode': Param('a', 'mode', choices=('a', 'b')),
    'fixed': Param(0.5, 'read-only float'),
}


def make(args):
    ctx = Context()
    rclpy.init(args=['--ros-args', *args], context=ctx)
    return ctx, Node('param_test', context=ctx)


def close(ctx, node):
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def test_integer_accepted_for_float_and_values_coerced():
    ctx, node = make(['-p', 'rate_hz:=2', '-p', 'count:=3'])
    try:
        values = declare_parameters(node, SPEC)
        assert values['rate_hz'] == 2.0 and isinstance(values['rate_hz'], float)
        assert values['count'] == 3
    finally:
        close(ctx, node)


@pytest.mark.parametrize('arg, words', [('rate_hz:=-1.0', "'rate_hz' must be > 0.0"),
                                        ('rate_hz:=.nan', "'rate_hz' must be finite"),
                                        ('count:=11', "'count' must be >= 0 and <= 10"),
                                        ('count:=1.5', "'count' must be an integer"),
                                        ('mode:=c', "'mode' must be one of a, b")])
def test_bad_startup_value_is_one_clear_line(arg, words):
    ctx, node = make(['-p', arg])
    try:
        with pytest.raises(StartupError) as err:
            declare_parameters(node, SPEC)
        assert words in str(err.value) and '\n' not in str(err.value)
    finally:
        close(ctx, node)


def test_runtime_set_validated_applied_or_refused():
    ctx, node = make([])
    try:
        seen = []
        values = declare_parameters(node, SPEC, on_change=seen.append)
        assert not node.set_parameters([Parameter('rate_hz', value=-1.0)])[0].successful
        assert not node.set_parameters([Parameter('rate_hz', value=math.nan)])[0].successful
        assert values['rate_hz'] == 20.0 and seen == []
        assert node.set_parameters([Parameter('rate_hz', value=5)])[0].successful
        assert values['rate_hz'] == 5.0 and seen == [{'rate_hz': 5.0}]
        res = node.set_parameters([Parameter('fixed', value=0.7)])[0]
        assert not res.successful and 'read-only' in res.reason and values['fixed'] == 0.5
    finally:
        close(ctx, node)


def test_on_change_can_refuse_and_values_roll_back():
    ctx, node = make([])
    try:
        def refuse(changed):
            raise ValueError('not now')
        values = declare_parameters(node, SPEC, on_change=refuse)
        res = node.set_parameters([Parameter('rate_hz', value=7.0)])[0]
        assert not res.successful and res.reason == 'not now' and values['rate_hz'] == 20.0
    finally:
        close(ctx, node)


def test_descriptor_states_the_rule_for_ros2_param_describe():
    ctx, node = make([])
    try:
        declare_parameters(node, SPEC)
        rate, mode, fixed = node.describe_parameters(['rate_hz', 'mode', 'fixed'])
        assert rate.description == 'rate Accepted: > 0.0.' and not rate.read_only
        assert mode.description == 'mode Accepted: one of a, b. Read-only.' and mode.read_only
        assert fixed.description == 'read-only float Read-only.'
    finally:
        close(ctx, node)


ARRAYS = {'seeds': Param((), 'seeds', min=0, max=10, item_type=int),
          'betas': Param((), 'betas', min=0.0, max=1.0, item_type=float),
          'names': Param((), 'names', choices=('paper', 'mix'), item_type=str)}


def test_array_parameters_typed_empty_by_default_and_every_item_checked():
    ctx, node = make([])
    try:
        assert declare_parameters(node, ARRAYS) == {'seeds': [], 'betas': [], 'names': []}
        assert node.describe_parameter('seeds').type == Parameter.Type.INTEGER_ARRAY.value
        assert node.describe_parameter('seeds').read_only
    finally:
        close(ctx, node)
    ctx, node = make(['-p', 'seeds:=[1, 2]', '-p', 'betas:=[0.0, 0.5]', '-p', 'names:=[paper, mix]'])
    try:
        assert declare_parameters(node, ARRAYS) == {'seeds': [1, 2], 'betas': [0.0, 0.5], 'names': ['paper', 'mix']}
    finally:
        close(ctx, node)
    for arg, words in (('seeds:=[1, 11]', "'seeds[1]' must be >= 0 and <= 10"),
                       ('names:=[paper, nobody]', "'names[1]' must be one of paper, mix"),
                       ('seeds:=[0.5]', 'INTEGER_ARRAY')):
        ctx, node = make(['-p', arg])
        try:
            with pytest.raises(StartupError, match=r'.*') as err:
                declare_parameters(node, ARRAYS)
            assert words in str(err.value), err.value
        finally:
            close(ctx, node)


def test_release_logging_stops_forwarding_to_a_destroyed_node():
    import logging

    import rclpy

    from assist_common.ros_io import forward_logging, release_logging
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = rclpy.create_node('logging_owner', context=ctx)
        handler = forward_logging(node)
        assert handler in logging.getLogger().handlers and handler._logger('a.b').name == 'logging_owner.a.b'
        node.destroy_node()
        release_logging()
        assert handler not in logging.getLogger().handlers and handler._logger('a.b').name == 'a.b'
    finally:
        rclpy.shutdown(context=ctx)
