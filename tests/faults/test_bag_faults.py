"""Bag tools against hostile or failing inputs (no ROS graph): full disks, alias bombs, paths out of the bag,
absurd step rates and timestamps, existing outputs, malformed landing JSON. Each bad input gives one
`error:` line and a non-zero exit (CLI) or a BagError, and nothing already written is lost."""
from __future__ import annotations

import errno
import json
import os
import random
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Writer

from assist_bags import bagio, msgs, plot, replay
from assist_bags.bagio import CONTRACT_TOPICS, BagError, BagReader, BagWriter

BIN = Path(sys.executable).parent
T0 = 1_000_000_000


def errors_of(stderr: str) -> list[str]:
    """The `error:` lines of a tool's stderr."""
    return [ln for ln in stderr.splitlines() if ln.startswith('error:')]


def run_tool(tool: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run a console script; a hang fails the test (TimeoutExpired) instead of blocking the suite."""
    return subprocess.run([str(BIN / tool), *args], capture_output=True, text=True, timeout=timeout)


def flight_bag(path: Path, n: int = 20, cmd_vel: bool = True, landing: dict | None = None,
               far_future_s: float | None = None) -> Path:
    """A small oracle-replayable flight: /odom, /pilot/cmd_vel, /sim/goal (+ /cmd_vel, /sim/landing) at 20 Hz."""
    with BagWriter(path) as w:
        topics = ['/odom', '/pilot/cmd_vel', '/sim/goal'] + (['/cmd_vel'] if cmd_vel else []) + (
            ['/sim/landing'] if landing is not None else [])
        for t in topics:
            w.add_topic(t, *CONTRACT_TOPICS[t])
        w.write_msg('/sim/goal', T0, msgs.point_stamped(T0, (4.0, 0.5, 0.8)))
        for k in range(n):
            t = T0 + k * 50_000_000
            pos = (0.1 * k, 0.0, 2.0 - 0.05 * k)
            w.write_msg('/odom', t, msgs.odometry(t, pos, (0.0, 0.0, 0.0, 1.0), (1.0, 0.0, -0.5)))
            w.write_msg('/pilot/cmd_vel', t, msgs.twist_stamped(t, (1.0, 0.0, -0.5)))
            if cmd_vel:
                w.write_msg('/cmd_vel', t + 1_000_000, msgs.twist_stamped(t + 1_000_000, (1.0, 0.0, -0.5)))
        if far_future_s is not None:
            t = T0 + int(far_future_s * 1e9)
            w.write_msg('/pilot/cmd_vel', t, msgs.twist_stamped(t, (0.0, 0.0, 0.0)))
        if landing is not None:
            t = T0 + n * 50_000_000
            w.write_msg('/sim/landing', t, msgs.string(json.dumps(landing)))
    return path


# ---------------------------------------------------------------------------------------------- full disk
class FakeDisk:
    """A filesystem of `capacity` bytes as free_bytes reports it: capacity minus what the bag holds on disk."""

    def __init__(self, root: Path, capacity: int):
        self.root, self.capacity = root, capacity

    def __call__(self, path) -> int:
        used = sum(f.stat().st_size for f in self.root.rglob('*') if f.is_file())
        return self.capacity - used


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_full_disk_stops_the_writer_and_keeps_every_accepted_message(tmp_path, monkeypatch, storage):
    """Free space below the reserve fails the writer before the storage sees the message; close() keeps all."""
    rng = random.Random(7)
    capacity = rng.randint(300_000, 600_000)
    monkeypatch.setattr(bagio, 'free_bytes', FakeDisk(tmp_path, capacity))
    bag = tmp_path / 'b'
    w = BagWriter(bag, storage=storage, split_size_bytes=60_000, min_free_bytes=100_000)
    w.add_topic('/camera/depth/image_raw', *CONTRACT_TOPICS['/camera/depth/image_raw'])
    accepted = []
    with pytest.raises(BagError, match='disk full') as err:
        for k in range(10_000):
            t = T0 + k * 50_000_000
            w.write_msg('/camera/depth/image_raw', t, msgs.image(t, np.full((32, 32), k, np.float32)))
            accepted.append(k)
    assert '\n' not in str(err.value) and w.failed is not None
    assert 10 < len(accepted) < 10_000
    with pytest.raises(BagError, match='disk full'):          # nothing more is taken, no new file started
        w.write_msg('/camera/depth/image_raw', T0, msgs.image(T0, np.zeros((32, 32), np.float32)))
    w.close()
    with BagReader(bag) as r:
        got = [int(msgs.image_array(r.deserialize(raw, tp))[0, 0]) for tp, _, raw in r.messages()]
    assert got == accepted and w.messages == len(accepted)
    assert not [p for p in bag.iterdir() if p.name.startswith('.writing')]


def test_a_failed_file_is_never_deleted_by_the_next_one(tmp_path, monkeypatch):
    """ENOSPC while finishing a file at a split: its data stays on disk; no later write starts a new file."""
    real_close, calls = Writer.close, []

    def failing_close(self):
        calls.append(self.path)
        if len(calls) == 2:           # the disk is full when the second file is finished
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_close(self)
    monkeypatch.setattr(Writer, 'close', failing_close)
    bag = tmp_path / 'b'
    w = BagWriter(bag, split_duration_ns=500_000_000, min_free_bytes=0)
    w.add_topic('/camera/depth/image_raw', *CONTRACT_TOPICS['/camera/depth/image_raw'])

    def frame(k: int):
        t = T0 + k * 50_000_000
        return t, msgs.image(t, np.full((256, 256), k, np.float32))     # 256 kB: the mcap writer flushes chunks
    written = 0
    with pytest.raises(BagError, match='No space left on device'):
        for k in range(100):
            w.write_msg('/camera/depth/image_raw', *frame(k))
            written += 1
    assert written == 20                      # two files of 10 messages; finishing the second one failed
    kept = bag / '.writing_b_1'
    data = [p for p in kept.iterdir() if p.suffix == '.mcap']
    assert data and data[0].stat().st_size > 1_000_000
    size = data[0].stat().st_size
    for k in range(20, 23):                   # the recorder's next messages: refused, nothing deleted
        with pytest.raises(BagError, match='No space left on device'):
            w.write_msg('/camera/depth/image_raw', *frame(k))
    w.close()
    assert data[0].stat().st_size == size and len(list(bag.glob('.writing_*'))) == 1
    with BagReader(bag) as r:                # the first file is complete and listed
        got = [int(msgs.image_array(r.deserialize(raw, tp))[0, 0]) for tp, _, raw in r.messages()]
    assert got == list(range(10))


def test_writer_refuses_to_start_on_a_full_disk(tmp_path, monkeypatch):
    monkeypatch.setattr(bagio, 'free_bytes', lambda path: 1_000_000)
    with pytest.raises(BagError, match='disk full'):
        BagWriter(tmp_path / 'b', min_free_bytes=8_000_000)
    assert not (tmp_path / 'b').exists()


# ---------------------------------------------------------------------------------------------- metadata.yaml
def bomb(levels: int = 12) -> str:
    """A billion-laughs metadata.yaml of a few kB (10**levels strings once expanded)."""
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels):
        lines.append(f'a{i}: &a{i} [' + ','.join([f'*a{i - 1}'] * 10) + ']')
    lines.append('rosbag2_bagfile_information:')
    lines.append('  version: 9')
    lines.append('  storage_identifier: mcap')
    lines.append('  relative_file_paths: [b_0.mcap]')
    lines.append(f'  custom_data: {{boom: *a{levels - 1}}}')
    return '\n'.join(lines) + '\n'


def test_alias_bomb_metadata_is_refused_at_once(tmp_path):
    bag = flight_bag(tmp_path / 'b', n=3)
    (bag / 'metadata.yaml').write_text(bomb())
    assert (bag / 'metadata.yaml').stat().st_size < 6000
    t = time.monotonic()
    with pytest.raises(BagError, match='aliases'):
        BagReader(bag)
    assert time.monotonic() - t < 5.0
    for tool, extra in (('plot_flight', []), ('replay_assist', ['--mode', 'oracle']), ('bag_play', [])):
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        proc = run_tool(tool, str(bag), *extra, timeout=60)
        assert proc.returncode == 1 and 'Traceback' not in proc.stderr, (tool, proc.stderr)
        errs = errors_of(proc.stderr)
        assert len(errs) == 1 and 'aliases' in errs[0], (tool, proc.stderr)
        assert resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss < max(before, 1_500_000)   # kB: no blow-up


@pytest.mark.parametrize('text,match', [
    ('x: ' + '[' * 200 + ']' * 200 + '\n', 'nested deeper'),
    ('rosbag2_bagfile_information: {version: 9, storage_identifier: mcap, relative_file_paths: 7}\n',
     'not a list of file names'),
    ('- just\n- a list\n', 'unreadable bag metadata'),
    ('\xff\xfe not utf-8', 'unreadable bag metadata'),
])
def test_malformed_metadata_gives_one_line(tmp_path, text, match):
    bag = flight_bag(tmp_path / 'b', n=2)
    (bag / 'metadata.yaml').write_bytes(text.encode('latin-1'))
    with pytest.raises(BagError, match=match) as err:
        BagReader(bag)
    assert '\n' not in str(err.value)


def test_oversized_metadata_is_refused_without_parsing(tmp_path):
    bag = flight_bag(tmp_path / 'b', n=2)
    with open(bag / 'metadata.yaml', 'a') as fh:
        fh.write('# ' + 'x' * (bagio.METADATA_MAX_BYTES + 10) + '\n')
    with pytest.raises(BagError, match='larger than'):
        BagReader(bag)


def _list_files(bag: Path, files: list[str]) -> None:
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())
    meta['rosbag2_bagfile_information']['relative_file_paths'] = files
    (bag / 'metadata.yaml').write_text(yaml.safe_dump(meta))


def test_data_files_outside_the_bag_are_refused(tmp_path):
    """../other/x.mcap, an absolute path or a symlink out of the bag: another bag's data is never read or played."""
    other = flight_bag(tmp_path / 'other', n=5)
    victim = flight_bag(tmp_path / 'victim', n=2)
    (victim / 'link.mcap').symlink_to(other / 'other_0.mcap')
    for files in (['../other/other_0.mcap'], [str(other / 'other_0.mcap')], ['victim_0.mcap', 'sub/../../other/'
                                                                                              'other_0.mcap'],
                  ['link.mcap']):
        _list_files(victim, files)
        with pytest.raises(BagError, match='outside the bag directory'):
            BagReader(victim)
    _list_files(victim, ['../other/other_0.mcap'])
    for tool, extra in (('plot_flight', []), ('replay_assist', ['--mode', 'oracle']), ('bag_play', [])):
        proc = run_tool(tool, str(victim), *extra, timeout=60)
        assert proc.returncode == 1 and 'Traceback' not in proc.stderr, (tool, proc.stderr)
        errs = errors_of(proc.stderr)
        assert len(errs) == 1 and 'outside the bag directory' in errs[0], (tool, proc.stderr)
    _list_files(victim, ['victim_0.mcap'])               # the bag's own file is still fine
    with BagReader(victim) as r:
        assert r.message_count == 2 * 3 + 1


# ---------------------------------------------------------------------------------------------- replay_assist
@pytest.mark.parametrize('rate', ['inf', '1e10', '-inf', '0', 'nan'])
def test_replay_refuses_unusable_step_rates(tmp_path, rate):
    bag = flight_bag(tmp_path / 'b', n=5, cmd_vel=False)
    proc = run_tool('replay_assist', str(bag), '--mode', 'oracle', f'--rate-hz={rate}', '--out', str(tmp_path / 'o'),
                    timeout=60)
    assert proc.returncode != 0 and 'Traceback' not in proc.stderr
    errs = errors_of(proc.stderr)
    assert len(errs) == 1 and '--rate-hz' in errs[0]
    assert not (tmp_path / 'o').exists()
    with pytest.raises(ValueError, match='rate must be'):
        replay.replay(bag, replay.ReplayConfig(mode='oracle', rate_hz=float(rate)))


def test_replay_refuses_a_far_future_timestamp_instead_of_stepping_to_it(tmp_path):
    bag = flight_bag(tmp_path / 'b', n=10, cmd_vel=False, far_future_s=1e9)     # one message ~32 years later
    proc = run_tool('replay_assist', str(bag), '--mode', 'oracle', '--out', str(tmp_path / 'o'), timeout=90)
    assert proc.returncode == 1 and 'Traceback' not in proc.stderr, proc.stderr
    errs = errors_of(proc.stderr)
    assert len(errs) == 1 and 'wrong timestamp' in errs[0] and '/pilot/cmd_vel' in errs[0]
    assert not (tmp_path / 'o').exists() and not (tmp_path / 'o.summary.json').exists()
    # the same flight without that message replays at --rate-hz
    res = replay.replay(flight_bag(tmp_path / 'ok', n=10, cmd_vel=False), replay.ReplayConfig(mode='oracle'))
    assert len(res.times_ns) == 9           # a step every 50 ms before the last message


def test_replay_never_overwrites_an_existing_summary(tmp_path):
    bag = flight_bag(tmp_path / 'b', n=10)
    summary = tmp_path / 'mine.json'
    summary.write_text('{"precious": true}')
    proc = run_tool('replay_assist', str(bag), '--mode', 'oracle', '--out', str(tmp_path / 'o'),
                    '--summary', str(summary))
    assert proc.returncode == 1 and 'Traceback' not in proc.stderr
    errs = errors_of(proc.stderr)
    assert len(errs) == 1 and 'mine.json' in errs[0] and 'not overwriting' in errs[0]
    assert summary.read_text() == '{"precious": true}'
    assert not (tmp_path / 'o').exists()                  # refused before any work
    default = tmp_path / 'o2.summary.json'                # the default summary name too
    default.write_text('old')
    proc = run_tool('replay_assist', str(bag), '--mode', 'oracle', '--out', str(tmp_path / 'o2'))
    assert proc.returncode == 1 and default.read_text() == 'old' and not (tmp_path / 'o2').exists()
    proc = run_tool('replay_assist', str(bag), '--mode', 'oracle', '--out', str(tmp_path / 'o3'))
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / 'o3.summary.json').read_text())['steps'] == 10


