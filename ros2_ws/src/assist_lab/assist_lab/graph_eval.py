"""evaluate_graph: `evaluate`'s landings flown through the real node graph, as a user runs it.

For each condition one graph runs every landing in turn, never restarted between landings: sim_node
(auto_reset, use_sim_time, `--real-time-factor`), encoder_node (latent only; depth noise on), policy_node
(mode = the condition, its default rules as `evaluate` flies them, or as --safety/--override/--recall/--damper
set them) and sim_pilot_node, each the console script of this virtualenv in its own process on a private
ROS_DOMAIN_ID (`--domain-id`; 0 picks one no other graph on this machine is using). Unassisted: no
policy_node; sim_node flies /pilot/cmd_vel (its /cmd_vel input remapped).

Same landings as `evaluate`: landing k at beta index b has seed `--seed` + 1000 b + k, and
assist_lab.episodes_plan.landing_plan turns it into what LandingAssistEnv.reset draws (scene seed, pilot
family and seed, depth-noise seed). The graph is told the plan in order: sim_node `episode_seeds` (scene of
episode 0, 1, ...), sim_pilot_node `episode_seeds`/`episode_betas`/`episode_pilots` (the env's pilot of each
landing), sim_node `episode_timeout_s` = `--max-episode-s` (the env's 60 s cut; the world's own is 90 s).
encoder_node has one `noise_seed` for the whole run (the first landing's noise seed), while the env reseeds its
depth noise per landing; with message timing and frames dropped under load, landings agree with the env within
noise, not bit for bit.

Each landing is read from /sim/landing by a small rclpy listener in this process; the row has evaluate's
columns (evaluate.LANDING_FIELDS) and condition names. active_fraction counts /assist/agent_cmd messages above
the blending threshold per control step (20 Hz); guard/wall/override/recall/damper fractions come from
policy_node's /diagnostics counters, published once a wall second and interpolated at the landing's start
and end in sim time (approximate); aimed_index from sim_pilot_node's goal_estimate on /diagnostics.

    evaluate_graph --out runs/graph_eval --landings 4 --betas 0 0.5 1 --conditions unassisted latent
    evaluate_graph --out runs/graph_eval_mix --pilot mix --landings 4 --betas 0 0.5 1 --real-time-factor 2

Writes <out>/landings.csv, summary.csv, paired.txt, error_vs_beta.png as `evaluate` does (crash-safe and
resumable the same way: an interrupted run flies only the landings still missing) and every node's log
under <out>/nodes/. One run at a time per <out> (a second exits 2 naming the holder's pid). The graph must
keep up with the sim: each landing's policy coverage (control steps the policy ran / sim steps) is logged and a
warning printed below 90 %; lower --real-time-factor then.
Children are stopped with SIGINT (SIGKILL after a timeout) on the way out, Ctrl-C and errors included,
and die with this process (PR_SET_PDEATHSIG) if it is killed.

`--autopilot sitl` flies the landings on real ArduCopter SITL (docs/ardupilot-sitl-json.md): per condition it
starts `--sitl-binary` (`--model JSON:127.0.0.1 --wipe -I<instance> --speedup <s>`, parameters from
`--sitl-defaults`: ArduPilot's copter.parm, then assist_sim's ardupilot_json_quad.parm), sim_node as its JSON
physics (udp 9002 + 10 * instance, `episode_seeds` from the plan: SITL restarts do not shift the scenes),
mavlink_bridge_node (tcp 5760 + 10 * instance), landing_runner (arms, takes off and lands each landing; its
results file in nodes/<condition>/ gives the rows' autopilot_landed), the pilot starting each landing at 1.5 m and
encoder_node with level_camera. `--sitl-connection` flies a SITL already running instead. When SITL dies, goes
silent or never arms, the condition's graph and SITL are started afresh for the landings still missing
(`--sitl-restarts` times). SITL sets the pace (`--sitl-speedup`; --real-time-factor is not used):

    evaluate_graph --autopilot sitl --conditions unassisted oracle --betas 0.5 --landings 3 --seed 11
"""
from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

import numpy as np
import rclpy
import rclpy.signals
from assist_common.constants import BLEND_THRESHOLD_MPS
from assist_common.domains import DOMAIN_IDS_ENV, domain_range
from assist_common.ros_io import LANDING_QOS, LATCHED_QOS, RELIABLE_QOS, stamp_to_sec
from assist_sim.core.arducopter import FLIGHT_CONTROLLERS
from assist_sim.pilots import GRAPH_PILOT_NAMES
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, TwistStamped
from rcl_interfaces.srv import SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from assist_common.settings import check_settings, parse_command, setting
from .cluster import DirectoryBusy, hold_directory
from .episodes_plan import LandingPlan, evaluation_plans
from assist_policy.rules import RULES, Rule, rule_fields
from .evaluate import (
    CONDITIONS,
    MAX_EVAL_SEED,
    EvalArgs,
    LandingLog,
    condition_name,
    cues_shown,
    print_results,
    rule_option,
    rules_flying,
    write_results,
)

log = logging.getLogger(__name__)

BIN = Path(sys.executable).parent
CONTROL_HZ = 20.0                       # the world's control rate: the policy's and the pilot's step
# policy_node diagnostics counters -> evaluate's fraction columns
POLICY_COUNTERS = {'wall_fraction': 'wall_guard_engaged',
                   **{f'{r.flag}_fraction': f'{r.switch}_engaged' for r in RULES}}
