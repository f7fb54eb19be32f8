"""Bag container layer (no ROS graph): real rosbag2 bags, our writer's output, damaged bags, CLI errors."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from assist_bags import msgs
from assist_bags.bagio import CONTRACT_TOPICS, BagError, BagReader, BagWriter

FIXTURES = Path(__file__).parent / 'fixtures' / 'rosbag2'
BIN = Path(sys.executable).parent

# (fixture, messages the metadata lists): every real bag is read completely
REAL = [('talker_mcap_v4', 20), ('talker_sqlite3_v4', 20), ('rewriter_a_mcap_v5', 150), ('cdr_test_mcap_v7', 7),
        ('service_events_sqlite3_v8', 10)]


@pytest.mark.parametrize('name,count', REAL)
def test_reads_every_message_of_real_rosbag2_bags(name, count):
    meta = yaml.safe_load((FIXTURES / name / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['message_count'] == count
    with BagReader(FIXTURES / name) as r:
        got = list(r.messages())
        assert len(got) == count == r.message_count
        times = [t for _, t, _ in got]
        assert times == sorted(times)
        per_topic = {t['topic_metadata']['name']: t['message_count'] for t in meta['topics_with_message_count']}
        assert {k: v.count for k, v in r.topics.items() if v.count} == {k: v for k, v in per_topic.items() if v}


@pytest.mark.parametrize('name', ['talker_mcap_v4', 'talker_sqlite3_v4'])
def test_real_talker_bag_decodes(name):
    with BagReader(FIXTURES / name) as r:
        r.check_definitions(['/topic'])
        texts = [r.deserialize(raw, '/topic').data for _, _, raw in r.messages(['/topic'])]
    assert texts == [f'Hello, world! {i}' for i in range(10)]


def test_other_serialisation_format_is_refused():
    with pytest.raises(BagError, match="'wrong_format', not cdr"):
        BagReader(FIXTURES / 'wrong_format_mcap_v6').open()


def test_other_distros_definition_is_detected():
    with BagReader(FIXTURES / 'service_events_sqlite3_v8') as r:
        r.check_definitions(['/test_topic1'])     # test_msgs: not installed here, nothing to compare
        with pytest.raises(BagError, match='WriteSplitEvent differs from this install'):
            r.check_definitions(['/events/write_split'])


def _write(path: Path, storage: str, n: int = 60, **kw) -> BagWriter:
    w = BagWriter(path, storage=storage, **kw)
    for t in ('/cmd_vel', '/camera/depth/image_raw', '/sim/goal'):
        w.add_topic(t, *CONTRACT_TOPICS[t])
    w.write_msg('/sim/goal', 10**9, msgs.point_stamped(10**9, (4.0, 1.0, 0.8)))
    for k in range(n):
        t = 10**9 + k * 50_000_000
        w.write_msg('/cmd_vel', t, msgs.twist_stamped(t, (k * 0.01, -1.0, 0.5)))
        w.write_msg('/camera/depth/image_raw', t, msgs.image(t, np.full((4, 5), k, np.float32)))
    return w


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_writer_round_trip_with_splits_and_v9_metadata(tmp_path, storage):
    bag = tmp_path / 'b'
    _write(bag, storage, split_duration_ns=1_000_000_000).close()
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['version'] == 9 and meta['storage_identifier'] == storage
    assert len(meta['relative_file_paths']) == 3            # 3 s of messages, a file per second
    assert meta['message_count'] == 121
    topics = {t['topic_metadata']['name']: t for t in meta['topics_with_message_count']}
    cmd = topics['/cmd_vel']['topic_metadata']
    assert cmd['type'] == 'geometry_msgs/msg/TwistStamped' and cmd['type_description_hash'].startswith('RIHS01_')
    assert cmd['offered_qos_profiles'][0]['reliability'] == 'reliable'
    depth_qos = topics['/camera/depth/image_raw']['topic_metadata']['offered_qos_profiles'][0]
    assert depth_qos['reliability'] == 'best_effort'
    assert topics['/sim/goal']['topic_metadata']['offered_qos_profiles'][0]['durability'] == 'transient_local'
    with BagReader(bag) as r:
        got = [(topic, t, r.deserialize(raw, topic)) for topic, t, raw in r.messages()]
    cmds = [(t, m) for topic, t, m in got if topic == '/cmd_vel']
    assert [t for t, _ in cmds] == [10**9 + k * 50_000_000 for k in range(60)]
    assert [m.twist.linear.x for _, m in cmds] == pytest.approx([k * 0.01 for k in range(60)])
    depth = [m for topic, _, m in got if topic == '/camera/depth/image_raw']
    assert msgs.image_array(depth[7]).tolist() == np.full((4, 5), 7, np.float32).tolist()


def test_official_mcap_reader_decodes_our_bags(tmp_path):
    """Our MCAP files decode with the official mcap + mcap-ros2-support readers (another implementation)."""
    from mcap import reader  # test-only dependency (requirements.txt)
    from mcap_ros2 import decoder
    bag = tmp_path / 'b'
    _write(bag, 'mcap', n=5).close()
    with open(bag / 'b_0.mcap', 'rb') as fh:
        got = [(ch.topic, sch.name, m) for sch, ch, _, m in
               reader.make_reader(fh, decoder_factories=[decoder.DecoderFactory()]).iter_decoded_messages()]
    assert len(got) == 11
    cmd = [m for topic, _, m in got if topic == '/cmd_vel']
    assert [c.twist.linear.y for c in cmd] == [-1.0] * 5
    assert {name for _, name, _ in got} == {'geometry_msgs/msg/TwistStamped', 'sensor_msgs/msg/Image',
                                            'geometry_msgs/msg/PointStamped'}


def test_unclosed_writer_loses_at_most_the_file_being_written(tmp_path):
    bag = tmp_path / 'b'
    w = _write(bag, 'mcap', split_duration_ns=1_000_000_000)   # never closed: as if the process was killed
    with BagReader(bag) as r:
        n = sum(1 for _ in r.messages())
    assert n == 1 + 2 * 20 * 2     # goal + the two finished 1 s files; the open third file (40) is lost
    w.abort()


def test_atomic_writer_leaves_nothing_on_error(tmp_path):
    bag = tmp_path / 'b'
    with pytest.raises(RuntimeError):
        with _write(bag, 'mcap', atomic=True):
            raise RuntimeError('boom')
    assert not bag.exists() and list(tmp_path.iterdir()) == []


def test_unwritable_output_and_existing_bag(tmp_path):
    (tmp_path / 'file').write_text('x')
    with pytest.raises(BagError, match='cannot create output directory'):
        BagWriter(tmp_path / 'file' / 'bag')
    _write(tmp_path / 'b', 'mcap').close()
    with pytest.raises(BagError, match='exists already'):
        BagWriter(tmp_path / 'b')


@pytest.fixture
def damaged(tmp_path):
    """Bags broken in the ways users meet: truncated, corrupt, missing file, missing metadata, not a bag."""
    out = {}
    for storage in ('mcap', 'sqlite3'):
        src = tmp_path / f'ok_{storage}'
        _write(src, storage).close()
        data = next(p for p in src.iterdir() if p.suffix in ('.mcap', '.db3'))
        trunc = tmp_path / f'truncated_{storage}'
        shutil.copytree(src, trunc)
        f = trunc / data.name
        f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
        out[f'truncated_{storage}'] = trunc
        corrupt = tmp_path / f'corrupt_{storage}'
        shutil.copytree(src, corrupt)
        f = corrupt / data.name
        raw = bytearray(f.read_bytes())
        raw[: 64] = os.urandom(64)
        f.write_bytes(bytes(raw))
        out[f'corrupt_{storage}'] = corrupt
    gone = tmp_path / 'missing_file'
    shutil.copytree(tmp_path / 'ok_mcap', gone)
    (gone / 'ok_mcap_0.mcap').unlink()
    out['missing_file'] = gone
    nometa = tmp_path / 'no_metadata'
    nometa.mkdir()
    out['no_metadata'] = nometa
    out['missing_bag'] = tmp_path / 'nothing_here'
    return out


CASES = ['truncated_mcap', 'truncated_sqlite3', 'corrupt_mcap', 'corrupt_sqlite3', 'missing_file', 'no_metadata',
         'missing_bag']


@pytest.mark.parametrize('case', CASES)
def test_damaged_bags_give_bag_error(damaged, case):
    with pytest.raises(BagError) as err:
        with BagReader(damaged[case]) as r:
            for _ in r.messages():
                pass
    assert '\n' not in str(err.value) and str(damaged[case]) in str(err.value)


@pytest.mark.parametrize('tool', ['plot_flight', 'replay_assist'])
@pytest.mark.parametrize('case', ['truncated_mcap', 'corrupt_sqlite3', 'missing_bag'])
def test_cli_one_line_error_on_damaged_bag(damaged, tmp_path, tool, case):
    out = tmp_path / f'out_{tool}_{case}'
    proc = subprocess.run([str(BIN / tool), str(damaged[case]), '--out', str(out)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 1
    assert 'Traceback' not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith('error:')]
    assert len(errors) == 1 and str(damaged[case]) in errors[0]
    assert not out.exists()


def test_play_clock_and_remaps():
    from assist_bags.play_core import PlayClock, parse_remaps
    c = PlayClock(first_ns=5_000_000_000, start_wall=100.0, rate=2.0)
    assert c.due(5_000_000_000) == 100.0 and c.due(7_000_000_000) == pytest.approx(101.0)
    assert c.bag_time(101.0) == 7_000_000_000
    assert parse_remaps(['/a:=/b', '/c/d:=/e']) == {'/a': '/b', '/c/d': '/e'}
    for bad in (['/a'], ['a:=/b'], ['/a:=']):
        with pytest.raises(ValueError):
            parse_remaps(bad)


def test_size_split(tmp_path):
    bag = tmp_path / 'b'
    _write(bag, 'sqlite3', split_size_bytes=4000).close()     # ~140 B per message pair -> several files
    with BagReader(bag) as r:
        assert len(r.files) >= 3 and r.message_count == 121
        assert sum(1 for _ in r.messages()) == 121


def other_distro_bag(path: Path) -> Path:
    """A bag whose /odom carries a nav_msgs/Odometry definition unlike Jazzy's (as another distro might)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    ts = get_typestore(Stores.EMPTY)
    ts.register(get_types_from_msg('float64 x\nfloat64 y', 'nav_msgs/msg/Odometry'))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection('/odom', 'nav_msgs/msg/Odometry', typestore=ts)
        jazzy = get_typestore(Stores.ROS2_JAZZY)
        pilot = w.add_connection('/pilot/cmd_vel', 'geometry_msgs/msg/TwistStamped', typestore=jazzy)
        goal = w.add_connection('/sim/goal', 'geometry_msgs/msg/PointStamped', typestore=jazzy)
        w.write(goal, 10**9, jazzy.serialize_cdr(msgs.point_stamped(10**9, (1, 2, 3)),
                                                 'geometry_msgs/msg/PointStamped'))
        for k in range(3):
            w.write(c, 10**9 + k, ts.serialize_cdr(ts.types['nav_msgs/msg/Odometry'](x=1.0, y=2.0),
                                                  'nav_msgs/msg/Odometry'))
            w.write(pilot, 10**9 + k, jazzy.serialize_cdr(msgs.twist_stamped(10**9 + k, (1, 0, 0)),
                                                          'geometry_msgs/msg/TwistStamped'))
    return path


@pytest.mark.parametrize('tool', ['plot_flight', 'replay_assist'])
def test_cli_refuses_other_distros_definitions_and_unwritable_output(tmp_path, tool):
    bag = other_distro_bag(tmp_path / 'other')
    proc = subprocess.run([str(BIN / tool), str(bag), '--out', str(tmp_path / 'o'), '--mode' if tool == 'replay_assist'
                           else '--threshold', 'oracle' if tool == 'replay_assist' else '0.25'],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and 'Traceback' not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith('error:')]
    assert len(errors) == 1, proc.stderr
    assert '/odom' in errors[0] and 'Odometry differs from this install' in errors[0]
    (tmp_path / 'file').write_text('x')
    proc = subprocess.run([str(BIN / tool), str(bag), '--out', str(tmp_path / 'file' / 'o')], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 1 and 'not a writable directory' in proc.stderr and 'Traceback' not in proc.stderr
