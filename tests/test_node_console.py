"""Console convention of every node executable: `--help` lists its parameters (type, default, range, run-time or
read-only, description) and `--version` prints its package's version; both exit 0 without starting the node.
A Ctrl-C while an executable is still starting leaves no traceback."""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from assist_common.console import node_executables
from assist_common.domains import private_domain_id

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SRC = REPO / 'ros2_ws' / 'src'
# executable -> (package, module holding its PARAMS): the workspace's node registry
NODES = node_executables(sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file()))


def test_the_registry_holds_every_node_and_no_tool():
    assert {'sim_node', 'sim_pilot_node', 'encoder_node', 'policy_node', 'mavlink_bridge_node', 'teleop_keyboard',
            'pilot_station', 'landing_runner', 'image_relay', 'image_decoder', 'bag_record', 'bag_play'} == set(NODES)
    assert NODES['policy_node'] == ('assist_policy', 'assist_policy.policy_node')


@pytest.fixture(scope='module')
def answers():
    """executable -> (--help process, --version process), all run side by side."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id()))
    procs = {(name, flag): subprocess.Popen([str(BIN / name), flag], env=env, stdin=subprocess.DEVNULL,
                                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name in NODES for flag in ('--help', '--version')}
    out = {}
    for key, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=300)
        out[key] = (proc.returncode, stdout, stderr)
    return out


@pytest.mark.parametrize('name', NODES)
def test_help_lists_every_parameter(answers, name):
    package, module = NODES[name]
    code, stdout, stderr = answers[(name, '--help')]
    assert code == 0, stderr[-3000:]
    assert stdout.startswith(f'usage: {name} [-h] [--version] [--ros-args')
    params = importlib.import_module(module).PARAMS
    lines = stdout.splitlines()
    for pname, p in params.items():
        entry = next((i for i, ln in enumerate(lines) if ln.startswith(f'  {pname} (')), None)
        assert entry is not None, f'{name} --help does not list {pname}'
        facts = lines[entry]
        assert f'default {p.default!r}' in facts
        assert ('run-time' if p.dynamic else 'read-only') in facts
        if p.rule():
            assert p.rule() in facts
        assert lines[entry + 1].strip() == p.description
    # the node never started: no ROS log line, nothing on stderr
    assert stderr == ''


@pytest.mark.parametrize('name', NODES)
def test_version_is_the_package_version(answers, name):
    code, stdout, stderr = answers[(name, '--version')]
    assert code == 0, stderr[-3000:]
    assert stdout == answers_version(name)


def test_version_is_answered_without_importing_the_node(tmp_path):
    """A node's --version comes from its package, before the node's module (rclpy, torch) is imported: with an rclpy
    that cannot be imported, --version still answers and --help fails."""
    broken = tmp_path / 'rclpy'
    broken.mkdir()
    (broken / '__init__.py').write_text("raise ImportError('rclpy is not importable in this test')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get('PYTHONPATH', '')]),
               ROS_DOMAIN_ID=str(private_domain_id()))
    version = subprocess.run([str(BIN / 'policy_node'), '--version', '--ros-args', '-p', 'mode:=latent'],
                             capture_output=True, text=True, timeout=60, env=env)
    assert version.returncode == 0 and version.stdout == answers_version('policy_node'), version.stderr
    helped = subprocess.run([str(BIN / 'policy_node'), '--version', '--help'], capture_output=True, text=True,
                            timeout=60, env=env)
    assert helped.returncode != 0 and 'rclpy is not importable in this test' in helped.stderr


def answers_version(name: str) -> str:
    """What `name --version` prints: 'name (package) version' from the package's package.xml."""
    package, _ = NODES[name]
    version = ET.parse(REPO / 'ros2_ws' / 'src' / package / 'package.xml').getroot().findtext('version')
    return f'{name} ({package}) {version}\n'


def test_flags_after_ros_args_are_not_ours():
    """`--ros-args ... --help` belongs to ROS: the node is not answered with our help."""
    from assist_common.ros_params import console_request

    def factory():
        raise AssertionError('never built')
    assert console_request(factory, ['--ros-args', '-p', 'x:=1', '--help'], {}) is None
    assert console_request(factory, ['--version', '--ros-args'], {}).endswith('\n')


