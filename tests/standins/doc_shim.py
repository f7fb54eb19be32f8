"""Stand-in for each program a documented command calls (tests/test_documented_commands.py; tests only).

`doc_shim.py PROGRAM ARGS...`: what PROGRAM would do, at a test's budget, with a JSON line per call in
$DOC_SHIM_LOG ({program, args, how, rc}). `how` is one of:

- `run`: the workspace's own command-line tools run for real, with their long budgets cut (one landing
  of at most LANDING_S, one beta, eight frames, one epoch, a few training steps; see `budget`), each in a child forked
  from the test's fork server when $DOC_SHIM_FORKSERVER names one (tests/standins/doc_forkserver.py);
  bag_record / bag_play run for real and get a Ctrl-C after a few seconds, as the docs say to stop them.
- `checked`: what cannot run inside a test without a robot or the ROS 2 CLI is checked instead of run:
  `ros2 launch` (every `name:=value` is a declared argument and one of its choices, from the launch
  file itself through the launch stand-in), `ros2 run` and a node executable with `--ros-args` (the
  executable exists; each `-p name:=value` is a declared parameter whose value its type and range
  accept; each `--params-file` exists and holds only declared parameters), `ros2 service call` (a
  node of the workspace creates that service with that type).
- `elsewhere`: `make demo|test|colcon`, `python -m pytest|bench`: tested by the suite itself.
- `unavailable`: ArduPilot's `sim_vehicle.py` (not installable from a registry).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(os.environ['DOC_SHIM_REPO'])
REAL_BIN = Path(os.environ['DOC_SHIM_REAL_BIN'])
LOG = Path(os.environ['DOC_SHIM_LOG'])
STARTED = time.monotonic()


def _node_modules() -> dict[str, str]:
    """node executable -> module with its PARAMS: the node registry docs/nodes.md is made from (docs/gen_nodes.py)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location('gen_nodes', REPO / 'docs' / 'gen_nodes.py')
    gen_nodes = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen_nodes)
    return {exe: module for exe, module in gen_nodes.nodes().items() if exe not in ('bag_record', 'bag_play')}


NODES = _node_modules()
# sim seconds a documented landing may last: the commands' plumbing is what is checked, not the landing
LANDING_S = 1.5
STOPPED_BY_CTRL_C = {'bag_record': 4.0, 'bag_play': 4.0}     # seconds they run before the Ctrl-C


def _values(args: list[str], opt: str) -> list[str] | None:
    """The values after the last `opt` (None when absent)."""
    found = None
    for i, a in enumerate(args):
        if a == opt:
            j = i + 1
            while j < len(args) and not args[j].startswith('--'):
                j += 1
            found = args[i + 1:j]
    return found


def _set(args: list[str], opt: str, *values: str) -> list[str]:
    """`args` without any `opt` (and its values), then `opt values...` appended."""
    out, i = [], 0
    while i < len(args):
        if args[i] == opt:
            i += 1
            while i < len(args) and not args[i].startswith('--'):
                i += 1
            continue
        out.append(args[i])
        i += 1
    return out + [opt, *values]


def _cap(args: list[str], opt: str, most: float, default_when_absent: bool = True) -> list[str]:
    """At most `most` for a numeric option (set to `most` when absent and default_when_absent)."""
    got = _values(args, opt)
    if got:
        value = min(float(got[0]), most)
    elif default_when_absent:
        value = most
    else:
        return args
    return _set(args, opt, str(int(value)) if float(value).is_integer() else str(value))


def _first(args: list[str], opt: str, fallback: str | None) -> list[str]:
    """Only the first value of a list option (`fallback` when absent; untouched when that is None)."""
    got = _values(args, opt)
    if got:
        return _set(args, opt, got[0])
    return _set(args, opt, fallback) if fallback is not None else args


