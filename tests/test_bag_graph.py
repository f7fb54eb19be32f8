"""bag_record and bag_play in a real graph (subprocesses, private domain): record -> play -> record round trip."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import TwistStamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosgraph_msgs.msg import Clock

from assist_bags import msgs
from assist_bags.bagio import LATCHED, RELIABLE, SENSOR, BagReader
from assist_common.domains import private_domain_id

pytestmark = pytest.mark.graph
BIN = Path(sys.executable).parent
START = 1_700_000_000_000_000_000       # bag time of the first message (ns)
N = 40                                   # /pilot/cmd_vel messages at 20 Hz
TOPICS = ['/pilot/cmd_vel', '/camera/color/image_raw', '/sim/goal', '/note']


def other_tool_bag(path: Path, storage: str) -> Path:
    """A bag written with the rosbags writer directly (as another tool would), incl. a type this install lacks."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    other = get_typestore(Stores.EMPTY)
    other.register(get_types_from_msg('string text\nint32 n', 'my_pkg/msg/Note'))
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        cmd = w.add_connection('/pilot/cmd_vel', 'geometry_msgs/msg/TwistStamped', typestore=ts,
                               offered_qos_profiles=[RELIABLE])
        img = w.add_connection('/camera/color/image_raw', 'sensor_msgs/msg/Image', typestore=ts,
                               offered_qos_profiles=[SENSOR])
        goal = w.add_connection('/sim/goal', 'geometry_msgs/msg/PointStamped', typestore=ts,
                                offered_qos_profiles=[LATCHED])
        note = w.add_connection('/note', 'my_pkg/msg/Note', typestore=other)
        w.write(goal, START, ts.serialize_cdr(msgs.point_stamped(START, (8.0, 1.0, 0.9)),
                                              'geometry_msgs/msg/PointStamped'))
        for k in range(N):
            t = START + k * 50_000_000
            w.write(cmd, t, ts.serialize_cdr(msgs.twist_stamped(t, (0.01 * k, 0.5, -0.2)),
                                             'geometry_msgs/msg/TwistStamped'))
            if k % 8 == 0:
                rgb = np.full((64, 64, 3), k, np.uint8)
                w.write(img, t, ts.serialize_cdr(msgs.image(t, rgb), 'sensor_msgs/msg/Image'))
                w.write(note, t, other.serialize_cdr(other.types['my_pkg/msg/Note'](text='hi', n=k),
                                                     'my_pkg/msg/Note'))
    return path


def read(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """topic -> [(time ns, CDR bytes)] in order."""
    out: dict[str, list] = {}
    with BagReader(bag) as r:
        for topic, t, raw in r.messages():
            out.setdefault(topic, []).append((t, raw))
    return out


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_record_play_record_round_trip(start_node, tmp_path, storage):
    a = other_tool_bag(tmp_path / 'a', storage)
    b = tmp_path / 'b'
    rec = start_node('bag_record', {'output': str(b), 'topics': TOPICS, 'storage': storage,
                                    'discovery_period_s': 0.1})
    play = start_node('bag_play', {'bag': str(a), 'wait_for_subscribers': 3, 'delay_s': 0.0})
    assert play.proc.wait(timeout=120) == 0, play.log()
    time.sleep(1.0)                                  # let the last messages arrive
    assert rec.stop() == 0, rec.log()
    warnings = [ln for ln in play.log().splitlines() if 'skipping /note' in ln]
    assert len(warnings) == 1 and 'my_pkg/msg/Note is not installed' in warnings[0]
    src, got = read(a), read(b)
    assert '/note' not in got
    # reliable topics: every message, in order, byte for byte
    assert [raw for _, raw in got['/pilot/cmd_vel']] == [raw for _, raw in src['/pilot/cmd_vel']]
    assert [raw for _, raw in got['/sim/goal']] == [raw for _, raw in src['/sim/goal']]
    # best effort images: what arrived is in order and intact
    imgs = [raw for _, raw in got['/camera/color/image_raw']]
    assert len(imgs) >= 4 and all(raw in [r for _, r in src['/camera/color/image_raw']] for raw in imgs)
    # timing: the recorded intervals reproduce the bag's 50 ms spacing
    t_src = np.array([t for t, _ in src['/pilot/cmd_vel']]) * 1e-9
    t_got = np.array([t for t, _ in got['/pilot/cmd_vel']]) * 1e-9
    err = np.abs(np.diff(t_got) - np.diff(t_src))
    assert np.median(err) < 0.015, err
    assert abs((t_got[-1] - t_got[0]) - (t_src[-1] - t_src[0])) < 0.3
    with BagReader(b) as r:
        assert r.metadata['version'] == 9 and r.metadata['storage_identifier'] == storage
        assert r.topics['/sim/goal'].qos[0].durability.name == 'TRANSIENT_LOCAL'
        assert r.topics['/camera/color/image_raw'].qos[0].reliability.name == 'BEST_EFFORT'


def test_play_rate_offset_loop_remap_and_clock(ros, start_node, tmp_path, wait):
    a = other_tool_bag(tmp_path / 'a', 'mcap')
    lock = threading.Lock()
    cmds: list[tuple[float, float]] = []
    clock: list[int] = []

    def on_cmd(m):
        with lock:
            cmds.append((time.monotonic(), m.twist.linear.x))

    def on_clock(m):
        with lock:
            clock.append(m.clock.sec * 1_000_000_000 + m.clock.nanosec)
    subs = [ros.create_subscription(TwistStamped, '/replayed/cmd_vel', on_cmd, 50),
            ros.create_subscription(Clock, '/clock', on_clock,
                                    QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))]
    try:
        play = start_node('bag_play', {'bag': str(a), 'rate': 2.0, 'start_offset_s': 1.0, 'loop': True,
                                       'topics': ['/pilot/cmd_vel'], 'remap': ['/pilot/cmd_vel:=/replayed/cmd_vel'],
                                       'clock': True, 'wait_for_subscribers': 1, 'delay_s': 0.0})
        assert wait(lambda: len(cmds) >= 30, 60), play.log()
        assert play.stop() == 0
    finally:
        for s in subs:
            ros.destroy_subscription(s)
    with lock:
        xs = [x for _, x in cmds]
        times = [t for t, _ in cmds]
        ck = list(clock)
    # offset 1 s skips the first 20 of 40 messages; the loop starts again at the offset
    assert xs[:30] == pytest.approx([0.01 * k for k in list(range(20, 40)) + list(range(20, 30))])
    # rate 2: the 19 intervals of 50 ms of one pass take 0.475 s
    assert times[19] - times[0] == pytest.approx(19 * 0.05 / 2, abs=0.15)
    assert len(ck) > 20
    assert min(ck) >= START + 1_000_000_000 and max(ck) <= START + (N - 1) * 50_000_000
    first_pass = ck[: ck.index(max(ck)) + 1]
    assert first_pass == sorted(first_pass)