AUTO_DOMAINS = range(200, 233)          # 233+ overflow Fast DDS's default UDP ports
AUTOPILOTS = ('none', 'sitl')
# ArduPilot SITL (AP_HAL_SITL/SITL_cmdline.cpp): -I N moves SERIAL0 (tcp 5760) and the JSON physics port (SIM_OUT_PORT
# 9002, where --model JSON sends its servo frames) up by 10 N each
SITL_MAVLINK_PORT = 5760
SITL_JSON_PORT = 9002
SITL_PORT_STRIDE = 10
PEERS_SITL_BINARY = Path('/work/peers/ardupilot/build/sitl/bin/arducopter')
SITL_START_ALTITUDE_M = 1.5             # the pilot starts each landing after landing_runner's takeoff climb
SITL_RUNNER_RESULTS = 'landing_runner'  # <log_dir>/landing_runner-<start time>.csv: the runner's results
RUNNER_VERDICT_WAIT_S = 10.0            # landing_runner writes a row after the autopilot's verdict (3 s at most)
# the sim starts slowly while the other nodes' subscriptions match its publishers and their first inferences
# warm up (at full speed the first landing lost ~15 % of its policy steps), then runs at --real-time-factor
WARMUP_RTF = 0.5
WARMUP_WALL_S = 3.0
_EVAL = EvalArgs()
# how a run is carried out, not what it measures: a resumed run may change them
RUN_ONLY_ARGS = ('out', 'plot', 'domain_id', 'landing_timeout_s', 'startup_timeout_s', 'sitl_binary', 'sitl_defaults',
                 'sitl_instance', 'sitl_connection', 'sitl_preload', 'sitl_restarts')


@dataclass
@rule_fields(rule_option, lambda r: bool | None)     # a field per non-learned rule, as evaluate's
class GraphEvalArgs:
    """Command-line arguments of evaluate_graph (every field is a --flag)."""

    out: str = setting('runs/graph_eval', nonempty=True)
    conditions: tuple[str, ...] = setting(('unassisted', 'latent'), choices=CONDITIONS, min_len=1)
    alpha: float = setting(_EVAL.alpha, ge=0.0, le=1.0)
    betas: tuple[float, ...] = setting(_EVAL.betas, ge=0.0, le=1.0, min_len=1)
    landings: int = setting(_EVAL.landings, ge=1, le=100_000)
    seed: int = setting(_EVAL.seed, ge=0, le=MAX_EVAL_SEED)
    pilot: str = setting('paper', choices=GRAPH_PILOT_NAMES)
    latent_model: str = ''
    oracle_model: str = ''
    end_to_end_model: str = ''
    encoder_path: str = ''
    max_episode_s: float = setting(_EVAL.max_episode_s, gt=0.0, le=3600.0)
    real_time_factor: float = setting(2.0, gt=0.0, le=100.0)
    domain_id: int = setting(0, ge=0, le=232)
    depth_noise: bool = True
    landing_timeout_s: float = setting(300.0, gt=0.0, le=86_400.0)
    startup_timeout_s: float = setting(180.0, gt=0.0, le=3600.0)
    policy_params: tuple[str, ...] = ()
    flight_controller: str = setting('ideal', choices=FLIGHT_CONTROLLERS)
    autopilot: str = setting('none', choices=AUTOPILOTS)
    sitl_binary: str = ''
    sitl_defaults: tuple[str, ...] = ()
    sitl_instance: int = setting(0, ge=0, le=50)
    sitl_speedup: float = setting(1.0, gt=0.0, le=100.0)
    sitl_connection: str = ''
    sitl_preload: str = ''
    sitl_restarts: int = setting(2, ge=0, le=100)
    cues: bool = False
    cue_trust: float = setting(1.0, ge=0.0, le=1.0)
    plot: bool = True


HELP = {
    'out': 'output directory (landings.csv, summary.csv, paired.txt, error_vs_beta.png, nodes/*.log)',
    'conditions': 'any of unassisted latent oracle end_to_end (policy_node modes; evaluate\'s names)',
    'betas': 'pilot skills (landing k at beta index b: seed + 1000 b + k, as evaluate)',
    'flight_controller': 'sim_node flight_controller: ideal or arducopter (ArduCopter GUIDED as the bridge flies it; '
                         'encoder_node then levels the leaning camera, level_camera true)',
    'landings': 'landings per beta and condition',
    'pilot': 'simulated pilot: paper or an assist_sim.pilots family or population (mix: a held-out family per landing)',
    'latent_model': 'policy_node model_path for latent (default: the shipped actor)',
    'oracle_model': 'policy_node model_path for oracle',
    'end_to_end_model': 'policy_node model_path for end_to_end',
    'encoder_path': 'encoder_node model_path (default: the shipped CM-VAE)',
    'max_episode_s': 'sim_node episode_timeout_s: a landing not finished by then is a timeout (the env\'s cut)',
    **{r.field: (f'policy_node {r.switch} (rows +{r.flag})' if not r.goal_agnostic else
                 f'policy_node {r.switch} for every assistant; unset: policy_node\'s default for the mode')
       for r in RULES},
    'real_time_factor': 'sim_node real_time_factor: sim seconds per wall second (the nodes must keep up: 2 on two '
                        'cores; 0 = as fast as possible, which they do not)',
    'domain_id': 'ROS_DOMAIN_ID of the graph (1-232); 0: the first of 200-232 nobody on this machine uses',
    'depth_noise': 'encoder_node depth_noise (the env\'s camera noise)',
    'landing_timeout_s': 'wall seconds without a landing after which the graph counts as stalled (error)',
    'startup_timeout_s': 'wall seconds the nodes may take to come up',
    'policy_params': 'extra policy_node parameters, name:=value (e.g. floor_guard_wall_radius_m:=0.0); rows keep '
                     'their names, the settings file records them',
    'autopilot': 'none: the sim flies the commands (--flight-controller); sitl: real ArduCopter SITL flies them '
                 '(sim_node as its JSON physics, mavlink_bridge_node, landing_runner; --real-time-factor unused)',
    'sitl_binary': f'arducopter SITL binary started per condition (default {PEERS_SITL_BINARY} if it exists)',
    'sitl_defaults': 'SITL --defaults parameter files, in order (default: <ardupilot>/Tools/autotest/default_params/'
                     'copter.parm of the binary\'s checkout, then assist_sim\'s config/ardupilot_json_quad.parm)',
    'sitl_instance': 'SITL -I instance: MAVLink tcp:127.0.0.1:5760+10*I, JSON physics udp 9002+10*I',
    'sitl_speedup': 'SITL --speedup (sim seconds per wall second; the graph must keep up: watch the coverage)',
    'sitl_connection': 'MAVLink address of a SITL already running (started with --model JSON:127.0.0.1 and the '
                       'instance\'s JSON port); empty: evaluate_graph starts its own, wiped, per condition',
    'cues': 'the simulated pilot reads the assistant\'s intent (sim_pilot_node cue_trust; policy_node publishes it '
            'always); the assisted conditions are named <condition>+cues, as evaluate\'s',
    'cue_trust': 'with --cues: the chance per landing that the pilot reads the cues',
    'sitl_preload': 'LD_PRELOAD for the SITL process (e.g. a shim that binds its ports to loopback)',
    'sitl_restarts': 'times a condition\'s graph (its own SITL included) is started afresh for the landings still '
                     'missing after SITL died, went silent or never armed',
}


