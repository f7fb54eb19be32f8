"""MAVLink signing key paths that are not regular files (a FIFO, a directory, a device): refused at once.

Opening a FIFO for reading blocks until something writes to it, so a key path naming one used to hang
mavlink_bridge_node (and sim_node's MAVLink vehicle) at start-up without a word. The key loader
checks the file type before it opens anything: one clear line, and the node exits non-zero.
"""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from assist_common.mavlink_io import load_signing_key
from assist_sim.testing import free_udp_port
from assist_common.domains import private_domain_id

BIN = Path(sys.executable).parent
HANG_S = 5.0          # a loader that has not answered by then is blocked in open()


@pytest.fixture
def fifo(tmp_path):
    """A FIFO with a key file's mode (600); whatever still waits on it is released at teardown."""
    path = tmp_path / 'mavlink.key'
    os.mkfifo(path, 0o600)
    yield path
    try:                                    # a reader blocked in open() returns once a writer comes and goes
        os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
    except OSError:
        pass                                # nobody is waiting


def _answer_within(fn, timeout: float = HANG_S):
    """(returned, raised) of fn() run on a thread; AssertionError if it has not answered within `timeout`."""
    box: dict = {}

    def run():
        try:
            box['value'] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box['error'] = exc
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout)
    assert not thread.is_alive(), f'no answer within {timeout} s: blocked opening the key file'
    return box.get('value'), box.get('error')


def test_a_fifo_key_path_is_refused_without_blocking(fifo):
    _, err = _answer_within(lambda: load_signing_key(str(fifo)))
    assert isinstance(err, ValueError) and 'not a regular file (a FIFO)' in str(err), err
    assert '\n' not in str(err) and str(fifo) in str(err)


@pytest.mark.parametrize('path, kind', [('/dev/null', 'a character device'), (None, 'a directory')])
def test_other_non_regular_key_paths_are_refused(tmp_path, path, kind):
    _, err = _answer_within(lambda: load_signing_key(path or str(tmp_path)))
    assert isinstance(err, ValueError) and f'not a regular file ({kind})' in str(err), err


def test_the_sim_vehicle_refuses_a_fifo_key_without_blocking(fifo):
    from assist_sim.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleConfig
    from assist_sim.testing import KinematicWorld

    def build():
        vehicle = MavlinkVehicle(KinematicWorld(), f'udpin:127.0.0.1:{free_udp_port()}',
                                 MavlinkVehicleConfig(signing_key_file=str(fifo)))
        vehicle.close()
    _, err = _answer_within(build)
    assert isinstance(err, ValueError) and 'not a regular file' in str(err), err


def test_the_bridge_core_refuses_a_fifo_key_without_blocking(fifo):
    from assist_bridge.bridge_core import BridgeConfig, MavlinkBridge
    cfg = BridgeConfig(connection=f'udpin:127.0.0.1:{free_udp_port()}', signing_key_file=str(fifo))
    _, err = _answer_within(lambda: MavlinkBridge(cfg).close())
    assert isinstance(err, ValueError) and 'not a regular file' in str(err), err


@pytest.mark.parametrize('executable, key_param, url_param', [
    ('mavlink_bridge_node', 'signing_key_file', 'connection'),
    ('sim_node', 'mavlink_signing_key_file', 'mavlink_url'),
])
def test_the_node_exits_at_once_with_one_error_line(fifo, executable, key_param, url_param):
    exe = BIN / executable
    if not exe.exists():
        pytest.skip(f'{exe} not installed (run make venv)')
    env = dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id()), PYTHONUNBUFFERED='1')
    try:
        done = subprocess.run([str(exe), '--ros-args', '-p', f'{key_param}:={fifo}',
                               '-p', f'{url_param}:=udpin:127.0.0.1:{free_udp_port()}'],
                              env=env, capture_output=True, text=True, timeout=60, start_new_session=True)
    except subprocess.TimeoutExpired as exc:
        raise AssertionError(f'{executable} hung at start-up: {exc.stderr!r}') from None
    assert done.returncode != 0
    errors = [line for line in done.stderr.splitlines() if 'error' in line.lower()]
    assert len(errors) == 1 and 'not a regular file (a FIFO)' in errors[0] and str(fifo) in errors[0], done.stderr
    assert 'Traceback' not in done.stderr + done.stdout
