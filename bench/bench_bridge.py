"""Bridge bench: /cmd_vel -> SET_POSITION_TARGET_LOCAL_NED latency through mavlink_bridge_node, and
the setpoint rate it holds with no command coming in.

The bridge runs as its own process (console script) on a private ROS domain; this process is
both the ROS publisher of /cmd_vel and a minimal ArduCopter endpoint on UDP loopback
(assist_sim.testing.SilentAutopilot: HEARTBEAT in GUIDED and armed, ATTITUDE heading East) that
timestamps every setpoint on arrival. Each command carries a
unique forward speed, so every setpoint is matched to the command that caused it.

Arrival times are the kernel's receive timestamps on the autopilot's socket (SO_TIMESTAMPNS), so the
figure is publish -> datagram at the vehicle, and does not include how long this process's own
receive thread takes to wake up (a real autopilot is another machine). Send and arrival times are
both CLOCK_REALTIME.
"""
from __future__ import annotations

import math
import os
import random
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from assist_sim.testing import SilentAutopilot, free_udp_port, stop_process

N_COMMANDS = 1000          # p99 = the 10th-worst: a steadier tail estimate than 400 samples
N_WARMUP = 50            # commands sent and discarded first: DDS discovery/matching and first-use allocations
COMMAND_RATE_HZ = 50.0
HOLD_WINDOW_S = 4.0
SETPOINT_RATE_HZ = 10.0


def run() -> list[dict]:
    """Measure the bridge; rows of name/value/unit/target."""
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from rclpy.context import Context
    from rclpy.node import Node

    from assist_sim.ros_common import RELIABLE_QOS

    domain = random.Random(os.getpid() ^ time.monotonic_ns()).randint(200, 230)
    port = free_udp_port()
    exe = Path(sys.executable).parent / 'mavlink_bridge_node'
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    proc = subprocess.Popen([str(exe), '--ros-args', '-p', f'connection:=udpin:127.0.0.1:{port}',
                             '-p', f'setpoint_rate_hz:={SETPOINT_RATE_HZ}'], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    ap = SilentAutopilot(port, yaw_ned_rad=math.pi / 2)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('bench_bridge', context=ctx)
    pub = node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
    try:
        deadline = time.monotonic() + 60.0
        while (pub.get_subscription_count() == 0 or not ap.setpoints()) and time.monotonic() < deadline:
            time.sleep(0.05)
        if pub.get_subscription_count() == 0 or not ap.setpoints():
            raise RuntimeError('bridge did not come up (no subscriber or no setpoints)')
        time.sleep(1.0)
        # 1) latency: unique forward speeds (FLU x = NED vy for a vehicle heading East); the first
        #    N_WARMUP commands warm the path up and are not timed
        sent: dict[int, float] = {}
        msg = TwistStamped()
        msg.header.frame_id = 'base_link'
        period = 1.0 / COMMAND_RATE_HZ
        t_next = time.monotonic()
        for i in range(1, N_WARMUP + N_COMMANDS + 1):
            msg.twist.linear.x = i * 1e-3
            msg.header.stamp = node.get_clock().now().to_msg()
            sent[i] = time.time()
            pub.publish(msg)
            t_next += period
            time.sleep(max(0.0, t_next - time.monotonic()))
        time.sleep(0.5)
        first_arrival: dict[int, float] = {}
        for t, _vx, vy in ap.setpoints():
            i = int(round(vy * 1e3))
            if i > N_WARMUP and i in sent and abs(vy - i * 1e-3) < 1e-6 and t >= sent[i]:
                first_arrival.setdefault(i, t)
        lat_ms = np.array([(first_arrival[i] - sent[i]) * 1e3 for i in sorted(first_arrival)])
        # 2) setpoint rate held with no command (zero velocity after the command timeout)
        time.sleep(1.0)
        t0 = time.time()
        time.sleep(HOLD_WINDOW_S)
        t1 = time.time()
        window = [t for t, _vx, _vy in ap.setpoints() if t0 <= t <= t1]
        gaps_ms = np.diff(window) * 1e3 if len(window) > 1 else np.array([math.inf])
        rate = (len(window) - 1) / (window[-1] - window[0]) if len(window) > 1 else 0.0
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        ap.close()
        stop_process(proc)
    if lat_ms.size == 0:
        raise RuntimeError('no setpoint matched a command')
    return [
        dict(name='cmd_vel->setpoint latency p50', value=float(np.percentile(lat_ms, 50)), unit='ms', target=''),
        dict(name='cmd_vel->setpoint latency p99', value=float(np.percentile(lat_ms, 99)), unit='ms',
             target='<= 2'),
        dict(name='commands delivered as setpoints', value=f'{lat_ms.size}/{N_COMMANDS}', unit='',
             target=f'{N_COMMANDS}/{N_COMMANDS}'),
        dict(name='setpoint rate held (no input)', value=float(rate), unit='Hz', target=f'{SETPOINT_RATE_HZ:g}'),
        dict(name='setpoint max gap (no input)', value=float(np.max(gaps_ms)), unit='ms',
             target=f'< {3000:d} (GUID_TIMEOUT)'),
    ]


if __name__ == '__main__':
    for row in run():
        print(row)