class GraphError(RuntimeError):
    """The graph could not start, a node died, or landings stopped coming."""


# ----------------------------------------------------------------------------------------- processes
# util-linux setpriv sets PR_SET_PDEATHSIG and execs the node: it gets SIGTERM if this process dies, even killed
SETPRIV = shutil.which('setpriv')


def _yaml_value(value: Any) -> str:
    """A parameter value in YAML flow style (json is YAML; floats keep their point)."""
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_yaml_value(v) for v in value) + ']'
    if isinstance(value, float):
        return repr(float(value))
    return json.dumps(value)


def write_params_file(path: Path, node: str, params: dict[str, Any]) -> None:
    """A ROS 2 --params-file for one node."""
    lines = [f'{node}:', '  ros__parameters:'] + [f'    {k}: {_yaml_value(v)}' for k, v in params.items()]
    path.write_text('\n'.join(lines) + '\n', encoding='utf-8')


class NodeGroup:
    """Node console scripts as child processes on one domain; stop() ends them all (SIGINT, then SIGKILL)."""

    def __init__(self, domain_id: int, log_dir: Path):
        self.domain_id = domain_id
        self.log_dir = log_dir
        log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: dict[str, Any] = {}

    def start(self, executable: str, params: dict[str, Any], remaps: dict[str, str] | None = None,
              extra: tuple[str, ...] = ()) -> None:
        """Start `executable` with these parameters (written to a params file) and remappings."""
        exe = BIN / executable
        if not exe.exists():
            raise GraphError(f'{exe} not installed (make venv)')
        param_file = self.log_dir / f'{executable}.params.yaml'
        write_params_file(param_file, executable, params)
        cmd = [str(exe), '--ros-args', '--params-file', str(param_file)]
        if SETPRIV:
            cmd = [SETPRIV, '--pdeathsig', 'TERM', *cmd]
        for arg in extra:
            cmd += ['-p', arg]
        for k, v in (remaps or {}).items():
            cmd += ['-r', f'{k}:={v}']
        env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain_id), PYTHONUNBUFFERED='1')
        fh = open(self.log_dir / f'{executable}.log', 'a', encoding='utf-8')  # closed in stop()
        fh.write(f'$ {" ".join(cmd)}\n')
        fh.flush()
        self._logs[executable] = fh
        self.procs[executable] = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT,
                                                  start_new_session=True)
        log.info('started %s (pid %d, domain %d)', executable, self.procs[executable].pid, self.domain_id)

    def start_process(self, name: str, cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> None:
        """Start a program that is not a node (SITL) in `cwd`, logged to <log_dir>/<name>.log; stopped with the rest.

        Not in a session of its own and no setpriv: ArduPilot SITL exits by itself once its parent (this process)
        is gone."""
        cwd.mkdir(parents=True, exist_ok=True)
        fh = open(self.log_dir / f'{name}.log', 'a', encoding='utf-8')  # closed in stop()
        fh.write(f'$ (cd {cwd}) {" ".join(cmd)}\n')
        fh.flush()
        self._logs[name] = fh
        self.procs[name] = subprocess.Popen(cmd, cwd=cwd, env=dict(os.environ, **(env or {})), stdout=fh,
                                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            process_group=0)
        log.info('started %s (pid %d)', name, self.procs[name].pid)

    def tail(self, executable: str, chars: int = 1500) -> str:
        """The end of a node's log."""
        path = self.log_dir / f'{executable}.log'
        return path.read_text(encoding='utf-8', errors='replace')[-chars:] if path.exists() else ''

    def check(self, done_ok: tuple[str, ...] = ()) -> None:
        """GraphError if a node has exited (those in `done_ok` may exit with status 0)."""
        for name, proc in self.procs.items():
            if proc.poll() is not None and not (name in done_ok and proc.returncode == 0):
                raise GraphError(f'{name} exited with code {proc.returncode}:\n{self.tail(name)}')

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGINT every node, wait up to `timeout_s` for all of them, SIGKILL the rest (their process groups)."""
        for proc in self.procs.values():
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGINT)
                except ProcessLookupError:
                    pass
        end = time.monotonic() + timeout_s
        for name, proc in self.procs.items():
            try:
                proc.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning('%s did not stop on SIGINT within %.0f s: killed', name, timeout_s)
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                proc.wait(5)
        for fh in self._logs.values():
            fh.close()
        self.procs.clear()
        self._logs.clear()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


# ----------------------------------------------------------------------------------------- listener
class Listener:
    """rclpy node in this process: landings, episode starts, scenes, agent commands and diagnostics."""

    def __init__(self, domain_id: int, clock: bool = False):
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
        self.node = Node('graph_eval_listener', context=self.ctx)
        self.lock = threading.Lock()
        self.landings: dict[int, dict] = {}
        self.goal_stamps: list[float] = []             # sim time each episode started (/sim/goal stamp)
        self.scenes: list[np.ndarray] = []             # pad top centres of each episode
        self.scene_stamps: list[float] = []            # sim time of each /sim/scene
        self.now = 0.0                                 # latest /clock (clock=True)
        self.landing_stamps: dict[int, float] = {}     # episode -> /clock when its landing came (clock=True)
        self.agent: list[tuple[float, float]] = []     # (sim stamp, |a|) of /assist/agent_cmd
        self.policy_diag: list[tuple[float, dict[str, float]]] = []
        self.pilot_diag: dict[int, dict[str, str]] = {}   # episodes counter -> values (first seen)
        n = self.node
        n.create_subscription(String, '/sim/landing', self._on_landing, LANDING_QOS)
        n.create_subscription(PointStamped, '/sim/goal', self._on_goal, LATCHED_QOS)
        n.create_subscription(MarkerArray, '/sim/scene', self._on_scene, LATCHED_QOS)
        n.create_subscription(TwistStamped, '/assist/agent_cmd', self._on_agent, RELIABLE_QOS)
        n.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)
        if clock:   # SITL: episodes start on the ground, so a landing's window is read back from its end
            n.create_subscription(Clock, '/clock', self._on_clock, 10)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(n)
        self.thread = threading.Thread(target=self._spin, name='graph_eval_listener', daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception as exc:  # noqa: BLE001 - shutdown races end the spin; anything else is logged
            if self.ctx.ok():
                log.error('listener stopped: %r', exc)

    def _on_landing(self, msg) -> None:
        data = json.loads(msg.data)
        with self.lock:
            self.landings[int(data['episode'])] = data
            self.landing_stamps[int(data['episode'])] = self.now

    def _on_clock(self, msg) -> None:
        with self.lock:
            self.now = max(self.now, stamp_to_sec(msg.clock))

    def _on_goal(self, msg) -> None:
        with self.lock:
            self.goal_stamps.append(stamp_to_sec(msg.header.stamp))

    def _on_scene(self, msg) -> None:
        tops = {m.id: (m.pose.position.x, m.pose.position.y, m.pose.position.z + 0.5 * m.scale.z)
                for m in msg.markers if m.ns == 'platforms'}
        if tops:
            with self.lock:
                self.scenes.append(np.array([tops[k] for k in sorted(tops)], dtype=float))
                self.scene_stamps.append(stamp_to_sec(msg.markers[0].header.stamp))

    def scene_at(self, t: float) -> np.ndarray | None:
        """Pad top centres of the last /sim/scene stamped at or before sim time t (None: none yet)."""
        with self.lock:
            found = [pads for stamp, pads in zip(self.scene_stamps, self.scenes) if stamp <= t + 1e-6]
        return found[-1] if found else None

    def _on_agent(self, msg) -> None:
        a = msg.twist.linear
        with self.lock:
            self.agent.append((stamp_to_sec(msg.header.stamp), math.sqrt(a.x * a.x + a.y * a.y + a.z * a.z)))

    def _on_diag(self, msg) -> None:
        stamp = stamp_to_sec(msg.header.stamp)
        for st in msg.status:
            values = {kv.key: kv.value for kv in st.values}
            if st.hardware_id == 'policy_node':
                counts = {}
                for key in POLICY_COUNTERS.values():
                    try:
                        counts[key] = float(values.get(key, 0))
                    except ValueError:
                        counts[key] = 0.0
                with self.lock:
                    self.policy_diag.append((stamp, counts))
            elif st.hardware_id == 'sim_pilot_node' and 'episodes' in values:
                with self.lock:
                    self.pilot_diag.setdefault(int(values['episodes']), values)

    def set_sim_real_time_factor(self, rtf: float, timeout_s: float = 10.0) -> None:
        """Set sim_node's real_time_factor through its parameter service; GraphError if refused or unanswered."""
        client = self.node.create_client(SetParameters, '/sim_node/set_parameters')
        try:
            if not client.wait_for_service(timeout_sec=timeout_s):
                raise GraphError('sim_node parameter service not available')
            req = SetParameters.Request(parameters=[Parameter('real_time_factor', value=float(rtf)).to_parameter_msg()])
            future = client.call_async(req)
            end = time.monotonic() + timeout_s
            while not future.done() and time.monotonic() < end:
                time.sleep(0.05)
            if not future.done() or not future.result().results[0].successful:
                raise GraphError(f'sim_node did not take real_time_factor {rtf:g}')
        finally:
            self.node.destroy_client(client)

    def forget_before(self, t: float) -> None:
        """Drop the agent commands stamped before sim time t (landings already scored)."""
        with self.lock:
            self.agent = [x for x in self.agent if x[0] >= t]

    def publishers(self, topic: str) -> int:
        """Publishers of `topic` in the graph."""
        return self.node.count_publishers(topic)

    def counter_at(self, key: str, t: float) -> float | None:
        """policy_node counter `key` at sim time t, interpolated between diagnostics snapshots (None: no data)."""
        with self.lock:
            snaps = list(self.policy_diag)
        if not snaps:
            return None
        snaps.sort(key=lambda s: s[0])
        times = np.array([s[0] for s in snaps])
        vals = np.array([s[1][key] for s in snaps])
        return float(np.interp(t, times, vals))

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        if self.ctx.ok():
            rclpy.shutdown(context=self.ctx)
        self.thread.join(timeout=5.0)


def domain_in_use(domain_id: int, listen_s: float = 2.0) -> bool:
    """True when some ROS 2 node on this machine's network already runs on `domain_id`."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = Node('graph_eval_probe', context=ctx)
    try:
        end = time.monotonic() + listen_s
        while time.monotonic() < end:
            if [n for n in node.get_node_names() if n != 'graph_eval_probe']:
                return True
            time.sleep(0.1)
        return False
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def pick_domain_id() -> int:
    """A domain with no node on it: from $ASSIST_DOMAIN_IDS when set (assist_common.domains), else from AUTO_DOMAINS,
    starting from one derived from this process id."""
    lo, hi = domain_range() if os.environ.get(DOMAIN_IDS_ENV) else (AUTO_DOMAINS.start, AUTO_DOMAINS.stop - 1)
    domains = range(lo, hi + 1)
    first = os.getpid() % len(domains)
    for i in range(len(domains)):
        candidate = domains[(first + i) % len(domains)]
        if not domain_in_use(candidate):
            return candidate
    raise GraphError(f'every ROS_DOMAIN_ID in {lo}-{hi} is in use: pass --domain-id')


# ----------------------------------------------------------------------------------------- one condition
def sitl_ports(instance: int) -> tuple[int, int]:
    """(MAVLink SERIAL0 tcp port, JSON physics udp port) of SITL instance `instance` (its -I)."""
    return SITL_MAVLINK_PORT + SITL_PORT_STRIDE * instance, SITL_JSON_PORT + SITL_PORT_STRIDE * instance


def node_params(args: GraphEvalArgs, cond: str, plans: list[LandingPlan], on: dict[Rule, bool],
                runner_results: str = '') -> dict[str, dict]:
    """Parameters of every node of `cond`'s graph, for these landings in order (`runner_results`: landing_runner's
    results_file with --autopilot sitl)."""
    nodes = {
        'sim_node': {'seed': int(args.seed), 'real_time_factor': float(args.real_time_factor), 'auto_reset': True,
                     'episode_seeds': [p.scene_seed for p in plans], 'episode_timeout_s': float(args.max_episode_s),
                     'camera_rate_hz': 20.0, 'flight_controller': args.flight_controller},
        'sim_pilot_node': {'use_sim_time': True, 'alpha': float(args.alpha), 'pilot': args.pilot,
                           'blend_threshold': BLEND_THRESHOLD_MPS, 'episode_seeds': [p.pilot_seed for p in plans],
                           'episode_betas': [float(p.beta) for p in plans],
                           'episode_pilots': [p.pilot_family for p in plans]},
    }
    sitl = args.autopilot == 'sitl'
    if sitl:
        # SITL flies the airframe: sim_node is its JSON physics (lock-step, SITL's --speedup sets the pace);
        # episodes start landed, landing_runner arms / takes off / lands them, the pilot starts after the climb
        mav_port, json_port = sitl_ports(args.sitl_instance)
        sim = nodes['sim_node']
        del sim['real_time_factor'], sim['flight_controller']
        sim.update(physics='ardupilot_json', json_port=json_port)
        nodes['mavlink_bridge_node'] = {'use_sim_time': True, 'allow_force_disarm': True,
                                        'connection': args.sitl_connection or f'tcp:127.0.0.1:{mav_port}'}
        nodes['landing_runner'] = {'episodes': len(plans), 'reboot_after_crash': True, 'results_file': runner_results}
        nodes['sim_pilot_node']['start_altitude_m'] = SITL_START_ALTITUDE_M
    if cues_shown(args, cond):
        nodes['sim_pilot_node']['cue_trust'] = float(args.cue_trust)
    if cond == 'unassisted':
        nodes['sim_node']['camera_rate_hz'] = 0.0       # nothing looks at the camera
        return nodes
    model = getattr(args, f'{cond}_model', '')
    policy = {'use_sim_time': True, 'mode': cond, **{r.switch: bool(flies) for r, flies in on.items()}}
    if model:
        policy['model_path'] = str(Path(model).resolve())
    nodes['policy_node'] = policy
    if cond == 'latent':
        enc = {'use_sim_time': True, 'depth_noise': bool(args.depth_noise), 'noise_seed': int(plans[0].noise_seed),
               'level_camera': sitl or args.flight_controller != 'ideal'}     # the airframe leans: level, as deployed
        if args.encoder_path:
            enc['model_path'] = str(Path(args.encoder_path).resolve())
        nodes['encoder_node'] = enc
    return nodes


def ready_topics(cond: str) -> dict[str, str]:
    """Topic whose publisher shows each node is up (created after its models load)."""
    topics = {'sim_pilot_node': '/pilot/cmd_vel'}
    if cond != 'unassisted':
        topics['policy_node'] = '/assist/agent_cmd'
    if cond == 'latent':
        topics['encoder_node'] = '/assist/latent'
    return topics


def landing_row(listener: Listener, data: dict, seed: int, plan: LandingPlan, name: str,
                assisted: bool, sitl: bool = False) -> tuple[dict, float]:
    """evaluate's row of one landing from its /sim/landing JSON and what the listener saw; (row, policy coverage).

    `sitl`: episodes start on the ground and their clock at takeoff, and SITL restarts publish extra scenes, so the
    landing's window ends at the /clock its result came with and its scene is the last one before the window."""
    ep = int(data['episode'])
    duration = float(data['duration_s'])
    steps = max(1, round(duration * CONTROL_HZ))
    with listener.lock:
        if sitl:
            end = listener.landing_stamps.get(ep)
            t0 = None if end is None else end - duration
        else:
            t0 = listener.goal_stamps[ep] if ep < len(listener.goal_stamps) else None
            pads = listener.scenes[ep] if ep < len(listener.scenes) else None
        pilot_values = listener.pilot_diag.get(ep + 1, {})
        agent = list(listener.agent) if assisted else []
    if sitl:
        pads = None if t0 is None else listener.scene_at(t0)
    active, coverage = 0.0, 1.0
    fractions = {k: 0.0 for k in POLICY_COUNTERS}
    if assisted and t0 is not None:
        t1 = t0 + duration
        in_window = [n for t, n in agent if t0 < t <= t1 + 1e-6]
        active = sum(n > BLEND_THRESHOLD_MPS for n in in_window) / steps
        coverage = len(in_window) / steps
        for col, key in POLICY_COUNTERS.items():
            a, b = listener.counter_at(key, t0), listener.counter_at(key, t1)
            fractions[col] = 0.0 if a is None or b is None else max(0.0, b - a) / steps
    aimed = None
    estimate = pilot_values.get('goal_estimate')
    if estimate and pads is not None:
        g = np.array(json.loads(estimate), dtype=float)
        aimed = int(np.argmin(np.linalg.norm(pads[:, :2] - g[:2], axis=1)))
    row = {'condition': name, 'beta': float(plan.beta), 'seed': seed, 'scene_seed': plan.scene_seed,
           'goal_index': int(data['goal_index']), 'landed_index': data.get('landed_index'),
           'nearest_index': data.get('nearest_index'), 'aimed_index': aimed,
           'error_m': round(float(data['error_m']), 4), 'nearest_error_m': round(float(data['nearest_error_m']), 4),
           'outcome': data['outcome'], 'success': bool(data['success']), 'crash': bool(data['crash']),
           'duration_s': round(duration, 2), 'active_fraction': round(min(active, 1.0), 3),
           'pilot': pilot_values.get('pilot', plan.pilot_family_resolved),
           **{k: round(min(v, 1.0), 3) for k, v in fractions.items()},
           'autopilot_landed': '' if data.get('autopilot_landed') is None else bool(data['autopilot_landed'])}
    return row, coverage


