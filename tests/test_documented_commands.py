"""Every command in the READMEs, docs/results.md and the model cards runs as written, from the repository root.

Each fenced shell block runs in bash (`-eu -o pipefail`, so every line must succeed), in order, file after
file (GROUPS), in a scratch copy of the repository root (models/ copied, the rest linked read-only), so the
commands' outputs (runs/, flights/, data/) and their chaining (a bag recorded by one line and replayed
by the next) are exercised as a user meets them. Programs are found on PATH / .venv/bin as written, but
each is tests/standins/doc_shim.py: the workspace's tools run for real with tiny budgets (one landing,
one beta, eight frames, a few training steps), and what needs a robot or the ROS 2 CLI (`ros2 launch`,
`ros2 run`, `ros2 service call`, node executables with `--ros-args`) is checked against the launch
files' declared arguments and the nodes' declared parameters instead. The suite and the benchmarks
(`make test`, `python -m pytest`, `python -m bench`) are run elsewhere; ArduPilot's `sim_vehicle.py` is
the only program not available here.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from assist_common.cache import CACHE_ENV, OFF, cache_root
from assist_common.domains import private_domain_ids

pytestmark = pytest.mark.slow(seconds=350)

REPO = Path(__file__).resolve().parents[1]
SHIM = REPO / 'tests' / 'standins' / 'doc_shim.py'
REAL_BIN = Path(sys.executable).parent
# Documents in groups: within a group in order, in one scratch root (a later block uses what an earlier one
# made); each group has its own scratch root; the longest first.
GROUPS = [['ros2_ws/src/assist_station/README.md'],
          ['README.md', 'ros2_ws/src/assist_sim/README.md', 'ros2_ws/src/assist_bridge/README.md', 'bench/README.md',
           'docs/deployment.md'],
          ['ros2_ws/src/assist_perception/README.md'],
          ['models/cmvae.md'],
          ['ros2_ws/src/assist_lab/README.md', 'ros2_ws/src/assist_policy/README.md', 'docs/bags.md'],
          ['docs/results.md'],
          ['models/td3_latent_actor.md', 'models/td3_oracle_actor.md', 'models/td3_end_to_end_actor.md']]
DOCUMENTS = [doc for group in GROUPS for doc in group]
SHELL_BLOCK = re.compile(r'^```(?:bash|sh|shell)\n(.*?)^```', re.S | re.M)


def console_scripts() -> list[str]:
    """Every executable the workspace's packages install (their setup.py console_scripts)."""
    names = []
    for setup in sorted((REPO / 'ros2_ws' / 'src').glob('*/setup.py')):
        names += re.findall(r"'(\w+) = [\w.]+:\w+'", setup.read_text())
    return names


PROGRAMS = console_scripts()
UNAVAILABLE = {'sim_vehicle.py'}        # ArduPilot SITL: checked by hand (assist_bridge README)


def shell_blocks(path: Path) -> list[str]:
    """The fenced bash/sh blocks of a Markdown file."""
    return SHELL_BLOCK.findall(path.read_text())


def test_every_document_with_commands_is_listed():
    listed = {REPO / d for d in DOCUMENTS}
    candidates = [REPO / 'README.md', *(REPO / 'ros2_ws' / 'src').glob('*/README.md'), *(REPO / 'docs').glob('*.md'),
                  *(REPO / 'models').glob('*.md'), *(REPO / 'bench').glob('*.md')]
    unlisted = [str(p.relative_to(REPO)) for p in candidates if shell_blocks(p) and p not in listed]
    assert not unlisted, f'documents with shell blocks that no test runs: {unlisted}'


def scratch_root(tmp: Path) -> Path:
    """A repository root to run commands in: models/ copied (a command may write there), the rest linked."""
    root = tmp / 'repo'
    root.mkdir()
    shutil.copytree(REPO / 'models', root / 'models')
    for name in ('docs', 'bench', 'tests', 'Makefile', 'requirements.txt'):
        (root / name).symlink_to(REPO / name)
    (root / 'ros2_ws' / 'install').mkdir(parents=True)
    (root / 'ros2_ws' / 'src').symlink_to(REPO / 'ros2_ws' / 'src')
    # `make colcon` and sourcing a real install are exercised by tests/test_launch_files.py
    (root / 'ros2_ws' / 'install' / 'setup.bash').write_text('# stand-in for a colcon install\n')
    venv_bin = root / '.venv' / 'bin'
    venv_bin.mkdir(parents=True)
    (venv_bin / 'activate').write_text('# the scratch venv: PATH is set by the test\n')
    shims = tmp / 'shims'
    shims.mkdir()
    for name in (*PROGRAMS, 'python'):
        _shim(venv_bin / name, name)
    for name in ('ros2', 'make', 'sim_vehicle.py', *PROGRAMS):
        _shim(shims / name, name)
    return root


