"""pilot_station's intent-cue inputs as an rclpy node in this process (timers not spun): each unusable message on
/assist/goal_estimate and /cmd_vel is counted by reason, and the view state carries the cues only while the
assistant is live and the cue's parameter is on."""
import math
import random

import pytest
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped, TwistStamped
from rclpy.context import Context
from rclpy.parameter import Parameter
from std_msgs.msg import Bool
from visualization_msgs.msg import Marker, MarkerArray

from assist_common.ros_common import sec_to_stamp
from assist_station.pilot_station import PilotStation


@pytest.fixture
def station():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=random.randint(80, 89))
    node = PilotStation(context=ctx, parameter_overrides=[Parameter('port', value=0)])
    try:
        yield node
    finally:
        node.close()
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def callback(node, topic):
    """The callback rclpy calls for a message on `topic` (the node's own subscription)."""
    return next(s.callback for s in node.subscriptions if s.topic_name == topic)


def stamped(node, msg, frame, offset_s=0.0):
    msg.header.frame_id = frame
    sec_to_stamp(node.get_clock().now().nanoseconds * 1e-9 + offset_s, msg.header.stamp)
    return msg


def estimate(node, p, var=0.01, frame='odom', offset_s=0.0):
    g = PoseWithCovarianceStamped()
    g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z = p
    g.pose.pose.orientation.w = 1.0
    cov = [0.0] * 36
    cov[0] = cov[7] = cov[14] = var
    cov[21] = cov[28] = cov[35] = 1e6
    g.pose.covariance = cov
    return stamped(node, g, frame, offset_s)


def twist(node, v, frame='base_link', offset_s=0.0):
    t = TwistStamped()
    t.twist.linear.x, t.twist.linear.y, t.twist.linear.z = v
    return stamped(node, t, frame, offset_s)


def scene():
    m = Marker(ns='platforms', id=0, type=Marker.CUBE, action=Marker.ADD)
    m.pose.position.x, m.pose.position.y, m.pose.position.z = 4.0, 1.0, 0.5
    m.pose.orientation.w = 1.0
    m.scale.x, m.scale.y, m.scale.z = 1.0, 1.0, 1.0
    return MarkerArray(markers=[m])


def test_unusable_intent_messages_are_counted_by_reason(station):
    callback(station, '/sim/scene')(scene())
    on_goal, on_cmd = callback(station, '/assist/goal_estimate'), callback(station, '/cmd_vel')
    on_goal(estimate(station, (4.0, 1.0, 1.0)))                           # on pad 0's top: fine
    on_goal(estimate(station, (math.nan, 1.0, 1.0)))
    on_goal(estimate(station, (4.0, 1.0, 1.0), frame='map'))
    on_goal(estimate(station, (4.0, 1.0, 1.0), var=-0.1))
    on_goal(estimate(station, (4.0, 1.0, 1.0), offset_s=-3.0))
    on_goal(estimate(station, (4.0, 1.0, 1.0), offset_s=3.0))
    on_goal(estimate(station, (0.0, 0.0, 1.0)))
    on_cmd(twist(station, (1.0, 0.0, 0.0), frame='odom'))
    on_cmd(twist(station, (math.inf, 0.0, 0.0)))
    for kind in ('nonfinite', 'frame', 'variance', 'stale_stamp', 'future_stamp', 'unknown_pad'):
        assert station.diag.get(f'goal_estimate_rejected_{kind}') == 1, kind
    assert station.diag.get('cmd_vel_rejected_frame') == 1 and station.diag.get('cmd_vel_rejected_nonfinite') == 1
    assert station.diag.get('goal_estimate_errors') == 0 and station.diag.get('cmd_vel_errors') == 0


def test_the_view_state_carries_cues_only_while_assisted_and_switched_on(station):
    callback(station, '/sim/scene')(scene())
    callback(station, '/assist/goal_estimate')(estimate(station, (4.1, 0.9, 1.0)))
    callback(station, '/assist/descent_ok')(Bool(data=False))
    callback(station, '/cmd_vel')(twist(station, (0.0, 0.4, 0.0)))      # the station published no u yet: u = 0
    assert station._state()['cues'] == {'goal': None, 'descent': None, 'push': None}     # no agent_cmd yet
    callback(station, '/assist/agent_cmd')(twist(station, (0.1, 0.0, 0.0)))
    cues = station._state()['cues']
    assert cues['goal']['pad'] == 0 and cues['goal']['state'] == 'sure' and cues['goal']['p'] == [4.1, 0.9, 1.0]
    assert cues['descent'] == 'hold' and cues['push'] == [0.0, 0.4, 0.0]
    station._publish([0.0, 0.4, 0.0])                                     # the pilot's own u: no push left
    assert station._state()['cues']['push'] is None
    results = station.set_parameters([Parameter('cue_goal', value=False), Parameter('cue_descent', value=False)])
    assert all(r.successful for r in results)
    cues = station._state()['cues']
    assert cues['goal'] is None and cues['descent'] is None
    refused = station.set_parameters([Parameter('cue_push', value=3)])
    assert not refused[0].successful and station.p['cue_push'] is True
