"""Keyboard teleop: the assistant's intent line (core validation and wording), and the real node showing it under its
status line in a tmux terminal while the test publishes /odom, /assist/goal_estimate and /assist/descent_ok."""
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from assist_bridge.teleop_core import IntentConfig, IntentError, IntentLine, check_goal_estimate
from assist_common.domains import private_domain_id
from assist_common.settings import SettingsError

BIN = Path(sys.executable).parent
LEVEL = (0.0, 0.0, 0.0, 1.0)
NORTH = (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4))      # heading +90 deg: body forward = odom +y


def cov(var=0.01):
    c = [0.0] * 36
    c[0] = c[7] = c[14] = var
    c[21] = c[28] = c[35] = 1e6
    return c


# ---------------------------------------------------------------------- core
def test_the_goal_pad_is_placed_in_body_terms():
    line = IntentLine(IntentConfig(timeout_s=0.5))
    assert line.note_odom((1.0, 2.0, 3.0), NORTH, 10.0)
    line.note_goal('odom', 10.0, (0.6, 4.3, 1.1), LEVEL, cov(), 10.0)   # 2.3 m along +y (ahead), 0.4 m along -x
    line.note_descent(True, 10.0)
    assert line.line(10.1) == 'goal pad 2.3 m ahead, 0.4 m left, 1.9 m below   descend: ok'
    assert line.note_odom((1.0, 2.0, 0.5), LEVEL, 10.2)                  # heading 0: +y is left, -x behind
    assert line.goal_text(10.2) == 'goal pad 0.4 m behind, 2.3 m left, 0.6 m above'


def test_a_large_sigma_reads_unsure():
    line = IntentLine(IntentConfig(max_sigma_m=0.5))
    line.note_odom((0.0, 0.0, 3.0), LEVEL, 1.0)
    line.note_goal('', 1.0, (2.0, -1.0, 1.0), LEVEL, cov(0.2), 1.0)        # sigma 0.45
    assert line.goal_text(1.0) == 'goal pad 2.0 m ahead, 1.0 m right, 2.0 m below'
    line.note_goal('', 1.0, (2.0, -1.0, 1.0), LEVEL, cov(0.3), 1.0)        # sigma 0.55
    assert line.goal_text(1.0) == 'goal pad 2.0 m ahead, 1.0 m right, 2.0 m below (unsure)'


def test_the_descent_word_follows_its_arrival_and_the_line_empties_without_intent():
    line = IntentLine(IntentConfig(timeout_s=0.5))
    assert line.line(0.0) == ''                                             # nothing arrived: nothing about intent
    line.note_descent(False, 5.0)
    assert line.line(5.3) == 'goal pad ?   descend: hold'
    line.note_odom((0.0, 0.0, 3.0), LEVEL, 5.4)
    line.note_goal('odom', 5.4, (1.0, 0.0, 1.0), LEVEL, cov(), 5.4)
    assert line.line(5.6) == 'goal pad 1.0 m ahead, 0.0 m left, 2.0 m below   descend: ?'   # descent_ok 0.6 s old
    assert line.line(6.0) == ''                                             # the estimate is 0.6 s old too
    line.note_descent(True, 6.0)
    assert line.line(6.0) == 'goal pad ?   descend: ok'


def test_a_rejected_estimate_reads_as_unknown_and_odometry_is_needed():
    line = IntentLine()
    line.note_goal('odom', 1.0, (1.0, 0.0, 1.0), LEVEL, cov(), 1.0)
    assert line.goal_text(1.0) == 'goal pad ? (no /odom)'
    assert not line.note_odom((math.nan, 0.0, 3.0), LEVEL, 1.0)
    assert not line.note_odom((0.0, 0.0, 3.0), (0.0, 0.0, 0.0, 0.0), 1.0)
    assert line.note_odom((0.0, 0.0, 3.0), LEVEL, 1.0)
    assert line.goal_text(1.0).startswith('goal pad 1.0 m ahead')
    with pytest.raises(IntentError):
        line.note_goal('odom', 1.0, (math.nan, 0.0, 1.0), LEVEL, cov(), 1.0)
    assert line.goal_text(1.0) == 'goal pad ?'
    line.note_goal('odom', 1.1, (1.0, 0.0, 1.0), LEVEL, cov(), 1.1)
    assert line.goal_text(1.1).startswith('goal pad 1.0 m ahead')