def test_killed_recorder_keeps_finished_files(start_node, tmp_path):
    a = other_tool_bag(tmp_path / 'a', 'mcap')
    b = tmp_path / 'b'
    rec = start_node('bag_record', {'output': str(b), 'topics': ['/pilot/cmd_vel'], 'split_duration_s': 0.5,
                                    'discovery_period_s': 0.1})
    play = start_node('bag_play', {'bag': str(a), 'loop': True, 'wait_for_subscribers': 1, 'delay_s': 0.0})
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        meta = b / 'metadata.yaml'
        if meta.exists() and meta.read_text().count('.mcap') >= 4:    # >= 2 finished files listed
            break
        time.sleep(0.2)
    os.killpg(rec.proc.pid, signal.SIGKILL)
    rec.proc.wait(10)
    play.stop()
    with BagReader(b) as r:
        assert len(r.files) >= 2
        xs = [r.deserialize(raw, '/pilot/cmd_vel').twist.linear.x for _, _, raw in r.messages()]
    assert len(xs) >= 10 and len(xs) == r.message_count
    assert set(np.round(xs, 2)) <= {round(0.01 * k, 2) for k in range(N)}


def test_play_refuses_bad_input_with_one_line(tmp_path):
    a = other_tool_bag(tmp_path / 'a', 'mcap')
    data = a / 'a.mcap'
    data.write_bytes(data.read_bytes()[:500])
    cases = [[str(a)], [str(tmp_path / 'none')], [str(other_tool_bag(tmp_path / 'c', 'mcap')), '--topics', '/x'],
             [str(tmp_path / 'c'), '--remap', 'nonsense']]
    for args in cases:
        proc = subprocess.run([str(BIN / 'bag_play'), *args], capture_output=True, text=True, timeout=60,
                              env=dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id())))
        assert proc.returncode == 1, (args, proc.stderr)
        assert 'Traceback' not in proc.stderr
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith('error:')]
        assert len(errors) == 1, proc.stderr


def test_recorder_closes_cleanly_on_sigterm(start_node, tmp_path):
    a = other_tool_bag(tmp_path / 'a', 'sqlite3')
    b = tmp_path / 'b'
    rec = start_node('bag_record', {'output': str(b), 'topics': ['/pilot/cmd_vel'], 'storage': 'sqlite3',
                                    'discovery_period_s': 0.1})
    play = start_node('bag_play', {'bag': str(a), 'wait_for_subscribers': 1, 'delay_s': 0.0})
    assert play.proc.wait(timeout=120) == 0
    time.sleep(0.5)
    rec.proc.send_signal(signal.SIGTERM)
    assert rec.proc.wait(timeout=30) == 0, rec.log()
    assert [raw for _, raw in read(b)['/pilot/cmd_vel']] == [raw for _, raw in read(a)['/pilot/cmd_vel']]
    assert not [p for p in b.iterdir() if p.name.startswith('.writing')]


def test_recorder_refuses_bad_input_with_one_line(tmp_path):
    (tmp_path / 'file').write_text('x')
    cases = [[str(tmp_path / 'file' / 'bag')], [str(tmp_path / 'ok'), '--storage', 'rosbag1'],
             ['--ros-args', '-p', f'output:={tmp_path / "ok2"}', '-p', "topics:=['']"]]
    for args in cases:
        proc = subprocess.run([str(BIN / 'bag_record'), *args], capture_output=True, text=True, timeout=60,
                              env=dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id())))
        assert proc.returncode == 1, (args, proc.stderr)
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith('error:')]
        assert len(errors) == 1 and 'Traceback' not in proc.stderr, proc.stderr
    assert not (tmp_path / 'ok').exists() and not (tmp_path / 'ok2').exists()
