"""Graph section of `make bench`: camera-to-latent and camera-to-command latency through the real graph.

sim_node (real_time_factor 1, 64x64 RGB-D at 20 Hz) -> encoder_node -> policy_node (mode latent,
step_on_latent, use_sim_time) run as subprocesses on a private ROS domain; this bench node listens.

Definitions (all times are this process's receive times, perf_counter, in its executor thread):
- a frame is the depth image with sim stamp s (its colour image has the same stamp);
- frame s's latent time is the receipt of /assist/pad_estimate stamped s: /assist/latent has no
  header, and the encoder publishes the pad estimate (with the frame's header) right after that
  frame's latent, from the same thread (one small MLP later);
- frame s's command is the /cmd_vel the policy publishes on receiving that latent: the policy's
  clock is the sim clock, which does not move until the next frame, so that command carries
  header.stamp == s, and it is the last /cmd_vel stamped s (the policy's timer stays quiet while
  latents arrive); latency = its receipt - receipt of frame s's depth image.
Counting starts at the first frame that got both a pad estimate and a command (every
subscription of this node matched: DDS discovery of the pad estimate may finish after the first
command). Frames with no latent or command before the next frame count as lost, except (each
counted on its own row) frames whose depth has too few valid pixels for the encoder (it skips them
on purpose, e.g. at touchdown) and frames followed by the next one within half a camera period
(the sim fell behind the wall clock and caught up: no pipeline can finish a frame in that gap).

Profile a node under this load with e.g.
    py-spy record -o encoder.svg --pid <encoder_node pid>      (or: py-spy top --pid ...)
"""
from __future__ import annotations

import bisect
import os
import random
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from assist_sim.testing import stop_process

BIN = Path(sys.executable).parent
FRAMES = 400          # 20 s of camera at 20 Hz after start-up
PERIOD_S = 1.0 / 20.0
MIN_VALID_DEPTH = 0.01    # encoder_node's default min_valid_depth_fraction


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far; NaN once it is gone."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return float('nan')


def _start(exe: str, params: dict, env: dict, log) -> subprocess.Popen:
    cmd = [str(BIN / exe), '--ros-args']
    for k, v in params.items():
        cmd += ['-p', f'{k}:={str(v).lower() if isinstance(v, bool) else v}']
    return subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def latent_receipt(latents: list[float], after: float, before: float, fallback: float) -> float:
    """The first /assist/latent receipt in (after, before) (sorted `latents`), else `fallback`."""
    i = bisect.bisect_right(latents, after)
    return latents[i] if i < len(latents) and latents[i] < before else fallback


RT_PRIORITY = 50        # SCHED_FIFO priority of encoder_node and policy_node in the second run
RECORDER_PRIORITY = 60  # SCHED_FIFO priority of this bench's recorder (above the nodes)


def count_frames(fr: list[tuple[int, float, float]], pad: dict[int, float], cm: dict[int, float],
                 frames: int = FRAMES, latents: list[float] | None = None) -> dict:
    """Match frames (stamp ns, receipt, valid depth fraction) to their latent, pad-estimate and command
    receipts under the rules in the module doc; returns latencies (s), lost counts, gaps.

    A frame's latent time is its /assist/latent receipt when `latents` (sorted receipts) holds one
    between the frame (or the previous frame's pad estimate, if that came later) and the frame's own
    pad estimate, else the pad estimate's receipt."""
    first = next((i for i, (s, _, _) in enumerate(fr) if s in cm and s in pad), None)
    if first is None:
        raise RuntimeError('no frame got both a pad estimate and a command')
    fr = fr[first:first + frames + 1]
    latents = latents or []
    to_latent, to_cmd = [], []
    lost = {'latent': 0, 'cmd': 0, 'no_depth': 0, 'burst': 0}
    prev = None
    for (s, t_img, valid), (_, t_next, _) in zip(fr[:-1], fr[1:]):
        got_latent = s in pad and t_img < pad[s] < t_next
        got_cmd = s in cm and cm[s] > t_img
        if got_latent:
            after = max(t_img, pad.get(prev, t_img))    # prev None (first frame): t_img
            to_latent.append(latent_receipt(latents, after, pad[s] + 1e-9, pad[s]) - t_img)
        if got_cmd:
            to_cmd.append(cm[s] - t_img)
        prev = s
        if got_latent and got_cmd:
            continue
        if valid < MIN_VALID_DEPTH:
            lost['no_depth'] += 1          # the encoder skips it on purpose
        elif t_next - t_img < 0.5 * PERIOD_S:
            lost['burst'] += 1             # the next frame came right behind it
        else:
            lost['latent'] += not got_latent
            lost['cmd'] += not got_cmd
    return {'to_latent': to_latent, 'to_cmd': to_cmd, 'lost': lost, 'gaps': np.diff([t for _, t, _ in fr])}