def test_publish_new_never_replaces(tmp_path):
    dst = tmp_path / 'x.json'
    dst.write_text('old')
    tmp = tmp_path / '.x.partial'
    tmp.write_text('new')
    with pytest.raises(BagError, match='exists already'):
        bagio.publish_new(tmp, dst)
    assert dst.read_text() == 'old' and not tmp.exists()


# ---------------------------------------------------------------------------------------------- plot_flight
def test_plot_flight_never_overwrites_figures(tmp_path):
    bag = flight_bag(tmp_path / 'b', n=30, landing={'goal_index': 1, 'error_m': 0.3, 'success': True})
    out = tmp_path / 'figs'
    assert plot.main([str(bag), '--out', str(out)]) == 0
    png = out / 'b_landing0.png'
    before = png.read_bytes()
    proc = run_tool('plot_flight', str(bag), '--out', str(out))
    assert proc.returncode == 1 and 'Traceback' not in proc.stderr
    errs = errors_of(proc.stderr)
    assert len(errs) == 1 and 'b_landing0.png' in errs[0] and 'not overwriting' in errs[0]
    assert png.read_bytes() == before
    other = out / 'notes.txt'                            # an existing directory with other files is fine
    other.write_text('x')
    assert plot.main([str(flight_bag(tmp_path / 'c', n=30)), '--out', str(out)]) == 0
    assert (out / 'c_landing0.png').exists() and other.read_text() == 'x' and png.read_bytes() == before


