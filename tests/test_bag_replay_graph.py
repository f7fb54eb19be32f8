"""replay_assist on a bag recorded from the live graph (sim_node + encoder_node with depth noise + policy_node +
sim_pilot_node + bag_record, subprocesses on a private domain): the latents, the mode and the commands that flew.

What is deterministic, and asserted tightly: the recorder stores encoder_node's and policy_node's parameters, every
frame's depth noise is a function of (noise_seed, frame stamp), so each recorded latent is re-encoded from the same
frame through the same noise (ONNX Runtime on both sides: identical, bound 1e-4); every recorded /assist/agent_cmd
is paired with its step by header stamp. What is not: policy_node publishes no record of which /odom and pilot
message it had at a step, and on a loaded machine those race with the step; so the commands are held to agree
exactly on most steps (the pilot's races are resolved from the recorded V and a: pilot_alignment), not on all.
"""
from __future__ import annotations

import importlib.util
import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from geometry_msgs.msg import TwistStamped
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from assist_bags.bagio import PARAMS_KEY, BagReader, BagWriter
from assist_bags.replay import ReplayConfig, pair_latents, replay, summarize

pytestmark = pytest.mark.graph
REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location('bag_replay_graph_helpers', REPO / 'tests' / 'conftest.py')
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)
NodeProcess = _helpers.NodeProcess      # a node subprocess on the test's domain (shared with the fixtures)
wait_for = _helpers.wait_for
SIM_TOPICS = ('/camera/color/image_raw', '/camera/depth/image_raw', '/odom')
STEPS = 140                     # /cmd_vel messages to record (7 s of sim time at 20 Hz)


def _params_recorded(bag: Path) -> bool:
    try:
        custom = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']['custom_data']
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return False
    return bool(custom) and all(PARAMS_KEY + n in custom for n in ('encoder_node', 'policy_node'))


@pytest.fixture(scope='module')
def graph_bag(ros, domain_id, tmp_path_factory):
    """A few seconds of the live latent-assisted graph, recorded by bag_record on sim time.

    The encoder, the policy and the recorder start first, the pilot and the sim last, so every node (and the bag)
    sees the flight from its first message: what the assistant remembers of a flight is then in the bag too."""
    tmp = tmp_path_factory.mktemp('graph_bag')
    bag = tmp / 'bag'
    count, lock = [0], threading.Lock()

    def on_cmd(_msg) -> None:
        with lock:
            count[0] += 1
    sub = ros.create_subscription(TwistStamped, '/cmd_vel', on_cmd, 50)
    procs = [NodeProcess('encoder_node', {'use_sim_time': True, 'depth_noise': True, 'noise_seed': 7}, domain_id,
                         tmp),
             NodeProcess('policy_node', {'use_sim_time': True, 'mode': 'latent'}, domain_id, tmp),
             NodeProcess('bag_record', {'output': str(bag), 'use_sim_time': True, 'discovery_period_s': 0.1},
                         domain_id, tmp)]
    try:
        deadline = time.monotonic() + 180
        while not _params_recorded(bag) and time.monotonic() < deadline:
            assert all(p.proc.poll() is None for p in procs), '\n'.join(p.log()[-2000:] for p in procs)
            time.sleep(0.2)
        assert _params_recorded(bag), '\n'.join(p.log()[-2000:] for p in procs)
        procs.append(NodeProcess('sim_pilot_node', {'use_sim_time': True, 'seed': 2, 'beta': 1.0}, domain_id, tmp))
        # the sim crawls (one step per 5 s) until the recorder has subscribed to its topics: every frame the encoder
        # sees is then in the bag
        procs.append(NodeProcess('sim_node', {'seed': 4, 'real_time_factor': 0.01, 'reset_delay_s': 0.5},
                                 domain_id, tmp))
        deadline = time.monotonic() + 120
        while not all(f'recording {t} ' in procs[2].log() for t in SIM_TOPICS) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(1.0)                                      # the new subscriptions match their publisher
        client = AsyncParameterClient(ros, 'sim_node')
        assert client.wait_for_services(30.0), procs[-1].log()
        fut = client.set_parameters([Parameter('real_time_factor', value=1.0)])
        assert wait_for(fut.done, 30.0) and fut.result().results[0].successful, procs[-1].log()
        deadline = time.monotonic() + 240
        while count[0] < STEPS and time.monotonic() < deadline:
            assert all(p.proc.poll() is None for p in procs), '\n'.join(p.log()[-2000:] for p in procs)
            time.sleep(0.2)
        assert count[0] >= STEPS, '\n'.join(p.log()[-2000:] for p in procs)
        assert procs[2].stop() == 0, procs[2].log()          # the recorder first: the bag ends while all run
    finally:
        for p in procs:
            p.stop()
        ros.destroy_subscription(sub)
    return bag


