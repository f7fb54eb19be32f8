"""The one assistant chain (assistant.Assistant) and the flight boundaries (flight.FlightMonitor)."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from assist_policy.assistant import Assistant, AssistantConfig, rules_off
from assist_policy.stage import DepthFrame, StepContext
from assist_lab.evaluate import EvalArgs, evaluate
from assist_policy.flight import FlightConfig, FlightMonitor
from assist_policy.policy_core import InputRejected, PolicyCore, PolicyCoreConfig
from assist_policy.rules import GOAL_AGNOSTIC, RULES, switched
from assist_policy.testing import LATENT, constant_actor

pytestmark = pytest.mark.slow(seconds=50)

FLOOR_3M = np.full((64, 64), 3.0 - 0.05, np.float32)        # bare floor seen from 3 m


def ctx(t: float, u, position=(0.0, 0.0, 3.0), depth=None, mean_u=None) -> StepContext:
    """A step context at rest at `position` (frame: `depth` or none)."""
    frame = None if depth is None else DepthFrame(t, lambda: depth, lambda: (np.asarray(position, float), None))
    u = np.asarray(u, float)
    return StepContext(t, u, u if mean_u is None else np.asarray(mean_u, float), np.asarray(position, float),
                       np.zeros(3), None, frame, (1.0, 1.0, 0.6))


def test_chain_blends_then_clamps_and_says_why():
    chain = Assistant(rules_off())
    r = chain.step(ctx(0.0, [1.0, 0.0, 0.0]), np.array([1.0, 1.0, 0.0]))
    np.testing.assert_allclose(r.velocity, [1.0, 0.5, 0.0])          # (u + a) / 2, within 1.5 m/s
    assert r.key == 'assisting' and r.acted == ()
    r = chain.step(ctx(0.05, [0.5, 0.0, 0.0]), np.array([0.1, 0.0, 0.0]))
    np.testing.assert_allclose(r.velocity, [0.5, 0.0, 0.0])          # |a| <= 0.25: V = u
    assert r.key == 'small_action'
    chain.configure(max_speed_mps=0.4)                                # run-time limits reach the clamp
    r = chain.step(ctx(0.1, [1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(r.velocity, [0.4, 0.0, 0.0])
    with pytest.raises(ValueError):
        chain.configure(max_speed_mps=float('nan'))
    assert chain.cfg.max_speed_mps == 0.4                             # nothing changed


def test_chain_guard_protects_a_relinquished_pilot_and_the_actor_alike():
    chain = Assistant(AssistantConfig())
    low = (0.0, 0.0, 0.8)
    floor = np.full((64, 64), 0.8 - 0.05, np.float32)
    for agent, key in ((None, 'feature_stale'), (np.array([0.0, 0.0, -0.6]), '')):
        r = chain.step(ctx(0.0, [0.0, 0.0, -0.5], low, floor), agent, key, 'why')
        assert r.key == 'floor_guard' and r.velocity[2] > 0.0, r       # no descent over bare floor below 1 m
        assert r.acted == ('floor_guard',)
    # without a depth frame the guard cannot look: the descent passes, the input's reason stays
    r = chain.step(ctx(0.1, [0.0, 0.0, -0.5], low), None, 'feature_stale', 'latent stale')
    assert r.key == 'feature_stale' and r.velocity[2] == pytest.approx(-0.5)


def test_chain_order_the_override_wins_over_the_recall_and_the_recall_maps_anyway():
    chain = Assistant(AssistantConfig())
    pad = FLOOR_3M.copy()
    pad[22:42, 22:42] = 3.0 - 0.05 - 0.8                               # a 0.8 m pad right below
    t = 0.0
    for k in range(30):                                                # 1.5 s of a held key forward
        t = 0.05 * k
        r = chain.step(ctx(t, [1.0, 0.0, 0.0], depth=pad, mean_u=[1.0, 0.0, 0.0]), np.array([-0.9, 0.0, -0.5]))
    assert r.key == 'pilot_override' and 'pad_recall' not in r.acted
    assert len(chain.recall.map.pads) == 1                             # mapped although the override acted
    np.testing.assert_allclose(r.velocity[:2], [1.0, 0.0])             # the pilot's key passes
    assert chain.engaged['pilot_override'] > 0 and chain.modes['pilot_override:held_key'] > 0
    chain.reset()                                                      # a new flight forgets the map
    assert not chain.recall.map.pads


def test_flight_monitor_boundaries():
    m = FlightMonitor(FlightConfig())
    assert m.update(0.0, [0, 0, 3.0], [0.5, 0, 0], 0.0) is None
    assert m.update(0.05, [0.025, 0, 3.0], [0.5, 0, 0], 0.0) is None          # flying: moves as fast as it says
    assert m.update(0.10, [4.0, 2.0, 5.0], [0, 0, 0], 0.0) == 'odom_jump'     # teleported (sim reset, EKF reset)
    # a hover (command not descending) is not a landing, however long
    assert all(m.update(0.1 + 0.05 * k, [4.0, 2.0, 5.0], [0, 0, 0], 0.0) is None for k in range(1, 60))
    # coming down onto a surface (0.5 m/s from 5 m to 1 m) and at rest there while the command descends: landed
    # about rest_s after touchdown (a rest with no descent before it, like the hover above, is not)
    seen = [m.update(3.05 + 0.05 * k, [4.0, 2.0, max(5.0 - 0.025 * k, 1.0)], [0, 0, -0.5 if k < 160 else 0.0], -0.3)
            for k in range(200)]
    assert seen.count('landed') == 1 and 160 < seen.index('landed') <= 182 and m.landed
    # a 0.3 m lift is no take-off; a climb past flight_takeoff_climb_m (0.5 m) is
    assert all(m.update(13.05 + 0.05 * k, [4.0, 2.0, 1.0 + min(0.03 * k, 0.3)], [0, 0, 0.6], 0.6) is None
               for k in range(40))
    seen = [m.update(15.05 + 0.05 * k, [4.0, 2.0, 1.3 + 0.03 * k], [0, 0, 0.6], 0.6) for k in range(20)]
    assert seen.count('takeoff') == 1 and not m.landed
    # an autopilot starting on the ground (at rest low for a rest window): its first take-off is a boundary
    g = FlightMonitor()
    assert all(g.update(0.05 * k, [0, 0, 0.02], [0, 0, 0], 0.0) is None for k in range(25)) and g.landed
    climb = [g.update(1.25 + 0.05 * k, [0, 0, 0.02 + 0.03 * k], [0, 0, 0.6], 0.6) for k in range(30)]
    assert climb.count('takeoff') == 1
    off = FlightMonitor(FlightConfig(enabled=False))
    off.update(0.0, [0, 0, 3.0], [0, 0, 0], 0.0)
    assert off.update(0.05, [9.0, 0, 3.0], [0, 0, 0], 0.0) is None
    assert m.update(6.0, [np.nan, 0, 1.0], [0, 0, 0], 0.0) is None            # non-finite odometry: no judgement
    with pytest.raises(ValueError):
        FlightConfig(jump_m=0.0)


def test_policy_core_forgets_the_flight_at_an_odometry_jump_and_on_request(tmp_path):
    path = constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0])
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    pad = FLOOR_3M.copy()
    pad[22:42, 22:42] = 3.0 - 0.05 - 0.8
    for k in range(10):                                       # hovering over a pad: mapped, history filled
        t = 0.05 * k
        core.set_odom(t, [0, 0, 3.0], [0, 0, 0])
        core.set_depth(t, pad)
        core.set_latent(t, np.zeros(LATENT))
        core.set_pilot(t, [0.3, 0, 0])
        core.step(t)
    assert len(core.recall.map.pads) == 1 and len(core.builder.history) > 0
    core.set_odom(0.55, [6.0, 1.0, 3.0], [0, 0, 0])          # the next episode's start pose
    assert not core.recall.map.pads and len(core.builder.history) == 0
    assert core.flight_resets['odom_jump'] == 1 and core.last_reset == (0.55, 'odom_jump')
    # the last flight's camera is gone: its latest frame (taken over the pad) is not mapped from the new pose, and a
    # frame stamped before the jump that arrives after it is refused
    assert core._depth is None and core._feature is None
    with pytest.raises(InputRejected) as exc:
        core.set_depth(0.56, pad, stamp=0.5)
    assert exc.value.reason == 'depth_before_flight'
    assert core.step(0.55).key == 'feature_stale'              # no latent of this flight yet: relinquished
    core.set_depth(0.6, FLOOR_3M, stamp=0.6)
    core.set_latent(0.6, np.zeros(LATENT))
    core.step(0.6)
    assert not core.walls.near(np.array([6.0, 1.0]))[0].size and not core.recall.map.pads
    core.reset()
    assert core.flight_resets['service'] == 1 and len(core.builder.history) == 0


def _hand_chained_row(condition: str, pilot: str, rules: bool, seed: int, beta: float) -> dict:
    """One landing flown by driving the env step by step here, the assistant's rules configured by hand (the
    shipped actor; the CM-VAE for latent): the row evaluate should write for it."""
    import torch

    from assist_policy.actor import load_actor
    from assist_lab.env import EnvConfig, LandingAssistEnv
    from assist_perception.latent import make_latent_fn
    from assist_policy.policy_core import default_model_path
    actor, meta = load_actor(default_model_path(condition))
    cfg = EnvConfig(condition=condition, alpha=0.5, max_episode_s=60.0, max_speed=tuple(meta['max_speed']),
                    latent_dim=int(meta['latent_dim']), pilot_family=pilot,
                    **{r.field: switched(r, rules) for r in RULES},
                    feature_lags_s=tuple(meta['feature_lags_s']), memory_displacement=meta['memory_displacement'])
    env = LandingAssistEnv(cfg, latent_fn=make_latent_fn()[0]) if condition == 'latent' else LandingAssistEnv(cfg)
    try:
        obs, info = env.reset(seed=seed, options={'beta': beta})
        counts = dict.fromkeys(('active', 'guard', 'walls', 'override', 'recall', 'damper'), 0)
        steps = 0
        while True:
            with torch.no_grad():
                act = actor(torch.as_tensor(obs).unsqueeze(0))[0].numpy().astype(float)
            obs, _, term, trunc, step = env.step(act)
            steps += 1
            for key in counts:
                counts[key] += int(step[key])
            if term or trunc:
                break
        res = step['result']
    finally:
        env.close()
    share = {key: str(round(n / steps, 3)) for key, n in counts.items()}
    return {'pilot': info['pilot'], 'scene_seed': str(info['scene_seed']), 'goal_index': str(res['goal_index']),
            'aimed_index': str(info['aimed_index']), 'error_m': str(round(float(res['error_m']), 4)),
            'outcome': res['outcome'], 'duration_s': str(round(float(res['duration_s']), 2)),
            'active_fraction': share['active'], 'guard_fraction': share['guard'], 'wall_fraction': share['walls'],
            'override_fraction': share['override'], 'recall_fraction': share['recall'],
            'damper_fraction': share['damper']}


@pytest.mark.timeout(900)
def test_evaluate_rows_identical_to_the_hand_chained_env(tmp_path: Path):
    """evaluate's rows (its plan, seeds, pilot mix, rules as policy_node runs them, rounding) are the env driven step
    by step by hand on the same landings, both run here: held-out pilots with the override, recall and damper
    acting, and the bare end-to-end actor."""
    runs = {'mix': (EvalArgs(out=str(tmp_path / 'mix'), conditions=('latent',), betas=(0.0, 0.25), landings=1,
                             pilot='mix', plot=False), True),
            'paper': (EvalArgs(out=str(tmp_path / 'paper'), conditions=('end_to_end',), betas=(0.0,), landings=1,
                               pilot='paper', plot=False, safety=False, override=False, recall=False, damper=False),
                      False)}
    acted = dict.fromkeys(('override_fraction', 'recall_fraction', 'damper_fraction'), 0.0)
    for pilot, (args, rules) in runs.items():
        evaluate(args)
        rows = list(csv.DictReader(open(Path(args.out) / 'landings.csv', encoding='utf-8')))
        assert [(r['beta'], int(r['seed'])) for r in rows] == [(str(b), 2024 + 1000 * i) for i, b in
                                                               enumerate(args.betas)]
        for r in rows:
            hand = _hand_chained_row(args.conditions[0], pilot, rules, int(r['seed']), float(r['beta']))
            assert {k: r[k] for k in hand} == hand, (pilot, r['seed'])
            if rules:
                for key in acted:
                    acted[key] += float(r[key])
    assert all(v > 0 for v in acted.values()), acted        # the rules under test did act on these landings


def test_policy_node_loads_the_actor_without_the_training_code():
    import subprocess
    import sys
    code = ('import sys, assist_policy.policy_node; '
            'print(sorted(m for m in ("assist_lab.td3", "assist_lab.env", "assist_lab.train", "pybullet", '
            '"gymnasium") if m in sys.modules))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == '[]', out.stdout       # no replay buffer, no simulator on the deploy path


def test_policy_node_parameters_and_assist_yaml_come_from_the_config_dataclasses():
    import yaml

    from assist_policy import policy_node, settings
    derived = settings.parameters(PolicyCoreConfig)
    assert len(derived) >= 40 and set(derived) <= set(policy_node.PARAMS)
    cfg = PolicyCoreConfig()
    for name, f in derived.items():
        p = policy_node.PARAMS[name]
        assert (p.default, p.description, p.min, p.max, p.dynamic) == (f.default, f.spec.description, f.spec.min,
                                                                       f.spec.max, f.spec.dynamic), name
        obj = cfg
        for part in f.path[:-1]:
            obj = getattr(obj, part) or dataclasses_default(type(cfg), part)
        assert getattr(obj, f.path[-1]) == f.default, name        # the dataclass default is the parameter's
    yml = yaml.safe_load(open(Path(policy_node.__file__).parents[1] / 'config' / 'assist.yaml', encoding='utf-8'))
    shipped = yml['policy_node']['ros__parameters']
    assert set(shipped) <= set(policy_node.PARAMS), set(shipped) - set(policy_node.PARAMS)
    # every parameter but the per-mode switches (their default depends on the mode) is in the file, at its default
    missing = set(policy_node.PARAMS) - set(shipped) - {r.switch for r in GOAL_AGNOSTIC}
    assert not missing, missing
    assert {k: v for k, v in shipped.items() if v != policy_node.PARAMS[k].default} == {}
    # a run-time set reaches the live settings through the same table
    changes = settings.changes_for(derived, {'floor_guard_wall_radius_m': 0, 'max_speed': 1, 'flight_rest_s': 2})
    assert changes == {('safety',): {'wall_radius_m': 0.0}, (): {'max_speed_mps': 1.0}, ('flight',): {'rest_s': 2.0}}


def dataclasses_default(cls, name):
    """The default instance of a nested config field left None."""
    import dataclasses
    from assist_policy.settings import NESTED_KEY
    return next(f.metadata[NESTED_KEY] for f in dataclasses.fields(cls) if f.name == name)()


@pytest.mark.parametrize('value', [1e-300, 0.0, 0.05, -1.0, float('nan')])
def test_speed_limits_that_would_silently_stop_every_motion_are_refused(value, tmp_path):
    from assist_policy import policy_node
    for name in ('max_speed_mps', 'max_vertical_mps'):
        with pytest.raises(ValueError):
            PolicyCoreConfig(**{name: value})
    for param in ('max_speed', 'max_vertical_speed'):
        with pytest.raises(ValueError):
            policy_node.PARAMS[param].coerce(param, value)
    core = PolicyCore(constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]), PolicyCoreConfig())
    with pytest.raises(ValueError):
        core.configure(max_speed_mps=value)
    assert core.assistant.cfg.max_speed_mps == 1.5            # nothing changed