def json_quad_parm() -> Path:
    """assist_sim's ardupilot_json_quad.parm: the installed share/assist_sim/config, else the source checkout's."""
    try:
        from ament_index_python.packages import get_package_share_directory
        installed = Path(get_package_share_directory('assist_sim')) / 'config' / 'ardupilot_json_quad.parm'
        if installed.is_file():
            return installed
    except (ImportError, LookupError, OSError, ValueError):
        pass                                  # no ament index (editable install): the source checkout
    import assist_sim
    return Path(assist_sim.__file__).resolve().parents[1] / 'config' / 'ardupilot_json_quad.parm'


def sitl_binary(args: GraphEvalArgs) -> Path:
    """The SITL binary to start: --sitl-binary, else the peers build; ValueError when there is none."""
    if args.sitl_binary:
        path = Path(args.sitl_binary).expanduser()
        if not (path.is_file() and os.access(path, os.X_OK)):
            raise ValueError(f'--sitl-binary {args.sitl_binary}: not an executable file')
        return path.resolve()
    if PEERS_SITL_BINARY.is_file():
        return PEERS_SITL_BINARY
    raise ValueError(f'--autopilot sitl needs --sitl-binary (an arducopter SITL build; {PEERS_SITL_BINARY} is absent) '
                     'or --sitl-connection of a SITL already running')


