"""Bridge bench: /cmd_vel -> SET_POSITION_TARGET_LOCAL_NED through mavlink_bridge_node: the latency of
a change, the setpoint rate out under a ~900 Hz command flood, and the rate held with no command.

The bridge sends the latest command at setpoint_rate_hz plus at most one immediate send of a changed
command per period, so: (1) commands at 8 Hz (slower than the 10 Hz schedule) each
go out at once, and their publish -> datagram latency is timed; (2) a flood of ~900 changing commands
per second must leave at no more than twice setpoint_rate_hz; (3) with no command, zero velocity at
setpoint_rate_hz; (4) a one-way link loss while the pilot keeps commanding: how soon the sim's
ArduCopter stand-in is at zero velocity (the bridge core against it in-process).

The bridge runs as its own process (console script) on a private ROS domain; this process is
both the ROS publisher of /cmd_vel and a minimal ArduCopter endpoint on UDP loopback
(assist_sim.testing.SilentAutopilot: HEARTBEAT in GUIDED and armed, ATTITUDE heading East) that
timestamps every setpoint on arrival. Each timed command carries a unique forward speed, so every
setpoint is matched to the command that caused it.

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

N_COMMANDS = 200           # timed changes; p99 = the 2nd-worst
N_WARMUP = 20             # commands sent and discarded first: DDS discovery/matching and first-use allocations
COMMAND_RATE_HZ = 8.0     # slower than the setpoint schedule: every change may leave at once
FLOOD_RATE_HZ = 900.0
FLOOD_S = 3.0
HOLD_WINDOW_S = 4.0
SETPOINT_RATE_HZ = 10.0


def _publish_at(pub, msg, node, values, rate_hz: float) -> tuple[dict[int, float], float]:
    """Publish one command per value at rate_hz; send wall times by index and the achieved rate."""
    sent: dict[int, float] = {}
    period = 1.0 / rate_hz
    t_next = t0 = time.monotonic()
    for i, vx in values:
        msg.twist.linear.x = vx
        msg.header.stamp = node.get_clock().now().to_msg()
        sent[i] = time.time()
        pub.publish(msg)
        t_next += period
        time.sleep(max(0.0, t_next - time.monotonic()))
    return sent, len(sent) / (time.monotonic() - t0)


def _brake_after_link_loss(runs: int = 3) -> tuple[float, float]:
    """One-way link loss with the pilot still commanding 1 m/s: (worst ms from the bridge declaring the
    loss to the stand-in at zero velocity, worst s from the cut to it), over `runs` runs of the core
    against the sim's ArduCopter stand-in (GUID_TIMEOUT 30 s, so only the bridge's brake can stop it)."""
    import threading

    from assist_bridge.bridge_core import BridgeConfig, MavlinkBridge
    from assist_sim.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleConfig
    from assist_sim.testing import KinematicWorld

    after_decl, after_cut = [], []
    for _ in range(runs):
        port = free_udp_port()
        declared: list[float] = []
        bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}', takeoff_altitude_m=1.0),
                               on_link=lambda up, _why, declared=declared:
                               None if up else declared.append(time.monotonic()))
        world = KinematicWorld()
        vehicle = MavlinkVehicle(world, f'udpout:127.0.0.1:{port}',
                                 MavlinkVehicleConfig(ekf_ready_delay_s=0.3, guid_timeout_s=30.0))
        stop = threading.Event()

        def step_vehicle(stop=stop, vehicle=vehicle):
            while not stop.is_set():
                vehicle.step(0.02)
                time.sleep(0.02)

        def pilot(stop=stop, bridge=bridge):
            while not stop.is_set():
                bridge.set_command([1.0, 0.0, 0.0])
                time.sleep(0.05)
        threads = [threading.Thread(target=step_vehicle, daemon=True), threading.Thread(target=pilot, daemon=True)]
        bridge.start()
        threads[0].start()
        try:
            if not bridge.wait_heartbeat(10.0):
                raise RuntimeError('stand-in never connected')
            deadline = time.monotonic() + 20.0
            while not bridge.arm()[0]:
                if time.monotonic() > deadline:
                    raise RuntimeError('stand-in never armed')
                time.sleep(0.2)
            if not bridge.takeoff(1.0)[0]:
                raise RuntimeError('takeoff refused')
            while bridge.snapshot()['taking_off'] and time.monotonic() < deadline:
                time.sleep(0.02)
            threads[1].start()
            while world.vel[0] < 0.9 and time.monotonic() < deadline:
                time.sleep(0.01)
            t_cut = time.monotonic()
            vehicle.set_telemetry_muted(True)   # one-way loss: the vehicle still hears the bridge
            while (not declared or np.linalg.norm(world.vel) != 0.0) and time.monotonic() < t_cut + 10.0:
                time.sleep(0.001)
            if not declared or np.linalg.norm(world.vel) != 0.0:
                raise RuntimeError('the vehicle was not stopped after the link loss')
            t_stop = time.monotonic()
            after_decl.append((t_stop - declared[0]) * 1e3)
            after_cut.append(t_stop - t_cut)
        finally:
            stop.set()
            for t in threads:
                if t.is_alive():
                    t.join()
            bridge.close()
            vehicle.close()
    return max(after_decl), max(after_cut)


def run() -> list[dict]:
    """Measure the bridge; rows of name/value/unit/target."""
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from rclpy.context import Context
    from rclpy.node import Node

    from assist_common.ros_io import RELIABLE_QOS

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
        msg = TwistStamped()
        msg.header.frame_id = 'base_link'
        # 1) latency of a change: unique forward speeds (FLU x = NED vy for a vehicle heading East)
        sent, _ = _publish_at(pub, msg, node, [(i, i * 1e-3) for i in range(1, N_WARMUP + N_COMMANDS + 1)],
                              COMMAND_RATE_HZ)
        time.sleep(0.5)
        first_arrival: dict[int, float] = {}
        for t, _vx, vy in ap.setpoints():
            i = int(round(vy * 1e3))
            if i > N_WARMUP and i in sent and abs(vy - i * 1e-3) < 1e-6 and t >= sent[i]:
                first_arrival.setdefault(i, t)
        lat_ms = np.array([(first_arrival[i] - sent[i]) * 1e3 for i in sorted(first_arrival)])
        # 2) flood: ~900 changing commands per second (distinct from the values above)
        time.sleep(1.0)
        n_flood = int(FLOOD_RATE_HZ * FLOOD_S)
        t0 = time.time()
        _, flood_in_hz = _publish_at(pub, msg, node, [(k, 0.5 + 0.4 * math.sin(k * 0.01)) for k in range(n_flood)],
                                     FLOOD_RATE_HZ)
        t1 = time.time()
        flood_out = [t for t, _vx, _vy in ap.setpoints() if t0 <= t <= t1]
        flood_out_hz = (len(flood_out) - 1) / (flood_out[-1] - flood_out[0]) if len(flood_out) > 1 else 0.0
        arr = np.array(flood_out)
        flood_max_1s = int(max((np.searchsorted(arr, t + 1.0, side='right') - k for k, t in enumerate(arr)),
                               default=0))
        # 3) setpoint rate held with no command (zero velocity after the command timeout)
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
    brake_ms, brake_s = _brake_after_link_loss()
    return [
        dict(name='change->setpoint latency p50 (8 Hz commands)', value=float(np.percentile(lat_ms, 50)), unit='ms',
             target=''),
        dict(name='change->setpoint latency p99 (8 Hz commands)', value=float(np.percentile(lat_ms, 99)), unit='ms',
             target='<= 2'),
        dict(name='changes delivered as setpoints', value=f'{lat_ms.size}/{N_COMMANDS}', unit='',
             target=f'{N_COMMANDS}/{N_COMMANDS}'),
        dict(name='flood: /cmd_vel published', value=float(flood_in_hz), unit='Hz', target=f'~{FLOOD_RATE_HZ:g}'),
        dict(name='flood: setpoints out', value=float(flood_out_hz), unit='/s',
             target=f'~{2 * SETPOINT_RATE_HZ:g} (2 per period)'),
        dict(name='flood: most setpoints in any 1 s', value=flood_max_1s, unit='',
             target=f'<= {2 * (SETPOINT_RATE_HZ + 1):g} (2 per period; 1 s touches 11)'),
        dict(name='setpoint rate held (no input)', value=float(rate), unit='Hz', target=f'{SETPOINT_RATE_HZ:g}'),
        dict(name='setpoint max gap (no input)', value=float(np.max(gaps_ms)), unit='ms',
             target=f'< {3000:d} (GUID_TIMEOUT)'),
        dict(name='link loss: declared -> vehicle stopped (worst of 3)', value=float(brake_ms), unit='ms', target=''),
        dict(name='link loss: cut -> vehicle stopped (worst of 3)', value=float(brake_s), unit='s',
             target='<= link_timeout_s (2) + 0.02'),
    ]


if __name__ == '__main__':
    for row in run():
        print(row)
