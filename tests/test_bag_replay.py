"""evaluate --record-dir bags: replay_assist reproduces the flown commands; plot_flight draws the landing."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from assist_lab import evaluate
from assist_bags import plot
from assist_bags.bagio import BagReader, BagWriter
from assist_lab.landing_bags import DEPTH_NOISE_KEY, landing_bag_name
from assist_bags.replay import ReplayConfig, replay, rules_on, summarize, write_outputs

BIN = Path(sys.executable).parent
BARE = ['--safety', 'false', '--override', 'false', '--recall', 'false', '--damper', 'false']   # the actor alone


@pytest.fixture(scope='module')
def landing(tmp_path_factory):
    """One latent-assisted landing flown by evaluate with --record-dir (shipped CM-VAE and actor)."""
    out = tmp_path_factory.mktemp('eval')
    code = evaluate.main(['--out', str(out), '--conditions', 'latent', '--betas', '1.0', '--landings', '1',
                          '--max-episode-s', '10', '--record-dir', str(out / 'bags'), '--plot', 'false', *BARE])
    assert code == 0
    row = evaluate.read_landings(out / 'landings.csv')['latent'][0]
    bag = out / 'bags' / landing_bag_name('latent', row['beta'], row['seed'])
    assert sorted(p.name for p in (out / 'bags').iterdir()) == [bag.name]
    return bag, row


@pytest.fixture(scope='module')
def override_landing(tmp_path_factory):
    """One latent landing flown with the pilot override on (evaluate --override true): rows latent+override."""
    out = tmp_path_factory.mktemp('eval_override')
    code = evaluate.main(['--out', str(out), '--conditions', 'latent', '--betas', '0.3', '--landings', '1',
                          '--pilot', 'late_correction', '--max-episode-s', '10',
                          '--record-dir', str(out / 'bags'), '--plot', 'false', *BARE, '--override', 'true'])
    assert code == 0
    row = evaluate.read_landings(out / 'landings.csv')['latent+override'][0]
    return out / 'bags' / landing_bag_name('latent+override', row['beta'], row['seed']), row


RULE_FLAGS = ('guard', 'override', 'recall', 'damper')


def _fly_with_every_rule(out: Path, pilot: str, seed: int, beta: float, max_s: float) -> tuple[Path, dict]:
    """One latent landing flown with every non-learned rule on and recorded; the assistant's intent shown (--cues) to
    a pilot who does not read it, so the bag records the intent. (bag, landings.csv row)"""
    code = evaluate.main(['--out', str(out), '--conditions', 'latent', '--betas', str(beta), '--landings', '1',
                          '--seed', str(seed), '--pilot', pilot, '--safety', 'true', '--override', 'true',
                          '--recall', 'true', '--damper', 'true', '--max-episode-s', str(max_s),
                          '--record-dir', str(out / 'bags'), '--plot', 'false', '--cues', '--cue-trust', '0'])
    assert code == 0
    cond = 'latent+guard+override+recall+damper+cues'
    row = evaluate.read_landings(out / 'landings.csv')[cond][0]
    return out / 'bags' / landing_bag_name(cond, row['beta'], row['seed']), row


@pytest.fixture(scope='module')
def rules_landings(tmp_path_factory):
    """Two landings between which every rule acts: a low flyer the floor guard, override and recall act on, and a
    delayed pilot circling its pad at beta 1, whom the damper (with override and recall) damps. Which rule acts in a
    landing depends on its whole trajectory, so no single landing is asked to show all four."""
    return [_fly_with_every_rule(tmp_path_factory.mktemp('eval_rules'), 'low_flyer', 3025, 0.5, 25.0),
            _fly_with_every_rule(tmp_path_factory.mktemp('eval_damped'), 'delay', 10014, 1.0, 40.0)]


def test_landing_bag_matches_its_csv_row(landing):
    bag, row = landing
    with BagReader(bag) as r:
        steps = r.topics['/cmd_vel'].count
        assert steps > 50
        for topic in ('/camera/color/image_raw', '/camera/depth/image_raw', '/odom', '/pilot/cmd_vel',
                      '/assist/latent', '/assist/agent_cmd'):
            assert r.topics[topic].count >= steps
        (_, _, raw), = list(r.messages(['/sim/landing']))
        result = json.loads(r.deserialize(raw, '/sim/landing').data)
    assert result['goal_index'] == row['goal_index'] and result['error_m'] == pytest.approx(row['error_m'])
    assert result['assisted'] is True


def test_recording_a_landing_does_not_change_it(landing, tmp_path):
    """The same landing flown without --record-dir gives the same row (the recorder passes the noise reset on)."""
    code = evaluate.main(['--out', str(tmp_path), '--conditions', 'latent', '--betas', '1.0', '--landings', '1',
                          '--max-episode-s', '10', '--plot', 'false', *BARE])
    assert code == 0
    assert evaluate.read_landings(tmp_path / 'landings.csv')['latent'][0] == landing[1]


def test_replay_reproduces_the_recorded_commands(landing):
    bag, _ = landing
    res = replay(bag, ReplayConfig())
    s = summarize(res)
    assert s['mode'] == 'latent' and s['latent_source'] == 'encode' and s['velocity_frame'] == 'odom'
    with BagReader(bag) as r:
        n = r.topics['/cmd_vel'].count
    assert s['steps'] == s['cmd_vel']['compared'] == s['agent_cmd']['compared'] == n
    assert s['agent_cmd']['only_new'] == s['agent_cmd']['only_recorded'] == 0
    assert s['latent']['max'] < 1e-5
    assert s['agent_cmd']['max'] < 1e-4 and s['cmd_vel']['max'] < 1e-4
    # the comparison sees a change: an assistant that never blends in flies V = u, not what was flown
    off = summarize(replay(bag, ReplayConfig(latent='recorded', blend_threshold=10.0)))
    assert off['cmd_vel']['max'] > 0.1


def test_replay_follows_the_pilot_override_the_bag_was_flown_with(landing, override_landing):
    bag, row = override_landing
    assert float(row['override_fraction']) > 0                 # the pilot's held keys engaged it
    s = summarize(replay(bag, ReplayConfig()))
    assert s['mode'] == 'latent' and s['pilot_override'] is True   # parsed from the condition latent+override
    assert s['agent_cmd']['max'] < 1e-4 and s['cmd_vel']['max'] < 1e-4   # the bag holds the applied commands
    assert summarize(replay(landing[0], ReplayConfig(latent='recorded')))['pilot_override'] is False
    assert summarize(replay(bag, ReplayConfig(latent='recorded', override='off')))['pilot_override'] is False
    with pytest.raises(ValueError, match='override must be'):
        replay(bag, ReplayConfig(override='maybe'))


def test_replay_cli_writes_a_bag_and_summary(landing, tmp_path):
    bag, _ = landing
    out = tmp_path / 'replayed'
    proc = subprocess.run([str(BIN / 'replay_assist'), str(bag), '--out', str(out)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert 'cmd_vel    vs recorded' in proc.stdout
    summary = json.loads((tmp_path / 'replayed.summary.json').read_text())
    assert summary['cmd_vel']['max'] < 1e-4
    with BagReader(out) as r:
        n = summary['steps']
        counts = {t: v.count for t, v in r.topics.items()}
        assert {t: counts.pop(t) for t in ('/assist/latent', '/assist/agent_cmd', '/cmd_vel')} == dict.fromkeys(
            ('/assist/latent', '/assist/agent_cmd', '/cmd_vel'), n)
        # and the assistant's intent: a goal estimate once a pad is mapped, the descent flag where the depth tells
        assert 0 < counts.pop('/assist/goal_estimate') <= n and 0 < counts.pop('/assist/descent_ok') <= n
        assert not counts
    # the same result as CSV
    res = replay(bag, ReplayConfig(latent='recorded'))
    csv_path = write_outputs(res, tmp_path / 'replayed.csv')
    lines = csv_path.read_text().splitlines()
    assert len(lines) == 1 + len(res.times_ns) and lines[0].startswith('t_s,agent_x')


def test_plot_flight_draws_the_landing(landing, tmp_path):
    bag, row = landing
    assert plot.main([str(bag), '--out', str(tmp_path)]) == 0
    png = tmp_path / f'{bag.name}_landing0.png'
    import matplotlib.image as mpimg
    img = mpimg.imread(png)
    assert img.shape[0] > 500 and img.shape[1] > 900 and img.std() > 0.05
    (f,) = plot.read_flights(bag)
    assert len(f.pads) == 5 and f.goal_index == row['goal_index']
    assert np.allclose(f.goal[:2], f.pads[row['goal_index']]['centre'][:2])
    fig = plot.plot_flight(f, tmp_path / 'again.png', 'test')
    assert [ax.get_title() for ax in fig.axes] == list(plot.PANELS)
    labels = {line.get_label() for ax in fig.axes[2:] for line in ax.get_lines()}
    assert {'pilot u', 'assistant a', 'blended V'} <= labels


def test_plot_flight_without_scene_marks_the_goal_from_sim_goal(landing, tmp_path):
    bag, row = landing
    stripped = tmp_path / 'no_scene'
    with BagReader(bag) as r, BagWriter(stripped) as w:
        keep = [t for t in r.topics if t != '/sim/scene']
        for t in keep:
            info = r.topics[t]
            w.add_topic(t, info.msgtype, info.qos)
        for topic, t, raw in r.messages(keep):
            w.write(topic, t, raw)
    (f,) = plot.read_flights(stripped)
    assert f.pads == [] and f.goal is not None and f.goal_index == row['goal_index']
    assert 'pads not recorded' in plot.describe(f, 'x', 0)
    assert plot.main([str(stripped), '--out', str(tmp_path / 'p')]) == 0
    assert (tmp_path / 'p' / 'no_scene_landing0.png').stat().st_size > 10_000


def test_replay_runs_the_rules_the_bag_was_flown_with(rules_landings, landing):
    """Depth frames and attitude reach the core, so the floor guard, override, recall and damper act as they flew."""
    acted = {rule: [bag for bag, row in rules_landings if float(row[f'{rule}_fraction']) > 0] for rule in RULE_FLAGS}
    assert all(acted.values()), {rule: len(bags) for rule, bags in acted.items()}    # each rule acted in a landing
    for bag, _ in rules_landings:
        with BagReader(bag) as r:
            assert DEPTH_NOISE_KEY in r.metadata['custom_data']      # the encoder's noise seeds, the depth as rendered
        s = summarize(replay(bag, ReplayConfig()))
        assert s['rules'] == {'safety': True, 'override': True, 'recall': True, 'damper': True}
        assert s['depth_noise'] is not None and s['velocity_frame'] == 'odom'
        assert s['latent']['max'] < 1e-5                             # the same noise re-applied to the same frames
        assert s['agent_cmd']['max'] < 1e-4 and s['cmd_vel']['max'] < 1e-4
        assert s['agent_cmd']['only_new'] == s['agent_cmd']['only_recorded'] == 0
        # the assistant's intent as it was recorded: every goal estimate and descent flag, the same
        assert s['goal_estimate']['compared'] > 50 and s['goal_estimate']['max'] < 1e-9
        assert s['descent_ok']['compared'] == s['steps'] and s['descent_ok']['agree'] == s['steps']
    for flag, rule in zip(RULE_FLAGS, ('safety', 'override', 'recall', 'damper')):   # each one's commands are in
        off = summarize(replay(acted[flag][0], ReplayConfig(latent='recorded', **{rule: 'off'})))   # a bag it acted in
        assert off['rules'][rule] is False and off['cmd_vel']['max'] > 0.05, rule
    # a bag evaluate flew without rules replays without them; a graph's bag (no condition) with all, as policy_node
    assert summarize(replay(landing[0], ReplayConfig(latent='recorded')))['rules'] == dict.fromkeys(
        ('safety', 'override', 'recall', 'damper'), False)
    assert rules_on(ReplayConfig(), '', []) == dict.fromkeys(('safety', 'override', 'recall', 'damper'), True)
    assert rules_on(ReplayConfig(), '', [], 'oracle') == {'safety': True, 'override': False, 'recall': False,
                                                          'damper': False}
    with pytest.raises(ValueError, match='recall must be'):
        replay(rules_landings[0][0], ReplayConfig(recall='sometimes'))


def test_replay_a_folder_of_bags(landing, override_landing, tmp_path, capsys):
    """replay_assist on a folder of bags (evaluate --record-dir's): each replayed into <bag>_replay with its summary,
    one line each; a second run refuses to overwrite and says so per bag (exit 1)."""
    import shutil

    from assist_bags.replay import main as replay_main
    folder = tmp_path / 'bags'
    folder.mkdir()
    for bag, _ in (landing, override_landing):
        shutil.copytree(bag, folder / bag.name)
    assert replay_main([str(folder)]) == 0
    out = capsys.readouterr().out
    assert '2 of 2 bags replayed' in out
    for bag, _ in (landing, override_landing):
        summary = json.loads((folder / f'{bag.name}_replay.summary.json').read_text())
        assert summary['cmd_vel']['max'] < 1e-9 and f'{bag.name}: ' in out
    assert replay_main([str(folder)]) == 1                       # outputs exist: never overwritten
    assert '0 of 2 bags replayed' in capsys.readouterr().out
    assert replay_main([str(folder), '--summary', str(tmp_path / 's.json')]) == 2


def test_replay_ends_the_flight_where_the_vehicle_reported_it_landed(landing, tmp_path):
    """A bag with the vehicle's /uav/landed_state: replay feeds it to the flight monitor as policy_node does."""
    from assist_bags import msgs
    from assist_bags.bagio import CONTRACT_TOPICS
    bag, _ = landing
    assert replay(bag, ReplayConfig()).info['flight_resets'].get('vehicle_landed', 0) == 0
    copy = tmp_path / 'with_landed_state'
    with BagReader(bag) as r:
        start, end = r.start_ns, r.end_ns
        mid = start + (end - start) // 2
        w = BagWriter(copy)
        for name, info in r.topics.items():
            w.add_topic(name, info.msgtype, info.qos)
        w.add_topic('/uav/landed_state', *CONTRACT_TOPICS['/uav/landed_state'])
        for key, value in (r.metadata.get('custom_data') or {}).items():
            w.custom_data[key] = value
        with w:
            for topic, t, raw in r.messages():
                w.write(topic, t, raw)
            landed = msgs.T('std_msgs/msg/UInt8')
            w.write_msg('/uav/landed_state', start, landed(data=2))       # in the air
            w.write_msg('/uav/landed_state', mid, landed(data=1))         # on the ground
    assert replay(copy, ReplayConfig()).info['flight_resets'].get('vehicle_landed', 0) == 1