def _with_custom(src: Path, dst: Path, custom: dict | None) -> Path:
    """A copy of bag `src` whose metadata.yaml custom_data is `custom`."""
    shutil.copytree(src, dst)
    meta = yaml.safe_load((dst / 'metadata.yaml').read_text())
    meta['rosbag2_bagfile_information']['custom_data'] = custom
    (dst / 'metadata.yaml').write_text(yaml.safe_dump(meta, sort_keys=False))
    return dst


def test_recorder_stores_the_nodes_parameters(graph_bag):
    with BagReader(graph_bag) as r:
        custom = r.metadata['custom_data']
        counts = {t: i.count for t, i in r.topics.items()}
    enc = json.loads(custom[PARAMS_KEY + 'encoder_node'])
    pol = json.loads(custom[PARAMS_KEY + 'policy_node'])
    assert enc['depth_noise'] is True and enc['noise_seed'] == 7 and enc['level_camera'] is False
    assert pol['mode'] == 'latent' and pol['use_sim_time'] is True
    assert custom['assist.record_clock'] == 'sim'
    assert counts['/cmd_vel'] >= STEPS - 20 and counts['/assist/latent'] > 20 and counts['/assist/agent_cmd'] > 20


def test_replay_reproduces_the_latents_and_commands_that_flew(graph_bag):
    s = summarize(replay(graph_bag, ReplayConfig()))
    with BagReader(graph_bag) as r:
        n_latent, n_agent, n_cmd = (r.topics[t].count for t in ('/assist/latent', '/assist/agent_cmd', '/cmd_vel'))
    assert s['mode'] == 'latent' and s['mode_from'] == 'policy_node parameters'
    assert s['depth_noise'] == {'noise_seed': 7, 'per': 'frame stamp'}
    assert s['latents_at'] == 'recorded /assist/latent times'
    # every recorded latent whose frame the recorder kept is re-encoded through the same noise: identical
    assert s['latent_frames_rejected'] == 0
    assert s['latent']['compared'] == n_latent - s['latent_frames_missing'] >= n_latent - 3
    assert s['latent']['max'] < 1e-4
    # every step is one recorded /cmd_vel; every recorded agent_cmd is paired with its step by header stamp
    assert s['steps'] == s['cmd_vel']['compared'] == n_cmd
    # (a recorder that falls more than its queue depth of 10 behind loses a /cmd_vel and keeps its agent_cmd: on a
    # loaded machine one step in a run can be unpaired; the recorder stops first, so the last one may be too)
    assert s['agent_cmd_unpaired'] <= 2 and s['agent_cmd_after_last_step'] <= 1, s
    # every recorded agent_cmd is compared with its step, was not re-run, or came after the bag's last step
    assert s['agent_cmd']['compared'] + s['agent_cmd']['only_recorded'] + s['agent_cmd_after_last_step'] == n_agent
    assert s['agent_cmd']['compared'] >= n_agent - 5
    res = replay(graph_bag, ReplayConfig())
    d = np.array([np.linalg.norm(res.agent[i] - res.rec_agent[i]) for i in sorted(set(res.agent) & set(res.rec_agent))])
    assert np.median(d) < 1e-4, np.percentile(d, [50, 75, 90, 100])     # most steps' inputs line up exactly
    # the assistant's intent, recorded (bag_record takes the contract's topics): paired with its step by header
    # stamp; the same pad estimated at most steps (its mapped centre moves by a few cm with which frames the map
    # had taken when the step ran: the same race as the commands'), the descent flag the same at most
    with BagReader(graph_bag) as r:
        n_goal = r.topics['/assist/goal_estimate'].count
    g = s['goal_estimate']
    assert n_goal > 20 and g['compared'] >= n_goal - 5, (g, n_goal)
    d = np.array([np.linalg.norm(res.goal[i] - res.rec_goal[i]) for i in sorted(set(res.goal) & set(res.rec_goal))])
    assert np.mean(d < 0.3) > 0.9 and np.median(d) < 0.05, (np.percentile(d, [50, 75, 90, 100]), g)
    assert s['descent_ok']['agree'] >= 0.9 * s['descent_ok']['compared'] > 0, s['descent_ok']