def budget(program: str, args: list[str]) -> list[str]:
    """The documented arguments with the long budgets cut to a test's."""
    if program == 'evaluate' and '--from-csv' not in args:
        # one landing, no figure (evaluate's plot is tested by the lab's own tests)
        args = _cap(_first(_set(_set(args, '--landings', '1'), '--plot', 'false'), '--betas', '0.5'),
                    '--max-episode-s', LANDING_S)
        return _set(args, '--workers', '1') if '--workers' in args else args     # a few landings: no worker processes
    if program == 'evaluate_graph':
        args = _cap(_first(_set(_set(args, '--landings', '1'), '--plot', 'false'), '--betas', '0.5'),
                    '--max-episode-s', LANDING_S)
        conditions = _values(args, '--conditions')
        return _set(args, '--conditions', conditions[-1]) if conditions else args
    if program == 'train_td3':
        for opt, most in (('--total-steps', 40), ('--start-steps', 20), ('--demo-episodes', 1),
                          ('--dagger-episodes', 1), ('--bc-steps', 2), ('--critic-warmup-updates', 5),
                          ('--eval-episodes-per-beta', 1), ('--buffer-size', 5000), ('--max-episode-s', LANDING_S)):
            args = _cap(args, opt, most,
                        default_when_absent=opt in ('--total-steps', '--max-episode-s', '--eval-episodes-per-beta'))
        args = _set(args, '--workers', '1') if '--workers' in args else args   # no pool (the lab's tests fly one)
        return _cap(args, '--dagger-rounds', 1, default_when_absent=False)
    if program == 'simulate_study':
        # the graph at 3x real time, as tests/test_study_graph.py flies it, and landings of at most 3 s (the
        # landings need not be flown well: the protocol, its files and their analysis are what is checked)
        for opt, value in (('--participants', '1'), ('--landings-per-block', '1'), ('--practice', '0'),
                           ('--browser-participants', '0'), ('--record-bags', 'false'), ('--real-time-factor', '3'),
                           ('--max-landing-s', '3')):
            args = _set(args, opt, value)
        return args
    if program == 'make_dataset':
        return args + ['--frames', '8', '--frames-per-scene', '4', '--scenes-per-shard', '1', '--no-progress']
    if program == 'train_cmvae':
        return args + ['--epochs', '1', '--max-frames', '8', '--batch-size', '4', '--no-progress']
    if program == 'evaluate_cmvae':
        return args + ['--max-frames', '4', '--pairs', '1', '--steps', '2', '--batch-size', '2']
    return args


def _log(program: str, args: list[str], how: str, rc: int, note: str = '') -> int:
    with open(LOG, 'a') as f:
        f.write(json.dumps({'program': program, 'args': args, 'how': how, 'rc': rc, 'note': note,
                            'seconds': round(time.monotonic() - STARTED, 1)}) + '\n')
    return rc


def _fail(program: str, args: list[str], why: str) -> int:
    sys.stderr.write(f'{program}: {why}\n')
    return _log(program, args, 'checked', 1, why)


