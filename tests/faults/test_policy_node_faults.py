"""Fault injection, policy_node: hostile messages, failing control steps, bad parameters, wrong frames;
diagnostics that tell the state. In-process tests drive the node's callbacks on a private context;
graph tests run the console script on the test's private domain.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
import rclpy.duration
import torch
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.parameter import Parameter
from std_msgs.msg import Float32MultiArray

from assist_policy.policy_node import PolicyNode, ReasonThrottle
from assist_policy.testing import LATENT, constant_actor
from assist_common.domains import private_domain_id

REPO = Path(__file__).resolve().parents[2]
OK, WARN, ERROR = (int.from_bytes(x, 'little') for x in (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                                                          DiagnosticStatus.ERROR))


# ------------------------------------------------------------------ in-process: the node's own callbacks
class InProcess:
    """PolicyNode on a private context; publishes into its callbacks and records its outputs."""

    def __init__(self, model, **params):
        self.ctx = Context()
        args = ['--ros-args', '-p', f'model_path:={model}', '-p', 'mode:=latent']
        params.setdefault('step_on_latent', 'false')     # these tests drive the control step themselves
        for k, v in params.items():
            args += ['-p', f'{k}:={v}']
        rclpy.init(args=args, context=self.ctx, domain_id=private_domain_id())
        self.node = PolicyNode(context=self.ctx)
        self.cmds, self.agents = [], []
        self.node.pub_cmd.publish = lambda m: self.cmds.append(_vec(m))
        self.node.pub_agent.publish = lambda m: self.agents.append(_vec(m))

    def inputs(self, u=(0.0, 1.0, 0.0), frame='base_link', odom_v=(0.0, 0.0, 0.0), latent=0.0):
        od = Odometry()
        od.pose.pose.position.z = 2.0
        od.twist.twist.linear.x, od.twist.twist.linear.y, od.twist.twist.linear.z = odom_v
        subs = list(self.node.subscriptions)
        subs[0].callback(od)
        tw = TwistStamped()
        tw.header.frame_id = frame
        tw.twist.linear.x, tw.twist.linear.y, tw.twist.linear.z = (float(x) for x in u)
        subs[1].callback(tw)
        if latent is not None:
            subs[2].callback(Float32MultiArray(data=[float(latent)] * LATENT))

    def tick(self, n=1):
        for _ in range(n):
            self.node._tick()
        return self.cmds[-1]

    @property
    def level(self):
        return self.node.diag._level, self.node.diag._message

    def close(self):
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


def _vec(msg):
    return np.array([msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z])


@pytest.fixture
def model(tmp_path):
    return constant_actor(tmp_path / 'actor.pt', [0.8, 0.0, 0.0])


@pytest.fixture
def make(model):
    made = []

    def _make(**params):
        made.append(InProcess(model, **params))
        return made[-1]
    yield _make
    for m in made:
        m.close()


def test_exception_anywhere_in_the_step_relinquishes_counts_and_stays_up(make):
    n = make()
    n.inputs(u=(0.0, 2.0, 0.3))
    np.testing.assert_allclose(n.tick(), [0.4, 1.0, 0.15], atol=1e-6)     # assisting: (u + a) / 2
    assert n.level == (OK, 'assisting') and len(n.agents) == 1

    def boom(now):
        raise RuntimeError('simulated failure in the step')
    n.node.core.step = boom            # an exception the core itself does not catch
    np.testing.assert_allclose(n.tick(), [0.0, 1.5, 0.3], atol=1e-9)      # V = u, clamped to max_speed
    assert len(n.agents) == 1                                              # no agent command
    assert n.node.diag.get('fault_step_error') == 1 and n.node.diag.get('fault_RuntimeError') == 1
    assert n.level[0] == WARN and 'RuntimeError' in n.level[1]
    n.tick(25)                          # many failures in a row: ERROR
    assert n.level[0] == ERROR and 'consecutive failed steps' in n.level[1]
    assert all(np.allclose(v, [0.0, 1.5, 0.3]) for v in n.cmds[1:])


def test_broken_actor_output_is_an_error_state_not_ok(make):
    n = make(error_after_faults=5)
    n.inputs()
    actor = n.node.core.actor

    class Overflowing:
        """The actor of the node (its metadata and backend) with a network that overflows at run time."""
        meta, backend = actor.meta, actor.backend

        def __call__(self, obs, position):
            return np.full(3, math.nan), None
    n.node.core.actor = Overflowing()
    n.tick()
    assert n.level[0] == WARN and 'not finite' in n.level[1]
    n.inputs()
    n.tick(5)
    assert n.level[0] == ERROR
    np.testing.assert_allclose(n.cmds[-1], [0, 1, 0])


def test_odometry_overflowing_float32_is_rejected_and_flying_goes_on(make):
    n = make()
    n.inputs(odom_v=(1e39, 0.0, 0.0))
    assert n.node.diag.get('rejected_odom_velocity_range') == 1
    np.testing.assert_allclose(n.tick(), [0, 1, 0])                # no odometry yet: V = u
    assert n.level[0] == WARN and 'odometry' in n.level[1]


def test_pilot_frame_and_speed_norm(make):
    n = make(max_input_speed=5.0)
    n.inputs(u=(0.0, 1.0, 0.0))
    n.inputs(u=(3.0, 0.0, 0.0), frame='map')                        # refused: last good u stays
    assert n.node.diag.get('rejected_pilot_frame') == 1
    np.testing.assert_allclose(n.tick(), [0.4, 0.5, 0.0], atol=1e-6)
    n.inputs(u=(4.0, 4.0, 0.0))                                     # each axis < 5, speed 5.66: refused
    assert n.node.diag.get('rejected_pilot_range') == 1
    n.inputs(u=(0.0, 1.0, 0.0), frame='')                           # no frame: body frame
    assert n.node.diag.get('rejected_pilot') == 2


def test_pilot_commands_arriving_late_still_fly(make):
    # a starved CPU or a slow link delivers every pilot command 0.8 s after its stamp (> pilot_timeout_s)
    n = make()
    stamp = n.node.get_clock().now() - rclpy.duration.Duration(seconds=0.8)
    od = Odometry()
    od.pose.pose.position.z = 2.0
    subs = list(n.node.subscriptions)
    subs[0].callback(od)
    tw = TwistStamped()
    tw.header.stamp, tw.header.frame_id = stamp.to_msg(), 'base_link'
    tw.twist.linear.x, tw.twist.linear.z = 0.4, -0.3
    subs[1].callback(tw)
    np.testing.assert_allclose(n.tick(), [0.4, 0.0, -0.3])          # no latent: V = u, the late u
    assert n.node.diag.get('pilot_late') == 1 and n.node.diag.get('rejected_pilot') == 0
    assert float(n.node.diag._values['pilot_latency_s']) >= 0.8
    tw.header.stamp = (n.node.get_clock().now() - rclpy.duration.Duration(seconds=5.0)).to_msg()
    subs[1].callback(tw)                                            # beyond pilot_max_latency_s: refused
    assert n.node.diag.get('rejected_pilot_stale_stamp') == 1


def test_runtime_parameters_are_validated_and_applied(make):
    n = make()
    node = n.node
    for name, bad in [('max_speed', -1.0), ('max_vertical_speed', -1.0), ('max_speed', math.nan),
                      ('blend_threshold', -0.5), ('pilot_timeout_s', 0.0), ('max_input_speed', math.inf)]:
        res = node.set_parameters([Parameter(name, value=bad)])[0]
        assert not res.successful, (name, bad)
    assert node.core.cfg.max_speed_mps == 1.5 and node.core.cfg.max_vertical_mps == 1.0
    for name in ('mode', 'model_path', 'rate_hz', 'frame_id', 'torch_threads'):
        value = {'mode': 'oracle', 'model_path': '/x', 'rate_hz': 5.0, 'frame_id': 'map', 'torch_threads': 2}[name]
        res = node.set_parameters([Parameter(name, value=value)])[0]
        assert not res.successful and 'read-only' in res.reason, name
    assert node.set_parameters([Parameter('max_speed', value=0.2)])[0].successful
    assert node.set_parameters([Parameter('max_vertical_speed', value=1)])[0].successful   # int for float
    n.inputs(u=(0.0, 1.0, -3.0))
    v = n.tick()
    assert math.hypot(v[0], v[1]) == pytest.approx(0.2) and v[2] == pytest.approx(-1.0)


def test_each_reason_has_its_own_throttle():
    clock = [0.0]
    t = ReasonThrottle(2.0, clock=lambda: clock[0])
    assert t.ready('pilot_frame') and t.ready('odom_velocity_range')     # distinct faults: both logged
    assert not t.ready('pilot_frame')
    clock[0] = 1.9
    assert not t.ready('odom_velocity_range')
    clock[0] = 2.0
    assert t.ready('pilot_frame') and t.ready('odom_velocity_range')


# ------------------------------------------------------------------ graph: the console script

@pytest.mark.graph
def test_node_survives_hostile_odometry_and_wrong_frames(probe, start_node, wait, model):
    """An /odom twist of 1e39 used to kill policy_node (the ValueError escaped the timer)."""
    # the probe's pilot holds a key: the pilot override (its own graph test) would take over from the actor
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'pilot_override': False})
    t0 = time.monotonic()
    while not probe.since(probe.cmd, t0) and node.proc.poll() is None and time.monotonic() - t0 < 60:
        probe.run(0.2)
    assert probe.since(probe.cmd, t0), node.log()
    t1 = probe.run(2.5)
    assert any(s.level == DiagnosticStatus.OK and s.message == 'assisting' for s in probe.since(probe.diag, t1)), \
        ([s.message for _, s in probe.diag[-5:]], node.log())
    # hostile odometry and a command in another frame within the same 2 s: both rejected, both logged
    probe.run(1.5, odom_v=(1e39, 0.0, 0.0), u=(1.0, 0.0, 0.0), frame='map')
    assert node.proc.poll() is None, node.log()
    t3 = probe.run(2.5, odom_v=(1e39, 0.0, 0.0))
    late = probe.since(probe.cmd, t3 + 1.0)
    # only hostile odometry arrives: odometry stale, relinquished, V = u = (0, 1, 0), and the node says so
    assert late and all(np.allclose(v, [0, 1, 0], atol=1e-6) for v in late), late[-3:]
    assert any(s.level == DiagnosticStatus.WARN and 'odometry' in s.message
               for s in probe.since(probe.diag, t3 + 1.0)), [s.message for _, s in probe.diag[-5:]]
    log = node.log()
    assert 'rejected odom (odom_velocity_range)' in log and 'rejected pilot (pilot_frame)' in log, log
    assert node.proc.poll() is None


@pytest.mark.graph
@pytest.mark.parametrize('param, value, words', [('max_vertical_speed', '-1.0', "'max_vertical_speed' must be >= 0.1"),
                                                 ('max_speed', '.nan', "'max_speed' must be finite"),
                                                 ('rate_hz', '0', "'rate_hz' must be > 0")])
def test_bad_parameter_exits_with_one_line(start_node, wait, model, param, value, words):
    """max_vertical_speed:=-1 used to publish a continuous 1 m/s descent; max_speed:=-1 a ZeroDivisionError."""
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), param: value})
    assert wait(lambda: node.proc.poll() is not None, 60), node.log()
    log = node.log()
    assert node.proc.returncode == 1 and words in log and 'Traceback' not in log, log
    assert len([ln for ln in log.splitlines() if ln.startswith('error:')]) == 1


@pytest.mark.graph
def test_nan_max_speed_model_exits_with_one_line(start_node, wait, tmp_path):
    """A model file with a NaN max_speed used to start and then crash on the first tick."""
    path = constant_actor(tmp_path / 'nan_speed.pt', [0.5, 0.0, 0.0])
    blob = torch.load(path, weights_only=True)
    blob['meta']['max_speed'] = [math.nan, 1.0, 0.6]
    torch.save(blob, path)
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(path)})
    assert wait(lambda: node.proc.poll() is not None, 60), node.log()
    log = node.log()
    assert node.proc.returncode == 1 and 'max_speed' in log and str(path) in log and 'Traceback' not in log, log


def test_a_step_during_shutdown_publishes_nothing_and_reports_no_fault(make):
    """Ctrl-C: rclpy invalidates the context while a step may still run; that is no publish error to warn of."""
    n = make()
    n.inputs(u=(0.0, 1.0, 0.0))
    n.tick()
    sent = len(n.cmds)

    def invalid(_msg):
        raise RuntimeError("Failed to publish: publisher's context is invalid")
    n.node.pub_cmd.publish = invalid
    n.node._tick()                                             # context still valid: a real publish error
    assert n.node.diag.get('publish_errors') == 1
    ok = n.node.context.ok
    going = iter([True, False])                                # valid at the start of the step, gone by its end
    n.node.context.ok = lambda: next(going)
    n.node._tick()
    assert n.node.diag.get('publish_errors') == 1 and len(n.cmds) == sent
    n.node.context.ok = lambda: False                          # already gone: the step does not run
    n.node.core.step = lambda now: pytest.fail('stepped after shutdown')
    n.node._tick()
    n.node.context.ok = ok
