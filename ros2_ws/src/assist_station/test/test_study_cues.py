"""The study's assisted-with-cues condition: the conditions option, the balanced Latin square of block orders, the
three-block protocol and its files, resuming in the third block, the per-landing measures and the key counter."""
import csv
import itertools
import json
from collections import Counter
from pathlib import Path

import pytest
import yaml

from assist_station.study import (ALL_CONDITIONS, BASE_COLUMNS, CONDITIONS, LANDING_COLUMNS, MEASURE_COLUMNS,
                                  SURVEY, KeyCounter, StudyConfig, StudyError, StudySession, block_condition,
                                  condition_order, first_condition, latin_square, order_name, phases)

TEXT = 'sequence: [1, 3]\npractice_landings: 1\nconditions: [unassisted, assisted, assisted_cues]\n'
CFG = StudyConfig.from_text(TEXT)
CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'


def landing(goal, outcome='success'):
    return {'episode': 3, 'goal_index': goal, 'landed_index': goal if outcome == 'success' else None,
            'nearest_index': goal, 'error_m': 0.2, 'nearest_error_m': 0.2, 'success': outcome == 'success',
            'crash': outcome == 'crash', 'outcome': outcome, 'duration_s': 14.25, 'assisted': True}


def fly(session, measures=None):
    spec = session.start_landing(bag=None)
    return spec, session.record_landing(landing(spec.goal_index), start_pad=None, episode=3, bag=None,
                                        measures=measures)


def rows(path):
    with open(path, newline='') as fh:
        return list(csv.DictReader(fh))


