"""MAVLink fuzzer against the bridge: random bytes, well-formed frames with arbitrary field values
(NaN, inf, huge, wrong enums, other system ids), mutated frames (bit flips, truncation, splices,
forged lengths and flags), from the locked vehicle's address and from spoofed sources (another port,
another host).

Contract: the bridge stays alive (no exception out of poll/tick); what it publishes is
finite; a spoofed source changes nothing, is counted and never receives a byte; the bridge never
sends a mode change on its own; every setpoint it sends is finite and inside the clamps. The core
runs in-process on a fake clock (so the link never times out between examples); one graph-level run
throws a seeded corpus at mavlink_bridge_node itself.
"""
from __future__ import annotations

import math
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from assist_bridge.bridge_core import BridgeConfig, MavlinkBridge
from assist_common.mavlink_io import mavlink
from assist_sim.testing import SilentAutopilot, free_udp_port

SETTINGS = settings(max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
# messages the bridge reads, plus a few it does not
MESSAGES = [mavlink.MAVLink_heartbeat_message, mavlink.MAVLink_attitude_message,
            mavlink.MAVLink_local_position_ned_message, mavlink.MAVLink_command_ack_message,
            mavlink.MAVLink_statustext_message, mavlink.MAVLink_extended_sys_state_message,
            mavlink.MAVLink_sys_status_message, mavlink.MAVLink_global_position_int_message,
            mavlink.MAVLink_set_position_target_local_ned_message, mavlink.MAVLink_command_long_message,
            mavlink.MAVLink_param_set_message, mavlink.MAVLink_setup_signing_message]
INT_RANGES = {'uint8_t': (0, 255), 'int8_t': (-128, 127), 'uint16_t': (0, 65535), 'int16_t': (-32768, 32767),
              'uint32_t': (0, 2**32 - 1), 'int32_t': (-2**31, 2**31 - 1), 'uint64_t': (0, 2**64 - 1),
              'int64_t': (-2**63, 2**63 - 1)}
FLOATS = st.one_of(st.floats(width=32, allow_nan=True, allow_infinity=True),
                   st.sampled_from([math.nan, math.inf, -math.inf, 1e38, -1e38, 3.4e38, 0.0, -0.0, 1e-45]))


def _field(ftype: str, length: int):
    if ftype in ('float', 'double'):
        base = FLOATS if ftype == 'float' else st.floats(allow_nan=True, allow_infinity=True)
    elif ftype == 'char':
        return st.binary(max_size=length or 1)
    else:
        lo, hi = INT_RANGES[ftype]
        base = st.one_of(st.integers(lo, hi), st.sampled_from([lo, hi, 0]))
    return st.lists(base, min_size=length, max_size=length) if length else base


@st.composite
def frames(draw, locked_ids: bool = False):
    """A well-formed MAVLink 2 frame (valid CRC) of a drawn message type with drawn field values."""
    cls = draw(st.sampled_from(MESSAGES))
    values = [draw(_field(t, n)) for t, n in zip(cls.fieldtypes, cls.array_lengths)]
    if cls is mavlink.MAVLink_heartbeat_message and draw(st.booleans()):
        values[1] = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA            # often a plausible autopilot
    system, component = (1, 1) if locked_ids or draw(st.booleans()) else \
        (draw(st.integers(0, 255)), draw(st.integers(0, 255)))
    mav = mavlink.MAVLink(None, system, component)
    try:
        return bytes(cls(*values).pack(mav))
    except (struct.error, OverflowError, TypeError, ValueError):
        return bytes(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(mav))


@st.composite
def mutated(draw):
    """A valid frame, then bit flips / truncation / splice / forged length or flags."""
    data = bytearray(draw(frames()))
    kind = draw(st.sampled_from(['flip', 'truncate', 'splice', 'length', 'flags', 'repeat']))
    if kind == 'flip':
        for pos in draw(st.lists(st.integers(0, len(data) - 1), min_size=1, max_size=4)):
            data[pos] ^= 1 << draw(st.integers(0, 7))
    elif kind == 'truncate':
        data = data[:draw(st.integers(0, len(data) - 1))]
    elif kind == 'splice':
        other = draw(frames())
        data = data[:draw(st.integers(0, len(data)))] + other[draw(st.integers(0, len(other))):]
    elif kind == 'length':
        data[1] = draw(st.integers(0, 255))
    elif kind == 'flags':
        data[2] = draw(st.integers(0, 255))        # incompat flags: signed bit and unknown bits
    else:
        data = data * draw(st.integers(2, 40))
    return bytes(data)


PAYLOADS = st.one_of(st.binary(max_size=600), frames(), frames(locked_ids=True), mutated())
SOURCES = st.sampled_from(['vehicle', 'vehicle', 'spoof_port', 'spoof_host'])


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Rig:
    """The bridge core on UDP loopback, a vehicle socket it is locked onto, and two spoofers."""

    def __init__(self):
        self.clock = FakeClock()
        self.port = free_udp_port()
        self.odoms = []
        self.bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{self.port}', link_timeout_s=30.0,
                                                 max_speed_mps=2.0),
                                    clock=self.clock, on_odometry=self.odoms.append)
        self.socks = {}
        for name, host in (('vehicle', '127.0.0.1'), ('spoof_port', '127.0.0.1'), ('spoof_host', '127.0.0.2')):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind((host, 0))
            s.setblocking(False)
            self.socks[name] = s
        self.vehicle_rx = mavlink.MAVLink(None, 1, 1)
        self.vehicle_rx.robust_parsing = True
        self.sent_to_vehicle = []
        mav = mavlink.MAVLink(None, 1, 1)
        self.send('vehicle', mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                  mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, 4).pack(mav))
        self.send('vehicle', mav.attitude_encode(0, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0).pack(mav))
        self.step()
        assert self.bridge.peer is not None and self.bridge.peer.address == self.socks['vehicle'].getsockname()

    def send(self, source: str, payload: bytes) -> None:
        try:
            self.socks[source].sendto(payload, ('127.0.0.1', self.port))
        except OSError:              # e.g. EMSGSIZE for a repeated frame over 64 KiB: not sent
            pass

    def step(self) -> None:
        self.clock.t += 0.013
        self.bridge.poll()
        self.bridge.tick()
        self.bridge.set_command([3.0, -3.0, 3.0])     # clamps apply; sent only in GUIDED + armed
        self.drain_vehicle()

    def drain_vehicle(self) -> None:
        while True:
            try:
                data = self.socks['vehicle'].recv(65535)
            except BlockingIOError:
                return
            msgs = self.vehicle_rx.parse_buffer(data) or []
            self.sent_to_vehicle += [m for m in msgs if m.get_type() != 'BAD_DATA']

    def spoofers_received(self) -> int:
        n = 0
        for name in ('spoof_port', 'spoof_host'):
            while True:
                try:
                    self.socks[name].recv(65535)
                    n += 1
                except BlockingIOError:
                    break
        return n

    def close(self):
        for s in self.socks.values():
            s.close()
        self.bridge.close()


