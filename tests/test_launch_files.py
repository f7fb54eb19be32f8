"""What a ROS user does with the colcon-installed workspace: `ros2 launch` each launch file, wait for
its topics, Ctrl-C, and expect a clean exit (0, no traceback, no error line, every node finished).

`ros2 launch` is tests/standins/ros2launch.py over a stand-in of the launch / launch_ros API (the
real ones do not install from a package registry here; see tests/standins/README.md), run with the
environment of `source install/setup.bash`, so the installed executables, share/ files and
models are used, not the editable venv.
"""
from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from assist_common.ros_io import RELIABLE_QOS

pytestmark = [pytest.mark.graph, pytest.mark.slow(seconds=70)]

REPO = Path(__file__).resolve().parents[1]
RUNNER = REPO / 'tests' / 'standins' / 'ros2launch.py'
START_TIMEOUT_S = 180.0   # torch imports and pybullet start-up on 2 loaded cores
STOP_TIMEOUT_S = 60.0
QUIET = ('Traceback', 'Failed to publish', 'never awaited', 'argv[0]=', 'process has died',
         'context is invalid', 'cannot connect to X server')


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nobody is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class Launch:
    """`ros2 launch PKG FILE args...` in its own process group (a terminal's Ctrl-C reaches all of it)."""

    def __init__(self, ws, domain_id: int, package: str, file: str, args: list[str], log_dir: Path,
                 prefixes: tuple[Path, ...] = ()):
        self.ws = ws
        env = dict(ws.env, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')
        if prefixes:          # more installed packages, found first (as a second underlay sourced after)
            env['AMENT_PREFIX_PATH'] = os.pathsep.join([*map(str, prefixes), env.get('AMENT_PREFIX_PATH', '')])
        env.pop('DISPLAY', None)
        self.log_path = log_dir / f'{file}-{time.monotonic_ns()}.log'
        self._log = open(self.log_path, 'w')
        self.proc = subprocess.Popen([sys.executable, str(RUNNER), package, file, *args], env=env,
                                     cwd=ws.root, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def output(self) -> str:
        """Everything printed so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors='replace')

    def ctrl_c(self) -> int:
        """SIGINT to the whole process group, as Ctrl-C in a terminal; the launch's exit code."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
        return self.wait()

    def wait(self, timeout: float = STOP_TIMEOUT_S) -> int:
        """Exit code (the group is killed and the test fails if it hangs)."""
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
            pytest.fail(f'launch did not exit within {timeout} s:\n{self.output()[-4000:]}')

    def kill(self) -> None:
        """Teardown: nothing may outlive the test."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)
        if not self._log.closed:
            self._log.close()


@pytest.fixture
def launch(colcon_workspace, domain_id, tmp_path):
    """Factory: launch(package, file, *args, symlink=False, prefixes=()) -> Launch; killed at teardown."""
    started: list[Launch] = []

    def _start(package: str, file: str, *args: str, symlink: bool = False, prefixes: tuple[Path, ...] = ()) -> Launch:
        ws = colcon_workspace(symlink)
        lau = Launch(ws, domain_id, package, file, list(args), tmp_path, prefixes)
        started.append(lau)
        return lau
    yield _start
    for lau in started:
        lau.kill()


def wait_for_topics(ros, topics: dict, lau: Launch, timeout: float = START_TIMEOUT_S) -> None:
    """Each topic (name -> (type, predicate or None)) delivers a matching message, or the test fails."""
    from rclpy.qos import qos_profile_sensor_data
    got = {name: threading.Event() for name in topics}
    subs = []
    for name, (msg_type, pred) in topics.items():
        def cb(msg, name=name, pred=pred):
            if pred is None or pred(msg):
                got[name].set()
        subs.append(ros.create_subscription(msg_type, name, cb, qos_profile_sensor_data))
    try:
        end = time.monotonic() + timeout
        while time.monotonic() < end and not all(e.is_set() for e in got.values()):
            if lau.proc.poll() is not None:
                break
            time.sleep(0.2)
        missing = [n for n, e in got.items() if not e.is_set()]
        assert not missing, f'no message on {missing}:\n{lau.output()[-5000:]}'
    finally:
        for s in subs:
            ros.destroy_subscription(s)


def from_node(name: str):
    """Predicate on DiagnosticArray: a status published by node `name`."""
    return lambda msg: any(st.hardware_id == name for st in msg.status)


def assert_clean_exit(code: int, out: str, nodes: int) -> None:
    """Exit 0, every node finished cleanly, no traceback / error line / known shutdown noise."""
    assert code == 0, out[-5000:]
    errors = [ln for ln in out.splitlines() if '[ERROR]' in ln or '[FATAL]' in ln]
    assert not errors, '\n'.join(errors) + '\n---\n' + out[-5000:]
    noisy = [word for word in QUIET if word in out]
    assert not noisy, f'{noisy}:\n{out[-5000:]}'
    assert out.count('process has finished cleanly') == nodes, out[-5000:]


def _types():
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float32MultiArray
    return DiagnosticArray, TwistStamped, Odometry, Clock, Image, Float32MultiArray


def test_sim_launch(ros, launch):
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    lau = launch('assist_sim', 'sim.launch.py', 'seed:=2', 'real_time_factor:=2')  # an integer for a float
    wait_for_topics(ros, {'/clock': (Clock, None), '/odom': (Odom, None),
                          '/camera/color/image_raw': (Image, None), '/camera/depth/image_raw': (Image, None),
                          '/diagnostics': (Diag, from_node('sim_node'))}, lau)
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=1)


def test_encoder_launch(ros, launch):
    Diag, *_ = _types()
    lau = launch('assist_perception', 'encoder.launch.py')
    wait_for_topics(ros, {'/diagnostics': (Diag, from_node('encoder_node'))}, lau)
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=1)


def test_bridge_launch(ros, launch):
    Diag, *_ = _types()
    lau = launch('assist_bridge', 'bridge.launch.py')
    wait_for_topics(ros, {'/diagnostics': (Diag, from_node('mavlink_bridge_node'))}, lau)
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=1)


def test_sim_mavlink_launch(ros, launch):
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    lau = launch('assist_lab', 'sim_mavlink.launch.py', f'port:={free_udp_port()}', 'seed:=1')
    # /odom here comes from the bridge (vehicle telemetry over MAVLink): the link is up
    wait_for_topics(ros, {'/odom': (Odom, None), '/camera/color/image_raw': (Image, None),
                          '/diagnostics': (Diag, from_node('mavlink_bridge_node'))}, lau)
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=2)


def test_onboard_and_base_station_split(ros, launch):
    """The two-machine deployment on one domain: the vehicle side (sim as camera and Pixhawk, bridge, image
    relay) and the base station (decoder, encoder, policy): relayed images reach the networks, the vehicle's
    odometry reaches the base station, the policy's /cmd_vel is flown by the vehicle's bridge."""
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    from geometry_msgs.msg import TwistStamped
    vehicle = launch('assist_bridge', 'onboard.launch.py', 'camera:=sim', f'port:={free_udp_port()}')
    base = launch('assist_station', 'base_station.launch.py', 'pilot:=none', 'sim_time:=true')
    pilot = ros.create_publisher(TwistStamped, '/pilot/cmd_vel', RELIABLE_QOS)
    stop = threading.Event()

    def fly():                    # the pilot holds a forward key the whole time
        while not stop.is_set():
            msg = TwistStamped()
            msg.header.frame_id = 'base_link'
            msg.twist.linear.x = 0.5
            pilot.publish(msg)
            time.sleep(0.05)
    flyer = threading.Thread(target=fly, daemon=True)
    flyer.start()
    try:
        wait_for_topics(ros, {'/link/camera/depth/image_raw': (Image, lambda m: m.encoding == '16UC1'),
                              '/assist/latent': (Floats, None), '/odom': (Odom, None),
                              '/cmd_vel': (Twist, None),
                              '/diagnostics': (Diag, from_node('image_relay'))}, base)
        assert vehicle.proc.poll() is None, vehicle.output()[-4000:]
    finally:
        stop.set()
        flyer.join(5)
    assert_clean_exit(base.ctrl_c(), base.output(), nodes=3)
    assert_clean_exit(vehicle.ctrl_c(), vehicle.output(), nodes=3)


def realsense_prefix(root: Path) -> Path:
    """An install prefix holding a realsense2_camera package whose realsense2_camera_node is the stand-in
    (tests/standins/realsense2_camera_node.py: the Jazzy driver's topics and profile, without a camera)."""
    prefix = root / 'realsense_prefix'
    index = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'realsense2_camera').write_text('')
    (prefix / 'share' / 'realsense2_camera').mkdir(parents=True)
    exe = prefix / 'lib' / 'realsense2_camera' / 'realsense2_camera_node'
    exe.parent.mkdir(parents=True)
    exe.write_text(f'#!/bin/sh\nexec "{sys.executable}" "{REPO / "tests" / "standins" / "realsense2_camera_node.py"}" '
                   '"$@"\n')
    exe.chmod(0o755)
    return prefix


def test_onboard_with_a_realsense_camera(ros, launch, tmp_path):
    """camera:=realsense: the driver's topics (/camera/camera/..., 640x480 rgb8 and aligned 16UC1 at 30 Hz)
    reach the contract's names through the launch file's remappings, the image relay sends them at the
    encoder's size, and the bridge (config/bridge_real.yaml) starts on `connection`; Ctrl-C ends all three."""
    from sensor_msgs.msg import CompressedImage

    from assist_bridge.image_link import LinkError, decode_color, decode_depth
    from assist_bridge.image_relay import PARAMS as RELAY
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    size = (RELAY['height'].default, RELAY['width'].default)

    def at_encoder_size(decode):
        """A payload that the base station's decoder reads (format, codec, header) at the encoder's size."""
        def check(msg) -> bool:
            try:
                return decode(msg.data, msg.format).shape[:2] == size
            except LinkError:
                return False
        return check
    lau = launch('assist_bridge', 'onboard.launch.py', 'camera:=realsense',
                 f'connection:=udpin:127.0.0.1:{free_udp_port()}', prefixes=(realsense_prefix(tmp_path),))
    wait_for_topics(ros, {'/camera/color/image_raw': (Image, lambda m: (m.width, m.encoding) == (640, 'rgb8')),
                          '/camera/depth/image_raw': (Image, lambda m: (m.width, m.encoding) == (640, '16UC1')),
                          '/camera/color/image_raw/compressed': (CompressedImage, at_encoder_size(decode_color)),
                          '/camera/depth/image_raw/compressedDepth': (CompressedImage, at_encoder_size(decode_depth)),
                          '/diagnostics': (Diag, from_node('mavlink_bridge_node'))}, lau)
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=3)


def test_station_launch_unassisted(ros, launch):
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    lau = launch('assist_station', 'station.launch.py', 'assisted:=false', f'port:={free_tcp_port()}')
    # the pilot's commands go straight to /cmd_vel without the assistant
    wait_for_topics(ros, {'/clock': (Clock, None), '/cmd_vel': (Twist, None),
                          '/diagnostics': (Diag, from_node('pilot_station'))}, lau)
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=2)