def sitl_defaults(args: GraphEvalArgs, binary: Path) -> list[Path]:
    """SITL's --defaults files: --sitl-defaults, else the checkout's copter.parm and ardupilot_json_quad.parm."""
    files = [Path(f).expanduser() for f in args.sitl_defaults] or [
        binary.parents[3] / 'Tools' / 'autotest' / 'default_params' / 'copter.parm', json_quad_parm()]
    for f in files:
        if not f.is_file():
            raise ValueError(f'SITL parameter file {f} not found (--sitl-defaults)')
    return [f.resolve() for f in files]


def sitl_command(args: GraphEvalArgs) -> list[str]:
    """arducopter's command line: JSON physics at 127.0.0.1, --speedup, -I, wiped parameters from the defaults."""
    binary = sitl_binary(args)
    return [str(binary), '--model', 'JSON:127.0.0.1', '--speedup', f'{args.sitl_speedup:g}',
            f'-I{args.sitl_instance}', '--defaults', ','.join(str(f) for f in sitl_defaults(args, binary)),
            '--wipe', '--serial0', 'tcp:0']        # tcp:0: boots without waiting for a MAVLink client


def check_sitl_args(args: GraphEvalArgs) -> None:
    """ValueError (one line) for --autopilot sitl settings that cannot fly."""
    if args.autopilot != 'sitl':
        return
    if args.flight_controller != 'ideal':
        raise ValueError(f'--flight-controller {args.flight_controller} models the autopilot; with --autopilot sitl '
                         'the autopilot is real: leave it ideal')
    if not args.sitl_connection:
        sitl_command(args)
    if args.sitl_preload and not Path(args.sitl_preload).is_file():
        raise ValueError(f'--sitl-preload {args.sitl_preload}: no such file')