def events(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


# ----------------------------------------------------------------------------------------- study file
def test_conditions_option_defaults_to_the_papers_two_and_takes_the_cue_block():
    assert StudyConfig().conditions == CONDITIONS and StudyConfig().n_blocks == 2
    assert CFG.conditions == ALL_CONDITIONS and CFG.n_blocks == 3
    listed_otherwise = StudyConfig.from_text('conditions: [assisted_cues, assisted, unassisted]\n')
    assert listed_otherwise == CFG.__class__(conditions=ALL_CONDITIONS)     # one study however the file lists them


@pytest.mark.parametrize('text, needle', [
    ('conditions: [unassisted, assisted, magic]\n',
     'conditions items must be one of unassisted, assisted, assisted_cues'),
    ('conditions: [unassisted, assisted_cues]\n', 'conditions must list'),
    ('conditions: [unassisted, assisted, assisted]\n', 'conditions must list'),
    ('conditions: assisted_cues\n', 'conditions must be a list'),
    ('practice_condition: assisted_cues\n', 'practice_condition must be first or one of the conditions'),
])
def test_a_bad_conditions_option_is_one_line_naming_it(text, needle):
    with pytest.raises(StudyError) as err:
        StudyConfig.from_text(text)
    assert needle in str(err.value) and '\n' not in str(err.value)


def test_the_default_study_writes_no_conditions_key_and_the_cue_study_round_trips():
    assert 'conditions' not in StudyConfig().to_dict()           # simulate_study's study.yaml as before
    d = CFG.to_dict()
    assert d['conditions'] == list(ALL_CONDITIONS)
    assert StudyConfig.from_text(yaml.safe_dump(d)) == CFG


def test_shipped_cue_study_is_the_papers_with_the_third_condition():
    paper, _ = StudyConfig.load(CONFIG_DIR / 'study.yaml')
    cues, _ = StudyConfig.load(CONFIG_DIR / 'study_cues.yaml')
    assert cues.conditions == ALL_CONDITIONS and paper.conditions == CONDITIONS
    differ = {k for k, v in cues.to_dict().items() if paper.to_dict().get(k) != v}
    assert differ == {'name', 'conditions'}


# ----------------------------------------------------------------------------------------- counterbalancing
def test_three_conditions_use_a_balanced_latin_square_over_participant_numbers():
    orders = [condition_order(f'P{k:02d}', ALL_CONDITIONS) for k in range(1, 7)]
    assert sorted(orders) == sorted(itertools.permutations(ALL_CONDITIONS))      # all six orders, once each
    assert orders[0] == ALL_CONDITIONS                                            # P01: the first row
    assert [condition_order(f'P{k + 6:02d}', ALL_CONDITIONS) for k in range(1, 7)] == orders    # then again
    for position in range(3):           # each condition in each block equally often
        assert Counter(o[position] for o in orders) == {c: 2 for c in ALL_CONDITIONS}
    successions = Counter((o[i], o[i + 1]) for o in orders for i in range(2))
    assert set(successions.values()) == {2} and len(successions) == 6        # each right after each other twice


def test_latin_square_rows_for_four_conditions_are_balanced():
    rows = latin_square(('a', 'b', 'c', 'd'))
    assert len(rows) == 4 and all(sorted(r) == ['a', 'b', 'c', 'd'] for r in rows)
    assert all(sorted(col) == ['a', 'b', 'c', 'd'] for col in zip(*rows))
    assert set(Counter((r[i], r[i + 1]) for r in rows for i in range(3)).values()) == {1}


def test_two_conditions_keep_the_odd_even_rule_and_their_order_names():
    for k in range(1, 9):
        pid = f'P{k:02d}'
        first = 'unassisted' if k % 2 else 'assisted'
        assert first_condition(pid) == first and order_name(pid) == f'{first}_first'
        assert block_condition(pid, 2) != first
    with pytest.raises(StudyError, match='blocks 1-2'):
        block_condition('P01', 3)
    assert order_name('P02', ALL_CONDITIONS) == 'assisted-assisted_cues-unassisted'
    assert block_condition('P02', 3, ALL_CONDITIONS) == 'unassisted'


def test_phases_of_a_three_block_study():
    assert phases(2) == ('consent', 'practice', 'block1', 'sus1', 'block2', 'sus2', 'survey', 'done')
    assert phases(3)[-4:] == ('block3', 'sus3', 'survey', 'done')


# ----------------------------------------------------------------------------------------- protocol
def test_three_blocks_in_the_participants_order_each_with_its_sus(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P02')        # order: assisted, assisted_cues, unassisted
    s.consent()
    spec, _ = fly(s)
    assert spec.block == 0 and spec.condition == 'assisted' and not spec.cues    # practice: first block's condition
    flown = []
    for block, condition, score in ((1, 'assisted', 50.0), (2, 'assisted_cues', 75.0), (3, 'unassisted', 100.0)):
        assert s.phase == f'block{block}'
        for trial, goal in enumerate((1, 3)):
            spec, row = fly(s)
            assert (spec.block, spec.trial, spec.goal_index, spec.condition) == (block, trial, goal, condition)
            assert spec.assisted == (condition != 'unassisted') and spec.cues == (condition == 'assisted_cues')
            assert row['condition'] == condition and row['order'] == 'assisted-assisted_cues-unassisted'
            flown.append(spec.name)
        assert s.phase == f'sus{block}'
        view = s.view()
        assert view['block'] == block and view['condition'] == condition
        answers = {50.0: [3] * 10, 75.0: [4, 2] * 5, 100.0: [5, 1] * 5}[score]
        assert s.submit_sus(answers) == score
    assert s.phase == 'survey'
    s.submit_survey({str(q['id']): ([] if q['kind'] == 'multi' else 1) for q in SURVEY})
    assert s.phase == 'done'
    d = tmp_path / 'P02'
    table = rows(d / 'landings.csv')
    assert [(r['block'], r['condition']) for r in table] == [('0', 'assisted'), ('1', 'assisted'), ('1', 'assisted'),
                                                             ('2', 'assisted_cues'), ('2', 'assisted_cues'),
                                                             ('3', 'unassisted'), ('3', 'unassisted')]
    survey = json.loads((d / 'survey.json').read_text())
    assert {b: e['condition'] for b, e in survey['sus'].items()} == {'1': 'assisted', '2': 'assisted_cues',
                                                                     '3': 'unassisted'}
    ev = events(d / 'protocol.log')
    started = {e['landing']: e['condition'] for e in ev if e['event'] == 'landing_started'}
    assert started['block2_00'] == 'assisted_cues' and started['block3_01'] == 'unassisted'
    assert [(e['block'], e['condition']) for e in ev if e['event'] == 'sus'] == [
        (1, 'assisted'), (2, 'assisted_cues'), (3, 'unassisted')]
    assert ev[0]['order'] == 'assisted-assisted_cues-unassisted'


def test_practice_shows_cues_only_when_it_flies_the_cue_condition(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P03')        # order: assisted_cues, unassisted, assisted
    s.consent()
    assert s.next_landing().condition == 'assisted_cues' and s.next_landing().cues
    text = TEXT + 'practice_condition: unassisted\n'
    other = StudySession(StudyConfig.from_text(text), text, tmp_path / 'b', 'P03')
    other.consent()
    assert other.next_landing().condition == 'unassisted' and not other.next_landing().cues


def test_resume_in_the_third_block_repeats_only_the_landing_in_flight(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P04')        # order: assisted_cues, assisted, unassisted
    s.consent()
    fly(s)
    for _ in range(2):
        fly(s)
        fly(s)
        s.submit_sus([3] * 10)
    fly(s)                                              # block 3, trial 0 recorded
    assert s.start_landing(bag='block3_01').trial == 1  # in flight when the station dies
    del s
    s2 = StudySession(CFG, TEXT, tmp_path, 'P04')
    assert s2.phase == 'block3'
    spec = s2.next_landing()
    assert (spec.block, spec.trial, spec.condition, spec.goal_index) == (3, 1, 'unassisted', 3)
    fly(s2)
    assert s2.phase == 'sus3' and s2.view()['condition'] == 'unassisted'
    keys = [(r['block'], r['trial']) for r in rows(tmp_path / 'P04' / 'landings.csv')]
    assert keys == [('0', '0'), ('1', '0'), ('1', '1'), ('2', '0'), ('2', '1'), ('3', '0'), ('3', '1')]


# ----------------------------------------------------------------------------------------- measures
def test_measures_are_written_after_the_base_columns_and_empty_when_not_measured(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    _, row = fly(s, measures={'path_length_m': 12.34567, 'key_presses': 9, 'corrective_keys': 2})
    assert (row['path_length_m'], row['key_presses'], row['corrective_keys']) == ('12.3457', '9', '2')
    _, row = fly(s)
    assert (row['path_length_m'], row['key_presses'], row['corrective_keys']) == ('', '', '')
    assert LANDING_COLUMNS == BASE_COLUMNS + MEASURE_COLUMNS
    assert (tmp_path / 'P01' / 'landings.csv').read_text().splitlines()[0] == ','.join(LANDING_COLUMNS)


def test_a_file_written_without_the_measures_resumes_in_its_own_columns(tmp_path):
    d = tmp_path / 'P01'
    d.mkdir()
    (d / 'study.yaml').write_text(TEXT)
    (d / 'protocol.log').write_text(json.dumps({'t': '2024-01-01T00:00:00.000Z', 'event': 'consent'}) + '\n')
    old = {c: '' for c in BASE_COLUMNS}
    old.update(participant='P01', block='0', condition='unassisted', order='unassisted-assisted-assisted_cues',
               trial='0', goal_index='2', error_m='0.1000', nearest_error_m='0.1000', success='true',
               crash='false', outcome='success', started_on_pad='false')
    with open(d / 'landings.csv', 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=BASE_COLUMNS, lineterminator='\n')
        w.writeheader()
        w.writerow(old)
    before = (d / 'landings.csv').read_text()
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    assert s.phase == 'block1'
    fly(s, measures={'path_length_m': 3.0, 'key_presses': 4, 'corrective_keys': 1})
    text = (d / 'landings.csv').read_text()
    assert text.startswith(before)                       # nothing written is lost or rewritten
    table = rows(d / 'landings.csv')
    assert tuple(table[0]) == BASE_COLUMNS and len(table) == 2 and table[1]['block'] == '1'


def test_a_file_of_other_columns_is_not_appended_to(tmp_path):
    d = tmp_path / 'P01'
    d.mkdir()
    (d / 'study.yaml').write_text(TEXT)
    (d / 'landings.csv').write_text(','.join(BASE_COLUMNS + ('path_length_m',)) + '\n')
    with pytest.raises(StudyError, match='columns differ'):
        StudySession(CFG, TEXT, tmp_path, 'P01')
    assert (d / 'landings.csv').read_text() == ','.join(BASE_COLUMNS + ('path_length_m',)) + '\n'


def counted(*held_sets, before=()):
    """(presses, corrective) of a landing during which the held keys went through `held_sets`."""
    k = KeyCounter()
    k.note(before)
    k.start()
    for held in held_sets:
        k.note(held)
    return k.stop()


@pytest.mark.parametrize('held_sets, before, expected', [
    ((['KeyW'], [], ['KeyW'], []), (), (2, 0)),                            # the same key again: not corrective
    ((['KeyW'], [], ['KeyS']), (), (2, 1)),                                # back after forward
    ((['KeyW'], ['KeyW', 'KeyS']), (), (2, 1)),                            # back pressed while forward is held
    ((['KeyA'], ['KeyA', 'KeyW'], ['KeyW'], ['KeyW', 'KeyD']), (), (3, 1)),  # axes apart: D against A
    ((['KeyW'], ['KeyW', 'KeyA'], ['KeyA']), (), (2, 0)),                  # another axis is no reversal
    ((['ArrowDown'], ['ArrowUp'], ['ArrowDown']), (), (3, 0)),            # vertical: presses, never corrective
    ((['Space'], [], ['Space']), (), (2, 2)),                              # every stop press is corrective
    ((['KeyS'],), ('KeyW',), (1, 1)),                                      # W held as the landing starts
    ((['KeyW'], ['KeyW']), ('KeyW',), (0, 0)),                             # held through: no key-down
])
def test_key_counter_definition(held_sets, before, expected):
    assert counted(*held_sets, before=before) == expected


def test_key_counter_counts_only_between_start_and_stop():
    k = KeyCounter()
    k.note(['KeyW'])
    k.note([])
    assert k.stop() is None                              # never started: nothing measured
    k.start()
    k.note(['KeyS'])                                     # the key before start does not make this corrective
    assert k.stop() == (1, 0)
    k.note([])
    k.note(['KeyW'])                                     # after stop: not counted
    k.start()
    assert k.stop() == (0, 0)


# ----------------------------------------------------------------------------------------- simulated participants
def test_cue_trust_is_drawn_apart_from_the_rest_of_the_profile():
    from dataclasses import asdict

    from assist_station.participant import draw_profiles
    low = draw_profiles(12, seed=5, cue_trust=(0.0, 0.1))
    high = draw_profiles(12, seed=5, cue_trust=(0.9, 1.0))
    assert all(0.0 <= p.cue_trust <= 0.1 for p in low) and all(0.9 <= p.cue_trust <= 1.0 for p in high)
    strip = [{k: v for k, v in asdict(p).items() if k != 'cue_trust'} for p in low]
    assert strip == [{k: v for k, v in asdict(p).items() if k != 'cue_trust'} for p in high]


def test_a_participant_reads_only_the_cues_the_station_shows():
    from assist_station.participant import cue_from_view, cue_shown
    assert cue_from_view(None) is None and not cue_shown({'goal': None, 'descent': None, 'push': None})
    assert cue_from_view({'goal': {'state': 'unknown', 'p': [1, 2, 3], 'sigma_m': 0.1}, 'descent': 'unknown',
                          'push': None}) is None                    # grey cues say nothing
    cue = cue_from_view({'goal': {'state': 'unsure', 'p': [1.0, 2.0, 0.5], 'pad': 2, 'sigma_m': 0.9},
                         'descent': 'hold', 'push': [0.1, 0.0, 0.0]})
    assert list(cue.goal) == [1.0, 2.0, 0.5] and cue.sigma_m == 0.9 and cue.descent_ok is False
    light_only = cue_from_view({'goal': None, 'descent': 'ok', 'push': None})
    assert light_only.goal is None and light_only.descent_ok is True
    assert cue_shown({'goal': None, 'descent': 'unknown', 'push': None})


@pytest.mark.parametrize('argv, needle', [
    (['--cue-trust', '0.9', '0.2'], '--cue-trust: the low end 0.9 is above the high end 0.2'),
    (['--cue-trust', '0.5', '1.5'], '--cue-trust'),
    (['--cue-trust', '0.5'], '--cue-trust'),
])
def test_simulate_study_refuses_a_bad_cue_trust_range_before_any_work(tmp_path, capsys, argv, needle):
    from assist_station import simulate_study
    with pytest.raises(SystemExit) as exit_:
        simulate_study.main(['--out', str(tmp_path / 'o'), *argv])
    assert exit_.value.code == 2 and needle in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()
