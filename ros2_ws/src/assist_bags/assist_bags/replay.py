"""replay_assist: re-run the encoder and policy cores offline on a bag's recorded inputs, compare with what was flown.

    replay_assist flights/run1                                  # shipped models -> flights/run1_replay/ (a bag)
    replay_assist flights/run1 --actor runs/td3/actor.pt --out new.csv
    replay_assist runs/eval/bags/latent_beta0.50_seed2024 --encoder runs/cmvae/cmvae.pt

No ROS graph: the bag's camera frames, /odom and /pilot/cmd_vel (and /sim/goal for the oracle) are fed to
the same cores the nodes run (assist_perception's LatentEncoder via make_latent_fn, PolicyCore) at the
recorded receive times; the policy steps once per recorded /cmd_vel message (or at --rate-hz, at most
1000 Hz, when the bag has none; a gap that would take more than a million such steps, e.g. one message with
a far-future timestamp, is refused). Writes /assist/latent, /assist/agent_cmd, /cmd_vel and the assistant's intent
(/assist/goal_estimate, /assist/descent_ok) into a new bag (or one CSV row per step) and prints (and writes as
JSON) the max, mean and rms difference of /cmd_vel, /assist/agent_cmd, the latent and the goal estimate from the
recorded ones (and how many descent_ok flags are the same), where the bag recorded them. Existing outputs (bag,
CSV, summary JSON) are refused, never overwritten. With the models that flew the bag the difference is ~0
(tests/test_bag_replay.py holds evaluate's bags to < 1e-4 m/s): that is the check that replay is faithful before a
new model is tried on old flights.

What flew, and where replay learns it (--mode/--actor/--encoder/--floor-guard/... decide instead):
* evaluate's bags: custom_data assist.condition (e.g. latent+guard+override+recall+damper) gives the mode and
  the rules; assist.depth_noise_seed the seeds of the landing's depth noise; the actor saw world-frame velocity
  (assist.velocity_frame, which --velocity-frame auto follows; policy_node feeds /odom's twist).
* graph bags (bag_record): custom_data assist.params.<node> holds policy_node's and encoder_node's parameters:
  the mode, the rule switches, blend_threshold, the timeouts and the model files (used when present here), and
  the encoder's depth noise (depth_noise, noise_seed). encoder_node draws each frame's noise from (noise_seed,
  the frame's stamp) (assist_perception.noise.frame_rng), so replay re-applies exactly the noise each frame got.
  Without those parameters (another recorder) the mode comes from policy_node's /diagnostics, else latent
  (warned), and frames are encoded without noise.
Graph bags are replayed as the graph ran, not as evaluate's env does: each recorded /assist/latent is
re-encoded from the frame it came from (paired through the /assist/pad_estimate published right after it,
which carries the frame's stamp: `pair_latents`; where the recorder took one of the two topics a frame ahead of
the other, the neighbouring frame whose latent is the recorded one is taken, and counted as
latent_frames_realigned) and reaches the core when the recorded latent did, so frames the encoder
dropped or rejected are left out as they were; each step runs on policy_node's clock at that step (its
/cmd_vel stamp); recorded /assist/agent_cmd messages are paired with their step by header stamp. policy_node
does not publish which pilot command a step had, and the pilot's messages race with the steps; the step's
own outputs say (V = blend(u, a): `pilot_alignment`), and --align-pilot (auto: graph bags) uses that. What
is left is the race of /odom with the steps (the actor's velocity and the rules' pose can lag one message):
measured on 25 s of the latent graph, latents identical, 72 % of the steps identical, agent_cmd mean
|diff| 0.011 m/s.

--latent recorded uses the bag's /assist/latent instead of re-encoding (a new actor on old latents).
The non-learned rules (floor guard, pilot override, pad recall, oscillation damper) run as in policy_node:
every depth frame reaches the core (the guard and the recall read it; /odom's orientation goes with the
position, as the recall's map needs). encoder_node's level_camera is not re-done: a bag flown with it
replays its tilted frames unlevelled (warned; --latent recorded is exact there).
"""
from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import os
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import msgs
from .bagio import (CONTRACT_TOPICS, DEPTH_NOISE_KEY, METADATA, PARAMS_KEY, VELOCITY_FRAME_KEY, BagError, BagReader,
                    BagWriter, check_output, publish_new)
from assist_policy.blending import DEFAULT_THRESHOLD
from assist_policy.rules import RULES, rule_fields
from assist_policy.poses import header_seconds

log = logging.getLogger(__name__)

RGB, DEPTH, ODOM, PILOT = '/camera/color/image_raw', '/camera/depth/image_raw', '/odom', '/pilot/cmd_vel'
LATENT, AGENT, CMD, GOAL = '/assist/latent', '/assist/agent_cmd', '/cmd_vel', '/sim/goal'
PAD, DIAG, LANDED = '/assist/pad_estimate', '/diagnostics', '/uav/landed_state'
GOAL_EST, DESCENT = '/assist/goal_estimate', '/assist/descent_ok'
PAIR_WINDOW = 25           # latents either side whose neighbours vote on the latent/pad-estimate offset
FRAME_MEMORY = 40          # recent camera frames kept for the latents that follow them (2 s at 20 Hz)
LATENT_MATCH = 1e-3        # a re-encoded latent this close (max abs) to a recorded one encodes the same frame
SAME_CLOCK_NS = 1_000_000_000   # a /cmd_vel stamp this close to its receive time is on the recorder's clock
MAX_RATE_HZ = 1000.0            # --rate-hz limit (policy_node runs at most 200 Hz)
MAX_STEPS = 1_000_000           # steps at --rate-hz that one gap between messages may take (14 h at 20 Hz)


@dataclass
# a field per non-learned rule (assist_policy.rules.RULES, by its settings field): on | off | auto (as the bag was
# flown)
@rule_fields(lambda r: field(default='auto'), lambda r: str)
class ReplayConfig:
    """What to re-run and how (replay_assist flags map 1:1); None / '' / 'auto': as the bag was flown."""

    mode: str = 'auto'                 # latent | oracle | end_to_end | auto (the mode the bag was flown in)
    actor: str = ''                    # default: the actor that flew (graph bags), else shipped td3_<mode>_actor.pt
    encoder: str = ''                  # default: the CM-VAE that flew (graph bags), else the shipped one
    latent: str = 'auto'               # encode | recorded | auto (encode when the bag has camera frames)
    velocity_frame: str = 'auto'       # twist | odom | auto
    rate_hz: float = 20.0              # step rate when the bag has no recorded /cmd_vel
    blend_threshold: float | None = None   # None: policy_node's recorded value, else 0.25
    timeout_s: float | None = None     # pilot, feature and odometry timeouts; None: recorded, else 0.5
    align_pilot: str = 'auto'          # on | off | auto (on for graph bags): see pilot_alignment