def runner_verdict(path: Path, episode: int, wait_s: float) -> bool | str:
    """autopilot_landed of `episode` in landing_runner's results file ('' when it has no such column or row);
    waits up to `wait_s` (wall) for the row: the runner writes it after the autopilot's verdict."""
    end = time.monotonic() + wait_s
    while True:
        if path.exists():
            with path.open(newline='', encoding='utf-8') as fh:
                rows = [r for r in csv.DictReader(fh) if r.get('episode') == str(episode)]
            if rows:
                value = rows[-1].get('autopilot_landed', '')
                return {'True': True, 'False': False}.get(value or '', '')
        if time.monotonic() > end:
            return ''
        time.sleep(0.2)


def fly_condition(args: GraphEvalArgs, cond: str, name: str, on: dict[Rule, bool],
                  todo: list[tuple[int, LandingPlan]], domain_id: int, log_dir: Path,
                  results: LandingLog, rows: list[dict] | None = None) -> list[dict]:
    """Start `cond`'s graph, fly the landings `todo` in order as consecutive episodes, write each row (also
    appended to `rows`); stop the graph."""
    plans = [p for _, p in todo]
    sitl = args.autopilot == 'sitl'
    runner_csv = log_dir / f'{SITL_RUNNER_RESULTS}-{time.strftime("%Y%m%d-%H%M%S")}.csv'
    params = node_params(args, cond, plans, on, str(runner_csv) if sitl else '')
    listener = Listener(domain_id, clock=sitl)
    rows = [] if rows is None else rows
    n_before = len(rows)
    try:
        with NodeGroup(domain_id, log_dir) as group:
            remaps = {'/cmd_vel': '/pilot/cmd_vel'} if cond == 'unassisted' else None
            topics = ready_topics(cond)
            if sitl:    # SITL and its physics first: the EKF converges while the models load
                if not args.sitl_connection:
                    group.start_process('arducopter', sitl_command(args), log_dir / 'sitl',
                                        {'LD_PRELOAD': args.sitl_preload} if args.sitl_preload else None)
                group.start('sim_node', params['sim_node'])
                group.start('mavlink_bridge_node', params['mavlink_bridge_node'], remaps=remaps)
                topics['mavlink_bridge_node'] = '/uav/landed_state'
            for node in ('encoder_node', 'policy_node', 'sim_pilot_node'):
                if node in params:
                    group.start(node, params[node], extra=args.policy_params if node == 'policy_node' else ())
            end = time.monotonic() + args.startup_timeout_s
            while not all(listener.publishers(t) > 0 for t in topics.values()):
                group.check()
                if time.monotonic() > end:
                    late = [n for n, t in topics.items() if listener.publishers(t) == 0]
                    raise GraphError(f'{", ".join(late)} not up after {args.startup_timeout_s:.0f} s')
                time.sleep(0.2)
            t_start = time.monotonic()
            if sitl:
                group.start('landing_runner', params['landing_runner'])   # last: it starts the first landing
            else:
                warmup = args.real_time_factor == 0 or args.real_time_factor > WARMUP_RTF
                sim_params = dict(params['sim_node'], real_time_factor=WARMUP_RTF) if warmup else params['sim_node']
                group.start('sim_node', sim_params, remaps=remaps)   # last: no episode starts unflown
                if warmup:
                    while not listener.goal_stamps:
                        group.check()
                        if time.monotonic() - t_start > args.startup_timeout_s:
                            raise GraphError(f'sim_node not up after {args.startup_timeout_s:.0f} s')
                        time.sleep(0.1)
                    time.sleep(WARMUP_WALL_S)
                    listener.set_sim_real_time_factor(args.real_time_factor)
            last = time.monotonic()
            for i, (seed, plan) in enumerate(todo):
                while True:
                    with listener.lock:
                        data = listener.landings.get(i)
                    if data is not None:
                        break
                    group.check(done_ok=('landing_runner',))
                    if time.monotonic() - last > args.landing_timeout_s:
                        raise GraphError(f'no landing {i} within {args.landing_timeout_s:.0f} s (wall); '
                                         f'sim_node:\n{group.tail("sim_node")}')
                    time.sleep(0.1)
                wall = time.monotonic() - last
                last = time.monotonic()
                row, coverage = landing_row(listener, data, seed, plan, name, cond != 'unassisted', sitl)
                if sitl:
                    row['autopilot_landed'] = runner_verdict(runner_csv, int(data['episode']),
                                                             RUNNER_VERDICT_WAIT_S)
                if cond != 'unassisted' and not data.get('assisted', False):
                    log.warning('%s landing %d (seed %d): sim_node saw no /assist/agent_cmd', name, i, seed)
                if coverage < 0.9:
                    log.warning('%s landing %d (seed %d): the policy ran %.0f %% of the control steps: the graph '
                                'did not keep up (lower --%s)', name, i, seed, 100 * coverage,
                                'sitl-speedup' if sitl else 'real-time-factor')
                log.info('%s %d/%d seed %d beta %.2f %s: %s (%s) error %.2f m, %.1f s, %.0f s wall%s%s', name, i + 1,
                         len(todo), seed, plan.beta, row['pilot'], row['outcome'], data.get('reason', ''),
                         row['error_m'], row['duration_s'], wall,
                         '' if cond == 'unassisted' else f', policy coverage {100 * coverage:.0f} %',
                         f", autopilot landed {row['autopilot_landed']}" if sitl else '')
                results.write(row)
                results.sync()
                rows.append(row)
                ep = int(data['episode'])
                with listener.lock:
                    started = listener.goal_stamps[ep] if ep < len(listener.goal_stamps) else None
                if sitl:
                    started = listener.landing_stamps.get(ep, 0.0) - float(data['duration_s'])
                if started is not None:
                    listener.forget_before(started + float(data['duration_s']))
            flown = rows[n_before:]
            log.info('%s: %d landings in %.0f s wall (%.1f sim s per wall s)', name, len(todo),
                     time.monotonic() - t_start,
                     sum(r['duration_s'] for r in flown) / max(1e-6, time.monotonic() - t_start))
    finally:
        listener.close()
    return rows[n_before:]