def measure(frames: int = FRAMES, startup_timeout_s: float = 90.0, node_params: dict | None = None,
            recorder_executor: str = 'events', recorder_priority: int = RECORDER_PRIORITY) -> dict:
    """Run the graph until `frames` frames have been seen after the first command; latencies in ms.

    `node_params` adds parameters per node, e.g. {'encoder_node': {'executor': 'single'}}; the
    bench's recorder node spins `recorder_executor` (the nodes' own default: events). Where allowed
    (root or an rtprio limit) the recorder runs under SCHED_FIFO `recorder_priority`, above the
    nodes, so that its receive times are the instrument's and not its wait for a core: with nodes
    at SCHED_FIFO and the recorder not, the encoder preempted the recorder and the recorder saw the
    camera frame late (latent p50 0.28 ms, less than the encoder's own work)."""
    import rclpy
    from geometry_msgs.msg import PointStamped, TwistStamped
    from rclpy.context import Context
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float32MultiArray

    from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS
    from assist_common.ros_run import make_executor, set_realtime_priority, spin_until_stopped

    domain = random.Random(os.getpid() ^ time.monotonic_ns()).randint(150, 199)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    log = tempfile.TemporaryFile()
    extra = node_params or {}
    procs = [
        _start('sim_node', {'seed': 3, 'real_time_factor': 1.0, 'camera_rate_hz': 20.0,
                            **extra.get('sim_node', {})}, env, log),
        _start('encoder_node', {'use_sim_time': True, **extra.get('encoder_node', {})}, env, log),
        _start('policy_node', {'use_sim_time': True, 'mode': 'latent', 'step_on_latent': True,
                               **extra.get('policy_node', {})}, env, log),
    ]
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('bench_graph', context=ctx)
    lock = threading.Lock()
    frames_seen: list[tuple[int, float, float]] = []     # (stamp ns, receipt, valid depth fraction)
    pads: dict[int, float] = {}                           # stamp ns -> receipt of /assist/pad_estimate
    cmds: dict[int, float] = {}                           # stamp ns -> receipt of the last /cmd_vel so stamped
    latents: list[float] = []                             # receipts of /assist/latent (no header: matched by time)
    done = threading.Event()

    def ns(stamp) -> int:
        return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)

    started: list[int] = []                               # frames seen when the first command came

    cpu0: list[tuple[float, list[float]]] = []           # (wall, CPU seconds per node) when counting starts

    def on_depth(msg: Image) -> None:
        t = time.perf_counter()
        depth = np.frombuffer(msg.data, np.float32)
        valid = float(np.count_nonzero(depth > 0)) / max(depth.size, 1)
        with lock:
            frames_seen.append((ns(msg.header.stamp), t, valid))
            if pads and cmds and not started:
                started.append(len(frames_seen))
                cpu0.append((time.monotonic(), [_cpu_s(p.pid) for p in procs]))
            if started and len(frames_seen) - started[0] > frames + 2:
                done.set()

    def on_pad(msg: PointStamped) -> None:
        t = time.perf_counter()
        with lock:
            pads.setdefault(ns(msg.header.stamp), t)

    def on_latent(msg: Float32MultiArray) -> None:
        t = time.perf_counter()
        with lock:
            latents.append(t)

    def on_cmd(msg: TwistStamped) -> None:
        t = time.perf_counter()
        with lock:
            cmds[ns(msg.header.stamp)] = t

    node.create_subscription(Image, '/camera/depth/image_raw', on_depth, SENSOR_QOS)
    node.create_subscription(PointStamped, '/assist/pad_estimate', on_pad, SENSOR_QOS)
    node.create_subscription(Float32MultiArray, '/assist/latent', on_latent, SENSOR_QOS)
    node.create_subscription(TwistStamped, '/cmd_vel', on_cmd, RELIABLE_QOS)
    ex = make_executor(recorder_executor, context=ctx)
    ex.add_node(node)
    stop_spin = threading.Event()

    # spin_once in a loop that the main thread can end: destroying the node or shutting the
    # executor down while this thread is inside the events executor crashes the process
    spin = threading.Thread(target=spin_until_stopped, args=(ex, stop_spin, ctx, 0.05), daemon=True)
    spin.start()
    fifo = recorder_priority > 0 and _may_use_fifo()
    if fifo:                 # after the nodes started: they must not inherit it
        set_realtime_priority(recorder_priority)
    cpu_share = [float('nan')] * len(procs)
    load0 = os.getloadavg()[0]
    try:
        t0 = time.monotonic()
        while not done.wait(1.0):
            if time.monotonic() - t0 > startup_timeout_s + frames / 20.0 * 3:
                break
            if any(p.poll() is not None for p in procs):
                break
        if cpu0:
            w0, c0 = cpu0[0]
            wall = time.monotonic() - w0
            cpu_share = [(_cpu_s(p.pid) - c) / wall for p, c in zip(procs, c0)]
    finally:
        if fifo:
            set_realtime_priority(0)
        stop_spin.set()
        spin.join(5.0)
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        for p in procs:
            stop_process(p)
        log.seek(0)
        tail = log.read()[-2000:].decode(errors='replace')
        log.close()
    with lock:
        fr, pad, cm, lat = list(frames_seen), dict(pads), dict(cmds), sorted(latents)
    if not cm:
        raise RuntimeError(f'the graph produced no /cmd_vel; node output tail:\n{tail}')
    c = count_frames(fr, pad, cm, frames, latents=lat)
    to_latent, to_cmd, lost, gaps = c['to_latent'], c['to_cmd'], c['lost'], c['gaps']
    if not to_cmd or not to_latent:
        raise RuntimeError('no frame could be matched to its latent and command')
    ms = lambda x: 1e3 * np.asarray(x)  # noqa: E731
    return {'frames': len(gaps),
            'latent_p50': float(np.percentile(ms(to_latent), 50)),
            'latent_p99': float(np.percentile(ms(to_latent), 99)),
            'cmd_p50': float(np.percentile(ms(to_cmd), 50)), 'cmd_p99': float(np.percentile(ms(to_cmd), 99)),
            'lost_latent': lost['latent'], 'lost_cmd': lost['cmd'], 'skipped_no_depth': lost['no_depth'],
            'lost_in_burst': lost['burst'], 'burst_frames': int(np.count_nonzero(gaps < 0.5 * PERIOD_S)),
            'load': (load0, os.getloadavg()[0]),
            'cpu_sim': 100 * cpu_share[0], 'cpu_encoder': 100 * cpu_share[1], 'cpu_policy': 100 * cpu_share[2]}