# replay option (ReplayConfig field, --option) -> the rule it switches (assist_policy.rules: evaluate's flag in a
# condition's name, policy_node's switch recorded by bag_record)
RULE_OPTIONS = {r.field: r for r in RULES}
# PolicyCoreConfig timeout -> policy_node's parameter
TIMEOUT_PARAMS = {'pilot_timeout_s': 'pilot_timeout_s', 'feature_timeout_s': 'latent_timeout_s',
                  'odom_timeout_s': 'odom_timeout_s'}
MODES = ('latent', 'oracle', 'end_to_end')


def rules_on(cfg: ReplayConfig, condition: str, flags: list[str], mode: str = 'latent',
             flown: dict | None = None) -> dict[str, bool]:
    """Which rules the re-run applies: each on|off as asked, else as evaluate flew the bag, else as policy_node's
    recorded parameters (`flown`) say, else policy_node's defaults for `mode` (all on; in mode oracle only the floor
    guard)."""
    out = {}
    for option, r in RULE_OPTIONS.items():
        v = getattr(cfg, option)
        if v not in ('auto', 'on', 'off'):
            raise ValueError(f'--{option} must be auto, on or off, got {v!r}')
        if condition:
            default = r.flag in flags
        elif flown is not None and isinstance(flown.get(r.switch), bool):
            default = flown[r.switch]
        else:
            default = r.default_on(mode)
        out[option] = v == 'on' or (v == 'auto' and default)
    return out


def recorded_params(custom: dict, node: str) -> dict | None:
    """The parameters bag_record stored for the node named `node` (any namespace); None when the bag has none."""
    keys = sorted(k for k in custom if k.startswith(PARAMS_KEY) and k[len(PARAMS_KEY):].split('/')[-1] == node)
    if not keys:
        return None
    if len(keys) > 1:
        log.warning('the bag holds the parameters of %d nodes named %s (%s); using %s', len(keys), node,
                    ', '.join(keys), keys[0])
    try:
        value = json.loads(custom[keys[0]])
    except (TypeError, ValueError) as exc:
        raise BagError(f'custom_data {keys[0]} is not JSON ({exc})') from None
    if not isinstance(value, dict):
        raise BagError(f'custom_data {keys[0]} is not a JSON object')
    return value


def diagnostics_mode(r: BagReader) -> str | None:
    """policy_node's mode as its /diagnostics reported it (bags from any recorder); None when not there."""
    if r.topics.get(DIAG) is None or not r.topics[DIAG].count:
        return None
    for _, _, raw in r.messages([DIAG]):
        for st in r.deserialize(raw, DIAG).status:
            if st.hardware_id.split('/')[-1] != 'policy_node':
                continue
            for kv in st.values:
                if kv.key == 'mode' and kv.value in MODES:
                    return kv.value
    return None


def pair_latents(events: list[tuple[str, int]], window: int = PAIR_WINDOW) -> dict[int, int]:
    """Recorded latent index -> stamp (ns) of the frame it encodes, from the bag's order of /assist/latent ('L',
    index) and /assist/pad_estimate ('P', stamp) messages.

    encoder_node publishes a frame's pad estimate (stamped with the frame) right after its latent, so each topic's
    messages are in frame order and the n-th latent goes with the n-th pad estimate, up to an offset: where the
    recorder's two subscriptions started (or lost a message) apart. The offset is read from the latents followed by
    a pad estimate in the bag, by majority over the `window` latents either side, so a burst in which the recorder
    took two latents before their pad estimates (L L P P) does not shift the pairing. A pad estimate
    goes with one latent at most; a latent without one is left out."""
    pads = [stamp for kind, stamp in events if kind == 'P']
    latents = [k for kind, k in events if kind == 'L']
    votes: list[tuple[int, int]] = []          # (latent index, pad index - latent index) of a latent then a pad
    n_pad = 0
    for (kind, v), (nxt, _) in zip(events, events[1:]):
        if kind == 'P':
            n_pad += 1
        elif nxt == 'P':
            votes.append((v, n_pad - v))
    if not votes:
        return {}
    out: dict[int, int] = {}
    used: set[int] = set()
    lo = 0
    for k in latents:
        while lo < len(votes) and votes[lo][0] < k - window:
            lo += 1
        near = [(abs(kv - k), o) for kv, o in votes[lo:lo + 2 * window + 1] if kv <= k + window]   # one per latent
        if not near:
            continue
        tally = Counter(off for _, off in near)
        top = max(tally.values())
        off = min((d, o) for d, o in near if tally[o] == top)[1]   # a tie: the offset of the nearest neighbours
        j = k + off
        if 0 <= j < len(pads) and j not in used:
            used.add(j)
            out[k] = pads[j]
    return out