def _shim(path: Path, program: str) -> None:
    path.write_text(f'#!/bin/sh\nexec "{sys.executable}" "{SHIM}" "{program}" "$@"\n')
    path.chmod(0o755)


@contextlib.contextmanager
def fork_server(sock: Path, root: Path, env: dict) -> Iterator[Path]:
    """tests/standins/doc_forkserver.py on `sock` with the group's environment, until the group is done."""
    proc = subprocess.Popen([sys.executable, str(REPO / 'tests' / 'standins' / 'doc_forkserver.py'), str(sock)],
                            cwd=root, env=env, stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not sock.exists():
            assert proc.poll() is None, f'the fork server exited ({proc.returncode})'
            assert time.monotonic() < deadline, 'the fork server did not start in 120 s'
            time.sleep(0.1)
        yield sock
    finally:
        os.killpg(proc.pid, signal.SIGKILL)          # the server and any child still running
        proc.wait(30)


def test_documented_commands_run_as_written(tmp_path):
    log = tmp_path / 'calls.jsonl'
    domains = private_domain_ids(len(GROUPS))             # a private DDS domain per group
    (tmp_path / 'home').mkdir()
    base = dict(os.environ, HOME=str(tmp_path / 'home'), DOC_SHIM_REPO=str(REPO), DOC_SHIM_REAL_BIN=str(REAL_BIN),
                DOC_SHIM_LOG=str(log), MPLBACKEND='Agg')
    base.pop('DISPLAY', None)
    # the user's cache (exported actors and encoders, generated textures), as every other test uses it: with only
    # the scratch HOME, each group's first node start would export the models again (torch, ~5 s of CPU a node)
    root = cache_root()
    base[CACHE_ENV] = str(root) if root is not None else OFF

    def run_group(index: int, sock: Path) -> list[str]:
        scratch = tmp_path / f'group{index}'
        scratch.mkdir()
        root = scratch_root(scratch)
        (scratch / 'home').mkdir()
        # each call hands the fork server its own directory and environment: one server serves every group
        env = dict(base, PATH=f'{root / ".venv" / "bin"}:{scratch / "shims"}:{os.environ["PATH"]}',
                   HOME=str(scratch / 'home'), ROS_DOMAIN_ID=str(domains[index]), DOC_SHIM_FORKSERVER=str(sock))
        failures = []
        for doc in GROUPS[index]:
            for k, block in enumerate(shell_blocks(REPO / doc)):
                proc = subprocess.run(['bash', '-eu', '-o', 'pipefail', '-c', block], cwd=root, env=env,
                                      stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=900)
                if proc.returncode != 0:
                    failures.append(f'--- {doc}, block {k + 1} (exit {proc.returncode}):\n{block}\n'
                                    f'{proc.stdout[-1500:]}\n{proc.stderr[-2500:]}')
        return failures
    # two groups at a time alone; one at a time beside another test worker (make test), which keeps the machine's
    # load what the graph tests beside it are written for
    with fork_server(tmp_path / 'fork.sock', tmp_path, base) as sock, \
            ThreadPoolExecutor(1 if os.environ.get('PYTEST_XDIST_WORKER') else 2) as pool:
        failures = [f for group_failures in pool.map(run_group, range(len(GROUPS)), [sock] * len(GROUPS))
                    for f in group_failures]
    calls = [json.loads(line) for line in log.read_text().splitlines()]
    assert not failures, '\n'.join(failures)
    unavailable = {c['program'] for c in calls if c['how'] == 'unavailable'}
    assert unavailable <= UNAVAILABLE, unavailable
    ran = {c['program'] for c in calls if c['how'] == 'run'}
    # the workspace's tools did run (not only checks): the documents exercise each of them
    assert {'evaluate', 'evaluate_graph', 'compare_landings', 'train_td3', 'replay_assist', 'plot_flight',
            'bag_record', 'bag_play', 'make_dataset', 'train_cmvae', 'evaluate_cmvae'} <= ran, sorted(ran)
    assert all(c['rc'] == 0 for c in calls), [c for c in calls if c['rc']]
