"""LandingRunnerCore: the GUIDED -> arm -> takeoff -> landing -> LAND sequence, driven by hand."""
import pytest

from assist_bridge.landing_runner_core import LandingRunnerCore, RunnerConfig, RunnerState


def sequencing(**kw) -> RunnerConfig:
    """The runner's settings for the sequencing tests: arming does not wait for /odom (tested on its own)."""
    return RunnerConfig(**{'settle_s': 0.0, **kw})


def answer(core, now, ok=True, msg='ACCEPTED'):
    """Poll once and answer the requested call; returns its name."""
    name = core.poll(now)
    assert name is not None, f'no call requested in state {core.state}'
    core.on_answer(name, ok, msg, now)
    return name


def landing(ep, success=True, crash=False, error=0.1):
    return {'episode': ep, 'success': success, 'crash': crash, 'error_m': error,
            'outcome': 'success' if success else 'crash', 'reason': 'landed'}


def test_two_episodes_with_arm_retries_then_done():
    core = LandingRunnerCore(sequencing(episodes=2, arm_retry_s=5.0))
    assert core.poll(0.0) is None                        # no goal yet: nothing to do
    core.on_goal(('g', 1), 0.0)
    assert answer(core, 0.0) == 'guided'
    assert answer(core, 0.1, ok=False, msg='arm: FAILED (PreArm: Need Position Estimate)') == 'arm'
    assert core.poll(1.0) is None                        # waits arm_retry_s before trying again
    assert core.state == RunnerState.ARMING
    assert answer(core, 5.2) == 'guided'
    assert answer(core, 5.3) == 'arm'
    assert core.state == RunnerState.TAKING_OFF
    assert answer(core, 5.4) == 'takeoff'
    assert core.state == RunnerState.FLYING
    assert core.poll(30.0) is None                       # the pilot flies
    core.on_goal(('g', 1), 31.0)                         # the latched goal again: not a new episode
    core.on_landing(landing(0), 40.0)
    assert answer(core, 40.0) == 'land'
    assert core.state == RunnerState.WAIT_EPISODE
    assert core.poll(41.0) is None                       # no new goal yet
    core.on_goal(('g', 2), 45.0)
    assert [answer(core, 45.0 + i) for i in range(3)] == ['guided', 'arm', 'takeoff']
    core.on_landing(landing(1, success=False, crash=True, error=1.5), 70.0)
    assert core.state == RunnerState.DONE and not core.finished
    assert answer(core, 70.0) == 'land'
    assert core.finished
    assert core.stats.summary() == ('2 landings: success 1/2 (50.0 %), crash 1/2 (50.0 %), '
                                    'mean error 0.800 m')


def test_takeoff_refused_goes_back_to_arming():
    core = LandingRunnerCore(sequencing(episodes=1, arm_retry_s=2.0))
    core.on_goal('a', 0.0)
    answer(core, 0.0), answer(core, 0.0)
    assert answer(core, 0.0, ok=False, msg='takeoff: FAILED') == 'takeoff'
    assert core.state == RunnerState.ARMING
    assert core.poll(1.0) is None
    assert answer(core, 2.5) == 'guided'


def test_gives_up_when_the_autopilot_never_arms():
    core = LandingRunnerCore(sequencing(episodes=0, arm_retry_s=1.0, arm_give_up_s=10.0))
    core.on_goal('a', 0.0)
    t = 0.0
    while core.state != RunnerState.FAILED and t < 30.0:
        name = core.poll(t)
        if name is not None:
            core.on_answer(name, name == 'guided', 'FAILED', t)
        t += 0.1
    assert core.state == RunnerState.FAILED
    assert 10.0 < t < 11.5
    assert 'did not arm' in core.failure
    assert core.poll(t + 1) is None


