"""Pilot override (assist_policy.override): the rule, and where it acts (env, evaluate, policy core)."""
import csv

import numpy as np
import pytest

import assist_lab.evaluate as evaluate_module
from assist_policy.blending import blend
from assist_lab.env import EnvConfig, LandingAssistEnv
from assist_lab.evaluate import EvalArgs, evaluate, make_policy
from assist_policy.flight import FlightConfig
from assist_policy.override import OverrideConfig, PilotOverride
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_lab.train import TrainArgs, env_config_from
from assist_policy.testing import LATENT, constant_actor

MS = (1.0, 1.0, 0.6)
THR = 0.25
CFG = OverrideConfig()


def apply(u, mean_u, altitude, cfg=None, now=1.0):
    """One decision of a fresh PilotOverride."""
    return PilotOverride(cfg).apply(now, np.asarray(u, float), np.asarray(mean_u, float), altitude, MS)


def test_a_held_key_passes_low_with_a_gentle_climb():
    u = np.array([1.0, 0.0, 0.0])
    a = apply(u, [0.9, 0.0, 0.0], 1.2)
    np.testing.assert_allclose(a, [1.0, 0.0, 0.6])
    np.testing.assert_allclose(blend(u, a, THR), [1.0, 0.0, 0.3])        # V: the pilot's key, rising 0.3 m/s
    # a diagonal held key over the window, the key up at this instant (tapping): V still rises
    a = apply(np.zeros(3), [0.6, 0.6, 0.0], 0.9)
    np.testing.assert_allclose(blend(np.zeros(3), a, THR), [0.0, 0.0, 0.3])
    # a pilot climbing faster than the climb keeps its own climb; a bang-bang key faster than max_speed is clipped
    u = np.array([1.5, 0.0, 0.5])
    a = apply(u, [1.5, 0.0, 0.5], 1.0)
    np.testing.assert_allclose(a, [1.0, 0.0, 0.5])
    assert blend(u, a, THR)[2] == pytest.approx(0.5)


def test_high_up_it_relinquishes_and_it_never_acts_on_taps_descents_or_when_off():
    u = np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(apply(u, [1.0, 0.0, 0.0], 2.5), np.zeros(3))
    assert apply(u, [0.5, 0.5, 0.0], 1.0) is None                      # 0.71 m/s: fine taps
    assert apply([1.0, 0.0, -0.5], [1.0, 0.0, -0.5], 1.0) is None      # descending: not a departure
    assert apply(u, u, 1.0, OverrideConfig(enabled=False)) is None
    assert apply(u, [np.nan, 0.0, 0.0], 1.0) is None                  # nothing to judge by
    with pytest.raises(ValueError, match='speed_mps'):
        OverrideConfig(speed_mps=-1.0)
    with pytest.raises(ValueError, match='reversal_s'):
        OverrideConfig(reversal_s=float('nan'))


def test_a_held_key_reversing_a_recent_one_is_an_overshoot_not_a_departure():
    ov = PilotOverride()
    fwd, back, left = np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    assert ov.apply(10.0, fwd, fwd, 1.0, MS) is not None           # held forward: passes
    assert ov.apply(12.0, back, back, 1.0, MS) is None             # 2 s later held back: an overshoot, helped
    assert ov.apply(12.05, left, left, 1.0, MS) is not None        # sideways reverses nothing
    assert ov.apply(12.1, back, back, 1.0, MS) is None             # still within 3 s of the forward key
    assert ov.apply(15.2, back, back, 1.0, MS) is not None         # the forward key is 5 s old: a departure
    ov.reset()
    assert ov.apply(15.3, fwd, fwd, 1.0, MS) is not None           # reset: nothing remembered
    ov = PilotOverride()
    ov.apply(20.0, fwd, fwd, 1.0, MS)
    assert ov.apply(5.0, back, back, 1.0, MS) is not None          # the clock went back: old keys forgotten


