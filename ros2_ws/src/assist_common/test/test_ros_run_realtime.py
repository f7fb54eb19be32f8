"""set_realtime_priority: every thread of a process under SCHED_FIFO, and back (no ROS graph needed)."""
import os
import subprocess
import sys
import time

import pytest

from assist_common.ros_run import set_realtime_priority

CHILD = ('import threading, time; '
         '[threading.Thread(target=time.sleep, args=(30,), daemon=True).start() for _ in range(3)]; time.sleep(30)')


def _policies(pid):
    return {int(t): (os.sched_getscheduler(int(t)), os.sched_getparam(int(t)).sched_priority)
            for t in os.listdir(f'/proc/{pid}/task')}


@pytest.fixture
def child():
    proc = subprocess.Popen([sys.executable, '-c', CHILD])
    deadline = time.monotonic() + 10
    while len(os.listdir(f'/proc/{proc.pid}/task')) < 4 and time.monotonic() < deadline:
        time.sleep(0.02)
    yield proc
    proc.kill()
    proc.wait()


def test_fifo_on_every_thread_then_back(child):
    assert set(_policies(child.pid).values()) == {(os.SCHED_OTHER, 0)}
    if os.geteuid() != 0:
        with pytest.raises(PermissionError):
            set_realtime_priority(30, child.pid)
        return
    assert set_realtime_priority(30, child.pid) == 4
    assert set(_policies(child.pid).values()) == {(os.SCHED_FIFO, 30)}
    assert set_realtime_priority(0, child.pid) == 4
    assert set(_policies(child.pid).values()) == {(os.SCHED_OTHER, 0)}


@pytest.mark.parametrize('bad', [-1, 100])
def test_priority_out_of_range(bad):
    with pytest.raises(ValueError, match='0-99'):
        set_realtime_priority(bad)