def test_flight_timeout_requests_land_once():
    core = LandingRunnerCore(sequencing(flight_timeout_s=60.0))
    core.on_goal('a', 0.0)
    for _ in range(3):
        answer(core, 0.0)
    assert core.state == RunnerState.FLYING
    assert core.poll(59.0) is None
    assert answer(core, 61.0) == 'land'
    assert core.poll(200.0) is None                      # asked once; the judge's result ends the episode
    core.on_landing(landing(0), 210.0)
    assert answer(core, 210.0) == 'land'
    assert core.state == RunnerState.WAIT_EPISODE       # episodes=0: runs until stopped


def test_one_call_at_a_time_and_stray_answers_ignored():
    core = LandingRunnerCore(sequencing())
    core.on_goal('a', 0.0)
    assert core.poll(0.0) == 'guided'
    assert core.poll(0.0) is None                        # guided still in flight
    core.on_answer('arm', True, 'x', 0.0)                # not the call in flight: ignored
    assert core.state == RunnerState.ARMING
    core.on_answer('guided', True, 'ok', 0.1)
    assert core.poll(0.1) == 'arm'


def test_no_land_after_touchdown_when_disabled():
    core = LandingRunnerCore(sequencing(land_after_touchdown=False))
    core.on_goal('a', 0.0)
    for _ in range(3):
        answer(core, 0.0)
    core.on_landing(landing(0), 5.0)
    assert core.poll(5.0) is None


@pytest.mark.parametrize('kwargs', [{'episodes': -1}, {'arm_retry_s': 0.0}, {'arm_give_up_s': float('nan')},
                                    {'flight_timeout_s': -5.0}])
def test_bad_config_refused(kwargs):
    with pytest.raises(ValueError):
        RunnerConfig(**kwargs)


def test_reboots_once_when_arming_is_refused_too_long():
    core = LandingRunnerCore(sequencing(arm_retry_s=2.0, arm_give_up_s=100.0, reboot_after_s=20.0))
    core.on_goal('a', 0.0)
    calls = []
    t = 0.0
    while t < 60.0:
        name = core.poll(t)
        if name is not None:
            calls.append((round(t, 1), name))
            core.on_answer(name, name in ('guided', 'reboot'), 'FAILED (Arm: Check mag field)', t)
        t += 0.1
    reboots = [c for c in calls if c[1] == 'reboot']
    assert len(reboots) == 1 and 20.0 <= reboots[0][0] < 21.0, reboots
    after = [c for c in calls if c[0] > reboots[0][0]]
    assert after[0][1] == 'guided' and after[0][0] >= reboots[0][0] + 2.0     # arming resumes after a pause
    assert core.state == RunnerState.ARMING and len(after) > 10          # still retrying, no second reboot


def test_reboot_before_the_episode_after_a_crash_only():
    core = LandingRunnerCore(sequencing(reboot_after_crash=True))
    core.on_goal('a', 0.0)
    assert [answer(core, 0.0) for _ in range(3)] == ['guided', 'arm', 'takeoff']
    core.on_landing(landing(0, success=False, crash=True), 10.0)
    assert answer(core, 10.0) == 'land'
    core.on_goal('b', 20.0)
    assert answer(core, 20.0) == 'reboot'
    assert core.poll(20.1) is None                       # a pause after the reboot
    assert [answer(core, 30.0 + i) for i in range(3)] == ['guided', 'arm', 'takeoff']
    core.on_landing(landing(1), 60.0)                    # a good landing: no reboot next time
    assert answer(core, 60.0) == 'land'
    core.on_goal('c', 70.0)
    assert answer(core, 70.0) == 'guided'


def landed_runner(result: dict, t: float = 30.0) -> LandingRunnerCore:
    """A runner (disarm_timeout_s 20) that flew one episode and asked for LAND after `result` at `t`."""
    core = LandingRunnerCore(sequencing(disarm_timeout_s=20.0))
    core.on_goal('a', 0.0)
    assert [answer(core, 0.0) for _ in range(3)] == ['guided', 'arm', 'takeoff']
    core.on_landing(result, t)
    assert answer(core, t) == 'land'
    return core