@pytest.mark.parametrize('error_m', [None, 'far', [1, 2], {'m': 1}, True, float('nan')])
def test_plot_flight_draws_a_landing_whose_error_is_not_a_number(tmp_path, error_m, caplog):
    landing = {'goal_index': 2, 'landed_index': None, 'error_m': error_m, 'success': False, 'crash': False}
    bag = flight_bag(tmp_path / 'b', n=30, landing=landing)
    caplog.set_level('WARNING', logger=plot.__name__)
    assert plot.main([str(bag), '--out', str(tmp_path / 'p')]) == 0          # the console script's own main
    assert [r.getMessage() for r in caplog.records if 'not a number' in r.getMessage()], caplog.text
    assert (tmp_path / 'p' / 'b_landing0.png').stat().st_size > 10_000
    (f,) = plot.read_flights(bag)
    assert 'error n/a' in plot.describe(f, 'b', 0)


def test_plot_flight_failure_leaves_no_empty_output_directory(tmp_path, monkeypatch):
    bag = flight_bag(tmp_path / 'b', n=30)

    def broken(*args, **kwargs):
        raise BagError('figure: cannot write (No space left on device)')
    monkeypatch.setattr(plot, 'plot_flight', broken)
    out = tmp_path / 'new' / 'plots'
    assert plot.main([str(bag), '--out', str(out)]) == 1
    assert not out.exists() and not (tmp_path / 'new').exists()