@pytest.fixture(scope='module')
def rig():
    r = Rig()
    yield r
    r.close()


def _status(bridge):
    st = bridge.status
    return (st.link_up, st.mode, st.armed, st.last_heartbeat, None if st.position_ned is None else
            tuple(st.position_ned), st.attitude, st.landed_state, bridge.peer)


@SETTINGS
@given(datagrams=st.lists(st.tuples(SOURCES, PAYLOADS), min_size=1, max_size=8))
def test_bridge_core_survives_and_ignores_spoofed_sources(rig, datagrams):
    b = rig.bridge
    before = _status(b)
    n_odom = len(rig.odoms)
    for source, payload in datagrams:
        rig.send(source, payload)
    rig.step()
    assert b.counters['loop_errors'] == 0
    if all(source != 'vehicle' for source, _ in datagrams):
        assert _status(b) == before, 'a spoofed source changed the status'
    assert b.peer == before[-1], 'the lock moved while the link was up'
    assert rig.spoofers_received() == 0, 'a spoofed source received data'
    st = b.status
    for arr in (st.position_ned, st.velocity_ned, st.attitude, st.rates_frd):
        assert arr is None or np.all(np.isfinite(np.asarray(arr, dtype=float)))
    for o in rig.odoms[n_odom:]:
        for v in (o.position, o.quaternion, o.linear_velocity, o.angular_velocity):
            assert np.all(np.isfinite(v))
    for m in rig.sent_to_vehicle:
        if m.get_type() == 'COMMAND_LONG':
            assert m.command != mavlink.MAV_CMD_DO_SET_MODE, 'the bridge changed the mode on its own'
        elif m.get_type() == 'SET_MODE':
            raise AssertionError('the bridge sent SET_MODE on its own')
        elif m.get_type() == 'SET_POSITION_TARGET_LOCAL_NED':
            v = np.array([m.vx, m.vy, m.vz])
            assert np.all(np.isfinite(v)) and np.linalg.norm(v) <= 2.0 + 1e-5
            assert math.isfinite(m.yaw)
    rig.sent_to_vehicle.clear()


def test_each_kind_of_rejection_is_counted(rig):
    """A spoofed port, a spoofed host, another system id on the vehicle's address, garbage: each counted."""
    c = rig.bridge.counters
    before = {k: c[k] for k in ('rx_foreign_address', 'rx_foreign_id', 'rx_bad_data')}
    mav = mavlink.MAVLink(None, 1, 1)
    other = mavlink.MAVLink(None, 42, 1)
    rig.send('spoof_port', mav.heartbeat_encode(2, 3, 0, 9, 4).pack(mav))
    rig.send('spoof_host', mav.heartbeat_encode(2, 3, 0, 9, 4).pack(mav))
    rig.send('vehicle', other.heartbeat_encode(2, 3, 0, 9, 4).pack(other))
    rig.send('vehicle', b'not a MAVLink frame')
    rig.step()
    assert c['rx_foreign_address'] - before['rx_foreign_address'] == 2
    assert c['rx_foreign_id'] - before['rx_foreign_id'] == 1
    assert c['rx_bad_data'] > before['rx_bad_data'] and c['loop_errors'] == 0
    assert rig.bridge.status.mode != 'LAND' and rig.spoofers_received() == 0


