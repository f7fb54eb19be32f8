"""bag_record and bag_play processes against failures: a disk that fills while recording (injected write
errors, and a real tiny tmpfs where mounting is allowed) and a loop over nothing to play."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from assist_bags import msgs
from assist_bags.bagio import CONTRACT_TOPICS, BagReader, BagWriter
from assist_common.domains import private_domain_id

pytestmark = pytest.mark.graph
BIN = Path(sys.executable).parent
T0 = 1_000_000_000
DOMAIN = str(private_domain_id())      # a private DDS domain per test process
ENV = dict(os.environ, ROS_DOMAIN_ID=DOMAIN, PYTHONUNBUFFERED='1')


def source_bag(path: Path, n: int, side: int = 8, period_ns: int = 20_000_000) -> Path:
    """n depth frames (side x side float32, value k) on /camera/depth/image_raw, offered reliable (none dropped)."""
    with BagWriter(path) as w:
        w.add_topic('/camera/depth/image_raw', 'sensor_msgs/msg/Image', CONTRACT_TOPICS['/cmd_vel'][1])
        for k in range(n):
            t = T0 + k * period_ns
            w.write_msg('/camera/depth/image_raw', t, msgs.image(t, np.full((side, side), k, np.float32)))
    return path


def frames(bag: Path) -> list[int]:
    """The frame numbers a bag holds, in order."""
    with BagReader(bag) as r:
        return [int(msgs.image_array(r.deserialize(raw, t))[0, 0]) for t, _, raw in r.messages()]


def record(out: Path, *flags: str, inject_after: int | None = None) -> subprocess.Popen:
    """bag_record as a process; with inject_after, the storage raises ENOSPC from that write on (a full disk)."""
    code = textwrap.dedent(f'''
        import errno, os, sys
        from rosbags.rosbag2 import Writer
        real, n = Writer.write, [0]
        def write(self, *args):
            n[0] += 1
            if {inject_after!r} is not None and n[0] > {inject_after!r}:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real(self, *args)
        Writer.write = write
        from assist_bags.record_node import main
        main(sys.argv[1:])
    ''')
    return subprocess.Popen([sys.executable, '-c', code, str(out), '--topics', '/camera/depth/image_raw',
                             '--discovery-period-s', '0.1', *flags], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def play(bag: Path, *flags: str) -> subprocess.Popen:
    """bag_play as a process on the test's domain."""
    return subprocess.Popen([str(BIN / 'bag_play'), str(bag), '--wait-for-subscribers', '1', '--delay-s', '0',
                             *flags], env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)


def finish(proc: subprocess.Popen, timeout: float) -> tuple[int | None, str]:
    """Wait for the process to end on its own; (exit code or None when it had to be stopped, its output)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
        return proc.returncode, out or ''
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, 2)
        try:
            out, _ = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            out, _ = proc.communicate()
        return None, out or ''


def test_write_error_stops_the_recorder_with_an_error_and_keeps_what_was_written(tmp_path):
    """ENOSPC from the storage after 25 messages: exit 1 on its own, one error line, those 25 messages kept."""
    src = source_bag(tmp_path / 'src', 120)
    out = tmp_path / 'rec'
    rec = record(out, '--split-duration-s', '0.5', inject_after=25)
    player = play(src)
    try:
        code, log = finish(rec, 60)
    finally:
        os.killpg(player.pid, 2)
        player.wait(15)
    assert code == 1, log
    errors = [ln for ln in log.splitlines() if ln.startswith('error:')]
    assert len(errors) == 1 and 'No space left on device' in errors[0], log
    assert 'Traceback' not in log
    kept = int(re.search(r'(\d+) messages kept', errors[0]).group(1))
    assert kept == 25
    assert frames(out) == list(range(25))          # every message written before the error, in order


def _mount_tmpfs(path: Path, size: str) -> bool:
    path.mkdir()
    if os.geteuid() != 0:
        return False
    return subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size}', 'tmpfs', str(path)],
                          capture_output=True).returncode == 0


def test_recording_onto_a_real_full_disk(tmp_path):
    """A 6 MB tmpfs filled by 64 kB frames: the recorder stops by itself (exit 1) and the bag holds every frame
    it reported writing, readable. Needs root and mount (CI runs as root); skipped elsewhere."""
    disk = tmp_path / 'disk'
    if not _mount_tmpfs(disk, '6m'):
        pytest.skip('cannot mount a tmpfs here (needs root and CAP_SYS_ADMIN)')
    try:
        src = source_bag(tmp_path / 'src', 200, side=128)            # 200 x 64 kB = 13 MB > the disk
        out = disk / 'rec'
        rec = record(out, '--min-free-mb', '2.5')
        player = play(src, '--rate', '0.5')
        try:
            code, log = finish(rec, 90)
        finally:
            os.killpg(player.pid, 2)
            player.wait(15)
        assert code == 1, log
        errors = [ln for ln in log.splitlines() if ln.startswith('error:')]
        assert len(errors) == 1 and 'disk full' in errors[0], log
        kept = int(re.search(r'(\d+) messages kept', errors[0]).group(1))
        got = frames(out)
        assert len(got) == kept and kept > 20
        assert got == sorted(got) and len(set(got)) == len(got)
    finally:
        subprocess.run(['umount', '-l', str(disk)], check=False)


@pytest.mark.parametrize('flags', [['--topics', '/empty'], ['--start-offset-s', '50'],
                                   ['--topics', '/early', '--start-offset-s', '3']])
def test_loop_over_nothing_to_play_ends_at_once_with_an_error(tmp_path, flags):
    """Old: `--loop true` spun at 100 % CPU forever (and took ~7.5 s to stop); now one error line, exit 1."""
    bag = tmp_path / 'b'
    with BagWriter(bag) as w:
        for topic in ('/empty', '/early', '/late'):
            w.add_topic(topic, *CONTRACT_TOPICS['/sim/landing'])
        for k in range(10):                 # /early: 0-0.9 s, /late: 0-4.5 s
            w.write_msg('/early', T0 + k * 100_000_000, msgs.string('e'))
            w.write_msg('/late', T0 + k * 500_000_000, msgs.string('l'))
    t = time.monotonic()
    proc = subprocess.Popen([str(BIN / 'bag_play'), str(bag), '--loop', 'true', '--delay-s', '0', *flags], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    code, log = finish(proc, 30)
    assert code == 1, log                              # ended on its own (old: killed after 30 s of spinning)
    errors = [ln for ln in log.splitlines() if ln.startswith('error:')]
    assert len(errors) == 1 and 'nothing to play' in errors[0], log
    assert 'Traceback' not in log and time.monotonic() - t < 30