def pilot_alignment(r: BagReader, threshold: float) -> dict[int, tuple[np.ndarray, str]]:
    """Step index -> (u, frame_id) of the recorded /pilot/cmd_vel message the live step flew with, where that is the
    one before or after the latest the recorder had (an ordering race between the pilot and the step).

    policy_node does not publish its inputs, but its outputs imply the pilot command it used: every step flies
    V = blend(u, a) with the a it publishes (the rules publish the a that gives their V), so u = 2V - a when
    |a| > threshold, else u = V. Steps whose implied u is the latest pilot message need nothing."""
    pilots: list[np.ndarray] = []
    frames: list[str] = []
    steps: list[tuple[int, int, np.ndarray]] = []        # (cmd stamp, latest pilot index, V)
    agents: dict[int, list[np.ndarray]] = {}
    for topic, _, raw in r.messages([PILOT, CMD, AGENT]):
        msg = r.deserialize(raw, topic)
        if topic == PILOT:
            pilots.append(msgs.twist_linear(msg))
            frames.append(msg.header.frame_id)
        elif topic == CMD:
            steps.append((msgs.stamp_ns(msg.header.stamp), len(pilots) - 1, msgs.twist_linear(msg)))
        else:
            agents.setdefault(msgs.stamp_ns(msg.header.stamp), []).append(msgs.twist_linear(msg))
    seen: dict[int, int] = {}
    out: dict[int, int] = {}
    for i, (stamp, p, v) in enumerate(steps):
        k = seen.get(stamp, 0)
        seen[stamp] = k + 1
        a = agents.get(stamp, [])[k] if k < len(agents.get(stamp, [])) else None
        u = 2 * v - a if a is not None and np.linalg.norm(a) > threshold else v
        if 0 <= p < len(pilots) and np.allclose(pilots[p], u, atol=1e-6):
            continue
        for q in (p - 1, p + 1):
            if 0 <= q < len(pilots) and np.allclose(pilots[q], u, atol=1e-6):
                out[i] = (pilots[q], frames[q])
                break
    return out


@dataclass
class ReplayResult:
    """Per-step outputs of the re-run and what was recorded at the same steps (keys: step index; latents: id)."""

    times_ns: list[int] = field(default_factory=list)       # bag time of each step
    agent: dict[int, np.ndarray] = field(default_factory=dict)
    cmd: dict[int, np.ndarray] = field(default_factory=dict)
    rec_agent: dict[int, np.ndarray] = field(default_factory=dict)
    rec_cmd: dict[int, np.ndarray] = field(default_factory=dict)
    step_latent: dict[int, int] = field(default_factory=dict)     # step -> id of the latent it used
    pilot: dict[int, np.ndarray] = field(default_factory=dict)    # step -> the pilot command u it used
    latents: dict[int, np.ndarray] = field(default_factory=dict)  # id -> re-encoded latent
    latent_times: dict[int, int] = field(default_factory=dict)    # id -> bag time it reached the core
    rec_latent: dict[int, np.ndarray] = field(default_factory=dict)   # id -> recorded latent
    goal: dict[int, np.ndarray] = field(default_factory=dict)         # step -> the intent's goal estimate
    cov: dict[int, list[float]] = field(default_factory=dict)         # step -> its 6x6 covariance
    descent: dict[int, bool] = field(default_factory=dict)            # step -> descent_ok
    rec_goal: dict[int, np.ndarray] = field(default_factory=dict)     # step -> the recorded goal estimate
    rec_descent: dict[int, bool] = field(default_factory=dict)        # step -> the recorded descent_ok
    info: dict = field(default_factory=dict)


def _noise_seeds(value: str | None) -> tuple[int, int] | None:
    """custom_data assist.depth_noise_seed '<base>,<landing>' -> (base, landing); None when absent."""
    if not value:
        return None
    try:
        base, landing = (int(v) for v in str(value).split(','))
    except ValueError:
        raise BagError(f'custom_data {DEPTH_NOISE_KEY} {value!r} is not "<base seed>,<landing seed>"') from None
    return base, landing


def _flown_mode(cfg: ReplayConfig, condition: str, policy: dict | None, r: BagReader) -> tuple[str, str]:
    """(mode, where it came from): the option, evaluate's condition, policy_node's recorded parameter or its
    /diagnostics, else latent (warned)."""
    if cfg.mode != 'auto':
        return cfg.mode, 'option'
    if condition:
        return condition, 'evaluate condition'
    if policy is not None and policy.get('mode'):
        return str(policy['mode']), 'policy_node parameters'
    mode = diagnostics_mode(r)
    if mode is not None:
        return mode, 'policy_node /diagnostics'
    log.warning('%s: the bag does not say which mode flew it (no evaluate condition, no policy_node parameters or '
                'diagnostics); replaying latent (--mode to choose)', r.path)
    return 'latent', 'default'


def _model(option: str, params: dict | None, what: str) -> str:
    """The model to load: the option, else the file the node flew with (when it exists here), else '' (shipped)."""
    if option:
        return option
    flown = str((params or {}).get('model_path') or '')
    if flown and not Path(flown).is_file():
        log.warning('the bag was flown with %s %s, which is not here; using the shipped one', what, flown)
        return ''
    return flown


def check_rate(rate_hz: float) -> None:
    """ValueError unless `rate_hz` is a usable step rate (finite, > 0, <= MAX_RATE_HZ)."""
    if not (math.isfinite(rate_hz) and 0 < rate_hz <= MAX_RATE_HZ):
        raise ValueError(f'rate must be > 0 and <= {MAX_RATE_HZ:g} Hz, got {rate_hz!r}')