def test_env_replaces_the_actors_action_while_the_pilot_holds_a_key():
    env = LandingAssistEnv(EnvConfig(condition='oracle', override=OverrideConfig()))
    env.reset(seed=2)
    x = float(env.world.pad_top_centers[:, 0].min()) - 2.0
    env.world.reset(seed=env.world.scene.seed, scene=env.world.scene, start_position=[x, 0.0, 1.0])
    push_down = np.array([0.0, -1.0, -1.0])               # an actor pulling sideways and pushing down
    for _ in range(20):                                   # 1 s of hovering fills the 1 s window
        env._u = np.zeros(3)
        assert not env.step(np.zeros(3))[4]['override']
    seen = []
    for _ in range(30):                                   # then 1.5 s of a held forward key
        env._u = np.array([1.0, 0.0, 0.0])
        _, _, term, _, info = env.step(push_down)
        seen.append(info['override'])
        assert not term
    assert not any(seen[:12]) and all(seen[20:])          # engages once the 1 s mean passes 0.75 m/s
    assert env.world.state.velocity[2] > 0.1 and env.world.state.velocity[0] > 0.7   # rising, moving on
    _, a_mean = env.builder.history.means(env.elapsed_s)
    assert a_mean[2] > 0.3                                 # the history holds the applied (override) action
    env.close()


def test_evaluate_override_rows_and_column(tmp_path):
    actor = constant_actor(tmp_path / 'down.pt', [0.0, 0.0, -0.9], condition='oracle', latent_dim=0)
    args = EvalArgs(out=str(tmp_path / 'ev'), conditions=('oracle', 'scripted_nearest_pad'), betas=(0.5,),
                    landings=1, pilot='late_correction', safety=True, override=True, recall=False, damper=False,
                    oracle_model=str(actor),
                    plot=False, max_episode_s=20.0)
    summary = evaluate(args)
    assert set(summary) == {'oracle+guard+override', 'scripted_nearest_pad+guard'}   # scripts stay as defined
    rows = {r['condition']: r for r in csv.DictReader(open(tmp_path / 'ev' / 'landings.csv'))}
    assert float(rows['oracle+guard+override']['override_fraction']) > 0.0      # the pilot's transit keys
    assert float(rows['scripted_nearest_pad+guard']['override_fraction']) == 0.0


def test_policy_core_override_engages_reports_and_turns_off(tmp_path):
    path = constant_actor(tmp_path / 'a.pt', [0.0, -0.9, -0.9])
    # synthetic odometry: the vehicle stays put under a descending command (the flight monitor would call it landed)
    core = PolicyCore(path, PolicyCoreConfig(mode='latent', flight=FlightConfig(enabled=False)))
    outs = []
    for k in range(50):                                   # 1 s hovering, then 1.5 s of a held key, 20 Hz, at 1.2 m
        t = 1.0 + 0.05 * k
        core.set_odom(t, [0, 0, 1.2], [0, 0, 0])
        core.set_pilot(t, [1.0, 0.0, 0.0] if k >= 20 else [0.0, 0.0, 0.0])
        core.set_latent(t, np.zeros(LATENT))
        outs.append(core.step(t))
    assert all(o.key == 'assisting' for o in outs[:32]) and outs[-1].key == 'pilot_override'
    np.testing.assert_allclose(outs[-1].velocity, [1.0, 0.0, 0.3])
    np.testing.assert_allclose(outs[-1].agent, [1.0, 0.0, 0.6])      # what /assist/agent_cmd shows
    assert core.engaged['pilot_override'] == sum(o.key == 'pilot_override' for o in outs) >= 10
    core.override.cfg = OverrideConfig(enabled=False)
    core.set_odom(3.0, [0, 0, 1.2], [0, 0, 0])
    core.set_pilot(3.0, [1.0, 0.0, 0.0])
    core.set_latent(3.0, np.zeros(LATENT))
    out = core.step(3.0)
    assert out.key == 'assisting' and out.velocity[2] < 0              # the actor's descent again


def test_train_td3_flies_with_the_override_only_when_asked():
    assert env_config_from(TrainArgs(pilot='train_mix')).override == OverrideConfig(enabled=False)
    cfg = env_config_from(TrainArgs(pilot='train_mix', override=True))
    assert cfg.override == OverrideConfig()
    assert LandingAssistEnv(cfg).assistant.override.cfg.enabled


