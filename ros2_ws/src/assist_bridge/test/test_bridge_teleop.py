"""Keyboard teleop: core key logic, and the real node driven by tmux send-keys in a real terminal."""
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from assist_bridge.teleop_core import KeyDecoder, TeleopConfig, TeleopCore
from assist_common.domains import private_domain_id

BIN = Path(sys.executable).parent


# ---------------------------------------------------------------------- core
def test_decoder_tokens_including_split_escape_sequences():
    d = KeyDecoder()
    assert d.feed('wA \x1b[A\x1bOB\x03') == ['w', 'a', ' ', 'UP', 'DOWN', 'CTRL_C']
    assert d.feed('\x1b') == [] and d.feed('[') == [] and d.feed('B') == ['DOWN']
    assert d.feed('\x1bx') == ['ESC', 'x']


def test_keys_map_to_flu_velocity_and_newest_key_on_an_axis_wins():
    core = TeleopCore(TeleopConfig(speed=2.0, speed_z=0.5))
    core.press('w', 0.0)
    core.press('a', 0.0)
    core.press('UP', 0.0)
    np.testing.assert_allclose(core.velocity(0.1), [2.0, 2.0, 0.5])
    core.press('s', 0.2)
    core.press('d', 0.2)
    core.press('DOWN', 0.2)
    np.testing.assert_allclose(core.velocity(0.3), [-2.0, -2.0, -0.5])


def test_release_detected_from_auto_repeat_stopping():
    cfg = TeleopConfig(initial_hold_s=0.5, repeat_timeout_s=0.1)
    core = TeleopCore(cfg)
    core.press('w', 0.0)                 # first press: held through the auto-repeat delay
    assert core.velocity(0.45)[0] == 1.0
    t = 0.45
    for _ in range(20):                  # auto-repeat every 30 ms
        t += 0.03
        core.press('w', t)
        assert core.velocity(t + 0.02)[0] == 1.0
    assert core.velocity(t + 0.09)[0] == 1.0
    assert core.velocity(t + 0.11)[0] == 0.0     # repeats stopped: released
    single = TeleopCore(cfg)
    single.press('a', 0.0)               # a tap without repeats ends after initial_hold_s
    assert single.velocity(0.49)[1] == 1.0 and single.velocity(0.51)[1] == 0.0


def test_space_stops_and_q_quits():
    core = TeleopCore()
    core.press('w', 0.0)
    core.press(' ', 0.1)
    np.testing.assert_allclose(core.velocity(0.1), [0.0, 0.0, 0.0])
    assert not core.quit
    core.press('x', 0.2)                 # unbound keys do nothing
    np.testing.assert_allclose(core.velocity(0.2), [0.0, 0.0, 0.0])
    core.press('q', 0.3)
    assert core.quit


def test_status_line_fits_the_terminal_width():
    core = TeleopCore()
    core.press('w', 0.0)
    wide = core.status_line(0.1)
    assert wide.startswith('vx +1.00  vy +0.00  vz +0.00 m/s  keys [w]') and 'q quit' in wide
    assert core.status_line(0.1, width=200) == wide
    line = core.status_line(0.1, width=80)
    assert line == 'vx +1.00  vy +0.00  vz +0.00 m/s  keys [w]'      # help dropped first
    assert core.status_line(0.1, width=20) == line[:19]               # then cut, never wrapped


def test_bad_teleop_config():
    with pytest.raises(ValueError):
        TeleopConfig(rate_hz=0.0)


def test_refuses_clearly_without_a_tty():
    env = dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id()))
    r = subprocess.run([str(BIN / 'teleop_keyboard')], stdin=subprocess.DEVNULL, capture_output=True,
                       text=True, env=env, timeout=60)
    assert r.returncode == 1
    assert 'not a terminal' in r.stderr
    assert 'Traceback' not in r.stderr


