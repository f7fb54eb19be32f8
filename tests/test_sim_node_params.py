"""sim_node / sim_pilot_node as a ROS user meets them: `ros2 param set` applies or is refused, integers
for decimal parameters, a burst of /sim/reset calls all answered, gui without a display one line."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image
from std_srvs.srv import Trigger

from assist_common.ros_io import SENSOR_QOS

pytestmark = pytest.mark.graph
BIN = Path(sys.executable).parent


def _value(v) -> ParameterValue:
    if isinstance(v, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=v)
    if isinstance(v, int):
        return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)
    return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(v))


def call(node, client, request, timeout: float = 30.0):
    """Synchronous service call from the probe (its executor spins in the background)."""
    assert client.wait_for_service(timeout_sec=timeout), client.srv_name
    done = threading.Event()
    fut = client.call_async(request)
    fut.add_done_callback(lambda f: done.set())
    assert done.wait(timeout), f'no answer from {client.srv_name}'
    return fut.result()


def param_set(node, target: str, name: str, value):
    """`ros2 param set /target name value` -> (successful, reason)."""
    client = node.create_client(SetParameters, f'/{target}/set_parameters')
    try:
        res = call(node, client, SetParameters.Request(parameters=[ParameterMsg(name=name, value=_value(value))]))
        return res.results[0].successful, res.results[0].reason
    finally:
        node.destroy_client(client)


def param_get(node, target: str, name: str):
    """`ros2 param get /target name` (double or integer value)."""
    client = node.create_client(GetParameters, f'/{target}/get_parameters')
    try:
        v = call(node, client, GetParameters.Request(names=[name])).values[0]
        return v.double_value if v.type == ParameterType.PARAMETER_DOUBLE else v.integer_value
    finally:
        node.destroy_client(client)


class Frames:
    """Counts camera frames and tracks sim time."""

    def __init__(self, node):
        self.node, self.lock = node, threading.Lock()
        self.frames, self.sim_t, self.diag_stamps = [], 0.0, []
        self.subs = [node.create_subscription(Image, '/camera/color/image_raw', self._img, SENSOR_QOS),
                     node.create_subscription(Clock, '/clock', self._clock, 10),
                     node.create_subscription(DiagnosticArray, '/diagnostics', self._diag, 10)]

    def _img(self, msg):
        with self.lock:
            self.frames.append(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec)

    def _clock(self, msg):
        with self.lock:
            self.sim_t = msg.clock.sec + 1e-9 * msg.clock.nanosec

    def _diag(self, msg):
        if any(st.hardware_id == 'sim_node' for st in msg.status):
            with self.lock:
                self.diag_stamps.append((msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, self.sim_t))

    def rate_over(self, sim_seconds: float, timeout: float = 120.0) -> float:
        """Camera frames per sim second over the next `sim_seconds` of sim time."""
        with self.lock:
            t0, n0 = self.sim_t, len(self.frames)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self.lock:
                if self.sim_t - t0 >= sim_seconds:
                    return (len(self.frames) - n0) / (self.sim_t - t0)
            time.sleep(0.05)
        raise AssertionError('sim time did not advance')

    def close(self):
        for s in self.subs:
            self.node.destroy_subscription(s)


def test_sim_node_parameters_apply_at_run_time_or_are_refused(ros, start_node, wait):
    start_node('sim_node', {'seed': 4, 'real_time_factor': 2, 'camera_rate_hz': 20})  # integers for floats
    frames = Frames(ros)
    try:
        assert wait(lambda: len(frames.frames) > 10, 120.0), 'no camera frames'
        assert frames.rate_over(2.0) == pytest.approx(20.0, abs=2.0)
        assert param_set(ros, 'sim_node', 'camera_rate_hz', 5) == (True, '')      # integer accepted, applied
        assert param_get(ros, 'sim_node', 'camera_rate_hz') == 5.0
        frames.rate_over(0.5)                                                     # let the change land
        assert frames.rate_over(4.0) == pytest.approx(5.0, abs=1.0)
        ok, reason = param_set(ros, 'sim_node', 'camera_rate_hz', -1.0)
        assert not ok and "'camera_rate_hz' must be >= 0.0" in reason
        ok, reason = param_set(ros, 'sim_node', 'camera_rate_hz', 50.0)
        assert not ok and 'above the sim step rate 20 Hz' in reason
        assert param_get(ros, 'sim_node', 'camera_rate_hz') == 5.0               # refused sets change nothing
        ok, reason = param_set(ros, 'sim_node', 'seed', 9)                       # read-only: refused
        assert not ok and 'read-only' in reason
        assert param_set(ros, 'sim_node', 'real_time_factor', 0.5) == (True, '')
        time.sleep(1.0)
        with frames.lock:
            s0, w0 = frames.sim_t, time.monotonic()
        time.sleep(4.0)
        with frames.lock:
            ratio = (frames.sim_t - s0) / (time.monotonic() - w0)
        assert 0.3 < ratio < 0.65, ratio                                       # the new pace is applied
        # /diagnostics is stamped with the node clock, which is the sim clock
        assert wait(lambda: len(frames.diag_stamps) >= 2, 60.0)
        stamp, sim_t = frames.diag_stamps[-1]
        assert abs(stamp - sim_t) < 1.5, frames.diag_stamps[-3:]
    finally:
        frames.close()


def test_a_burst_of_resets_is_answered(ros, start_node):
    start_node('sim_node', {'seed': 3, 'camera_rate_hz': 0.0})
    from rclpy.qos import QoSProfile
    # the client's own response queue must hold the burst too (default depth 10 drops answers)
    client = ros.create_client(Trigger, '/sim/reset', qos_profile=QoSProfile(depth=100))
    try:
        assert client.wait_for_service(timeout_sec=120.0)
        answered = []
        futs = [client.call_async(Trigger.Request()) for _ in range(50)]
        for f in futs:
            f.add_done_callback(lambda f: answered.append(f.result().success))
        end = time.monotonic() + 120.0
        while time.monotonic() < end and len(answered) < 50:
            time.sleep(0.1)
        assert len(answered) == 50 and all(answered)
        # a user study's sequence: the scene and goal pad of the next episodes, set at run time
        ok, reason = param_set(ros, 'sim_node', 'goal_index', 5)
        assert not ok and 'goal_index 5 is not a pad' in reason
        assert param_set(ros, 'sim_node', 'scene_seed', 7) == (True, '')
        for goal in (3, 0):
            assert param_set(ros, 'sim_node', 'goal_index', goal) == (True, '')
            res = call(ros, client, Trigger.Request())
            assert res.success and res.message.endswith(f'goal pad {goal}'), res.message
    finally:
        ros.destroy_client(client)


def test_sim_pilot_alpha_beta_settable_in_range(ros, start_node, wait):
    start_node('sim_pilot_node', {'alpha': 1, 'beta': 0})     # integers for decimal parameters
    assert wait(lambda: ('sim_pilot_node', '/') in ros.get_node_names_and_namespaces(), 60.0)
    assert param_get(ros, 'sim_pilot_node', 'alpha') == 1.0
    assert param_set(ros, 'sim_pilot_node', 'beta', 0.8) == (True, '')
    ok, reason = param_set(ros, 'sim_pilot_node', 'alpha', 1.5)
    assert not ok and "'alpha' must be >= 0.0 and <= 1.0" in reason
    ok, reason = param_set(ros, 'sim_pilot_node', 'rate_hz', 10.0)
    assert not ok and 'read-only' in reason


@pytest.mark.parametrize('exe, args, words', [
    ('sim_node', ['-p', 'gui:=true'], 'gui:=true needs a display but DISPLAY is not set'),
    ('sim_node', ['-p', 'seed:=-1'], "parameter 'seed' must be >= 0"),
    ('sim_pilot_node', ['-p', 'alpha:=2'], "parameter 'alpha' must be >= 0.0 and <= 1.0"),
])
def test_bad_start_is_one_clear_line(exe, args, words):
    env = {k: v for k, v in os.environ.items() if k not in ('DISPLAY', 'WAYLAND_DISPLAY')}
    r = subprocess.run([str(BIN / exe), '--ros-args', *args], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    lines = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    assert lines == [f'error: {exe}: ' + lines[0].split(f'error: {exe}: ', 1)[-1]] and words in lines[0], lines
