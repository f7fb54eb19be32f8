"""replay_assist: re-run the encoder and policy cores offline on a bag's recorded inputs, compare with what was flown.

    replay_assist flights/run1                                  # shipped models -> flights/run1_replay/ (a bag)
    replay_assist flights/run1 --actor runs/td3/actor.pt --out new.csv
    replay_assist runs/eval/bags/latent_beta0.50_seed2024 --encoder runs/cmvae/cmvae.pt

No ROS graph: the bag's camera frames, /odom and /pilot/cmd_vel (and /sim/goal for the oracle) are fed to
the same cores the nodes run (assist_perception's LatentEncoder via make_latent_fn, PolicyCore) at the
recorded receive times; the policy steps at the times of the recorded /cmd_vel messages (or at --rate-hz
when the bag has none). Writes /assist/latent, /assist/agent_cmd and /cmd_vel into a new bag (or one CSV
row per step) and prints how far the new commands are from the recorded ones. With the models that flew
the bag the difference is ~0 (tests/test_bag_replay.py holds evaluate's bags to < 1e-4 m/s): that is the
check that replay is faithful before a new model is tried on old flights.

--latent recorded uses the bag's /assist/latent instead of re-encoding (a new actor on old latents).
The non-learned rules (floor guard, pilot override, pad recall, oscillation damper) run as in policy_node:
every depth frame reaches the core (the guard and the recall read it; /odom's orientation goes with the
position, as the recall's map needs), and each rule is on as policy_node's default, unless the bag was
flown by evaluate (custom_data assist.condition, e.g. latent+guard+override+recall+damper), which says
which were (a graph's bag in mode oracle: the floor guard only, as policy_node's defaults there);
--floor-guard / --override / --recall / --damper on|off decide instead.
Velocity: the policy node feeds /odom's twist (base_link) to the actor; evaluate's env feeds world-frame
velocity, and its bags say so in custom_data, which --velocity-frame auto follows (the rules read the
twist either way, as both do). Depth noise: evaluate's bags hold the rendered depth and, when the
encoder saw it through the simulated sensor noise, the noise's seeds (custom_data
assist.depth_noise_seed), with which the frames are re-encoded through the same noise.
"""
from __future__ import annotations

import argparse
import csv
import json
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from . import msgs
from .bagio import CONTRACT_TOPICS, BagError, BagReader, BagWriter, check_output
from ..observation import Condition
from ..poses import header_seconds
from .episode import DEPTH_NOISE_KEY, VELOCITY_FRAME_KEY

log = logging.getLogger(__name__)

RGB, DEPTH, ODOM, PILOT = '/camera/color/image_raw', '/camera/depth/image_raw', '/odom', '/pilot/cmd_vel'
LATENT, AGENT, CMD, GOAL = '/assist/latent', '/assist/agent_cmd', '/cmd_vel', '/sim/goal'


@dataclass
class ReplayConfig:
    """What to re-run and how (replay_assist flags map 1:1)."""

    mode: str = 'auto'                 # latent | oracle | end_to_end | auto (bag's custom_data, else latent)
    actor: str = ''                    # default: shipped models/td3_<mode>_actor.pt
    encoder: str = ''                  # default: shipped CM-VAE
    latent: str = 'auto'               # encode | recorded | auto (encode when the bag has camera frames)
    velocity_frame: str = 'auto'       # twist | odom | auto
    rate_hz: float = 20.0              # step rate when the bag has no recorded /cmd_vel
    blend_threshold: float = 0.25
    timeout_s: float = 0.5             # pilot, feature and odometry timeouts
    override: str = 'auto'             # pilot override: on | off | auto (evaluate's bags say; else on, as policy_node)
    floor_guard: str = 'auto'          # floor guard: on | off | auto (as override)
    recall: str = 'auto'               # pad recall: on | off | auto (as override)
    damper: str = 'auto'               # oscillation damper: on | off | auto (as override)


# rule -> the flag evaluate adds to a condition's name when the rule flew (latent+guard+override+recall+damper)
RULE_FLAGS = {'floor_guard': 'guard', 'override': 'override', 'recall': 'recall', 'damper': 'damper'}


def rules_on(cfg: ReplayConfig, condition: str, flags: list[str], mode: str = 'latent') -> dict[str, bool]:
    """Which rules the re-run applies: each on|off as asked, else as evaluate flew the bag, else as policy_node's
    defaults for `mode` (all on; in mode oracle only the floor guard)."""
    out = {}
    for rule, flag in RULE_FLAGS.items():
        v = getattr(cfg, rule)
        if v not in ('auto', 'on', 'off'):
            raise ValueError(f"{rule.replace('_', '-')} must be auto, on or off, got {v!r}")
        default = flag in flags if condition else (rule == 'floor_guard' or not Condition(mode).knows_goal)
        out[rule] = v == 'on' or (v == 'auto' and default)
    return out