def replay(bag: str | Path, cfg: ReplayConfig, progress: bool = False) -> ReplayResult:
    """Re-run encoder + policy on the bag's inputs; BagError/ValueError with one line on bad input."""
    check_rate(cfg.rate_hz)
    res = ReplayResult()
    with BagReader(bag) as r:
        custom = (r.metadata.get('custom_data') or {}) if r.metadata else {}
        if not isinstance(custom, dict):
            raise BagError(f'{bag}: custom_data in the bag metadata is not a mapping')
        # evaluate names its rows (and bags) <condition>[+guard][+override]
        condition, *flags = custom.get('assist.condition', '').split('+')
        policy_params = None if condition else recorded_params(custom, 'policy_node')
        encoder_params = None if condition else recorded_params(custom, 'encoder_node')
        mode, mode_from = _flown_mode(cfg, condition, policy_params, r)
        if mode not in MODES:
            raise ValueError(f'{bag}: cannot replay mode {mode!r} (latent, oracle or end_to_end; '
                             f'pass --mode for a bag of an unassisted flight)')
        if policy_params is not None and policy_params.get('mode') not in (None, mode):
            policy_params = None        # another mode's actor and rules: policy_node's defaults for `mode`
        rules = rules_on(cfg, condition, flags, mode, policy_params)
        has_camera = RGB in r.topics and DEPTH in r.topics
        use_latent = cfg.latent if cfg.latent != 'auto' else ('encode' if has_camera else 'recorded')
        need = [ODOM, PILOT]
        if mode == 'latent':
            need += [RGB, DEPTH] if use_latent == 'encode' else [LATENT]
        elif mode == 'oracle':
            need += [GOAL]
        else:
            need += [RGB, DEPTH]
        missing = [t for t in need if t not in r.topics]
        if missing:
            raise BagError(f'{bag}: lacks {", ".join(missing)}: cannot re-run the {mode} assistant')
        used = need + [t for t in (AGENT, CMD, LATENT, PAD, LANDED, GOAL_EST, DESCENT)
                       if t in r.topics and t not in need]
        r.check_definitions(used)
        import torch  # heavy: only once the bag is known to be good

        from assist_policy import settings
        from assist_policy.policy_core import PolicyCore, PolicyCoreConfig, default_model_path
        torch.set_num_threads(1)
        frame = cfg.velocity_frame if cfg.velocity_frame != 'auto' else custom.get(VELOCITY_FRAME_KEY, 'twist')
        if frame not in ('twist', 'odom'):
            raise ValueError(f'velocity frame must be twist or odom, got {frame!r}')
        pp = policy_params or {}
        threshold = cfg.blend_threshold if cfg.blend_threshold is not None else float(
            pp.get('blend_threshold', DEFAULT_THRESHOLD))
        timeouts = {f: cfg.timeout_s if cfg.timeout_s is not None else float(pp.get(k, 0.5))
                    for f, k in TIMEOUT_PARAMS.items()}
        actor = Path(_model(cfg.actor, policy_params, 'the actor') or default_model_path(mode))
        # every setting policy_node flew with (graph bags), through the same table policy_node builds its core
        # with; the rule switches, threshold and timeouts as decided above
        flown = {**pp, **{RULE_OPTIONS[o].switch: on for o, on in rules.items()}, 'blend_threshold': threshold,
                 **{TIMEOUT_PARAMS[f]: v for f, v in timeouts.items()}}
        try:
            core_cfg = settings.config_from(PolicyCoreConfig, flown, mode=mode, actor_velocity=frame)
        except (TypeError, ValueError) as exc:
            raise BagError(f'{bag}: policy_node parameters recorded in the bag are not usable: {exc}') from None
        # the actor on what the node ran it on (a graph bag records actor_backend; evaluate's bags run torch)
        core = PolicyCore(actor, core_cfg, str(pp.get('actor_backend', 'torch')))
        encode = None
        noise_seeds = _noise_seeds(custom.get(DEPTH_NOISE_KEY))
        ep = encoder_params or {}
        frame_noise = noise_seeds is None and bool(ep.get('depth_noise', False))   # encoder_node's per-frame noise
        encoder_path = _model(cfg.encoder, encoder_params, 'the CM-VAE')
        if mode == 'latent' and use_latent == 'encode':
            from assist_perception.latent import make_latent_fn
            seed = noise_seeds[0] if noise_seeds else int(ep.get('noise_seed', 0))
            encode, dim = make_latent_fn(encoder_path or None, depth_noise=noise_seeds is not None or frame_noise,
                                         seed=seed)
            if noise_seeds is not None:
                encode.reset(noise_seeds[1])
            if dim != core.builder.latent_dim:
                raise ValueError(f'{actor}: expects a {core.builder.latent_dim}-d latent, the encoder gives {dim}')
            if not condition and encoder_params is None:
                log.warning('%s: the bag does not hold encoder_node\'s settings (recorded without bag_record\'s '
                            'parameters); re-encoding without depth noise', bag)
            if ep.get('level_camera'):
                log.warning('%s: encoder_node levelled the frames (level_camera); replay encodes them as recorded, '
                            'so latents of tilted frames differ', bag)
        # graph bags: re-encode the frame each recorded latent came from, at the time it reached the policy
        at_latents = (encode is not None and not condition and LATENT in r.topics and r.topics[LATENT].count > 0)
        frame_of: dict[int, int] = {}
        pads: list[int] = []
        pad_index: dict[int, int] = {}
        if at_latents:
            events: list[tuple[str, int]] = []
            n_events = 0
            for topic, _, raw in r.messages([LATENT, PAD] if PAD in r.topics else [LATENT]):
                if topic == LATENT:
                    events.append(('L', n_events))
                    n_events += 1
                else:
                    events.append(('P', msgs.stamp_ns(r.deserialize(raw, PAD).header.stamp)))
            frame_of = pair_latents(events)
            pads = [stamp for kind, stamp in events if kind == 'P']
            pad_index = {stamp: j for j, stamp in enumerate(pads)}
        ticks_from_bag = CMD in r.topics and r.topics[CMD].count > 0
        if cfg.align_pilot not in ('auto', 'on', 'off'):
            raise ValueError(f'align-pilot must be auto, on or off, got {cfg.align_pilot!r}')
        align = ticks_from_bag and (cfg.align_pilot == 'on' or (cfg.align_pilot == 'auto' and not condition))
        pilot_of = pilot_alignment(r, threshold) if align else {}
        pilot_msgs: list[tuple[float, np.ndarray, str]] = []     # every recorded pilot command so far: (t, u, frame)
        period = int(round(1e9 / cfg.rate_hz))
        next_tick = None
        frames: dict[int, tuple[np.ndarray | None, np.ndarray]] = {}   # depth stamp -> (rgb, depth), recent ones
        last_frame: int | None = None
        start = r.start_ns
        slop_ns = int(float(ep.get('sync_slop_s', 0.02)) * 1e9)
        counts = {'latent_frames_missing': 0, 'latent_frames_rejected': 0, 'latent_frames_realigned': 0,
                  'pilot_aligned': 0}
        res.info = {'bag': str(bag), 'mode': mode, 'mode_from': mode_from, 'actor': str(actor),
                    'latent_source': use_latent if mode == 'latent' else None,
                    'encoder': (encoder_path or 'shipped') if encode else None, 'velocity_frame': frame,
                    'pilot_override': rules['override'], 'rules': rules, 'blend_threshold': threshold,
                    'depth_noise': (list(noise_seeds) if noise_seeds is not None else
                                    {'noise_seed': int(ep.get('noise_seed', 0)), 'per': 'frame stamp'}
                                    if frame_noise else None) if encode is not None else None,
                    'latents_at': None if encode is None else 'recorded /assist/latent times' if at_latents
                    else 'depth frame times',
                    'steps_at': 'recorded /cmd_vel times' if ticks_from_bag else f'{cfg.rate_hz} Hz'}
        total = sum(r.topics[t].count for t in used)
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=total, unit='msg', desc='replay', file=sys.stderr)
        cmd_stamps: list[int | None] = []          # header stamp of each step's recorded /cmd_vel
        rec_agents: dict[int, list[np.ndarray]] = {}   # header stamp -> recorded /assist/agent_cmd
        rec_goals: dict[int, list[np.ndarray]] = {}    # header stamp -> recorded /assist/goal_estimate
        latent_id: int | None = None
        n_latent = 0

        def step(t: int, clock: int | None = None) -> None:
            """One policy step at bag time `t`, on the core's clock at `clock` (default `t`)."""
            i = len(res.times_ns)
            out = core.step(((t if clock is None else clock) - start) * 1e-9)
            res.times_ns.append(t)
            res.pilot[i] = core.pilot_command(((t if clock is None else clock) - start) * 1e-9)
            res.cmd[i] = out.velocity
            if out.agent is not None:
                res.agent[i] = out.agent
            if out.intent.goal is not None:
                res.goal[i], res.cov[i] = out.intent.goal, out.intent.pose_covariance()
            if out.intent.descent_ok is not None:
                res.descent[i] = out.intent.descent_ok
            if latent_id is not None:
                res.step_latent[i] = latent_id

        def encode_frame(stamp: int, count: bool = True) -> np.ndarray | None:
            """The re-encoded latent of the frame stamped `stamp` (None: frame not in the bag or rejected)."""
            rgb, depth = frames.get(stamp, (None, None))
            if rgb is None or depth is None:
                counts['latent_frames_missing'] += count
                return None
            rejected = encode.rejected
            mu = np.asarray(encode(rgb, depth, stamp_ns=stamp) if frame_noise else encode(rgb, depth), dtype=float)
            if encode.rejected != rejected and not condition:   # encoder_node publishes nothing for such a frame
                counts['latent_frames_rejected'] += count       # (evaluate's env repeats the last latent: as it flew)
                return None
            return mu

        waiting: dict[int, list[int]] = {}     # frame stamp -> recorded latents received before the frame
        # frame stamp -> (recorded latent, the latent of the frame it was paired with) that wait for a neighbouring
        # frame still on its way, which may be the one it encodes
        maybe: dict[int, list[tuple[int, np.ndarray]]] = {}
        next_frame: list[tuple[int, int, np.ndarray]] = []    # (frame stamp, latent, its mu): for the next frame

        def use_latent(k: int, mu: np.ndarray, t: int, now: float) -> None:
            """Hand re-encoded latent k to the core at bag time `t`."""
            nonlocal latent_id
            res.latents[k] = mu
            res.latent_times[k] = t
            core.set_latent(now, mu)
            latent_id = k

        def is_recorded(mu: np.ndarray | None, k: int) -> bool:
            """Whether `mu` is recorded latent k (the same frame through the same encoder)."""
            rec = res.rec_latent[k]
            return mu is not None and rec.shape == mu.shape and float(np.max(np.abs(mu - rec))) <= LATENT_MATCH

        def apply_latent(k: int, stamp: int, t: int, now: float) -> None:
            """Re-encode recorded latent k's frame and hand it to the core at bag time `t`.

            Where the frame paired by bag order does not give the recorded latent and the next or previous pad
            estimate's frame does (the recorder took one topic's messages a frame ahead of the other's), that frame
            is the one encoded; a neighbour still on its way is waited for."""
            mu = encode_frame(stamp)
            if mu is None:
                return
            j = pad_index.get(stamp)
            if is_recorded(mu, k) or j is None or res.rec_latent[k].shape != mu.shape:
                use_latent(k, mu, t, now)
                return
            for alt in (pads[i] for i in (j + 1, j - 1) if 0 <= i < len(pads)):
                rgb, depth = frames.get(alt, (None, None))
                if rgb is not None and depth is not None:
                    other = encode_frame(alt, count=False)
                    if is_recorded(other, k):
                        counts['latent_frames_realigned'] += 1
                        use_latent(k, other, t, now)
                        return
                elif alt > stamp:
                    maybe.setdefault(alt, []).append((k, mu))
                    return
            # no neighbouring pad estimate gives it (the bag ended before the next frame's pad estimate): the
            # complete frames right after and before this one in the bag
            complete = sorted(s for s, (c, d) in frames.items() if c is not None and d is not None and s != stamp)
            later = [s for s in complete if s > stamp][:1]
            for alt in later + [s for s in complete if s < stamp][-1:]:
                other = encode_frame(alt, count=False)
                if is_recorded(other, k):
                    counts['latent_frames_realigned'] += 1
                    use_latent(k, other, t, now)
                    return
            if not later:                 # the next frame is still on its way (recorded after this latent)
                next_frame.append((stamp, k, mu))
                return
            use_latent(k, mu, t, now)

        try:
            for topic, t, raw in r.messages(used):
                if not ticks_from_bag:
                    if next_tick is None:
                        next_tick = t
                    if (t - next_tick) // period > MAX_STEPS:
                        raise BagError(f'{bag}: {topic} at {(t - start) * 1e-9:.3f} s comes '
                                       f'{(t - next_tick) * 1e-9:.3g} s after the previous message: stepping '
                                       f'through that at {cfg.rate_hz:g} Hz would take more than {MAX_STEPS} '
                                       f'steps (a wrong timestamp?)')
                    while next_tick < t:
                        step(next_tick)
                        next_tick += period
                now = (t - start) * 1e-9
                msg = r.deserialize(raw, topic)
                try:
                    if topic == ODOM:
                        pos, quat, twist = msgs.odom_arrays(msg)
                        core.set_odom(now, pos, twist, quat, header_seconds(msg))
                    elif topic == PILOT:
                        pilot_msgs.append((now, msgs.twist_linear(msg), msg.header.frame_id))
                        core.set_pilot(now, msgs.twist_linear(msg), msg.header.frame_id)
                    elif topic == LANDED:            # the vehicle's own landed state: a flight boundary
                        core.set_landed_state(now, int(msg.data))
                    elif topic == GOAL and mode == 'oracle':
                        core.set_goal(msgs.point(msg))
                        core.reset()          # as policy_node does: a new goal is a new episode
                    elif topic in (RGB, DEPTH):
                        st = msgs.stamp_ns(msg.header.stamp)
                        rgb, depth = frames.pop(st, (None, None))
                        if topic == RGB:
                            rgb = msgs.image_array(msg)
                        else:
                            depth = msgs.image_array(msg)
                            core.set_depth(now, depth, header_seconds(msg))    # every mode: the rules read it
                            last_frame = st
                            if mode == 'end_to_end' and rgb is not None:
                                core.set_image(now, rgb, depth)
                        if rgb is not None and depth is None:    # encoder_node pairs colour and depth within its slop
                            near = [s for s, f in frames.items() if f[1] is not None and f[0] is None
                                    and abs(s - st) <= slop_ns]
                            if near:
                                st = min(near, key=lambda s: abs(s - st))
                                depth = frames.pop(st)[1]
                        elif depth is not None and rgb is None:
                            near = [s for s, f in frames.items() if f[0] is not None and f[1] is None
                                    and abs(s - st) <= slop_ns]
                            if near:
                                rgb = frames.pop(min(near, key=lambda s: abs(s - st)))[0]
                        frames[st] = (rgb, depth)
                        while len(frames) > FRAME_MEMORY:
                            del frames[next(iter(frames))]
                        if at_latents and rgb is not None and depth is not None:
                            for k in waiting.pop(st, []):     # latents the recorder got before their frame
                                apply_latent(k, st, t, now)
                            # latents waiting for the next frame after theirs, then those waiting for this one
                            pending = [(k, mu) for s0, k, mu in next_frame if s0 < st] + maybe.pop(st, [])
                            next_frame[:] = [e for e in next_frame if e[0] >= st]
                            other = encode_frame(st, count=False) if pending else None    # once per frame
                            for k, mu in pending:
                                hit = is_recorded(other, k)
                                counts['latent_frames_realigned'] += hit
                                use_latent(k, other if hit else mu, t, now)
                        if encode is not None and not at_latents and rgb is not None and depth is not None:
                            mu = encode_frame(st)              # every frame, once it is complete
                            if mu is not None:
                                res.latents[st] = mu
                                res.latent_times[st] = t
                                core.set_latent(now, mu)
                                latent_id = st
                    elif topic == LATENT:
                        rec = np.asarray(msg.data, dtype=float)
                        k = n_latent if at_latents else t
                        n_latent += 1
                        res.rec_latent[k] = rec
                        if at_latents:
                            stamp = frame_of.get(k, last_frame)
                            f = frames.get(stamp, (None, None))
                            if stamp is not None and (f[0] is None or f[1] is None):
                                waiting.setdefault(stamp, []).append(k)    # its frame is still on its way
                            elif stamp is None:
                                counts['latent_frames_missing'] += 1
                            else:
                                apply_latent(k, stamp, t, now)
                        elif mode == 'latent' and use_latent == 'recorded':
                            core.set_latent(now, rec)
                            latent_id = k
                    elif topic == AGENT:
                        rec_agents.setdefault(msgs.stamp_ns(msg.header.stamp) if ticks_from_bag else t, []).append(
                            msgs.twist_linear(msg))
                    elif topic == GOAL_EST:
                        rec_goals.setdefault(msgs.stamp_ns(msg.header.stamp) if ticks_from_bag else t, []).append(
                            msgs.pose_position(msg))
                    elif topic == DESCENT and res.times_ns:
                        # no header: the step published just before it arrived (each step publishes it last)
                        res.rec_descent[len(res.times_ns) - 1] = bool(msg.data)
                    elif topic == CMD:
                        i = len(res.times_ns)
                        res.rec_cmd[i] = msgs.twist_linear(msg)
                        stamp = msgs.stamp_ns(msg.header.stamp)
                        cmd_stamps.append(stamp)
                        # policy_node stamps /cmd_vel with its clock at the step: the step's own time whenever the
                        # recorder's clock is the graph's (a sim-time recorder receives it up to a /clock tick later)
                        live_pilot = pilot_of.get(i)
                        if live_pilot is not None:
                            core.set_pilot(now, *live_pilot)      # the message the live step had (pilot_alignment)
                            counts['pilot_aligned'] += 1
                        step(t, stamp if abs(stamp - t) <= SAME_CLOCK_NS else None)
                        if live_pilot is not None and pilot_msgs:
                            core.set_pilot(*pilot_msgs[-1])       # back to the latest, as the bag goes on
                except ValueError as exc:     # a bad recorded input is skipped, as the nodes do
                    log.warning('skipping %s at %.3f s: %s', topic, now, exc)
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:     # before any error line, which must start a line of its own
                bar.close()
    if not res.times_ns:
        raise BagError(f'{bag}: no policy step could be replayed (no inputs in the bag)')
    # the bag ended before these latents' frames: those waiting for their frame, and those whose frame paired by order
    # encodes to another latent while the frame after it, which may be theirs, was never recorded (the recorder
    # stopped between a latent and its images): not replayed, as a latent whose frame is missing
    counts['latent_frames_missing'] += (sum(len(ks) for ks in waiting.values())
                                        + sum(len(p) for p in maybe.values()) + len(next_frame))
    # recorded agent_cmd -> the step whose /cmd_vel carries the same header stamp (policy_node stamps both alike)
    keys = cmd_stamps if ticks_from_bag else res.times_ns
    steps_of: dict[int, list[int]] = {}
    for i, key in enumerate(keys):
        steps_of.setdefault(key, []).append(i)
    unpaired = after_last = 0
    last_step = max(keys, default=None)
    for key, recs in rec_goals.items():
        for i, g in zip(steps_of.get(key, []), recs):
            res.rec_goal[i] = g
    for key, recs in rec_agents.items():
        for i, a in zip(steps_of.get(key, []), recs):
            res.rec_agent[i] = a
        missing = max(0, len(recs) - len(steps_of.get(key, [])))
        if last_step is not None and key > last_step:
            after_last += missing      # the bag ended between a step's agent_cmd and its /cmd_vel
        else:
            unpaired += missing
    res.info.update(counts, agent_cmd_unpaired=unpaired, agent_cmd_after_last_step=after_last,
                    flight_resets=dict(core.flight_resets))
    if encode is not None and counts['latent_frames_missing'] + counts['latent_frames_rejected']:
        log.warning('%d recorded latents had no frame in the bag and %d frames were rejected on re-encoding: those '
                    'latents were not replayed', counts['latent_frames_missing'], counts['latent_frames_rejected'])
    return res