# ---------------------------------------------------------------------- graph level
def _corpus(rng: np.random.Generator, n: int) -> list[bytes]:
    """Seeded random and mutated frames (the graph run cannot use hypothesis' shrinking anyway)."""
    mav = mavlink.MAVLink(None, 1, 1)
    good = [mav.heartbeat_encode(2, 3, 0x81, 5, 4).pack(mav), mav.attitude_encode(0, math.nan, 0, 0, 0, 0, 0).pack(mav),
            mav.local_position_ned_encode(0, math.inf, 0, -1e38, 0, 0, 0).pack(mav),
            mav.statustext_encode(4, b'\xff' * 50).pack(mav), mav.command_ack_encode(400, 0).pack(mav),
            mav.heartbeat_encode(2, 3, 0x81, 9, 4).pack(mav)]
    out = []
    for _ in range(n):
        kind = rng.integers(0, 4)
        if kind == 0:
            out.append(rng.bytes(int(rng.integers(0, 400))))
        else:
            f = bytearray(good[int(rng.integers(0, len(good)))])
            if kind == 2:
                for _ in range(int(rng.integers(1, 4))):
                    f[int(rng.integers(0, len(f)))] ^= 1 << int(rng.integers(0, 8))
            elif kind == 3:
                f = f[:int(rng.integers(0, len(f)))]
            out.append(bytes(f))
    return out


def udp_backlog(port: int) -> int | None:
    """Bytes waiting in the receive queue of the local UDP socket bound to `port` (Linux /proc/net/udp; None when
    there is no such socket or no /proc)."""
    try:
        lines = Path('/proc/net/udp').read_text().splitlines()[1:]
    except OSError:
        return None
    for line in lines:
        fields = line.split()
        if int(fields[1].split(':')[1], 16) == port:
            return int(fields[4].split(':')[1], 16)
    return None


@pytest.mark.graph
def test_bridge_node_under_fuzz(ros, start_node, wait):
    """mavlink_bridge_node: 1500 spoofed and 500 on-link fuzzed datagrams; alive, locked, still flying commands."""
    from geometry_msgs.msg import TwistStamped
    from diagnostic_msgs.msg import DiagnosticArray

    from assist_common.ros_io import RELIABLE_QOS, fill_twist

    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}'})
    vehicle = SilentAutopilot(port)          # GUIDED, armed, heading north
    diag = {}
    sub = ros.create_subscription(DiagnosticArray, '/diagnostics',
                                  lambda m: [diag.update({kv.key: kv.value for kv in s.values})
                                             for s in m.status if s.name.endswith('mavlink_bridge_node')], 10)
    pub = ros.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
    spoof = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoof.bind(('127.0.0.1', 0))
    spoof.setblocking(False)
    try:
        assert wait(lambda: diag.get('link') == 'up', 60.0), bridge.log()
        rng = np.random.default_rng(9)
        for i, payload in enumerate(_corpus(rng, 2000)):
            if i % 4 == 0:
                vehicle.conn.port.sendto(payload, ('127.0.0.1', port))   # on the locked address
            else:
                spoof.sendto(payload, ('127.0.0.1', port))
            if i % 100 == 99:         # all at once would overflow the bridge socket's receive buffer on a loaded
                wait(lambda: udp_backlog(port) in (0, None), 10.0)    # machine: let the bridge read them first
        time.sleep(2.0)
        assert bridge.proc.poll() is None, bridge.log()[-2000:]
        received = 0
        while True:
            try:
                spoof.recv(65535)
                received += 1
            except BlockingIOError:
                break
        assert received == 0, 'the spoofer received data from the bridge'
        assert wait(lambda: int(diag.get('rx_foreign_address', 0)) >= 750, 20.0), diag
        assert int(diag.get('loop_errors', 0)) == 0 and diag.get('link') == 'up'
        assert int(diag.get('rx_bad_data', 0)) > 0
        # it still flies commands, and never asked the vehicle for a mode change
        msg = TwistStamped()
        msg.header.frame_id = 'base_link'
        assert wait(lambda: (pub.publish(fill_twist(msg, [0.77, 0.0, 0.0])) or True)
                    and any(abs(vx - 0.77) < 1e-4 for _, vx, _ in vehicle.setpoints()), 20.0)
        assert mavlink.MAV_CMD_DO_SET_MODE not in vehicle.commands()
        assert all(math.isfinite(vx) and math.isfinite(vy) for _, vx, vy in vehicle.setpoints())
    finally:
        spoof.close()
        ros.destroy_subscription(sub)
        ros.destroy_publisher(pub)
        vehicle.close()