# ----------------------------------------------------------------------------------------- run
def evaluate_graph(args: GraphEvalArgs) -> dict[str, dict]:
    """Fly every condition's landings through the node graph; write evaluate's files; return the summaries."""
    check_settings(args)                     # SettingsError (a ValueError): one line naming the --flag
    for cond in args.conditions:
        if cond not in CONDITIONS:
            raise ValueError(f'unknown condition {cond!r}; the graph flies {", ".join(CONDITIONS)}')
    if not 0 <= args.domain_id <= 232:
        raise ValueError(f'--domain-id {args.domain_id} out of range (0 = pick one, or 1-232)')
    check_sitl_args(args)
    # one run per --out: a second would fly the same landings and remove the first's partial file
    with hold_directory(args.out, 'evaluate_graph', 'wait for it to end, or choose another --out') as out:
        return _fly_all(args, out)


def _fly_all(args: GraphEvalArgs, out: Path) -> dict[str, dict]:
    """evaluate_graph's work on the held output directory `out`."""
    settings = {k: v for k, v in dataclasses.asdict(args).items() if k not in RUN_ONLY_ARGS}
    results = LandingLog(out, {'graph': True, **settings})
    planned = evaluation_plans(args.seed, tuple(args.betas), args.landings, args.pilot, args.alpha)
    domain_id = args.domain_id or pick_domain_id()
    rows_by_cond: dict[str, list[dict]] = {}
    try:
        for cond in args.conditions:
            on = rules_flying(args, cond)
            name = condition_name(cond, on, cues_shown(args, cond))
            done = {seed: results.flown(name, float(p.beta), seed) for seed, p in planned}
            todo = [(seed, p) for seed, p in planned if done[seed] is None]
            t0 = time.monotonic()
            flown: list[dict] = []
            starts = 0
            while todo:
                log.info('%s: flying %d landings through the graph on ROS_DOMAIN_ID %d', name, len(todo), domain_id)
                try:
                    fly_condition(args, cond, name, on, todo, domain_id, out / 'nodes' / name, results, flown)
                except GraphError as exc:
                    # SITL died, went silent or never armed: the landings still missing get a fresh graph and
                    # SITL; the plan's scenes and pilots go with them (episode_seeds), so they stay paired
                    starts += 1
                    if args.autopilot != 'sitl' or starts > args.sitl_restarts:
                        raise
                    log.warning('%s: %s', name, exc)
                    log.warning('%s: starting the graph afresh for the landings still missing (%d of %d '
                                '--sitl-restarts)', name, starts, args.sitl_restarts)
                done.update({r['seed']: r for r in flown})
                todo = [(seed, p) for seed, p in todo if done[seed] is None]
            rows_by_cond[name] = [done[seed] for seed, _ in planned]
            log.info('%s: %d landings in %.0f s', name, len(planned), time.monotonic() - t0)
    finally:
        results.close()
    return write_results(out, results.commit(rows_by_cond), args.plot)