# ---------------------------------------------------------------------- the node under tmux
@pytest.fixture
def teleop_tmux(tmp_path):
    """teleop_keyboard in a real tmux terminal + an rclpy subscriber on a private domain."""
    if shutil.which('tmux') is None:
        pytest.skip('tmux not installed')
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from assist_common.ros_io import RELIABLE_QOS

    domain = private_domain_id()
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('teleop_probe', context=ctx)
    got: list = []
    lock = threading.Lock()

    def on_msg(msg):
        with lock:
            got.append((msg.header.frame_id, msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z))
    node.create_subscription(TwistStamped, '/pilot/cmd_vel', on_msg, RELIABLE_QOS)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()

    sock = f'teleop-test-{os.getpid()}-{time.monotonic_ns()}'
    session = 'teleop'
    exit_file, stty_file = tmp_path / 'exit', tmp_path / 'stty'
    cmd = (f'{BIN / "teleop_keyboard"} --ros-args -p initial_hold_s:=30.0 -p repeat_timeout_s:=0.3 '
           f'-p speed:=1.0 -p speed_z:=0.5; echo $? > {exit_file}; stty -a > {stty_file}; sleep 60')
    env_cmd = f'env ROS_DOMAIN_ID={domain} bash -c "{cmd}"'
    subprocess.run(['tmux', '-L', sock, 'new-session', '-d', '-s', session, '-x', '80', '-y', '20', env_cmd],
                   check=True)

    class T:
        def keys(self, *k):
            subprocess.run(['tmux', '-L', sock, 'send-keys', '-t', session, *k], check=True)

        def msgs(self):
            with lock:
                return list(got)

        def wait(self, pred, timeout=20.0):
            end = time.monotonic() + timeout
            while time.monotonic() < end:
                if pred(self.msgs()):
                    return True
                time.sleep(0.02)
            return False

        def screen(self):
            return subprocess.run(['tmux', '-L', sock, 'capture-pane', '-p', '-t', session],
                                  capture_output=True, text=True).stdout

    t = T()
    t.exit_file, t.stty_file = exit_file, stty_file
    yield t
    subprocess.run(['tmux', '-L', sock, 'kill-server'], check=False)
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def test_teleop_in_tmux_keys_to_twist_stream(teleop_tmux):
    t = teleop_tmux
    # a stream at a fixed rate even with no key pressed: zeros in base_link
    assert t.wait(lambda m: len(m) >= 10, 30.0), f'no /pilot/cmd_vel stream; screen:\n{t.screen()}'
    assert all(m == ('base_link', 0.0, 0.0, 0.0) for m in t.msgs())
    assert 'vx +0.00' in t.screen()                                 # live status line
    # ... redrawn in place on one row of the 80-column terminal (cut to fit: no wrapping, no scrolling)
    rows = [ln for ln in t.screen().splitlines() if 'vx ' in ln]
    assert len(rows) == 1 and len(rows[0].rstrip()) < 80, t.screen()

    # hold W: the key auto-repeats (sent every 50 ms), forward at `speed`
    n0 = len(t.msgs())
    for _ in range(30):
        t.keys('w')
        time.sleep(0.05)
    seen = t.msgs()[n0:]
    assert any(m[1:] == (1.0, 0.0, 0.0) for m in seen), seen
    # release: the repeats stop, so the command goes back to zero (initial_hold is 30 s here,
    # so only the release detection can bring it back)
    n1 = len(t.msgs())
    assert t.wait(lambda m: any(x[1:] == (0.0, 0.0, 0.0) for x in m[n1:])), 'release did not stop'
    assert t.wait(lambda m: len(m) > n1 + 10 and all(x[1:] == (0.0, 0.0, 0.0) for x in m[-5:]))

    # up arrow climbs at speed_z; D is right (-y); space stops at once
    for _ in range(10):
        t.keys('Up')
        time.sleep(0.05)
    assert t.wait(lambda m: any(x[3] == 0.5 for x in m[n1:]))
    n2 = len(t.msgs())
    t.keys('d')                                                     # one tap: held for initial_hold (30 s)
    assert t.wait(lambda m: any(x[2] == -1.0 for x in m[n2:]))
    t.keys('Space')
    n3 = len(t.msgs())
    assert t.wait(lambda m: any(x[1:] == (0.0, 0.0, 0.0) for x in m[n3:]), 10.0), 'space did not stop'

    # q quits: zero command last, exit code 0, terminal restored (canonical mode, echo on)
    t.keys('w')
    assert t.wait(lambda m: m[-1][1] == 1.0)
    t.keys('q')
    assert t.wait(lambda m: t.exit_file.exists() and t.stty_file.exists(), 30.0), t.screen()
    time.sleep(0.3)
    assert t.exit_file.read_text().strip() == '0'
    assert t.msgs()[-1][1:] == (0.0, 0.0, 0.0)
    flags = set(t.stty_file.read_text().split())
    assert {'icanon', 'echo', 'isig'} <= flags