@dataclass
class ReplayResult:
    """Per-step outputs of the re-run and the recorded commands at the same times."""

    times_ns: list[int] = field(default_factory=list)
    latents: dict[int, np.ndarray] = field(default_factory=dict)
    agent: dict[int, np.ndarray] = field(default_factory=dict)
    cmd: dict[int, np.ndarray] = field(default_factory=dict)
    rec_agent: dict[int, np.ndarray] = field(default_factory=dict)
    rec_cmd: dict[int, np.ndarray] = field(default_factory=dict)
    rec_latent: dict[int, np.ndarray] = field(default_factory=dict)
    info: dict = field(default_factory=dict)


def _groups(it: Iterator[tuple[str, int, bytes]]) -> Iterator[list[tuple[str, int, bytes]]]:
    """Messages grouped by equal timestamp (inputs of one instant are applied before the step at it)."""
    group: list = []
    for item in it:
        if group and item[1] != group[0][1]:
            yield group
            group = []
        group.append(item)
    if group:
        yield group


def _noise_seeds(value: str | None) -> tuple[int, int] | None:
    """custom_data assist.depth_noise_seed '<base>,<landing>' -> (base, landing); None when absent."""
    if not value:
        return None
    try:
        base, landing = (int(v) for v in str(value).split(','))
    except ValueError:
        raise BagError(f'custom_data {DEPTH_NOISE_KEY} {value!r} is not "<base seed>,<landing seed>"') from None
    return base, landing


