"""landing_runner records ArduCopter's own landing verdict: after a touchdown result it waits up to
autopilot_confirm_s for /uav/landed_state ON_GROUND before LAND (autopilot_landed true/false; empty for a
timeout, a crash in the air, no landed state heard, or a runner stopped while waiting), and its results file
refuses other columns instead of appending mismatched rows."""
import csv

import pytest

from assist_bridge.landing_runner_core import (LandingRunnerCore, RunnerConfig, RunnerState, touched_down)
from assist_common.mavlink_io import mavlink

ON_GROUND, IN_AIR, TAKEOFF = (mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_IN_AIR,
                              mavlink.MAV_LANDED_STATE_TAKEOFF)


def answer(core, now, ok=True, msg='ACCEPTED'):
    """Poll once and answer the requested call; returns its name."""
    name = core.poll(now)
    assert name is not None, f'no call requested in state {core.state}'
    core.on_answer(name, ok, msg, now)
    return name


def landing(ep=0, outcome='success', reason='landed', crash=False):
    return {'episode': ep, 'success': outcome == 'success', 'crash': crash, 'error_m': 0.1, 'outcome': outcome,
            'reason': reason}


def flying(confirm_s=3.0, **cfg) -> LandingRunnerCore:
    """A runner whose vehicle has armed, taken off and reports being in the air."""
    core = LandingRunnerCore(RunnerConfig(autopilot_confirm_s=confirm_s, **{'settle_s': 0.0, **cfg}))
    core.on_goal('a', 0.0)
    core.on_landed_state(ON_GROUND, 0.0)
    assert [answer(core, 0.0) for _ in range(3)] == ['guided', 'arm', 'takeoff']
    core.on_landed_state(TAKEOFF, 1.0)
    core.on_landed_state(IN_AIR, 5.0)
    return core


def test_on_ground_within_the_wait_is_recorded_true_and_then_land():
    core = flying(confirm_s=3.0)
    core.on_landing(landing(), 20.0)
    assert core.state == RunnerState.CONFIRMING
    assert core.poll(20.0) is None and core.poll(21.0) is None      # no LAND while ArduCopter may still decide
    assert core.stats.results == []
    core.on_landed_state(IN_AIR, 21.5)                               # not yet
    assert core.state == RunnerState.CONFIRMING
    core.on_landed_state(ON_GROUND, 22.0)                            # its land detector declared the landing
    assert core.stats.results[-1]['autopilot_landed'] is True
    assert answer(core, 22.0) == 'land'
    assert core.state == RunnerState.WAIT_EPISODE
    assert core.stats.summary().endswith('autopilot landed 1/1')


def test_no_on_ground_is_recorded_false_after_the_wait_then_land_as_before():
    core = flying(confirm_s=3.0)
    core.on_landing(landing(), 20.0)
    core.on_landed_state(IN_AIR, 21.0)
    assert core.poll(22.9) is None and core.stats.results == []
    assert answer(core, 23.0) == 'land'                              # the wait is over: LAND as before
    assert core.stats.results[-1]['autopilot_landed'] is False
    core.on_landed_state(ON_GROUND, 24.0)                            # too late: the verdict stands
    assert core.stats.results[-1]['autopilot_landed'] is False and len(core.stats.results) == 1
    assert core.stats.summary().endswith('autopilot landed 0/1')


def test_an_on_ground_report_after_the_deadline_but_before_the_next_poll_is_not_in_time():
    core = flying(confirm_s=3.0)
    core.on_landing(landing(), 20.0)
    core.on_landed_state(ON_GROUND, 23.5)
    assert core.stats.results[-1]['autopilot_landed'] is False


@pytest.mark.parametrize('result', [landing(outcome='timeout', reason='no landing in time'),
                                    landing(outcome='crash', reason='tipped over', crash=True),
                                    landing(outcome='crash', reason='fell below the crash height', crash=True),
                                    landing(outcome='crash', reason='impact at 2.10 m/s', crash=True)])