@pytest.mark.parametrize('symlink', [False, True], ids=['plain', 'symlink'])
def test_assist_launch_latent(ros, launch, symlink):
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    lau = launch('assist_lab', 'assist.launch.py', 'mode:=latent', 'alpha:=1', symlink=symlink)
    wait_for_topics(ros, {'/pilot/cmd_vel': (Twist, None), '/assist/latent': (Floats, None),
                          '/assist/agent_cmd': (Twist, None), '/cmd_vel': (Twist, None)}, lau)
    # the installed shipped models, found through the ament index
    install = lau.ws.install
    out = lau.output()
    assert f'{install}/assist_policy/share/assist_policy/models/td3_latent_actor.pt' in out, out[-4000:]
    assert f'{install}/assist_perception/share/assist_perception/models/cmvae.pt' in out, out[-4000:]
    assert_clean_exit(lau.ctrl_c(), lau.output(), nodes=4)


def launch_errors(out: str) -> list[str]:
    """The launch's own error lines (not the nodes')."""
    return [ln for ln in out.splitlines() if ln.startswith('[ERROR] [launch]')]


def test_a_dead_required_node_ends_the_launch_with_the_reason(ros, launch):
    Diag, Twist, Odom, Clock, Image, Floats = _types()
    lau = launch('assist_lab', 'sim_mavlink.launch.py', f'port:={free_udp_port()}')
    wait_for_topics(ros, {'/odom': (Odom, None)}, lau)      # both up, the link too
    pid = int(re.search(r'\[sim_node-1\]: process started with pid \[(\d+)\]', lau.output()).group(1))
    os.kill(pid, signal.SIGKILL)                              # the sim crashes
    code = lau.wait(STOP_TIMEOUT_S)
    out = lau.output()
    assert code == 1, out[-4000:]           # ros2 launch fails because a required node did
    assert launch_errors(out) == [
        '[ERROR] [launch]: Caught exception in launch (see debug for traceback): sim_node-1 exited with code -9; '
        'the bridge has no vehicle without the sim: shutting the launch down'], out[-4000:]
    assert '[INFO] [mavlink_bridge_node-2]: process has finished cleanly' in out, out[-4000:]
    assert 'Traceback' not in out