def replay(bag: str | Path, cfg: ReplayConfig, progress: bool = False) -> ReplayResult:
    """Re-run encoder + policy on the bag's inputs; BagError/ValueError with one line on bad input."""
    res = ReplayResult()
    with BagReader(bag) as r:
        custom = (r.metadata.get('custom_data') or {}) if r.metadata else {}
        # evaluate names its rows (and bags) <condition>[+guard][+override]
        condition, *flags = custom.get('assist.condition', '').split('+')
        mode = cfg.mode if cfg.mode != 'auto' else (condition or 'latent')
        if mode not in ('latent', 'oracle', 'end_to_end'):
            raise ValueError(f'{bag}: cannot replay mode {mode!r} (latent, oracle or end_to_end; '
                             f'pass --mode for a bag of an unassisted flight)')
        rules = rules_on(cfg, condition, flags, mode)
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
        used = need + [t for t in (AGENT, CMD, LATENT) if t in r.topics and t not in need]
        r.check_definitions(used)
        import torch  # noqa: PLC0415 - heavy: only once the bag is known to be good

        from ..damper import DamperConfig  # noqa: PLC0415
        from ..override import OverrideConfig  # noqa: PLC0415
        from ..policy_core import PolicyCore, PolicyCoreConfig, default_model_path  # noqa: PLC0415
        from ..recall import RecallConfig  # noqa: PLC0415
        from ..safety import SafetyConfig  # noqa: PLC0415
        torch.set_num_threads(1)
        frame = cfg.velocity_frame if cfg.velocity_frame != 'auto' else custom.get(VELOCITY_FRAME_KEY, 'twist')
        if frame not in ('twist', 'odom'):
            raise ValueError(f'velocity frame must be twist or odom, got {frame!r}')
        actor = Path(cfg.actor) if cfg.actor else default_model_path(mode)
        core = PolicyCore(actor, PolicyCoreConfig(mode=mode, blend_threshold=cfg.blend_threshold,
                                                  pilot_timeout_s=cfg.timeout_s, feature_timeout_s=cfg.timeout_s,
                                                  odom_timeout_s=cfg.timeout_s, actor_velocity=frame,
                                                  safety=SafetyConfig(enabled=rules['floor_guard']),
                                                  override=OverrideConfig(enabled=rules['override']),
                                                  recall=RecallConfig(enabled=rules['recall']),
                                                  damper=DamperConfig(enabled=rules['damper'])))
        encode = None
        noise_seeds = _noise_seeds(custom.get(DEPTH_NOISE_KEY))
        if mode == 'latent' and use_latent == 'encode':
            from ..latent import make_latent_fn  # noqa: PLC0415
            encode, dim = make_latent_fn(cfg.encoder or None, depth_noise=noise_seeds is not None,
                                         seed=noise_seeds[0] if noise_seeds else 0)
            if noise_seeds is not None:
                encode.reset(noise_seeds[1])
            if dim != core.builder.latent_dim:
                raise ValueError(f'{actor}: expects a {core.builder.latent_dim}-d latent, the encoder gives {dim}')
        ticks_from_bag = CMD in r.topics and r.topics[CMD].count > 0
        period = int(round(1e9 / cfg.rate_hz))
        next_tick = None
        rgb_by_stamp: dict[int, np.ndarray] = {}
        start = r.start_ns
        res.info = {'bag': str(bag), 'mode': mode, 'actor': str(actor), 'latent_source': use_latent if mode == 'latent'
                    else None, 'encoder': (cfg.encoder or 'shipped') if encode else None, 'velocity_frame': frame,
                    'pilot_override': rules['override'], 'rules': rules,
                    'depth_noise': None if encode is None or noise_seeds is None else list(noise_seeds),
                    'steps_at': 'recorded /cmd_vel times' if ticks_from_bag else f'{cfg.rate_hz} Hz'}
        total = sum(r.topics[t].count for t in used)
        bar = None
        if progress:
            from tqdm import tqdm  # noqa: PLC0415
            bar = tqdm(total=total, unit='msg', desc='replay', file=sys.stderr)

        def step(t: int) -> None:
            out = core.step((t - start) * 1e-9)
            res.times_ns.append(t)
            res.cmd[t] = out.velocity
            if out.agent is not None:
                res.agent[t] = out.agent

        for group in _groups(r.messages(used)):
            t = group[0][1]
            if not ticks_from_bag:
                if next_tick is None:
                    next_tick = t
                while next_tick < t:
                    step(next_tick)
                    next_tick += period
            now = (t - start) * 1e-9
            tick_here = False
            for topic, _, raw in group:
                msg = r.deserialize(raw, topic)
                try:
                    if topic == ODOM:
                        pos, quat, twist = msgs.odom_arrays(msg)
                        core.set_odom(now, pos, twist, quat, header_seconds(msg))
                    elif topic == PILOT:
                        core.set_pilot(now, msgs.twist_linear(msg), msg.header.frame_id)
                    elif topic == GOAL and mode == 'oracle':
                        core.set_goal(msgs.point(msg))
                        core.reset()          # as policy_node does: a new goal is a new episode
                    elif topic == RGB:
                        rgb_by_stamp = {msgs.stamp_ns(msg.header.stamp): msgs.image_array(msg)}
                    elif topic == DEPTH:
                        depth = msgs.image_array(msg)
                        core.set_depth(now, depth, header_seconds(msg))    # every mode: the rules read it (policy_node)
                        rgb = rgb_by_stamp.get(msgs.stamp_ns(msg.header.stamp))
                        if rgb is not None:
                            if encode is not None:
                                mu = np.asarray(encode(rgb, depth), dtype=float)
                                res.latents[t] = mu
                                core.set_latent(now, mu)
                            elif mode == 'end_to_end':
                                core.set_image(now, rgb, depth)
                    elif topic == LATENT:
                        mu = np.asarray(msg.data, dtype=float)
                        res.rec_latent[t] = mu
                        if mode == 'latent' and use_latent == 'recorded':
                            core.set_latent(now, mu)
                    elif topic == AGENT:
                        res.rec_agent[t] = msgs.twist_linear(msg)
                    elif topic == CMD:
                        res.rec_cmd[t] = msgs.twist_linear(msg)
                        tick_here = True
                except ValueError as exc:     # a bad recorded input is skipped, as the nodes do
                    log.warning('skipping %s at %.3f s: %s', topic, now, exc)
            if tick_here and ticks_from_bag:
                step(t)
            if bar is not None:
                bar.update(len(group))
        if bar is not None:
            bar.close()
    if not res.times_ns:
        raise BagError(f'{bag}: no policy step could be replayed (no inputs in the bag)')
    return res


def summarize(res: ReplayResult) -> dict:
    """How far the re-run's commands are from the recorded ones (m/s; latent units for mu)."""
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
    return out


def write_outputs(res: ReplayResult, out: Path, storage: str = 'mcap') -> Path:
    """New bag (directory) or CSV (out ends in .csv), written to a temporary name and renamed when complete."""
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
                for t in res.times_ns:
                    lat = res.latents.get(t, [float('nan')] * dim)
                    w.writerow([f'{t * 1e-9:.9f}'] + [f'{x:.6g}' for x in lat] +
                               [f'{x:.6g}' for x in res.agent.get(t, nan3)] + [f'{x:.6g}' for x in res.cmd[t]] +
                               [f'{x:.6g}' for x in res.rec_cmd.get(t, nan3)])
            os.replace(tmp, out)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise BagError(f'{out}: cannot write ({exc.strerror})') from None
        return out
    with BagWriter(out, storage=storage, atomic=True) as w:
        if res.latents:
            w.add_topic(LATENT, *CONTRACT_TOPICS[LATENT])
        w.add_topic(AGENT, *CONTRACT_TOPICS[AGENT])
        w.add_topic(CMD, *CONTRACT_TOPICS[CMD])
        for t in res.times_ns:
            if t in res.latents:
                w.write_msg(LATENT, t, msgs.float_array(res.latents[t]))
            if t in res.agent:
                w.write_msg(AGENT, t, msgs.twist_stamped(t, res.agent[t]))
            w.write_msg(CMD, t, msgs.twist_stamped(t, res.cmd[t]))
    return out