def summarize(res: ReplayResult) -> dict:
    """How far the re-run's commands are from the recorded ones (m/s; latent units for mu): max, mean, rms."""
    def diff(new: dict, old: dict) -> dict:
        common = sorted(set(new) & set(old))
        if not common:
            return {'compared': 0}
        d = np.array([np.linalg.norm(new[t] - old[t]) for t in common])
        return {'compared': len(common), 'max': float(d.max()), 'rms': float(np.sqrt(np.mean(d ** 2))),
                'mean': float(d.mean())}
    out = dict(res.info)
    out['steps'] = len(res.times_ns)
    out['cmd_vel'] = diff(res.cmd, res.rec_cmd)
    out['agent_cmd'] = diff(res.agent, res.rec_agent)
    out['agent_cmd']['only_new'] = len(set(res.agent) - set(res.rec_agent))
    out['agent_cmd']['only_recorded'] = len(set(res.rec_agent) - set(res.agent))
    if res.latents:
        out['latent'] = diff(res.latents, res.rec_latent)
    if res.rec_goal or res.rec_descent:      # the assistant's intent, where the bag recorded it
        out['goal_estimate'] = diff(res.goal, res.rec_goal)
        common = sorted(set(res.descent) & set(res.rec_descent))
        out['descent_ok'] = {'compared': len(common),
                             'agree': sum(res.descent[i] == res.rec_descent[i] for i in common)}
    return out


