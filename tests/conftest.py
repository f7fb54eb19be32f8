"""Shared fixtures for graph tests: a private ROS_DOMAIN_ID, an rclpy probe node, node subprocesses."""
from __future__ import annotations

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

    def __init__(self, root: Path, symlink: bool):
        self.root, self.symlink = root, symlink
        self.ws = root / 'ros2_ws'
        self.install = self.ws / 'install'
        shutil.copytree(REPO / 'ros2_ws' / 'src', self.ws / 'src',
                        ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
        shutil.copytree(REPO / 'models', root / 'models')
        cmd = [str(BIN / 'colcon'), 'build'] + (['--symlink-install'] if symlink else [])
        proc = subprocess.run(cmd, cwd=self.ws, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        # what `source install/setup.bash` gives a ROS user
        out = subprocess.run(['bash', '-c', f'source {self.install}/setup.bash && env -0'],
                             capture_output=True, text=True, timeout=60, check=True).stdout
        self.env = dict(item.split('=', 1) for item in out.split('\0') if '=' in item)


@pytest.fixture(scope='session')
def colcon_workspace(tmp_path_factory):
    """Factory: colcon_workspace(symlink=False) -> ColconWorkspace, each kind built once per session."""
    built: dict[bool, ColconWorkspace] = {}

    def _get(symlink: bool = False) -> ColconWorkspace:
        if symlink not in built:
            built[symlink] = ColconWorkspace(tmp_path_factory.mktemp('symlink' if symlink else 'plain'), symlink)
        return built[symlink]
    return _get


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