def format_summary(s: dict) -> str:
    """Human-readable lines of a summary."""
    on = [k for k, v in s.get('rules', {}).items() if v]
    lines = [f"replayed {s['steps']} steps of {s['bag']} ({s['mode']}, actor {s['actor']}, "
             f"latent {s['latent_source']}, velocity {s['velocity_frame']}, steps at {s['steps_at']}, "
             f"rules {', '.join(on) or 'none'})"]
    for key in ('cmd_vel', 'agent_cmd', 'latent'):
        d = s.get(key)
        if not d:
            continue
        if d['compared']:
            lines.append(f"  {key:<10} vs recorded: {d['compared']} compared, max |diff| {d['max']:.3g}, "
                         f"rms {d['rms']:.3g}")
        else:
            lines.append(f'  {key:<10} vs recorded: nothing recorded to compare with')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    p = argparse.ArgumentParser(prog='replay_assist', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('bag', help='recorded bag (directory or .mcap/.db3)')
    p.add_argument('--out', default='', help='new bag directory, or a .csv file (default: <bag>_replay)')
    p.add_argument('--summary', default='', help='also write the summary as JSON here (default: <out>.summary.json)')
    p.add_argument('--storage', default='mcap', choices=('mcap', 'sqlite3'), help='storage of the new bag')
    d = ReplayConfig()
    p.add_argument('--mode', default=d.mode, choices=('auto', 'latent', 'oracle', 'end_to_end'),
                   help="assistant to re-run (auto: the bag's evaluate condition, else latent)")
    p.add_argument('--actor', default=d.actor, help='TD3 actor file (default: the shipped one for the mode)')
    p.add_argument('--encoder', default=d.encoder, help='CM-VAE weights (default: the shipped model)')
    p.add_argument('--latent', default=d.latent, choices=('auto', 'encode', 'recorded'),
                   help='re-encode the camera frames, or use the recorded /assist/latent')
    p.add_argument('--velocity-frame', default=d.velocity_frame, choices=('auto', 'twist', 'odom'),
                   help="actor's velocity input: /odom twist as is (policy_node) or rotated to odom (evaluate)")
    p.add_argument('--rate-hz', type=float, default=d.rate_hz, help='step rate when the bag has no /cmd_vel')
    p.add_argument('--blend-threshold', type=float, default=d.blend_threshold, help='|a| above which a is blended')
    p.add_argument('--timeout-s', type=float, default=d.timeout_s, help='input staleness timeout (s)')
    p.add_argument('--override', default=d.override, choices=('auto', 'on', 'off'),
                   help='pilot override (auto: as evaluate flew the bag, else on as policy_node)')
    p.add_argument('--floor-guard', default=d.floor_guard, choices=('auto', 'on', 'off'),
                   help='floor guard (auto: as evaluate flew the bag, else on as policy_node)')
    p.add_argument('--recall', default=d.recall, choices=('auto', 'on', 'off'),
                   help='pad recall (auto: as evaluate flew the bag, else on as policy_node)')
    p.add_argument('--damper', default=d.damper, choices=('auto', 'on', 'off'),
                   help='oscillation damper (auto: as evaluate flew the bag, else on as policy_node)')
    a = p.parse_args(argv)
    if not a.rate_hz > 0 or not a.timeout_s > 0 or not a.blend_threshold >= 0:
        print('error: --rate-hz and --timeout-s must be > 0, --blend-threshold >= 0', file=sys.stderr)
        return 2
    bag = Path(a.bag.rstrip('/'))
    out = Path(a.out) if a.out else bag.with_name(bag.name + '_replay')
    cfg = ReplayConfig(mode=a.mode, actor=a.actor, encoder=a.encoder, latent=a.latent,
                       velocity_frame=a.velocity_frame, rate_hz=a.rate_hz, blend_threshold=a.blend_threshold,
                       timeout_s=a.timeout_s, override=a.override, floor_guard=a.floor_guard, recall=a.recall,
                       damper=a.damper)
    try:
        check_output(out)
        res = replay(bag, cfg, progress=True)
        write_outputs(res, out, a.storage)
        summary = summarize(res)
        summary['output'] = str(out)
        spath = Path(a.summary) if a.summary else out.with_name(out.name + '.summary.json')
        tmp = spath.with_name(f'.{spath.name}.partial')
        tmp.write_text(json.dumps(summary, indent=2), encoding='utf-8')
        os.replace(tmp, spath)
    except (BagError, ValueError, OSError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    print(format_summary(summary))
    print(f'written: {out}, {spath}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