def write_outputs(res: ReplayResult, out: Path, storage: str = 'mcap') -> Path:
    """New bag (directory) or CSV (out ends in .csv), written to a temporary name and renamed when complete.

    The bag holds each re-encoded latent at the time it reached the policy core and each step's agent_cmd and
    cmd_vel at the step's time; the CSV one row per step with the latent that step used."""
    if out.suffix == '.csv':
        if out.exists():
            raise BagError(f'{out}: exists already; not overwriting')
        dim = len(next(iter(res.latents.values()))) if res.latents else 0
        tmp = out.with_name(f'.{out.name}.partial-{os.getpid()}')
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            with open(tmp, 'w', newline='', encoding='utf-8') as fh:
                w = csv.writer(fh)
                w.writerow(['t_s'] + [f'latent_{i}' for i in range(dim)] + ['agent_x', 'agent_y', 'agent_z', 'cmd_x',
                            'cmd_y', 'cmd_z', 'recorded_cmd_x', 'recorded_cmd_y', 'recorded_cmd_z'])
                nan3 = [float('nan')] * 3
                for i, t in enumerate(res.times_ns):
                    lat = res.latents.get(res.step_latent.get(i), [float('nan')] * dim)
                    w.writerow([f'{t * 1e-9:.9f}'] + [f'{x:.6g}' for x in lat] +
                               [f'{x:.6g}' for x in res.agent.get(i, nan3)] + [f'{x:.6g}' for x in res.cmd[i]] +
                               [f'{x:.6g}' for x in res.rec_cmd.get(i, nan3)])
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise BagError(f'{out}: cannot write ({exc.strerror})') from None
        publish_new(tmp, out)
        return out
    rows: list[tuple[int, int, str, object]] = [(t, 0, LATENT, msgs.float_array(res.latents[k]))
                                                for k, t in res.latent_times.items() if k in res.latents]
    for i, t in enumerate(res.times_ns):
        if i in res.agent:
            rows.append((t, 1, AGENT, msgs.twist_stamped(t, res.agent[i])))
        rows.append((t, 2, CMD, msgs.twist_stamped(t, res.cmd[i])))
        if i in res.goal:
            rows.append((t, 3, GOAL_EST, msgs.pose_with_covariance(t, res.goal[i], res.cov[i])))
        if i in res.descent:
            rows.append((t, 4, DESCENT, msgs.boolean(res.descent[i])))
    rows.sort(key=lambda row: row[:2])          # stable: steps at one time keep their order
    with BagWriter(out, storage=storage, atomic=True) as w:
        if res.latents:
            w.add_topic(LATENT, *CONTRACT_TOPICS[LATENT])
        w.add_topic(AGENT, *CONTRACT_TOPICS[AGENT])
        w.add_topic(CMD, *CONTRACT_TOPICS[CMD])
        for topic in (GOAL_EST, DESCENT):
            w.add_topic(topic, *CONTRACT_TOPICS[topic])
        for t, _, topic, msg in rows:
            w.write_msg(topic, t, msg)
    return out


