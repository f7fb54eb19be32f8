"""The three-block study (unassisted, assisted, assisted_cues) end to end: simulate_study flies it through the real
graph (sim_node, encoder_node, policy_node, pilot_station with config/study_cues.yaml), one participant in headless
Chromium through the station page (the WebSocket participant's three blocks: test_study_driver_cues), then
analyze_study reads it.

The station shows its intent cues in assisted_cues landings only (the participants count the pilot steps in which
the page's state carried a cue), each block's rows name the participant's Latin-square condition, assisted_cues
flies with the assistant on, every row carries its measures, and the analysis reports all three conditions.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from assist_station import analyze_study
from assist_station.simulate_study import SimulateArgs, simulate
from assist_station.study import ALL_CONDITIONS, MEASURE_COLUMNS, condition_order

pytestmark = [pytest.mark.graph, pytest.mark.slow(seconds=150)]
STUDY = Path(__file__).resolve().parents[1] / 'ros2_ws' / 'src' / 'assist_station' / 'config' / 'study_cues.yaml'
PIDS = ('S03',)                # order: assisted_cues-unassisted-assisted


@pytest.fixture(scope='module')
def run(tmp_path_factory, domain_id, study_max_landing_s):
    out = tmp_path_factory.mktemp('cues_study')
    args = SimulateArgs(out=str(out), participants=3, only=PIDS, landings_per_block=1, practice=0,
                        real_time_factor=3.0, browser_participants=1, study=str(STUDY), domain_id=domain_id,
                        max_landing_s=study_max_landing_s)
    results = simulate(args)
    return out, {r['participant']: r for r in results}


def test_blocks_follow_the_latin_square_and_cues_show_only_in_their_block(run):
    out, results = run
    assert set(results) == set(PIDS) and results['S03']['browser']
    for pid in PIDS:
        with open(out / pid / 'landings.csv', newline='') as fh:
            table = list(csv.DictReader(fh))
        order = condition_order(pid, ALL_CONDITIONS)
        assert [(r['block'], r['condition']) for r in table] == [(str(b), c) for b, c in enumerate(order, start=1)]
        for r in table:
            assert r['assist_live'] == ('false' if r['condition'] == 'unassisted' else 'true'), r
            assert all(r[c] != '' for c in MEASURE_COLUMNS), r
            assert float(r['path_length_m']) > 0
            assert int(r['corrective_keys']) <= int(r['key_presses'])
        survey = json.loads((out / pid / 'survey.json').read_text())
        assert {b: e['condition'] for b, e in survey['sus'].items()} == {'1': order[0], '2': order[1], '3': order[2]}
        steps = results[pid]['cue_steps']
        assert steps['assisted_cues'][1] > 0, steps                  # the station showed cues in that block
        for condition in ('unassisted', 'assisted'):
            assert steps[condition][0] > 0 and steps[condition][1] == 0, steps


def test_analyze_study_reports_the_three_conditions(run, tmp_path):
    out, _ = run
    summary = analyze_study.run([out / pid for pid in PIDS],
                                analyze_study.AnalyzeArgs(out=str(tmp_path / 'a'), trajectories=1))
    assert summary['validation']['rows_excluded_total'] == 0 and summary['participants'] == len(PIDS)
    m = summary['measures']
    assert m['conditions'] == list(ALL_CONDITIONS)
    for c in ALL_CONDITIONS:
        per = m['per_condition'][c]
        assert per['landings'] + m['excluded'][c] == len(PIDS)
        assert per['path_length_m']['n'] == per['landings'] and per['time_to_land_s']['n'] == per['landings']
    assert set(m['tests']) <= {'unassisted vs assisted', 'unassisted vs assisted_cues', 'assisted vs assisted_cues'}
    assert set(summary['sus']) == set(ALL_CONDITIONS) and summary['sus']['assisted_cues']['n'] == len(PIDS)
    for name in analyze_study.OUTPUTS:
        assert (tmp_path / 'a' / name).is_file()
