"""The user study end to end in a real graph: sim_node, encoder_node, policy_node and pilot_station with the
three-block study file (config/study_cues.yaml: unassisted, assisted, assisted_cues).

Two simulated participants go through the whole protocol (practice, three blocks, SUS, concluding survey):
S01 in headless Chromium through the station page's own forms and key handling (the page reloaded
mid-landing: that landing flown again), S02 over the station's WebSocket. The station is killed (SIGKILL)
while S02 flies a block landing and started again: S02 reconnects, the study resumes at that landing, and
nothing already recorded is lost or written twice. Both participants' blocks follow their Latin-square order,
the station shows its intent cues in assisted_cues landings only, assisted blocks fly with the assistant on,
every row carries its measures; analyze_study then reads both on three conditions. Chromium comes from
Debian (`make test` installs it). The two-block study is flown through the simulate_study command by the
station README's commands (tests/test_documented_commands.py).
"""
from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import threading
import time
from pathlib import Path

import pytest

from assist_station import analyze_study
from assist_station.browser_participant import BrowserParticipant
from assist_station.participant import Participant, draw_profiles
from assist_station.simulate_study import SimulateArgs, StudyGraph, free_tcp_port, graph_params, study_file
from assist_station.study import ALL_CONDITIONS, MEASURE_COLUMNS, condition_order

pytestmark = [pytest.mark.graph, pytest.mark.slow(seconds=110)]
RTF = 3.0                      # sim seconds per wall second (the landings need not be flown well here)
STUDY = Path(__file__).resolve().parents[1] / 'ros2_ws' / 'src' / 'assist_station' / 'config' / 'study_cues.yaml'


def rows(path: Path) -> list[dict]:
    with open(path, newline='') as fh:
        return list(csv.DictReader(fh))


