"""Shared fixtures for graph tests: a private ROS_DOMAIN_ID, an rclpy probe node, node subprocesses."""
from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from collections.abc import Callable

import pytest

from assist_sim.testing import stop_process
from assist_common.domains import private_domain_id

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _ros_arg(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value if value else "''"
    return repr(value)


class NodeProcess:
    """A console-script node running in its own process on the test's domain."""

    def __init__(self, executable: str, params: dict | None, domain_id: int, log_dir: Path,
                 remaps: dict | None = None):
        exe = BIN / executable
        if not exe.exists():
            raise FileNotFoundError(f'{exe} not installed (run make venv)')
        cmd = [str(exe), '--ros-args']
        for k, v in (params or {}).items():
            cmd += ['-p', f'{k}:={_ros_arg(v)}']
        for k, v in (remaps or {}).items():
            cmd += ['-r', f'{k}:={v}']
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED='1')
        self.log_path = log_dir / f'{executable}-{time.monotonic_ns()}.log'
        self._log = open(self.log_path, 'w')
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def log(self) -> str:
        """Everything the process printed so far."""
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors='replace')

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT, then SIGKILL if it does not exit; returns the exit code."""
        code = stop_process(self.proc, timeout)
        self._log.close()
        return code


@pytest.fixture(scope='module')
def domain_id() -> int:
    """A private DDS domain for this test module."""
    return private_domain_id()


@pytest.fixture(scope='module')
def ros(domain_id):
    """rclpy context on the private domain with one probe node spinning in the background."""
    import rclpy
    from rclpy.context import Context
    from rclpy.exceptions import InvalidHandle
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node

    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = Node('test_probe', context=ctx)
    # single-threaded: rclpy 7.1's MultiThreadedExecutor burns CPU (and the GIL) on bookkeeping
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        # Tests destroy their subscriptions from their own thread while this one spins; one the executor
        # holds at that moment raises InvalidHandle here ('destruction was requested'), which ended a plain
        # executor.spin and left every later wait in the test to run into its timeout.
        while not stop.is_set() and ctx.ok():
            try:
                executor.spin_once(timeout_sec=0.1)
            except InvalidHandle:
                continue
            except ExternalShutdownException:
                return
    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    yield node
    stop.set()
    thread.join(5.0)
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


class PolicyProbe:
    """policy_node's inputs published from the test's node (/odom, /pilot/cmd_vel, /assist/latent) and its outputs
    recorded with their arrival times (/cmd_vel, /assist/agent_cmd, its /diagnostics statuses)."""

    def __init__(self, node):
        import numpy as np
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import TwistStamped
        from nav_msgs.msg import Odometry
        from std_msgs.msg import Float32MultiArray

        from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS
        from assist_policy.testing import LATENT
        self._np, self._twist, self._odom, self._array, self._latent = (np, TwistStamped, Odometry,
                                                                          Float32MultiArray, LATENT)
        self.node, self.lock = node, threading.Lock()
        self.cmd, self.agent, self.diag = [], [], []
        self.subs = [node.create_subscription(TwistStamped, '/cmd_vel', self._rec(self.cmd), RELIABLE_QOS),
                     node.create_subscription(TwistStamped, '/assist/agent_cmd', self._rec(self.agent),
                                              RELIABLE_QOS),
                     node.create_subscription(DiagnosticArray, '/diagnostics', self._diag, 10)]
        self.pub_odom = node.create_publisher(Odometry, '/odom', SENSOR_QOS)
        self.pub_pilot = node.create_publisher(TwistStamped, '/pilot/cmd_vel', RELIABLE_QOS)
        self.pub_latent = node.create_publisher(Float32MultiArray, '/assist/latent', SENSOR_QOS)

    def _rec(self, store: list) -> Callable:
        def cb(msg) -> None:
            with self.lock:
                store.append((time.monotonic(), self._np.array([msg.twist.linear.x, msg.twist.linear.y,
                                                                msg.twist.linear.z])))
        return cb

    def _diag(self, msg) -> None:
        with self.lock:
            self.diag += [(time.monotonic(), s) for s in msg.status if s.hardware_id == 'policy_node']

    def since(self, store: list, t0: float) -> list:
        """The values of `store` recorded at or after monotonic time `t0`."""
        with self.lock:
            return [v for t, v in store if t >= t0]

    def publish(self, u=(0.0, 1.0, 0.0), frame: str = 'base_link', odom_v=(0.0, 0.0, 0.0), latent: bool = True,
                latent_value: float = 0.0) -> None:
        """One set of inputs: odometry 2 m up moving at `odom_v`, the pilot's `u` in `frame`, a latent (all
        `latent_value`) unless `latent` is False."""
        od = self._odom()
        od.pose.pose.position.z = 2.0
        od.twist.twist.linear.x, od.twist.twist.linear.y, od.twist.twist.linear.z = odom_v
        self.pub_odom.publish(od)
        tw = self._twist()
        tw.header.frame_id = frame
        tw.twist.linear.x, tw.twist.linear.y, tw.twist.linear.z = (float(x) for x in u)
        self.pub_pilot.publish(tw)
        if latent:
            self.pub_latent.publish(self._array(data=[float(latent_value)] * self._latent))

    def run(self, seconds: float, **kw) -> float:
        """Publish the inputs at 20 Hz for `seconds`; the monotonic time it began."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            self.publish(**kw)
            time.sleep(0.05)
        return t0

    def close(self) -> None:
        """Destroy the subscriptions and publishers."""
        for s in self.subs:
            self.node.destroy_subscription(s)
        for p in (self.pub_odom, self.pub_pilot, self.pub_latent):
            self.node.destroy_publisher(p)