def run_tool(program: str, args: list[str]) -> int:
    """The real tool with a test's budget (bag_record / bag_play: Ctrl-C after a few seconds)."""
    cmd = [str(REAL_BIN / program), *budget(program, args)]
    if program not in STOPPED_BY_CTRL_C:
        server = os.environ.get('DOC_SHIM_FORKSERVER')
        if server:          # the test's fork server: the same entry point without another interpreter start-up
            sys.path.insert(0, str(Path(__file__).resolve().parent))
            from doc_forkserver import call
            return _log(program, cmd[1:], 'run', call(server, program, cmd[1:]))
        return _log(program, cmd[1:], 'run', subprocess.call(cmd))
    proc = subprocess.Popen(cmd, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        rc = proc.wait(STOPPED_BY_CTRL_C[program])
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(60)
    return _log(program, cmd[1:], 'run', rc)


def _params_of(executable: str) -> dict:
    import importlib
    return importlib.import_module(NODES[executable]).PARAMS


def check_ros_args(program: str, executable: str, args: list[str]) -> int:
    """A node's --ros-args: declared parameters with acceptable values, existing parameter files."""
    if executable not in NODES:
        return _fail(program, args, f'no node executable {executable!r} in this workspace')
    params = _params_of(executable)
    rest = args[args.index('--ros-args') + 1:] if '--ros-args' in args else []
    if args[:len(args) - len(rest) - (1 if rest or '--ros-args' in args else 0)]:
        return _fail(program, args, f'unexpected arguments before --ros-args: {args}')
    i = 0
    while i < len(rest):
        flag = rest[i]
        value = rest[i + 1] if i + 1 < len(rest) else ''
        if flag == '-p':
            name, sep, text = value.partition(':=')
            if not sep or name not in params:
                return _fail(program, args, f'{executable} has no parameter {name!r}')
            try:
                params[name].coerce(name, yaml.safe_load(text))
            except ValueError as exc:
                return _fail(program, args, str(exc))
        elif flag == '--params-file':
            path = Path(value)
            if not path.is_file():
                return _fail(program, args, f'no parameter file {value}')
            doc = yaml.safe_load(path.read_text()) or {}
            for section in doc.values():
                unknown = set((section or {}).get('ros__parameters', {})) - set(params)
                if unknown:
                    return _fail(program, args, f'{value}: {executable} has no parameters {sorted(unknown)}')
        elif flag == '-r':
            if ':=' not in value:
                return _fail(program, args, f'malformed remapping {value!r}')
        else:
            return _fail(program, args, f'unknown --ros-args flag {flag!r}')
        i += 2
    return _log(program, args, 'checked', 0)


def check_launch(args: list[str]) -> int:
    """`ros2 launch PKG FILE name:=value...`: every name declared by the launch file, every value allowed."""
    package, file, pairs = args[0], args[1], args[2:]
    path = REPO / 'ros2_ws' / 'src' / package / 'launch' / file
    if not path.is_file():
        return _fail('ros2', args, f'no launch file {package}/{file}')
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import importlib.util

    from ament_index_python import packages
    packages.get_package_share_directory = lambda pkg: str(REPO / 'ros2_ws' / 'src' / pkg)
    spec = importlib.util.spec_from_file_location('doc_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.get_package_share_directory = packages.get_package_share_directory
    declared = {a.name: a for a in module.generate_launch_description().get_launch_arguments()}
    for pair in pairs:
        name, sep, value = pair.partition(':=')
        if not sep or name not in declared:
            return _fail('ros2', args, f'{file} declares no argument {name!r} (has {sorted(declared)})')
        choices = getattr(declared[name], 'choices', None)
        if choices and value not in choices:
            return _fail('ros2', args, f'{name}:={value} is not one of {choices}')
    return _log('ros2', args, 'checked', 0)


def check_service(args: list[str]) -> int:
    """`ros2 service call NAME TYPE`: a node module of the workspace creates a TYPE service and names NAME
    (whole, or its last part in quotes when the names are built in a loop)."""
    name, kind = args[2], args[3]
    short = kind.rsplit('/', 1)[-1]
    base = name.rsplit('/', 1)[-1]
    for src in (REPO / 'ros2_ws' / 'src').glob('*/*/*.py'):
        text = src.read_text()
        if f'create_service({short},' in text and (f"'{name}'" in text or f"'{base}'" in text):
            return _log('ros2', args, 'checked', 0, str(src.relative_to(REPO)))
    return _fail('ros2', args, f'no node creates the service {name} ({kind})')


def check_sitl_series(args: list[str]) -> int:
    """`evaluate_graph --autopilot sitl` needs ArduPilot SITL (checked by hand): its arguments parse and validate."""
    import argparse

    from assist_common.settings import add_dataclass_args, parse_dataclass_args
    from assist_lab.graph_eval import HELP, GraphEvalArgs
    parser = argparse.ArgumentParser(prog='evaluate_graph')
    add_dataclass_args(parser, GraphEvalArgs, HELP)
    try:
        parse_dataclass_args(parser, GraphEvalArgs, args)
    except SystemExit as exc:
        return _fail('evaluate_graph', args, f'arguments refused (exit {exc.code})')
    return _log('evaluate_graph', args, 'checked', 0, 'needs ArduPilot SITL: its arguments are checked')


def main(argv: list[str]) -> int:
    """Dispatch on the program name."""
    program, args = Path(argv[0]).name, argv[1:]
    if program == 'ros2':
        if args[:1] == ['launch'] and len(args) >= 3:
            return check_launch(args[1:])
        if args[:1] == ['run'] and len(args) >= 3:
            return check_ros_args('ros2', args[2], args[3:])
        if args[:2] == ['service', 'call'] and len(args) >= 4:
            return check_service(args)
        return _fail('ros2', args, 'only `ros2 launch|run|service call` are documented here')
    if program == 'make':
        if args and all(a in ('demo', 'test', 'colcon') for a in args):
            return _log(program, args, 'elsewhere', 0)
        return _fail(program, args, f'unknown make targets {args}')
    if program == 'python':
        if args[:2] in (['-m', 'pytest'], ['-m', 'bench']):
            return _log(program, args, 'elsewhere', 0)
        return _log(program, args, 'run', subprocess.call([sys.executable, *args]))
    if program == 'sim_vehicle.py':
        return _log(program, args, 'unavailable', 0)
    if program == 'evaluate_graph' and (_values(args, '--autopilot') or [])[:1] == ['sitl']:
        return check_sitl_series(args)
    if program in NODES:
        if any(a in ('-h', '--help', '--version') for a in args):
            return _log(program, args, 'run', subprocess.call([str(REAL_BIN / program), *args],
                                                              stdout=subprocess.DEVNULL))
        return check_ros_args(program, program, args)
    return run_tool(program, args)


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