def events(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.fixture(scope='module')
def study(tmp_path_factory, domain_id, study_max_landing_s):
    out = tmp_path_factory.mktemp('study')
    args = SimulateArgs(out=str(out), participants=2, landings_per_block=1, practice=1, real_time_factor=RTF,
                        browser_participants=1, study=str(STUDY), max_landing_s=study_max_landing_s)
    sim_dir = out / '.simulation'
    sim_dir.mkdir()
    cfg, path = study_file(args, sim_dir)
    graph = StudyGraph(graph_params(cfg, args, path, out, free_tcp_port()), domain_id, sim_dir / 'logs')
    graph.start()
    try:
        yield out, graph, draw_profiles(2, seed=0, practice=1)
    finally:
        graph.stop()


@contextlib.contextmanager
def node_logs_on_failure(graph: StudyGraph):
    """A participant that fails: the failure carries the end of every node's log (what the graph was doing)."""
    try:
        yield
    except (Exception, pytest.fail.Exception) as exc:
        tails = '\n'.join(f'--- {name}:\n{graph.group.tail(name, 2500)}' for name in graph.group.procs)
        raise AssertionError(f'{type(exc).__name__}: {exc}\n{tails}') from exc


def check_participant(d: Path, pid: str, n_practice: int) -> list[dict]:
    """The participant's rows, survey and study file: every landing once, blocks in the Latin-square order."""
    table = rows(d / 'landings.csv')
    keys = [(r['block'], r['trial']) for r in table]
    assert len(keys) == len(set(keys)), f'a landing recorded twice: {keys}'
    order = condition_order(pid, ALL_CONDITIONS)
    assert keys == [('0', str(t)) for t in range(n_practice)] + [(str(b), '0') for b in (1, 2, 3)]
    assert [r['condition'] for r in table if r['block'] != '0'] == list(order)
    for r in table:
        # the condition the row says is the one the graph flew: sim_node saw /assist/agent_cmd exactly then
        assert r['assist_live'] == ('false' if r['condition'] == 'unassisted' else 'true'), r
        assert r['outcome'] in ('success', 'wrong_pad', 'edge', 'crash', 'timeout')
        assert (d / 'bags' / r['bag'] / 'metadata.yaml').is_file()
        assert all(r[c] != '' for c in MEASURE_COLUMNS), r
        assert float(r['path_length_m']) > 0
        assert int(r['corrective_keys']) <= int(r['key_presses'])
    survey = json.loads((d / 'survey.json').read_text())
    assert {b: e['condition'] for b, e in survey['sus'].items()} == {'1': order[0], '2': order[1], '3': order[2]}
    assert len(survey['survey']) == 21
    assert (d / 'study.yaml').is_file()
    return table


def check_cues(cue_steps: dict) -> None:
    """The participant saw the station's intent cues in the assisted_cues block and in no other."""
    assert cue_steps['assisted_cues'][1] > 0, cue_steps
    for condition in ('unassisted', 'assisted'):
        assert cue_steps[condition][0] > 0 and cue_steps[condition][1] == 0, cue_steps


def test_browser_participant_goes_through_the_page(study):
    out, graph, profiles = study
    with node_logs_on_failure(graph):
        res = BrowserParticipant(graph.url, profiles[0], RTF, out / '.simulation' / 'browser',
                                 reload_during=('block2', 1)).run()    # the page reloaded in block 2's first landing
    assert res['landings_flown'] == 4 and res['reconnects'] == 1
    table = check_participant(out / 'S01', 'S01', 1)
    assert [int(r['goal_index']) for r in table if r['block'] != '0'] == [2, 2, 2]    # the sequence's first goal
    check_cues(res['cue_steps'])
    ev = events(out / 'S01' / 'protocol.log')
    aborted = [e for e in ev if e['event'] == 'landing_aborted']
    assert [e['landing'] for e in aborted] == ['block2_00'] and 'page went away' in aborted[0]['why']
    assert [e['landing'] for e in ev if e['event'] == 'landing_started'].count('block2_00') == 2


def test_station_killed_mid_block_resumes_without_loss_or_duplicates(study):
    out, graph, profiles = study
    part = Participant(graph.url, profiles[1], RTF, connect_timeout_s=90.0)
    result: dict = {}

    def run() -> None:
        try:
            result['res'] = asyncio.run(part.run())
        except Exception as exc:  # noqa: BLE001 - handed to the test thread
            result['error'] = exc
    with node_logs_on_failure(graph):
        t = threading.Thread(target=run, daemon=True)
        t.start()
        log = out / 'S02' / 'protocol.log'
        end = time.monotonic() + 240
        while time.monotonic() < end:   # block 1's landing in flight (its bag open, not only started): kill the station
            if log.exists():
                ev = events(log)
                if ev[-1]['event'] == 'landing_started' and ev[-1]['landing'] == 'block1_00' \
                        and (out / 'S02' / 'bags' / 'block1_00').is_dir():
                    break
            assert t.is_alive(), result
            time.sleep(0.2)
        else:
            pytest.fail('S02 never reached block1_00 with its bag open')
        time.sleep(1.0)
        graph.kill_station()
        recorded = rows(out / 'S02' / 'landings.csv')
        graph.start_station()
        t.join(300)
        assert not t.is_alive(), 'S02 did not finish after the station restart'
        assert 'error' not in result, result.get('error')
        assert result['res']['reconnects'] >= 1
    table = check_participant(out / 'S02', 'S02', 1)
    assert table[:len(recorded)] == recorded                   # rows written before the crash kept as they were
    ev = events(log)
    started = [e['landing'] for e in ev if e['event'] == 'landing_started']
    assert started.count('block1_00') == 2                     # flown again after the restart
    assert [e['landing'] for e in ev if e['event'] == 'landing_recorded'].count('block1_00') == 1
    assert (out / 'S02' / 'bags' / 'block1_00_2').is_dir()     # the interrupted landing's bag is kept
    assert len(recorded) == 1                                  # practice, written before the crash
    check_cues(result['res']['cue_steps'])


def test_analyze_study_reads_the_participants_on_three_conditions(study, tmp_path):
    out, _, _ = study
    pids = ('S01', 'S02')
    summary = analyze_study.run([out / pid for pid in pids], analyze_study.AnalyzeArgs(out=str(tmp_path / 'a'),
                                                                                        trajectories=2))
    assert summary['participants'] == 2 and summary['validation']['rows_excluded_total'] == 0
    assert summary['landings'] == {'unassisted': 2, 'assisted': 2}     # Table I: the paper's two conditions
    assert summary['trajectory_panels'] >= 2
    m = summary['measures']
    assert m['conditions'] == list(ALL_CONDITIONS)
    for c in ALL_CONDITIONS:
        per = m['per_condition'][c]
        assert per['landings'] + m['excluded'][c] == len(pids)
        assert per['path_length_m']['n'] == per['landings'] and per['time_to_land_s']['n'] == per['landings']
    assert set(m['tests']) <= {'unassisted vs assisted', 'unassisted vs assisted_cues', 'assisted vs assisted_cues'}
    assert set(summary['sus']) == set(ALL_CONDITIONS) and summary['sus']['assisted_cues']['n'] == len(pids)
    for name in analyze_study.OUTPUTS:
        assert (tmp_path / 'a' / name).is_file()