def path_cpu(n: int = 300) -> dict:
    """CPU ms per frame of the camera-to-command work, in one process: the sim's image messages,
    the encoder's decode + CM-VAE mu, the policy core's step (shipped latent actor). This is
    the work on the critical path without transport and scheduling."""
    import array

    import torch

    from assist_perception.encoder_core import LatentEncoder, decode_color, decode_depth
    from assist_policy.policy_core import PolicyCore, PolicyCoreConfig, default_model_path
    from assist_sim.core.world import LandingWorld

    torch.set_num_threads(1)
    world = LandingWorld(seed=0)
    world.reset(5)
    frames = [world.render_from(world.goal_position + np.array([dx, 0.2, 2.5])) for dx in np.linspace(-2, 2, 16)]
    world.close()
    enc = LatentEncoder(threads=1)
    core = PolicyCore(str(default_model_path('latent')), PolicyCoreConfig(mode='latent'))
    msgs = [(array.array('B', f.rgb.tobytes()), array.array('B', f.depth.astype('<f4').tobytes())) for f in frames]
    t_enc = t_pol = 0.0
    for k in range(n):
        rgb_b, dep_b = msgs[k % len(msgs)]
        now = 0.05 * k
        c0 = time.process_time()
        rgb = decode_color(rgb_b, 'rgb8', 64, 64, 192)
        dep = decode_depth(dep_b, '32FC1', 64, 64, 256)
        mu = enc.encode(rgb, dep, want_xyz=False).mu
        c1 = time.process_time()
        core.set_odom(now, [0.0, 0.0, 3.0], [0.0, 0.0, 0.0])
        core.set_pilot(now, [0.5, 0.0, -0.2])
        core.set_latent(now, mu)
        core.step(now)
        c2 = time.process_time()
        t_enc += c1 - c0
        t_pol += c2 - c1
    return {'encode_ms': 1e3 * t_enc / n, 'policy_ms': 1e3 * t_pol / n}




