"""policy_node's flight boundaries on a real graph (in-process executor, private DDS domain): the ~/reset rate limit,
the /uav/landed_state subscription, and /diagnostics saying why the assistant reset."""
from __future__ import annotations

import importlib.util
import os
import time
from pathlib import Path

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import UInt8
from std_srvs.srv import Trigger

from assist_common.ros_io import LATCHED_QOS
from assist_policy.policy_node import PolicyNode
from assist_common.domains import private_domain_id

_spec = importlib.util.spec_from_file_location('policy_core_helpers_flight_node',
                                               Path(__file__).with_name('test_policy_core.py'))
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)

WAIT_S = 30.0     # the most any one condition may take to come true (it normally takes milliseconds)


@pytest.fixture
def graph(tmp_path):
    """(policy_node, probe node, spin_until) on a private context and domain."""
    ctx = Context()
    domain = int(os.environ.get('ROS_DOMAIN_ID') or private_domain_id())
    model = _helpers.constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0])
    rclpy.init(args=['--ros-args', '-p', f'model_path:={model}', '-p', 'mode:=latent', '-p', 'step_on_latent:=false',
                     '-p', 'flight_reset_min_interval_s:=3600.0'], context=ctx, domain_id=domain)
    node = PolicyNode(context=ctx)
    probe = rclpy.create_node('flight_probe', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    executor.add_node(probe)

    def spin_until(condition, what: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not condition():
            assert time.monotonic() < deadline, f'not within {WAIT_S:g} s: {what}'
            executor.spin_once(timeout_sec=0.05)

    yield node, probe, spin_until
    executor.shutdown()
    probe.destroy_node()
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def _call(client, spin_until) -> Trigger.Response:
    future = client.call_async(Trigger.Request())
    spin_until(future.done, '~/reset answered')
    return future.result()


def test_reset_service_is_rate_limited(graph):
    node, probe, spin_until = graph
    client = probe.create_client(Trigger, '/policy_node/reset')
    spin_until(client.service_is_ready, '~/reset available')
    first = _call(client, spin_until)
    assert first.success and 'forgotten' in first.message
    again = _call(client, spin_until)                         # within flight_reset_min_interval_s (3600 s)
    assert not again.success and 'flight_reset_min_interval_s' in again.message
    assert node.core.flight_resets['service'] == 1 and node.core.flight.resets_refused == 1
    assert node.diag._values['flight_reset_refused'] == '1'
    node.set_parameters([Parameter('flight_reset_min_interval_s', value=0.0)])   # 0: no limit (run time)
    assert _call(client, spin_until).success and _call(client, spin_until).success
    assert node.core.flight_resets['service'] == 3


def test_landed_state_ends_and_begins_flights_and_diagnostics_say_why(graph):
    node, probe, spin_until = graph
    pub = probe.create_publisher(UInt8, '/uav/landed_state', LATCHED_QOS)
    statuses = []
    probe.create_subscription(DiagnosticArray, '/diagnostics', lambda m: statuses.extend(m.status), 10)
    flight = node.core.flight
    pub.publish(UInt8(data=2))                                     # IN_AIR: where the flight stands, no boundary
    spin_until(lambda: flight.vehicle_report == 2, 'IN_AIR received')
    pub.publish(UInt8(data=1))                                     # ON_GROUND: the flight ends
    spin_until(lambda: node.core.flight_resets['vehicle_landed'] == 1, 'ON_GROUND ends the flight')
    assert flight.landed
    pub.publish(UInt8(data=3))                                     # TAKEOFF after ON_GROUND: a new flight
    spin_until(lambda: node.core.flight_resets['vehicle_takeoff'] == 1, 'TAKEOFF begins a flight')
    assert not flight.landed and sum(node.core.flight_resets.values()) == 2
    pub.publish(UInt8(data=9))                                     # not a MAV_LANDED_STATE: rejected, counted
    spin_until(lambda: node.diag.get('rejected_landed_state_range') == 1, 'a bad landed state rejected')
    assert flight.vehicle_report == 3

    def said_why() -> bool:
        for st in statuses:
            values = {kv.key: kv.value for kv in st.values}
            if (values.get('last_flight_reset', '').startswith('vehicle_takeoff')
                    and 'TAKEOFF' in values['last_flight_reset'] and values.get('landed_state') == 'TAKEOFF'
                    and values.get('flight_reset_vehicle_landed') == '1'):
                return True
        return False
    spin_until(said_why, '/diagnostics says the assistant reset at the vehicle\'s take-off, and why')