def test_force_disarm_when_no_next_episode_follows_a_landing():
    core = landed_runner(landing(0, success=False, error=0.6))
    assert core.poll(49.0) is None                       # LAND may still disarm by itself
    assert answer(core, 50.5) == 'force_disarm'
    assert core.poll(80.0) is None                       # once
    core.on_goal('b', 81.0)                              # the sim reset after the disarm
    assert answer(core, 81.0) == 'guided'


def test_no_force_disarm_when_the_next_episode_comes_in_time():
    core = landed_runner(landing(0))
    core.on_goal('b', 36.0)
    assert [answer(core, 36.0 + i) for i in range(3)] == ['guided', 'arm', 'takeoff']
    assert all(core.poll(t) is None for t in (60.0, 100.0))    # flying: no force-disarm


def test_arming_waits_until_the_odometry_has_been_still_for_settle_s():
    # after the sim moves the vehicle to the next start spot, SITL's EKF slides its estimate there at up to
    # ~0.5 m/s for a few seconds: arming and taking off meanwhile misplaces the takeoff and the approach
    core = LandingRunnerCore(RunnerConfig(settle_s=1.0, settle_speed_mps=0.05, settle_drift_m=0.05))
    for k in range(30):                                  # resting where the last landing ended, before the goal
        core.on_odometry((3.0, 2.0, 0.5), (0.0, 0.0, 0.0), -1.5 + 0.05 * k)
    core.on_goal('a', 0.0)
    assert answer(core, 0.0) == 'guided'
    assert core.poll(0.1) is None                        # still before the announcement does not count
    t, x = 0.1, 3.0
    while x > 0.0:                                       # the estimate converges at 0.5 m/s
        core.on_odometry((x, 2.0, 0.5), (-0.5, 0.0, 0.0), t)
        assert core.poll(t) is None, t
        t, x = round(t + 0.05, 2), x - 0.025
    t_still = t
    while t < t_still + 0.95:                            # still, but not for settle_s yet
        core.on_odometry((0.0, 0.0, 0.0), (0.01, 0.0, 0.0), t)
        assert core.poll(t) is None, t
        t = round(t + 0.05, 2)
    core.on_odometry((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), t_still + 1.0)
    assert answer(core, t_still + 1.0) == 'arm'
    assert core.state == RunnerState.TAKING_OFF


def test_a_slow_drift_restarts_the_settle_window_and_stale_odometry_never_counts_as_settled():
    core = LandingRunnerCore(RunnerConfig(settle_s=1.0, settle_speed_mps=0.05, settle_drift_m=0.05))
    core.on_goal('a', 0.0)
    answer(core, 0.0)
    for k in range(61):                                  # reported still, yet moving 0.1 m/s: 0.05 m every 0.5 s
        t = 0.05 * k
        core.on_odometry((0.1 * t, 0.0, 0.0), (0.0, 0.0, 0.0), t)
        assert core.poll(t) is None, t
    assert core.state == RunnerState.ARMING and not core.odometry_settled(3.0)
    # still for 1 s, then silent: not settled once the last sample is older than settle_s
    for k in range(21):
        core.on_odometry((1.0, 0.0, 0.0), (0.0, 0.0, 0.0), 10.0 + 0.05 * k)
    assert core.odometry_settled(11.0)
    assert not core.odometry_settled(12.5)
    core.on_odometry((float('nan'), 0.0, 0.0), (0.0, 0.0, 0.0), 12.5)   # ignored, no fresher sample
    assert not core.odometry_settled(12.5)
    assert core.poll(12.5) is None


def test_settle_s_0_arms_without_odometry_and_bad_settle_settings_are_refused():
    core = LandingRunnerCore(RunnerConfig(settle_s=0.0))
    core.on_goal('a', 0.0)
    assert [answer(core, 0.0) for _ in range(3)] == ['guided', 'arm', 'takeoff']
    for bad in (dict(settle_s=-1.0), dict(settle_s=float('nan')), dict(settle_speed_mps=0.0),
                dict(settle_drift_m=float('inf'))):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RunnerConfig(**bad)