def _raise_interrupt(signum, frame) -> None:
    """SIGTERM handler: unwind like Ctrl-C, so the graph is stopped."""
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    """Console entry point: fly, print the table."""
    cmd = parse_command(GraphEvalArgs, 'evaluate_graph', __doc__, HELP, argv)   # a bad value: one error line, exit 2
    args = cmd.settings
    signal.signal(signal.SIGINT, signal.default_int_handler)    # even when started with SIGINT ignored (a `&` job)
    signal.signal(signal.SIGTERM, _raise_interrupt)
    t0 = time.monotonic()
    try:
        summary = evaluate_graph(args)
    except KeyboardInterrupt:
        print('interrupted: the graph was stopped; landings flown so far are in '
              f'{args.out}/landings.partial.csv (re-run to go on)', file=sys.stderr)
        return 130
    except DirectoryBusy as exc:          # another run holds --out
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except (OSError, ValueError, GraphError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    pace = (f'ArduCopter SITL speedup {args.sitl_speedup:g}' if args.autopilot == 'sitl'
            else f'real_time_factor {args.real_time_factor:g}')
    print(f'graph: pilot {args.pilot}, alpha {args.alpha}, betas {" ".join(f"{b:g}" for b in args.betas)}, '
          f'{args.landings} landings each, seed {args.seed}, {pace}, '
          f'{time.monotonic() - t0:.0f} s wall')
    print_results(summary, args.out, ', nodes/')
    return 0


if __name__ == '__main__':
    sys.exit(main())