def test_a_misspelt_parameter_is_refused_at_start_up_in_one_line(tmp_path):
    """A parameter the node does not declare (from a parameter file or -p) ends the start-up with one line naming
    it and the closest declared name, instead of being ignored."""
    params = tmp_path / 'pilot.yaml'
    params.write_text('sim_pilot_node:\n  ros__parameters:\n    bta: 0.9\n    alpha: 0.3\n')
    env = dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id()))
    proc = subprocess.run([str(BIN / 'sim_pilot_node'), '--ros-args', '--params-file', str(params),
                           '-p', 'rate_hz:=10.0', '-p', 'zz_unrelated:=1'],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 1, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith('error:')]
    assert errors == ["error: sim_pilot_node: unknown parameters 'bta' (did you mean 'beta'?), 'zz_unrelated'; "
                      "its --help lists the parameters"], proc.stderr
    assert 'Traceback' not in proc.stderr


def console_scripts() -> dict[str, str]:
    """Every console script of the workspace's packages: name -> 'module:function' (from each setup.py)."""
    import re
    found = {}
    for setup in sorted((REPO / 'ros2_ws' / 'src').glob('*/setup.py')):
        for name, target in re.findall(r"'(\w+) = ([\w.]+:\w+)'", setup.read_text()):
            found[name] = target
    return found


def test_every_console_script_imports_its_module_only_when_run():
    scripts = console_scripts()
    assert set(NODES) <= set(scripts) and len(scripts) >= 19
    for name, target in scripts.items():
        module, function = target.split(':')
        assert module.endswith('.entry_points') and function == name, target
        entry = getattr(importlib.import_module(module), function)
        assert callable(importlib.import_module(entry.target).main), target


def test_ctrl_c_while_starting_exits_quietly(loading_heavy_libraries, tmp_path):
    """A Ctrl-C while a program is still importing (rclpy, torch, pybullet): no traceback; nodes exit 0
    (what run_node returns after a Ctrl-C), command-line tools 130."""
    import signal
    import time
    env = dict(os.environ, ROS_DOMAIN_ID=str(private_domain_id()))
    tools = ('evaluate', 'train_td3', 'train_cmvae')
    from assist_bags import msgs
    from assist_bags.bagio import CONTRACT_TOPICS, BagWriter
    bag = BagWriter(tmp_path / 'bag')           # bag_play needs a bag to start with
    bag.add_topic('/cmd_vel', *CONTRACT_TOPICS['/cmd_vel'])
    bag.write_msg('/cmd_vel', 10**9, msgs.twist_stamped(10**9, (0.0, 0.0, 0.0)))
    bag.close()
    args = {'bag_play': [str(tmp_path / 'bag')], 'bag_record': [str(tmp_path / 'recorded')]}
    # teleop_keyboard refuses to start without a terminal (exit 1, racing the signal): it gets a pseudo-terminal
    terminal, tty = os.openpty()
    procs = {name: subprocess.Popen([str(BIN / name), *args.get(name, [])], env=env, stdout=subprocess.PIPE,
                                    stdin=tty if name == 'teleop_keyboard' else subprocess.DEVNULL,
                                    stderr=subprocess.STDOUT, text=True,
                                    preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
             for name in (*NODES, *tools)}
    os.close(tty)
    waiting = dict(procs)
    end = time.monotonic() + 120
    while waiting and time.monotonic() < end:
        for name, proc in list(waiting.items()):
            if loading_heavy_libraries(proc.pid) or proc.poll() is not None:
                proc.send_signal(signal.SIGINT)      # in the middle of its imports
                del waiting[name]
        time.sleep(0.005)
    assert not waiting, f'never loaded rclpy/torch/pybullet/cv2: {sorted(waiting)}'
    try:
        for name, proc in procs.items():
            out, _ = proc.communicate(timeout=120)
            assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, f'{name}:\n{out[-3000:]}'
            assert proc.returncode == (130 if name in tools else 0), f'{name}: {proc.returncode}\n{out[-3000:]}'
    finally:
        os.close(terminal)