def _may_use_fifo() -> bool:
    """Whether the nodes this process starts may set SCHED_FIFO RT_PRIORITY (root or an rtprio limit)."""
    import resource
    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= RT_PRIORITY


def _latency_rows(m: dict, how: str) -> list[dict]:
    """The four latency rows of one graph run; `how` says how the nodes were scheduled."""
    return [
        {'name': f'camera image -> /assist/latent p50 / p99 (real graph; {how})',
         'value': f"{m['latent_p50']:.2f} / {m['latent_p99']:.2f}", 'unit': 'ms', 'target': 'p99 <= 3 ms'},
        {'name': f'camera image -> /cmd_vel p50 / p99 (real graph, that frame\'s command; {how})',
         'value': f"{m['cmd_p50']:.2f} / {m['cmd_p99']:.2f}", 'unit': 'ms', 'target': 'p99 <= 5 ms'},
        {'name': f'  frames without a latent / command before the next frame (of {m["frames"]}; {how})',
         'value': f"{m['lost_latent']} / {m['lost_cmd']}", 'unit': 'frames', 'target': '0 / 0'},
        {'name': f'  CPU sim_node / encoder_node / policy_node; load average start / end ({how})',
         'value': f"{m['cpu_sim']:.1f} / {m['cpu_encoder']:.1f} / {m['cpu_policy']:.1f}; "
                  f"{m['load'][0]:.1f} / {m['load'][1]:.1f}", 'unit': '% of a core', 'target': ''},
    ]


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    cpu = path_cpu()
    m = measure()
    rows = [
        {'name': 'camera-to-command work, CPU per frame (decode + CM-VAE mu + policy step, one process)',
         'value': cpu['encode_ms'] + cpu['policy_ms'], 'unit': 'ms', 'target': '<= 5 ms (floor of the graph latency)'},
        {'name': '  of which decode + CM-VAE mu', 'value': cpu['encode_ms'], 'unit': 'ms', 'target': ''},
        {'name': '  of which policy core step (shipped latent actor)', 'value': cpu['policy_ms'], 'unit': 'ms',
         'target': ''},
        *_latency_rows(m, 'default scheduler'),
    ]
    if _may_use_fifo():
        rt = {'realtime_priority': RT_PRIORITY}
        m_rt = measure(node_params={'encoder_node': rt, 'policy_node': rt})
        rows += _latency_rows(m_rt, f'realtime_priority {RT_PRIORITY}')
    else:
        rows.append({'name': f'camera image -> /cmd_vel with realtime_priority {RT_PRIORITY}', 'value': 'not run',
                     'unit': '', 'target': 'needs root or an rtprio limit'})
    rows += [
        {'name': '  not counted: depth too sparse for the encoder (skipped on purpose, e.g. touchdown)',
         'value': m['skipped_no_depth'], 'unit': 'frames', 'target': ''},
        {'name': '  not counted: next frame < 25 ms behind (sim fell behind the wall clock)',
         'value': m['lost_in_burst'], 'unit': 'frames', 'target': ''},
        {'name': 'frames arriving < 25 ms after the previous one (sim pacing at 1x)', 'value': m['burst_frames'],
         'unit': 'frames', 'target': '0'},
    ]
    return rows