def test_replay_takes_the_mode_from_the_bag(graph_bag, tmp_path):
    with BagReader(graph_bag) as r:
        custom = dict(r.metadata['custom_data'])
    pol = json.loads(custom[PARAMS_KEY + 'policy_node'])
    oracle = _with_custom(graph_bag, tmp_path / 'oracle', {**custom, PARAMS_KEY + 'policy_node':
                                                           json.dumps({**pol, 'mode': 'oracle'})})
    s = summarize(replay(oracle, ReplayConfig(latent='recorded')))
    assert s['mode'] == 'oracle' and s['mode_from'] == 'policy_node parameters'
    assert s['rules'] == {'safety': True, 'override': True, 'recall': True, 'damper': True}   # as recorded
    # without the recorder's parameters: policy_node's /diagnostics say which mode flew
    bare = _with_custom(graph_bag, tmp_path / 'bare', None)
    s = summarize(replay(bare, ReplayConfig(latent='recorded')))
    assert s['mode'] == 'latent' and s['mode_from'] == 'policy_node /diagnostics'
    assert summarize(replay(bare, ReplayConfig(mode='oracle', latent='recorded')))['mode_from'] == 'option'


def test_pair_latents_matches_each_latent_with_its_pad_estimate():
    # the recorder took two latents before their pad estimates: the pairing is not shifted by it
    events = [('L', 0), ('P', 100), ('L', 1), ('L', 2), ('P', 150), ('P', 200), ('L', 3), ('P', 300)]
    assert pair_latents(events) == {0: 100, 1: 150, 2: 200, 3: 300}
    # the pad-estimate subscription matched two frames after the latent one
    events = [('L', 0), ('L', 1), ('L', 2), ('P', 200), ('L', 3), ('P', 300)]
    assert pair_latents(events) == {2: 200, 3: 300}
    # one pad estimate lost mid-flight: its latent is left out, the pairing on either side stays right
    events = [e for k in range(60) for e in (('L', k), ('P', 1000 + k)) if e != ('P', 1030)]
    assert pair_latents(events) == {k: 1000 + k for k in range(60) if k != 30}
    assert pair_latents([('L', 0), ('L', 1)]) == {}


def _copy(src: Path, dst: Path, keep) -> Path:
    """A copy of bag `src` with the messages (topic, time, raw) for which keep(index, message) is true."""
    with BagReader(src) as r:
        rows = list(r.messages())
        infos = dict(r.topics)
        custom = dict(r.metadata['custom_data'] or {})
    with BagWriter(dst) as w:
        for name, info in infos.items():
            w.add_topic(name, info.msgtype, info.qos)
        for key, value in custom.items():
            w.set_custom_data(key, value)
        for i, m in enumerate(rows):
            if keep(i, m):
                w.write(*m)
    return dst


def _last_latent_without_its_pad_estimate(src: Path, dst: Path) -> Path:
    """A copy of bag `src` that ends as a recording stopped between the last latent and its pad estimate."""
    with BagReader(src) as r:
        rows = [(i, m[0]) for i, m in enumerate(r.messages())]
    events = [('L', i) if topic == '/assist/latent' else ('P', i) for i, topic in rows
              if topic in ('/assist/latent', '/assist/pad_estimate')]
    last = max(i for kind, i in events if kind == 'L')
    drop = {p for k, p in pair_latents(events).items() if k == last}
    return _copy(src, dst, lambda i, m: i not in drop)