@pytest.mark.parametrize('args, kind', [
    ({'position': (0.0, math.inf, 0.0)}, 'nonfinite'),
    ({'orientation': (math.nan, 0.0, 0.0, 1.0)}, 'nonfinite'),
    ({'covariance': cov(math.nan)}, 'nonfinite'),
    ({'covariance': cov(-0.5)}, 'variance'),
    ({'frame_id': 'base_link'}, 'frame'),
    ({'stamp_s': 10.5}, 'future_stamp'),
    ({'stamp_s': 9.0}, 'stale_stamp'),
    ({'covariance': [0.0] * 6}, 'shape'),
])
def test_check_goal_estimate_rejects_by_kind(args, kind):
    call = dict(frame_id='odom', stamp_s=10.0, position=(1.0, 2.0, 0.5), orientation=LEVEL, covariance=cov(),
                now_s=10.0, max_age_s=0.5, tolerance_s=0.25)
    p, sigma, t = check_goal_estimate(**call)
    assert list(p) == [1.0, 2.0, 0.5] and sigma == pytest.approx(0.1) and t == 10.0
    with pytest.raises(IntentError) as err:
        check_goal_estimate(**dict(call, **args))
    assert err.value.kind == kind


def test_the_line_is_cut_to_the_terminal():
    line = IntentLine()
    line.note_descent(True, 0.0)
    assert line.line(0.0, width=12) == 'goal pad ? '
    with pytest.raises(SettingsError):
        IntentConfig(timeout_s=0.0)


# ---------------------------------------------------------------------- the node under tmux
@pytest.fixture
def teleop_with_intent(tmp_path):
    """teleop_keyboard in a real tmux terminal; the test's node publishes the assistant's intent at 20 Hz."""
    if shutil.which('tmux') is None:
        pytest.skip('tmux not installed')
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.node import Node
    from std_msgs.msg import Bool

    from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS, sec_to_stamp

    domain = private_domain_id()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('teleop_intent_probe', context=ctx)
    pub_odom = node.create_publisher(Odometry, '/odom', SENSOR_QOS)
    pub_goal = node.create_publisher(PoseWithCovarianceStamped, '/assist/goal_estimate', RELIABLE_QOS)
    pub_descent = node.create_publisher(Bool, '/assist/descent_ok', RELIABLE_QOS)
    state = {'on': True, 'descent': True}
    stop = threading.Event()

    def feed():
        while not stop.is_set():
            now = node.get_clock().now().nanoseconds * 1e-9
            od = Odometry()
            od.pose.pose.position.z, od.pose.pose.orientation.w = 3.0, 1.0
            pub_odom.publish(od)
            if state['on']:
                g = PoseWithCovarianceStamped()
                g.header.frame_id = 'odom'
                sec_to_stamp(now, g.header.stamp)
                g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z = 2.3, 0.4, 1.1
                g.pose.pose.orientation.w = 1.0
                g.pose.covariance = cov()
                pub_goal.publish(g)
                pub_descent.publish(Bool(data=state['descent']))
            time.sleep(0.05)
    thread = threading.Thread(target=feed, daemon=True)
    thread.start()
    sock = f'teleop-intent-{os.getpid()}-{time.monotonic_ns()}'
    cmd = f'{BIN / "teleop_keyboard"}; sleep 60'
    subprocess.run(['tmux', '-L', sock, 'new-session', '-d', '-s', 'teleop', '-x', '80', '-y', '20',
                    f'env ROS_DOMAIN_ID={domain} bash -c "{cmd}"'], check=True)

    def screen() -> str:
        return subprocess.run(['tmux', '-L', sock, 'capture-pane', '-p', '-t', 'teleop'], capture_output=True,
                              text=True).stdout

    def wait(pred, timeout=30.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if pred(screen()):
                return True
            time.sleep(0.05)
        return False
    try:
        yield state, screen, wait
    finally:
        subprocess.run(['tmux', '-L', sock, 'kill-server'], check=False)
        stop.set()
        thread.join(5)
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_teleop_shows_the_intent_under_its_status_line(teleop_with_intent):
    state, screen, wait = teleop_with_intent
    goal = 'goal pad 2.3 m ahead, 0.4 m left, 1.9 m below'
    assert wait(lambda s: f'{goal}   descend: ok' in s), screen()
    rows = screen().splitlines()
    status = [i for i, ln in enumerate(rows) if 'vx ' in ln]
    assert len(status) == 1 and len(rows[status[0]].rstrip()) < 80, screen()      # one status row, not wrapped
    assert rows[status[0] + 1].startswith(goal), screen()                        # the intent right under it
    state['descent'] = False
    assert wait(lambda s: f'{goal}   descend: hold' in s), screen()
    state['on'] = False                                                           # the assistant goes quiet
    assert wait(lambda s: 'goal pad' not in s and 'descend:' not in s and 'vx ' in s), screen()