def test_a_node_failing_at_start_up_is_one_line_and_exit_1(launch, tmp_path):
    taken = tmp_path / 'flight'
    taken.mkdir()
    (taken / 'keep.txt').write_text('an earlier recording')
    lau = launch('assist_lab', 'assist.launch.py', f'record:={taken}', 'real_time_factor:=2')
    code = lau.wait(START_TIMEOUT_S)
    out = lau.output()
    assert code == 1, out[-4000:]
    errors = launch_errors(out)
    assert len(errors) == 1, out[-4000:]
    # the node, its exit code, what it said, and what the launch needed it for, on one line
    assert re.fullmatch(r'\[ERROR\] \[launch\]: Caught exception in launch \(see debug for traceback\): '
                        r'bag_record-\d exited with code 1: error: .*flight: exists already; not overwriting a bag'
                        r'; the flight would go unrecorded: shutting the launch down', errors[0]), errors[0]
    # the siblings, stopped while still importing torch or starting, leave no traceback
    assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, out[-6000:]
    assert (taken / 'keep.txt').read_text() == 'an earlier recording'


def test_ctrl_c_during_start_up_leaves_no_traceback(launch, loading_heavy_libraries):
    lau = launch('assist_lab', 'assist.launch.py', 'mode:=latent', 'real_time_factor:=2')
    end = time.monotonic() + START_TIMEOUT_S
    pids: list[int] = []
    while time.monotonic() < end:           # until every node is inside its imports (rclpy, torch, pybullet)
        pids = [int(p) for p in re.findall(r'process started with pid \[(\d+)\]', lau.output())]
        if len(pids) == 4 and all(loading_heavy_libraries(pid) for pid in pids):
            break
        time.sleep(0.005)
    assert len(pids) == 4, lau.output()[-4000:]
    code = lau.ctrl_c()
    out = lau.output()
    assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, out[-6000:]
    assert_clean_exit(code, out, nodes=4)


def test_every_launch_argument_is_described(colcon_workspace):
    ws = colcon_workspace(False)
    files = sorted(ws.install.glob('*/share/*/launch/*.launch.py'))
    assert len(files) >= 6
    for path in files:
        pkg = path.parents[1].name
        out = subprocess.run([sys.executable, str(RUNNER), pkg, path.name, '--show-args'], env=ws.env,
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr[-2000:]
        assert "'" in out.stdout and 'no description given' not in out.stdout, (path.name, out.stdout)


def test_launch_arguments_are_never_evaluated_as_code(launch, tmp_path):
    marker = tmp_path / 'pwned'
    payload = f"__import__('pathlib').Path('{marker}').touch()"
    lau = launch('assist_lab', 'assist.launch.py', f"mode:=latent' == 'latent' or {payload} or '")
    assert lau.wait(START_TIMEOUT_S) == 1        # not one of latent / oracle / end_to_end
    assert 'is not valid' in lau.output() and 'process started' not in lau.output()
    lau = launch('assist_lab', 'sim_mavlink.launch.py', f"port:=1' + str({payload}) + '")
    lau.wait(START_TIMEOUT_S)
    assert not marker.exists(), lau.output()[-4000:]