def format_summary(s: dict) -> str:
    """Human-readable lines of a summary."""
    on = [k for k, v in s.get('rules', {}).items() if v]
    lines = [f"replayed {s['steps']} steps of {s['bag']} ({s['mode']} from {s.get('mode_from', '?')}, "
             f"actor {s['actor']}, latent {s['latent_source']}, velocity {s['velocity_frame']}, "
             f"steps at {s['steps_at']}, rules {', '.join(on) or 'none'})"]
    for key in ('cmd_vel', 'agent_cmd', 'latent', 'goal_estimate'):
        d = s.get(key)
        if not d:
            continue
        if d['compared']:
            lines.append(f"  {key:<10} vs recorded: {d['compared']} compared, max |diff| {d['max']:.3g}, "
                         f"mean {d['mean']:.3g}, rms {d['rms']:.3g}")
        else:
            lines.append(f'  {key:<10} vs recorded: nothing recorded to compare with')
    d = s.get('descent_ok')
    if d:
        lines.append(f"  descent_ok vs recorded: {d['compared']} compared, {d['agree']} the same")
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    p = argparse.ArgumentParser(prog='replay_assist', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('bag', help='recorded bag (directory or .mcap/.db3), or a folder of bags (e.g. evaluate '
                               '--record-dir): each is replayed into <bag>_replay')
    p.add_argument('--out', default='', help='new bag directory, or a .csv file (default: <bag>_replay)')
    p.add_argument('--summary', default='', help='also write the summary as JSON here (default: <out>.summary.json)')
    p.add_argument('--storage', default='mcap', choices=('mcap', 'sqlite3'), help='storage of the new bag')
    d = ReplayConfig()
    p.add_argument('--mode', default=d.mode, choices=('auto', 'latent', 'oracle', 'end_to_end'),
                   help="assistant to re-run (auto: the mode the bag was flown in: evaluate's condition, policy_node's "
                        "recorded mode parameter or /diagnostics; else latent)")
    p.add_argument('--actor', default=d.actor, help='TD3 actor file (default: the one policy_node flew, if recorded '
                                                    'and present, else the shipped one for the mode)')
    p.add_argument('--encoder', default=d.encoder, help='CM-VAE weights (default: the one encoder_node flew, if '
                                                        'recorded and present, else the shipped model)')
    p.add_argument('--latent', default=d.latent, choices=('auto', 'encode', 'recorded'),
                   help='re-encode the camera frames, or use the recorded /assist/latent')
    p.add_argument('--velocity-frame', default=d.velocity_frame, choices=('auto', 'twist', 'odom'),
                   help="actor's velocity input: /odom twist as is (policy_node) or rotated to odom (evaluate)")
    p.add_argument('--rate-hz', type=float, default=d.rate_hz,
                   help=f'step rate when the bag has no /cmd_vel (at most {MAX_RATE_HZ:g})')
    p.add_argument('--blend-threshold', type=float, default=d.blend_threshold,
                   help='|a| above which a is blended (default: policy_node\'s recorded value, else 0.25)')
    p.add_argument('--timeout-s', type=float, default=d.timeout_s,
                   help='input staleness timeout (s; default: policy_node\'s recorded timeouts, else 0.5)')
    for r in RULES:                          # --safety (--floor-guard), --override (--pilot-override), ...
        p.add_argument(f'--{r.field}', f'--{r.switch.replace("_", "-")}', dest=r.field, default=getattr(d, r.field),
                       choices=('auto', 'on', 'off'), help=f'{r.title} (auto: as the bag was flown)')
    p.add_argument('--align-pilot', default=d.align_pilot, choices=('auto', 'on', 'off'),
                   help='give each step the pilot command its recorded V and a imply, when that is the recorded '
                        'message before or after the latest (auto: graph bags)')
    a = p.parse_args(argv)
    if not (math.isfinite(a.rate_hz) and 0 < a.rate_hz <= MAX_RATE_HZ) or (
            a.timeout_s is not None and not (math.isfinite(a.timeout_s) and a.timeout_s > 0)) or (
            a.blend_threshold is not None and not (math.isfinite(a.blend_threshold) and a.blend_threshold >= 0)):
        print(f'error: --rate-hz must be > 0 and <= {MAX_RATE_HZ:g}, --timeout-s finite and > 0, --blend-threshold '
              f'finite and >= 0', file=sys.stderr)
        return 2
    bag = Path(a.bag.rstrip('/'))
    cfg = ReplayConfig(mode=a.mode, actor=a.actor, encoder=a.encoder, latent=a.latent,
                       velocity_frame=a.velocity_frame, rate_hz=a.rate_hz, blend_threshold=a.blend_threshold,
                       timeout_s=a.timeout_s, align_pilot=a.align_pilot,
                       **{r.field: getattr(a, r.field) for r in RULES})
    bags = bags_under(bag)
    if bags:
        return replay_many(bags, Path(a.out) if a.out else None, cfg, a.storage, summary_given=bool(a.summary))
    out = Path(a.out) if a.out else bag.with_name(bag.name + '_replay')
    spath = Path(a.summary) if a.summary else out.with_name(out.name + '.summary.json')
    try:
        summary = replay_one(bag, out, spath, cfg, a.storage, progress=True)
    except (BagError, ValueError, OSError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    print(format_summary(summary))
    print(f'written: {out}, {spath}')
    return 0


def bags_under(path: Path) -> list[Path]:
    """The bags directly inside `path` when it is a folder of bags (e.g. evaluate --record-dir), not a bag itself
    and not a replay's own output (`*_replay`); [] otherwise."""
    if not path.is_dir() or (path / METADATA).exists():
        return []
    return sorted(d for d in path.iterdir()
                  if d.is_dir() and (d / METADATA).exists() and not d.name.endswith('_replay'))


def replay_one(bag: Path, out: Path, spath: Path, cfg: ReplayConfig, storage: str, progress: bool) -> dict:
    """Replay one bag into `out` (bag or CSV) and its summary JSON `spath` (neither may exist); the summary."""
    check_output(out)
    check_output(spath)
    res = replay(bag, cfg, progress=progress)
    write_outputs(res, out, storage)
    summary = summarize(res)
    summary['output'] = str(out)
    tmp = spath.with_name(f'.{spath.name}.partial-{os.getpid()}')
    try:
        tmp.write_text(json.dumps(summary, indent=2), encoding='utf-8')
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise BagError(f'{spath}: cannot write ({exc.strerror})') from None
    publish_new(tmp, spath)
    return summary


def replay_many(bags: list[Path], out_dir: Path | None, cfg: ReplayConfig, storage: str, summary_given: bool) -> int:
    """Replay every bag of a folder, each into `<bag>_replay` (in `out_dir` when given) with its summary JSON,
    under one progress bar; one line per bag; exit 1 when any failed (the others are still replayed)."""
    from tqdm import tqdm
    if summary_given:
        print('error: --summary names one file: with a folder of bags each replay writes <out>.summary.json',
              file=sys.stderr)
        return 2
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
    failed = 0
    lines = []
    for bag in tqdm(bags, desc='replay_assist', unit='bag', file=sys.stderr, mininterval=1, disable=None):
        out = (out_dir or bag.parent) / (bag.name + '_replay')
        try:
            s = replay_one(bag, out, out.with_name(out.name + '.summary.json'), cfg, storage, progress=False)
        except (BagError, ValueError, OSError) as exc:
            failed += 1
            lines.append(f'{bag.name}: error: {exc}')
            continue
        diff = s['cmd_vel'].get('max', float('nan'))
        lines.append(f'{bag.name}: {s["steps"]} steps, /cmd_vel max |diff| {diff:.3g} m/s -> {out}')
    print('\n'.join(lines))
    print(f'{len(bags) - failed} of {len(bags)} bags replayed')
    return 1 if failed else 0

if __name__ == '__main__':
    sys.exit(main())