@pytest.fixture
def probe(ros):
    """A PolicyProbe on the test module's node."""
    p = PolicyProbe(ros)
    yield p
    p.close()


@pytest.fixture
def start_node(domain_id, tmp_path):
    """Factory: start_node('sim_node', {'seed': 1}) -> NodeProcess; all stopped at teardown."""
    procs: list[NodeProcess] = []

    def _start(executable: str, params: dict | None = None, remaps: dict | None = None) -> NodeProcess:
        proc = NodeProcess(executable, params, domain_id, tmp_path, remaps)
        procs.append(proc)
        return proc
    yield _start
    for proc in procs:
        proc.stop()


def wait_for(predicate: Callable[[], bool], timeout: float, interval: float = 0.05) -> bool:
    """Poll `predicate` until true or `timeout` seconds pass."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())


@pytest.fixture
def wait():
    """The wait_for(predicate, timeout) helper as a fixture (conftest is not importable by tests)."""
    return wait_for


class ColconWorkspace:
    """A colcon build of a copy of this checkout (ros2_ws/src + models/, laid out as in the repo)."""

    BUILT = 'colcon_build_done'       # written last: a folder without it holds a build that did not finish

    def __init__(self, root: Path, symlink: bool):
        self.root, self.symlink = root, symlink
        self.ws = root / 'ros2_ws'
        self.install = self.ws / 'install'
        if not (root / self.BUILT).is_file():
            self._build()
        # what `source install/setup.bash` gives a ROS user
        out = subprocess.run(['bash', '-c', f'source {self.install}/setup.bash && env -0'],
                             capture_output=True, text=True, timeout=60, check=True).stdout
        self.env = dict(item.split('=', 1) for item in out.split('\0') if '=' in item)

    def _build(self) -> None:
        for part in (self.ws, self.root / 'models'):       # what a failed build of another worker left
            shutil.rmtree(part, ignore_errors=True)
        shutil.copytree(REPO / 'ros2_ws' / 'src', self.ws / 'src',
                        ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
        shutil.copytree(REPO / 'models', self.root / 'models')
        cmd = [str(BIN / 'colcon'), 'build'] + (['--symlink-install'] if self.symlink else [])
        proc = subprocess.run(cmd, cwd=self.ws, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        (self.root / self.BUILT).write_text('')


@pytest.fixture(scope='session')
def colcon_workspace(tmp_path_factory):
    """Factory: colcon_workspace(symlink=False) -> ColconWorkspace, each kind built once per run.

    Under pytest-xdist the builds live in the run's folder that every worker shares, behind a lock: the first
    worker to need a kind builds it and the others use that build (test_workspace and test_launch_files run on
    different workers; building on each cost ~40 s of CPU). Tests only read and run what is installed."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get('PYTEST_XDIST_WORKER') else base
    built: dict[bool, ColconWorkspace] = {}

    def _get(symlink: bool = False) -> ColconWorkspace:
        if symlink not in built:
            root = shared / ('colcon_symlink' if symlink else 'colcon_plain')
            root.mkdir(exist_ok=True)
            with open(shared / f'{root.name}.lock', 'w') as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)        # released when the file closes
                built[symlink] = ColconWorkspace(root, symlink)
        return built[symlink]
    return _get


@pytest.fixture(scope='session')
def study_max_landing_s() -> float:
    """Sim seconds a landing of the study graph tests may last before it ends as a timeout (test_study_graph*).

    Those tests check the protocol, not the flying (their simulated pilots rarely end a landing by themselves within
    20 s, so most rows are timeouts either way): at their real-time factor 3 this is 4 s of wall time, still
    several times the station's switching of the assistant (a parameter call to policy_node, answered within a
    second) and a browser reload 1 s into a landing, and long enough for the intent cues to show."""
    return 12.0


#: Shared libraries only a program's own imports load (rclpy, torch, pybullet, OpenCV), never the interpreter.
HEAVY_LIBRARIES = ('_rclpy_pybind11', 'libtorch', 'pybullet', 'cv2')


def _loading_heavy_libraries(pid: int) -> bool:
    try:
        maps = Path(f'/proc/{pid}/maps').read_text()
    except OSError:
        return False
    return any(lib in maps for lib in HEAVY_LIBRARIES)


@pytest.fixture
def loading_heavy_libraries():
    """f(pid) -> True once the process has mapped one of HEAVY_LIBRARIES: it is past the interpreter's own
    start-up and inside the program's imports (False when it is gone or not there yet)."""
    return _loading_heavy_libraries