def push(ov, t0, seconds, u, v, altitude=3.0, over_floor=None, dt=0.05, pos=None):
    """Feed `seconds` of the pilot command `u` while the vehicle moves at `v` (at odom `pos`); the decisions."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    return [ov.apply(t0 + k * dt, u, u, altitude, MS, v, lambda: (over_floor, None), pos)
            for k in range(int(round(seconds / dt)) + 1)]


def test_a_persistent_push_held_back_passes_even_while_descending():
    ov = PilotOverride()
    glide = [0.7, 0.0, -0.3]                              # an analog stick: 0.7 m/s on, descending, held still
    out = push(ov, 10.0, 2.5, glide, [0.0, 0.0, -0.3])
    assert all(a is None for a in out[:40])               # under 2 s: the actor's action stands
    assert all(a is not None for a in out[41:]) and ov.mode == 'persistent'
    np.testing.assert_allclose(out[-1], np.zeros(3))      # 3 m up: relinquish, V = u
    low = push(PilotOverride(), 10.0, 2.0, glide, [0.0, 0.0, 0.0], altitude=1.2)[-1]
    np.testing.assert_allclose(low, [0.7, 0.0, 0.6])     # low: the held key's yield (a_z 0.9 clipped to 0.6)
    np.testing.assert_allclose(blend(np.array(glide), low, THR), [0.7, 0.0, 0.15])   # passes, rising
    # a held key while descending is no departure (bang-bang overshoot) until it has lasted persist_s
    assert PilotOverride().apply(1.0, np.array([1.0, 0, -0.5]), np.array([1.0, 0, -0.5]), 1.0, MS,
                                 np.zeros(3)) is None


def test_a_push_is_not_persistent_when_the_vehicle_goes_along_it_is_slow_or_it_reverses():
    assert push(PilotOverride(), 0.0, 3.0, [0.7, 0, -0.3], [0.4, 0, -0.3])[-1] is None   # moving at > half of it
    assert push(PilotOverride(), 0.0, 3.0, [0.55, 0, -0.3], [0.0, 0, 0])[-1] is None     # fine positioning speed
    ov = PilotOverride()                                   # taps around the aim: samples against the mean
    for k in range(61):
        u = np.array([1.0 if k % 8 < 6 else -0.3, 0.0, -0.3])
        a = ov.apply(k * 0.05, u, u, 3.0, MS, np.zeros(3))
    assert a is None and ov.mode is None
    ov = PilotOverride()                                   # a held key the other way 2 s before: an overshoot
    push(ov, 0.0, 0.5, [-1.0, 0, 0], [-1.0, 0, 0])
    assert push(ov, 0.55, 2.5, [0.8, 0, -0.3], [0.0, 0, 0])[-1] is None
    assert push(ov, 3.1, 0.5, [0.8, 0, -0.3], [0.0, 0, 0])[-1] is not None   # the old key is > 3 s away
    assert push(PilotOverride(OverrideConfig(persist_s=0.0)), 0.0, 3.0, [1.0, 0, -0.3], [0, 0, 0])[-1] is None
    assert push(PilotOverride(OverrideConfig(enabled=False)), 0.0, 3.0, [1.0, 0, -0.3], [0, 0, 0])[-1] is None
    ov = PilotOverride()                                   # no velocity for a step: the push is timed afresh
    push(ov, 0.0, 1.5, [0.7, 0, -0.3], [0, 0, 0])
    assert ov.apply(1.55, np.array([0.7, 0, -0.3]), np.array([0.7, 0, -0.3]), 3.0, MS, None) is None
    assert push(ov, 1.6, 1.5, [0.7, 0, -0.3], [0, 0, 0])[-1] is None
    with pytest.raises(ValueError, match='^OverrideConfig.persist_floor_speed_mps must be >= 0.01, got 0.0$'):
        OverrideConfig(persist_floor_speed_mps=0.0)      # a pilot pressing nothing would engage it


def test_no_persistent_push_in_the_last_metre_over_what_is_below():
    glide = [0.8, 0.0, -0.3]
    assert push(PilotOverride(), 0.0, 3.0, glide, [0, 0, -0.3], altitude=0.9)[-1] is None        # 0.9 m up
    ov = PilotOverride()
    out = [ov.apply(k * 0.05, np.array(glide), np.array(glide), 2.5, MS, np.zeros(3), lambda: (False, 0.7))
           for k in range(61)]
    assert out[-1] is None                                 # 2.5 m up, but 0.7 m over a pad top: positioning
    out = [ov.apply(3.05 + k * 0.05, np.array(glide), np.array(glide), 2.5, MS, np.zeros(3), lambda: (False, 1.4))
           for k in range(41)]
    assert out[-1] is not None and ov.mode == 'persistent'   # 1.4 m over it
    unknown = ov.apply(5.2, np.array(glide), np.array(glide), 1.4, MS, np.zeros(3), lambda: (False, float('nan')))
    assert unknown is not None                             # height unknown: the 1.4 m altitude stands in

    def never():
        raise AssertionError('the depth image was read for a push that cannot engage')
    ov = PilotOverride()
    slow = [ov.apply(k * 0.05, np.array([0.3, 0, 0]), np.array([0.3, 0, 0]), 2.5, MS, np.zeros(3), never)
            for k in range(61)]
    assert slow[-1] is None                                # under every speed threshold: the surface is not read


def test_over_bare_floor_a_slower_push_passes():
    taps = [0.45, 0.0, -0.5]                               # a novice's tapped transit while getting lower
    assert push(PilotOverride(), 0.0, 2.5, taps, [-0.1, 0, -0.5], over_floor=True)[-1] is not None
    assert push(PilotOverride(), 0.0, 2.5, taps, [-0.1, 0, -0.5], over_floor=False)[-1] is None   # over a pad
    assert push(PilotOverride(), 0.0, 2.5, taps, [-0.1, 0, -0.5], over_floor=None)[-1] is None    # unknown


def test_policy_core_passes_a_persistent_push_and_says_so(tmp_path):
    path = constant_actor(tmp_path / 'back.pt', [-0.9, 0.0, 0.0])   # an actor holding the pilot back
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    outs = []
    for k in range(60):                                    # 3 s of a 0.7 m/s push while descending, 3 m up
        t = 1.0 + 0.05 * k
        core.set_odom(t, [0, 0, 3.0], [0, 0, -0.3])
        core.set_pilot(t, [0.7, 0.0, -0.3])
        core.set_latent(t, np.zeros(LATENT))
        outs.append(core.step(t))
    assert all(o.key == 'assisting' for o in outs[:40])
    assert outs[-1].key == 'pilot_override' and 'persistent push' in outs[-1].reason
    np.testing.assert_allclose(outs[-1].velocity, [0.7, 0.0, -0.3])   # relinquished up there: V = u
    assert (core.assistant.modes['pilot_override:persistent'] == core.engaged['pilot_override']
            == sum(o.key == 'pilot_override' for o in outs) >= 15)


def test_a_held_climb_the_vehicle_does_not_make_passes_until_the_pilot_stops_climbing():
    ov = PilotOverride()
    up = [0.5, 0.0, 0.5]                                  # low over a pad: on and up; the actor pushes it down
    out = push(ov, 0.0, 2.5, up, [0.0, 0.0, -0.05], altitude=1.7)
    assert all(a is None for a in out[:40])               # under 2 s: the actor's action stands
    assert all(a is not None for a in out[41:]) and ov.mode == 'climb'
    np.testing.assert_allclose(out[-1], [0.5, 0.0, 0.5])  # the held key's yield low: V = u (the pilot's climb)
    # it holds while the climb goes on, though the vehicle now rises (no re-timing against the actor)
    assert all(a is not None for a in push(ov, 2.55, 2.0, up, [0.0, 0.0, 0.5], altitude=1.9))
    assert push(ov, 4.6, 0.0, [0.5, 0.0, 0.0], [0.0, 0.0, 0.5], altitude=2.1)[-1] is None   # stopped climbing
    assert ov.mode is None
    # not: a climb the vehicle makes, one under persist_climb_mps, one interrupted by a descent, off
    assert push(PilotOverride(), 0.0, 3.0, up, [0.0, 0.0, 0.3], altitude=1.7)[-1] is None
    assert push(PilotOverride(), 0.0, 3.0, [0, 0, 0.2], [0.0, 0.0, -0.1], altitude=1.7)[-1] is None
    ov = PilotOverride()
    push(ov, 0.0, 1.0, up, [0.0, 0.0, -0.05], altitude=1.7)
    push(ov, 1.05, 0.0, [0.5, 0.0, -0.5], [0.0, 0.0, -0.05], altitude=1.7)
    assert push(ov, 1.1, 1.5, up, [0.0, 0.0, -0.05], altitude=1.7)[-1] is None
    for cfg in (OverrideConfig(persist_climb_mps=0.0), OverrideConfig(persist_s=0.0), OverrideConfig(enabled=False)):
        assert push(PilotOverride(cfg), 0.0, 3.0, up, [0.0, 0.0, -0.05], altitude=1.7)[-1] is None


def taps(ov, t0, seconds, key, v, uz=0.0, height=0.7, dt=0.05, period=2.0, pos=None):
    """A novice tapping `key` (duty 0.5, `period` s) while the vehicle moves at `v` (at odom `pos`); the decisions
    (mean_u: 1 s)."""
    out = []
    for k in range(int(round(seconds / dt)) + 1):
        t = t0 + k * dt
        on = (t % period) < period / 2
        u = np.array([*(np.asarray(key, float) * on), uz])
        out.append(ov.apply(t, u, np.array([*(0.5 * np.asarray(key, float)), uz]), 1.8, MS,
                            np.asarray(v, float), lambda: (False, height), pos))
    return out


def test_a_long_slow_push_with_no_descent_lets_a_low_flyer_on_and_holds_until_it_descends():
    ov = PilotOverride()
    # low_flyer beta 0: cruising 0.7 m over a pad's top, tapping on (0.5 m/s mean) while the actor holds it there
    out = taps(ov, 0.0, 6.0, [1.0, 0.0], [0.0, 0.0, 0.0])
    assert all(a is None for a in out[:100])                   # under long_push_s (and too slow for persist)
    assert all(a is not None for a in out[100:]) and ov.mode == 'long'
    np.testing.assert_allclose(out[101], [0.0, 0.0, 0.6])       # key up, low: V = (0, 0, 0.3), a gentle climb
    np.testing.assert_allclose(out[-1], [1.0, 0.0, 0.6])        # key down: V = (1, 0, 0.3), the pilot's key
    # latched: it holds while the pilot taps on, though the vehicle now goes along
    out = taps(ov, 6.05, 4.0, [1.0, 0.0], [0.5, 0.0, 0.3])
    assert all(a is not None for a in out) and ov.mode == 'long'
    # a descent tapped on the way is the actor's that step; a held descent (over its aim) releases it
    out = taps(ov, 10.1, 5.0, [1.0, 0.0], [0.5, 0.0, 0.0], uz=-0.5)
    assert all(a is None for a in out)
    out = taps(ov, 15.15, 1.0, [1.0, 0.0], [0.0, 0.0, 0.0])
    assert all(a is None for a in out)                          # released: timed afresh, the descent in the window


def test_no_long_push_when_descending_going_along_reversing_touching_down_or_off():
    key, held = [1.0, 0.0], [0.0, 0.0, 0.0]
    assert taps(PilotOverride(), 0.0, 6.0, key, held, uz=-0.5)[-1] is None          # landing, not flying on
    assert taps(PilotOverride(), 0.0, 6.0, key, [0.3, 0.0, 0.0])[-1] is None        # the vehicle goes along
    assert taps(PilotOverride(), 0.0, 6.0, key, held, height=0.2)[-1] is None       # 0.2 m over the top
    assert taps(PilotOverride(), 0.0, 6.0, [0.5, 0.0], held)[-1] is None            # 0.25 m/s: too slow
    ov = PilotOverride()
    out = []
    for k in range(121):
        t = k * 0.05
        u = np.array([1.0 if (t % 2.0) < 1.0 else -0.2, 0.0, 0.0])
        out.append(ov.apply(t, u, np.array([0.4, 0.0, 0.0]), 1.8, MS, np.zeros(3), lambda: (False, 0.7)))
    assert all(a is None for a in out)                          # a sample against the mean: not one way
    for cfg in (OverrideConfig(long_push_s=0.0), OverrideConfig(enabled=False)):
        assert taps(PilotOverride(cfg), 0.0, 6.0, key, held)[-1] is None
    with pytest.raises(ValueError, match='long_push_speed_mps'):
        OverrideConfig(long_push_speed_mps=0.0)


def tried_to_land(ov, t0, spot, seconds=1.0):
    """The pilot descends for `seconds` at odom `spot`, not going anywhere (an ignorer over its own aim)."""
    u = np.array([0.0, 0.0, -0.5])
    for k in range(int(round(seconds / 0.05)) + 1):
        ov.apply(t0 + 0.05 * k, u, u, 1.8, MS, np.zeros(3), lambda: (False, 0.7), np.array([*spot, 1.8]))


def test_pushes_and_climbs_back_to_where_the_pilot_tried_to_land_stay_with_the_actor():
    here, held = np.array([0.0, 0.0, 1.8]), [0.0, 0.0, 0.0]
    # an ignorer tried to land 0.6 m ahead (its aim, off the pad), the actor took it back over the pad: its
    # long push back there is positioning, not flying on
    ov = PilotOverride()
    tried_to_land(ov, 0.0, (0.6, 0.0))
    assert all(a is None for a in taps(ov, 1.05, 7.0, [1.0, 0.0], held, pos=here))
    # pushed away from the spot (a pilot leaving the pad it tried), it passes as before
    ov = PilotOverride()
    tried_to_land(ov, 0.0, (0.6, 0.0))
    out = taps(ov, 1.05, 7.0, [-1.0, 0.0], held, pos=here)
    assert out[-1] is not None and ov.mode == 'long'
    # not when the spot is farther than spot_radius_m, forgotten after spot_memory_s, or with the test off
    for cfg, spot, t1 in ((CFG, (1.5, 0.0), 1.05), (CFG, (0.6, 0.0), 21.05),
                          (OverrideConfig(spot_memory_s=0.0), (0.6, 0.0), 1.05)):
        ov = PilotOverride(cfg)
        tried_to_land(ov, 0.0, spot)
        assert taps(ov, t1, 7.0, [1.0, 0.0], held, pos=here)[-1] is not None and ov.mode == 'long'
    # a descent while going somewhere (a glide path, 0.7 m/s on) marks no spot
    ov = PilotOverride()
    push(ov, 0.0, 1.0, [0.7, 0.0, -0.3], [0.7, 0.0, -0.3], pos=np.array([0.6, 0.0, 3.0]))
    assert taps(ov, 1.05, 7.0, [1.0, 0.0], held, pos=here)[-1] is not None
    # the persistent push back to the spot, and a held climb off it, stay with the actor too
    ov = PilotOverride()
    tried_to_land(ov, 0.0, (0.6, 0.0))
    assert push(ov, 1.05, 3.0, [0.8, 0.0, -0.3], [0.0, 0.0, 0.0], pos=here)[-1] is None
    assert push(ov, 4.1, 3.0, [0.0, 0.0, 0.5], [0.0, 0.0, -0.05], altitude=1.7, pos=here)[-1] is None
    ov = PilotOverride()
    tried_to_land(ov, 0.0, (2.0, 0.0))                     # a spot 2 m away: the climb passes
    assert push(ov, 1.05, 3.0, [0.0, 0.0, 0.5], [0.0, 0.0, -0.05], altitude=1.7, pos=here)[-1] is not None
    assert ov.mode == 'climb'
    # no position (a caller without odometry): no spot is remembered, the rules act as before
    ov = PilotOverride()
    tried_to_land(ov, 0.0, (np.nan, 0.0))
    assert taps(ov, 1.05, 7.0, [1.0, 0.0], held, pos=here)[-1] is not None
    with pytest.raises(ValueError, match='spot_radius_m'):
        OverrideConfig(spot_radius_m=-1.0)


def test_policy_core_passes_a_held_climb_and_says_so(tmp_path):
    path = constant_actor(tmp_path / 'down.pt', [0.0, 0.0, -0.99])   # an actor landing it where it is
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    for k in range(60):                                    # 3 s of climb asked, 1.5 m up, the vehicle sinking
        t = 1.0 + 0.05 * k
        core.set_odom(t, [0, 0, 1.5], [0, 0, -0.05])
        core.set_pilot(t, [0.0, 0.0, 0.5])
        core.set_latent(t, np.zeros(LATENT))
        out = core.step(t)
    assert out.key == 'pilot_override' and 'held climb' in out.reason
    assert out.velocity[2] == pytest.approx(0.5)           # the pilot's climb
    assert (core.assistant.modes['pilot_override:climb'] == core.engaged['pilot_override'] >= 15
            and core.assistant.modes['pilot_override:persistent'] == 0)


def test_policy_core_passes_a_long_push_and_says_so(tmp_path):
    path = constant_actor(tmp_path / 'back.pt', [-0.9, 0.0, 0.0])   # an actor holding the pilot back
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    outs = []
    for k in range(140):                                   # 7 s of novice taps (0.2 s on, 0.2 off), 1.8 m up, held
        t = 1.0 + 0.05 * k
        core.set_odom(t, [0, 0, 1.8], [0, 0, 0])
        core.set_pilot(t, [1.0 if (0.05 * k) % 0.4 >= 0.2 else 0.0, 0.0, 0.0])
        core.set_latent(t, np.zeros(LATENT))
        outs.append(core.step(t))
    assert all(o.key == 'assisting' for o in outs[:95])   # under 5 s
    assert outs[-1].key == 'pilot_override' and 'long push' in outs[-1].reason
    assert outs[-1].velocity[0] >= 0.0 and outs[-1].velocity[2] == pytest.approx(0.3)   # on, rising gently
    assert (core.assistant.modes['pilot_override:long'] == core.engaged['pilot_override'] >= 30
            and core.assistant.modes['pilot_override:persistent'] == 0)


def test_policy_core_keeps_a_push_back_to_where_the_pilot_tried_to_land_with_the_actor(tmp_path):
    path = constant_actor(tmp_path / 'back.pt', [-0.9, 0.0, 0.0])   # an actor holding the pilot back
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    outs = []
    for k in range(160):      # 1 s descending 0.6 m ahead (odometry), then 7 s of taps back toward it, held
        t = 1.0 + 0.05 * k
        descending = k < 20
        core.set_odom(t, [0.6 if descending else 0.0, 0, 1.8], [0, 0, 0])
        core.set_pilot(t, [0.0, 0.0, -0.5] if descending else [1.0 if (0.05 * k) % 0.4 >= 0.2 else 0.0, 0.0, 0.0])
        core.set_latent(t, np.zeros(LATENT))
        outs.append(core.step(t))
    assert all(o.key == 'assisting' for o in outs[20:])   # no long push back to the spot (positioning)
    assert (core.engaged['pilot_override'] == core.assistant.modes['pilot_override:long'] == 0
            and core.assistant.modes['pilot_override:spot_kept'] >= 30)


@pytest.mark.parametrize('surface, engages', [('floor', True), ('pad', False)])
def test_policy_core_reads_bare_floor_from_the_depth_image(tmp_path, surface, engages):
    from assist_policy.safety import SafetyConfig
    path = constant_actor(tmp_path / 'back.pt', [-0.9, 0.0, 0.0])
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    depth = np.full((64, 64), 3.0 - SafetyConfig().camera_offset_m - (0.0 if surface == 'floor' else 1.0))
    for k in range(60):                                    # 3 s of a 0.45 m/s push (novice taps), 3 m up
        t = 1.0 + 0.05 * k
        core.set_odom(t, [0, 0, 3.0], [0, 0, -0.3])
        core.set_pilot(t, [0.45, 0.0, -0.3])
        core.set_latent(t, np.zeros(LATENT))
        core.set_depth(t, depth)
        out = core.step(t)
    assert ((out.key == 'pilot_override') is engages
            and (core.assistant.modes['pilot_override:persistent'] > 0) is engages)


def test_evaluate_a_glide_pilot_passes_the_nearer_pad_with_the_persistent_push(tmp_path, monkeypatch):
    """glide beta 1, landing 4007: held over pad 3 and landed there without the push rule; with it, the goal."""
    runs = {}
    for persist in (0.0, OverrideConfig.persist_s):
        def with_persist(*args, rules, persist=persist, **kw):
            return make_policy(*args, rules={**rules, 'override': OverrideConfig(persist_s=persist)}, **kw)
        monkeypatch.setattr(evaluate_module, 'make_policy', with_persist)
        out = tmp_path / f'ev{persist}'
        evaluate(EvalArgs(out=str(out), conditions=('latent',), betas=(1.0,), landings=1, seed=4007, pilot='glide',
                          safety=True, override=True, recall=True, damper=True, plot=False))
        runs[persist] = list(csv.DictReader(open(out / 'landings.csv')))[0]
    off, on = runs[0.0], runs[OverrideConfig.persist_s]
    assert off['outcome'] == 'wrong_pad' and off['landed_index'] == '3' and off['goal_index'] == '4'
    assert on['outcome'] == 'success' and float(on['error_m']) < 0.15
    assert float(on['override_fraction']) > float(off['override_fraction'])
