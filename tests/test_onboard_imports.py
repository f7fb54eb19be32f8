"""What a vehicle runs never imports the simulator: each onboard node starts where assist_sim and pybullet cannot
be imported (ARCHITECTURE.md: encoder, policy, bridge, teleop, station and landing runner never import assist_sim).

Each executable runs in a subprocess whose PYTHONPATH holds a sitecustomize that puts a finder first on
sys.meta_path: it records every attempt to import assist_sim or pybullet (and their submodules) and raises
ImportError. The node is started with a bad parameter (or, teleop, without a terminal), so it imports everything
its main needs, builds as much of the node as it can and exits 1 with one `error:` line; `--help` exits 0.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from assist_common.domains import private_domain_id

BIN = Path(sys.executable).parent
BLOCKED = ('assist_sim', 'pybullet')

SITECUSTOMIZE = textwrap.dedent('''
    """Test blocker: importing assist_sim or pybullet fails and is recorded in $ASSIST_BLOCKED_LOG."""
    import os
    import sys
    import traceback

    BLOCKED = {blocked!r}


    class _Blocker:
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in BLOCKED:
                with open(os.environ['ASSIST_BLOCKED_LOG'], 'a') as fh:
                    where = ''.join(traceback.format_stack(limit=8)[:-1])
                    fh.write(f'import {{name}} attempted\\n{{where}}\\n')
                raise ImportError(f'{{name}} is blocked for this test')
            return None


    sys.meta_path.insert(0, _Blocker())
''').format(blocked=BLOCKED)

# executable -> arguments that make its main exit 1 at start-up, and the text its error line names
ONBOARD = {
    'encoder_node': (['--ros-args', '-p', 'threads:=-1'], "'threads'"),
    'policy_node': (['--ros-args', '-p', 'rate_hz:=-1.0'], "'rate_hz'"),
    'mavlink_bridge_node': (['--ros-args', '-p', 'setpoint_rate_hz:=-1.0'], "'setpoint_rate_hz'"),
    'teleop_keyboard': (['--ros-args', '-p', 'speed:=-1.0'], 'not a terminal'),   # stdin is not a TTY here
    'landing_runner': (['--ros-args', '-p', 'episodes:=-1'], "'episodes'"),
    'pilot_station': (['--ros-args', '-p', 'port:=-1'], "'port'"),
    'image_relay': (['--ros-args', '-p', 'rate_hz:=-1.0'], "'rate_hz'"),
    'image_decoder': (['--ros-args', '-p', 'color_topic:=7'], "'color_topic'"),
}


@pytest.fixture(scope='module')
def blocked_env(tmp_path_factory):
    """Environment whose Python cannot import assist_sim or pybullet; attempts land in the returned log."""
    root = tmp_path_factory.mktemp('blocker')
    (root / 'sitecustomize.py').write_text(SITECUSTOMIZE)
    log = root / 'attempts.log'
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(root), os.environ.get('PYTHONPATH')])),
               ASSIST_BLOCKED_LOG=str(log), ROS_DOMAIN_ID=str(private_domain_id()), PYTHONUNBUFFERED='1')
    return env, log


def test_the_blocker_blocks(blocked_env):
    env, log = blocked_env
    out = subprocess.run([sys.executable, '-c', 'import assist_sim.core.world'], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode != 0 and 'blocked for this test' in out.stderr
    assert 'import assist_sim attempted' in log.read_text()
    log.unlink()


def _run_all(env: dict, commands: dict[str, list[str]]) -> dict[str, subprocess.CompletedProcess]:
    """Run the commands side by side (each imports torch or rclpy: seconds apiece); name -> finished process."""
    procs = {name: subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                    stderr=subprocess.PIPE, text=True, start_new_session=True)
             for name, cmd in commands.items()}
    done = {}
    for name, proc in procs.items():
        try:
            stdout, stderr = proc.communicate(timeout=240)
        except subprocess.TimeoutExpired:
            proc.kill()
            stdout, stderr = proc.communicate()
        done[name] = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    return done


def test_onboard_nodes_start_without_the_simulator(blocked_env):
    env, log = blocked_env
    if log.exists():
        log.unlink()
    results = _run_all(env, {name: [str(BIN / name), *args] for name, (args, _) in ONBOARD.items()})
    attempts = log.read_text() if log.exists() else ''
    assert attempts == '', attempts[:4000]
    for name, (_, named) in ONBOARD.items():
        res = results[name]
        assert res.returncode == 1, f'{name}: exit {res.returncode}\n{res.stderr[-3000:]}'
        errors = [ln for ln in res.stderr.splitlines() if ln.startswith('error:')]
        assert len(errors) == 1 and named in errors[0], f'{name}: {res.stderr[-3000:]}'
        assert 'Traceback' not in res.stderr, f'{name}: {res.stderr[-3000:]}'


def test_onboard_nodes_answer_help_without_the_simulator(blocked_env):
    env, log = blocked_env
    if log.exists():
        log.unlink()
    results = _run_all(env, {name: [str(BIN / name), '--help'] for name in ONBOARD})
    assert not log.exists(), log.read_text()[:4000]
    for name, res in results.items():
        assert res.returncode == 0 and res.stdout.startswith(f'usage: {name}'), f'{name}: {res.stderr[-3000:]}'