def _last_latent_without_its_frame(src: Path, dst: Path) -> Path:
    """A copy of bag `src` that ends with a latent whose frame is not in it: cut right after the last latent that has
    a pad estimate, without that pad estimate and its frame's images (as a recorder that took the latent topic
    ahead of the cameras and stopped), the frames before kept."""
    with BagReader(src) as r:
        rows = list(r.messages())
        events, stamps, latent_rows = [], {}, []
        for i, (topic, _, raw) in enumerate(rows):
            if topic == '/assist/latent':
                events.append(('L', len(latent_rows)))
                latent_rows.append(i)
            elif topic in ('/assist/pad_estimate', *SIM_TOPICS[:2]):
                msg = r.deserialize(raw, topic)
                stamps[i] = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                if topic == '/assist/pad_estimate':
                    events.append(('P', stamps[i]))
    last, frame = max(pair_latents(events).items())
    drop = {i for i, stamp in stamps.items() if stamp >= frame} | set(range(latent_rows[last] + 1, len(rows)))
    return _copy(src, dst, lambda i, m: i not in drop)


def _reordered(src: Path, dst: Path) -> Path:
    """A copy of bag `src` in which each /assist/pad_estimate is recorded right after the /assist/latent that follows
    its own frame's latent: the order a recorder gives when it takes the latent topic one frame ahead of the pad
    estimates. Its own latent is the one the live bag pairs it with (pair_latents on the bag as recorded, which may
    itself hold a burst or a lost message), so every pad estimate is exactly one frame late."""
    with BagReader(src) as r:
        rows = list(r.messages())
        infos = dict(r.topics)
        custom = dict(r.metadata['custom_data'] or {})
    events, latent_times, pads = [], [], []
    for topic, t, raw in rows:
        if topic == '/assist/latent':
            events.append(('L', len(latent_times)))
            latent_times.append(t)
        elif topic == '/assist/pad_estimate':
            events.append(('P', len(pads)))           # its index stands for its stamp
            pads.append((t, raw))
    own = {j: k for k, j in pair_latents(events).items()}          # pad estimate -> its frame's latent
    out = [m for m in rows if m[0] != '/assist/pad_estimate']
    end = max(t for _, t, _ in rows)
    for j, (t, raw) in enumerate(pads):
        k = own.get(j)
        if k is not None:
            t = latent_times[k + 1] + 1 if k + 1 < len(latent_times) else end + 1 + j
        out.append(('/assist/pad_estimate', t, raw))
    with BagWriter(dst) as w:
        for name, info in infos.items():
            w.add_topic(name, info.msgtype, info.qos)
        for key, value in custom.items():
            w.set_custom_data(key, value)
        for topic, t, raw in sorted(out, key=lambda m: m[1]):
            w.write(topic, t, raw)
    return dst


def test_a_latent_whose_pad_estimate_was_never_recorded_is_found_by_its_frame(graph_bag, tmp_path):
    """The recording stopped between the last latent and its pad estimate, and the recorder took latents a frame
    ahead: the last latent's frame is the one after its bag-order partner, found by its images."""
    bag = _reordered(_last_latent_without_its_pad_estimate(graph_bag, tmp_path / 'cut'), tmp_path / 'ahead')
    s = summarize(replay(bag, ReplayConfig()))
    assert s['latent_frames_rejected'] == 0 and s['latent_frames_missing'] <= 3
    assert s['latent']['max'] < 1e-4


def test_replay_finds_each_latents_frame_when_the_recorder_took_latents_a_frame_ahead(graph_bag, tmp_path):
    bag = _reordered(graph_bag, tmp_path / 'ahead')
    s = summarize(replay(bag, ReplayConfig()))
    assert s['latent_frames_realigned'] > 20
    assert s['latent_frames_rejected'] == 0 and s['latent_frames_missing'] <= 3
    assert s['latent']['max'] < 1e-4


def test_a_latent_whose_frame_was_never_recorded_is_left_out(graph_bag, tmp_path):
    """The recording stopped between the last latent and its frame's images: that latent is not compared with the
    re-encoding of another frame (the one before it in the bag), it is one whose frame is missing."""
    bag = _last_latent_without_its_frame(graph_bag, tmp_path / 'cut')
    with BagReader(bag) as r:
        n_latent = r.topics['/assist/latent'].count
    s = summarize(replay(bag, ReplayConfig()))
    assert s['latent_frames_rejected'] == 0 and 1 <= s['latent_frames_missing'] <= 3
    assert s['latent']['compared'] == n_latent - s['latent_frames_missing']
    assert s['latent']['max'] < 1e-4