def test_a_timeout_or_crash_has_no_verdict_and_lands_at_once(result):
    assert not touched_down(result)
    core = flying()
    core.on_landing(result, 20.0)
    assert core.stats.results[-1]['autopilot_landed'] == ''
    assert answer(core, 20.0) == 'land'


@pytest.mark.parametrize('result', [landing(), landing(outcome='wrong_pad'), landing(outcome='edge')])
def test_touchdowns_wait_for_the_verdict(result):
    assert touched_down(result)


def test_no_wait_without_landed_state_reports_or_with_a_zero_wait():
    core = LandingRunnerCore(RunnerConfig(autopilot_confirm_s=3.0, settle_s=0.0))
    core.on_goal('a', 0.0)
    assert [answer(core, 0.0) for _ in range(3)] == ['guided', 'arm', 'takeoff']
    core.on_landing(landing(), 20.0)                                 # this autopilot reports no landed state
    assert core.stats.results[-1]['autopilot_landed'] == '' and answer(core, 20.0) == 'land'
    core = flying(confirm_s=0.0)
    core.on_landing(landing(), 20.0)
    assert core.stats.results[-1]['autopilot_landed'] == '' and answer(core, 20.0) == 'land'
    assert 'autopilot landed' not in core.stats.summary()


def test_the_last_episode_finishes_only_after_the_verdict_and_land():
    core = flying(episodes=1)
    core.on_landing(landing(), 20.0)
    assert not core.finished and core.state == RunnerState.CONFIRMING
    core.on_landed_state(ON_GROUND, 20.5)
    assert core.state == RunnerState.DONE and not core.finished
    assert answer(core, 20.5) == 'land'
    assert core.finished


def test_a_goal_during_the_wait_starts_the_next_episode_after_land():
    core = flying()
    core.on_landing(landing(), 20.0)
    core.on_goal('b', 20.5)                                          # the sim moved on meanwhile
    assert core.poll(21.0) is None
    assert answer(core, 23.0) == 'land'
    assert [answer(core, 23.1 + i) for i in range(3)] == ['guided', 'arm', 'takeoff']


def test_a_runner_stopped_while_waiting_keeps_the_result_without_a_verdict():
    core = flying()
    core.on_landing(landing(ep=4), 20.0)
    core.flush(21.0)
    assert [(r['episode'], r['autopilot_landed']) for r in core.stats.results] == [(4, '')]
    core.flush(22.0)                                                 # nothing twice
    assert len(core.stats.results) == 1


def test_the_wait_is_a_checked_setting():
    for bad in (-1.0, float('nan'), float('inf')):
        with pytest.raises(ValueError, match='autopilot_confirm_s'):
            RunnerConfig(autopilot_confirm_s=bad)


# ---------------------------------------------------------------------- node: results file and parameter
def test_results_file_with_other_columns_is_refused_untouched(tmp_path):
    landing_runner = pytest.importorskip('assist_bridge.landing_runner')
    fields = landing_runner._CSV_FIELDS
    assert fields[-1] == 'autopilot_landed'
    assert landing_runner.results_header_problem(tmp_path / 'new.csv') is None
    (tmp_path / 'empty.csv').write_text('')
    assert landing_runner.results_header_problem(tmp_path / 'empty.csv') is None
    same = tmp_path / 'same.csv'
    same.write_text(','.join(fields) + '\n')
    assert landing_runner.results_header_problem(same) is None
    old = tmp_path / 'old.csv'
    text = ','.join(fields[:-1]) + '\n1,0,0,0.1,True,False,success,landed,12.0,False\n'
    old.write_text(text)
    problem = landing_runner.results_header_problem(old)
    assert problem is not None and 'autopilot_landed' in problem and '\n' not in problem
    assert old.read_text() == text
    assert list(csv.reader(old.open()))[0] == list(fields[:-1])
    param = landing_runner.PARAMS['autopilot_confirm_s']
    assert param.default == RunnerConfig().autopilot_confirm_s == 3.0 and param.min == 0.0
