"""User-study protocol core: study file, counterbalancing, questionnaires, participant files, resume."""
import csv
import errno
import json
import os

import numpy as np
import pytest

from assist_station.participant import Profile, draw_profiles, keys_for, survey_answers, sus_answers
from assist_station.study import (LANDING_COLUMNS, SURVEY, SUS_ITEMS, StudyConfig, StudyError, StudySession,
                                  check_survey, first_condition, practice_goals, sus_score)

TEXT = 'sequence: [1, 3, 0]\npractice_landings: 2\n'
CFG = StudyConfig.from_text(TEXT)


def landing(goal, success=True, error=0.1, landed=None, episode=1):
    return {'episode': episode, 'goal_index': goal, 'landed_index': goal if success else landed,
            'nearest_index': goal, 'error_m': error, 'nearest_error_m': error, 'success': success,
            'crash': False, 'outcome': 'success' if success else 'wrong_pad', 'duration_s': 12.5, 'assisted': False}


def fly(session, success=True, start_pad=None, landed=None):
    spec = session.start_landing(bag=None)
    return spec, session.record_landing(landing(spec.goal_index, success, landed=landed), start_pad=start_pad,
                                        episode=7, bag=None)


def rows(path):
    with open(path, newline='') as fh:
        return list(csv.DictReader(fh))


def test_shipped_study_file_is_the_paper_protocol():
    from assist_station.simulate_study import shipped_study
    cfg, _ = StudyConfig.load(shipped_study())
    assert cfg.landings_per_block == 16 and cfg.practice_landings == 14 and cfg.n_pads == 5
    assert all(0 <= g < 5 for g in cfg.sequence) and set(cfg.sequence) == set(range(5))


@pytest.mark.parametrize('text, needle', [
    ('sequence: [1, 9]\n', 'sequence'),
    ('sequence: []\n', 'sequence'),
    ('practice_landings: -1\n', 'practice_landings'),
    ('seqeunce: [1]\n', 'unknown setting(s) seqeunce'),
    ('assistant_mode: magic\n', 'assistant_mode'),
    ('landing_timeout_s: .nan\n', 'landing_timeout_s'),
    ('[1, 2]\n', 'expected a mapping'),
    ('a: [\n', 'not valid YAML'),
    ('record_bags: 1\n', 'record_bags'),
    ('policy_model: 3\n', 'policy_model'),
])
def test_bad_study_files_are_refused_with_the_reason(text, needle):
    with pytest.raises(StudyError, match=None) as err:
        StudyConfig.from_text(text)
    assert needle in str(err.value)


def test_counterbalancing_follows_the_trailing_number():
    assert first_condition('P01') == 'unassisted' and first_condition('P02') == 'assisted'
    assert first_condition('lab-b-17') == 'unassisted' and first_condition('x10') == 'assisted'
    named = [first_condition(f'name{c}') for c in 'abcdefghijklmnop']
    assert 'assisted' in named and 'unassisted' in named       # IDs without a number: by hash, both orders occur


def test_sus_score_is_brookes_formula():
    assert sus_score([3] * 10) == 50.0
    assert sus_score([5, 1] * 5) == 100.0
    assert sus_score([1, 5] * 5) == 0.0
    assert sus_score([4, 2, 4, 2, 4, 2, 4, 2, 4, 2]) == 75.0
    for bad in ([3] * 9, [0] * 10, [3.0] * 10, ['3'] * 10, [True] * 10):
        with pytest.raises(StudyError):
            sus_score(bad)


def test_survey_answers_are_checked_per_question_kind():
    good = {str(q['id']): ([1] if q['kind'] == 'multi' else 1) for q in SURVEY}
    assert check_survey(good)['4'] == [1]
    assert len(SURVEY) == 21 and len(SUS_ITEMS) == 10
    for key, value, needle in (('2', 6, 'question 2'), ('1', 3, 'question 1'), ('4', [1, 1], 'question 4'),
                               ('9', None, 'question 9'), ('22', 1, 'unknown question')):
        bad = dict(good)
        bad[key] = value
        with pytest.raises(StudyError, match=needle):
            check_survey(bad)
    missing = dict(good)
    del missing['21']
    with pytest.raises(StudyError, match='question 21 is not answered'):
        check_survey(missing)


def test_whole_protocol_in_order_with_files(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P02')          # even: assisted first
    assert s.phase == 'consent'
    with pytest.raises(StudyError):
        s.start_landing()
    s.consent()
    assert s.phase == 'practice'
    spec, _ = fly(s)
    assert spec.block == 0 and spec.condition == 'assisted' and spec.goal_index == practice_goals(CFG, 'P02')[0]
    s.stop_practice()
    assert s.phase == 'block1'
    goals = []
    for _ in range(3):
        spec, row = fly(s)
        goals.append(spec.goal_index)
        assert spec.condition == 'assisted' and row['order'] == 'assisted_first'
    assert goals == [1, 3, 0] and s.phase == 'sus1'
    with pytest.raises(StudyError, match='SUS'):
        s.submit_sus([3] * 9)
    assert s.submit_sus([4, 2] * 5) == 75.0
    for expected_goal in (1, 3, 0):
        spec, _ = fly(s)
        assert spec.block == 2 and spec.condition == 'unassisted' and spec.goal_index == expected_goal
    s.submit_sus([3] * 10)
    assert s.phase == 'survey'
    s.submit_survey({str(q['id']): ([] if q['kind'] == 'multi' else 2) for q in SURVEY})
    assert s.phase == 'done'
    d = tmp_path / 'P02'
    table = rows(d / 'landings.csv')
    assert tuple(table[0]) == LANDING_COLUMNS and len(table) == 7
    assert [r['block'] for r in table] == ['0', '1', '1', '1', '2', '2', '2']
    survey = json.loads((d / 'survey.json').read_text())
    assert survey['sus']['1'] == {'condition': 'assisted', 'answers': [4, 2] * 5, 'score': 75.0}
    assert survey['sus']['2']['condition'] == 'unassisted' and len(survey['survey']) == 21
    assert (d / 'study.yaml').read_text() == TEXT
    events = [json.loads(line)['event'] for line in (d / 'protocol.log').read_text().splitlines()]
    assert events.count('landing_recorded') == 7 and events[-1] == 'done' and 'practice_done' in events


def test_practice_ends_by_itself_after_the_configured_number(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    fly(s)
    fly(s)
    assert s.phase == 'block1'
    with pytest.raises(StudyError):
        s.stop_practice()


def test_resume_after_a_crash_repeats_only_the_landing_in_flight(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    fly(s)
    fly(s)
    fly(s)                                      # block 1, trial 0 recorded
    spec = s.start_landing(bag='block1_01')     # in flight when the station dies: never recorded
    assert spec.trial == 1
    del s
    s2 = StudySession(CFG, TEXT, tmp_path, 'P01')
    assert s2.phase == 'block1' and s2.next_landing().trial == 1 and s2.next_landing().goal_index == 3
    fly(s2)
    table = rows(tmp_path / 'P01' / 'landings.csv')
    keys = [(r['block'], r['trial']) for r in table]
    assert keys == [('0', '0'), ('0', '1'), ('1', '0'), ('1', '1')]      # nothing lost, nothing twice


def test_a_row_torn_by_a_crash_is_dropped_not_kept_half(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    fly(s)
    path = tmp_path / 'P01' / 'landings.csv'
    with open(path, 'a') as fh:
        fh.write('P01,0,unassisted,unassisted_first,1,2,')          # the crash cut this row
    s2 = StudySession(CFG, TEXT, tmp_path, 'P01')
    assert s2.next_landing().trial == 1
    assert path.read_text().endswith('\n') and len(rows(path)) == 1
    assert 'torn_row_dropped' in (tmp_path / 'P01' / 'protocol.log').read_text()


def test_another_study_file_for_the_same_participant_is_refused(tmp_path):
    StudySession(CFG, TEXT, tmp_path, 'P01')
    other = 'sequence: [2, 2]\n'
    with pytest.raises(StudyError, match='different study file'):
        StudySession(StudyConfig.from_text(other), other, tmp_path, 'P01')


@pytest.mark.parametrize('pid', ['', '../x', 'a/b', '-x', 'x' * 33, 'a b', None, 7])
def test_bad_participant_ids_are_refused(tmp_path, pid):
    with pytest.raises(StudyError, match='participant ID'):
        StudySession(CFG, TEXT, tmp_path, pid)
    assert list(tmp_path.iterdir()) == []


def test_a_landing_result_for_another_goal_is_not_recorded(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    spec = s.start_landing()
    with pytest.raises(StudyError, match='goal pad'):
        s.record_landing(landing((spec.goal_index + 1) % 5), start_pad=None, episode=1, bag=None)
    assert not (tmp_path / 'P01' / 'landings.csv').exists()


def test_started_on_pad_marks_landings_on_the_starting_platform(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    _, row = fly(s, success=False, start_pad=4, landed=4)
    assert row['started_on_pad'] == 'true' and row['start_pad'] == '4'
    _, row = fly(s, success=False, start_pad=4, landed=2)
    assert row['started_on_pad'] == 'false'


def test_bag_names_never_reuse_an_existing_directory(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    a = s.store.new_bag_path('block1_00')
    a.mkdir()
    assert s.store.new_bag_path('block1_00').name == 'block1_00_2'


def test_simulated_participants_spread_skills_and_answer_consistently():
    profiles = draw_profiles(12, seed=3)
    betas = sorted(p.beta for p in profiles)
    assert betas[0] < 0.25 and betas[-1] > 0.75 and len({p.family for p in profiles}) >= 5
    assert [p.pid for p in profiles][:2] == ['S01', 'S02']
    rng = np.random.default_rng(0)
    good = np.mean([sus_score(sus_answers(rng, 0.95)) for _ in range(50)])
    bad = np.mean([sus_score(sus_answers(rng, 0.05)) for _ in range(50)])
    assert good > 80 > 20 > bad
    expert = Profile('S01', 'paper', 0.9, 0.5, 1, 2, experience=0.95)
    novice = Profile('S02', 'paper', 0.1, 0.5, 1, 2, experience=0.05)
    e = [np.mean([survey_answers(rng, p, {})[str(q)] for q in (2, 3, 5, 6)]) for p in (expert, novice)]
    assert e[0] > 4 and e[1] < 2
    check_survey(survey_answers(rng, expert, {'unassisted': 0.2, 'assisted': 0.9}))


def test_participant_keys_follow_the_pilot_command():
    assert keys_for(np.array([1.0, 0, -0.5]), 1.0) == ['KeyW', 'ArrowDown']
    assert keys_for(np.array([-1.0, -1.0, 0.5]), 1.0) == ['KeyS', 'KeyD', 'ArrowUp']
    assert keys_for(np.array([0.3, 0.2, 0.0]), 1.0) == []


def test_a_full_disk_loses_nothing_and_takes_no_half_step(tmp_path, monkeypatch):
    import errno
    import os as os_module
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    fly(s)
    path = tmp_path / 'P01' / 'landings.csv'
    before = path.read_bytes()
    real_fsync = os_module.fsync

    def full(fd):
        raise OSError(errno.ENOSPC, 'No space left on device')
    spec = s.start_landing()
    monkeypatch.setattr(os_module, 'fsync', full)
    with pytest.raises(OSError):
        s.record_landing(landing(spec.goal_index), start_pad=None, episode=3, bag=None)
    monkeypatch.setattr(os_module, 'fsync', real_fsync)
    assert path.read_bytes() == before and len(s.store.rows) == 1         # the failed row is taken back
    s.abort_landing('disk full')
    for _ in range(4):                  # the second practice landing, then block 1
        fly(s)
    assert s.phase == 'sus1'
    monkeypatch.setattr(os_module, 'fsync', full)
    with pytest.raises(OSError):
        s.submit_sus([3] * 10)
    monkeypatch.setattr(os_module, 'fsync', real_fsync)
    assert s.phase == 'sus1' and s.store.survey['sus'] == {}             # not taken: asked again
    assert not list((tmp_path / 'P01').glob('.*'))                        # no temporary left behind
    assert s.submit_sus([3] * 10) == 50.0 and s.phase == 'block2'


@pytest.mark.parametrize('argv, needle', [
    (['--participants', '3', '--only', 'S04'], '--only: S04 not among the 3 participants'),
    (['--participants', '2', '--browser-participants', '3'], 'at most --participants'),
    (['--families', 'paper', 'acrobat'], 'unknown pilot acrobat'),
    (['--real-time-factor', 'nan'], 'real-time-factor'),
    (['--participants', '0'], '--participants'),
])
def test_simulate_study_refuses_bad_arguments_before_any_work(tmp_path, capsys, argv, needle):
    from assist_station import simulate_study
    with pytest.raises(SystemExit) as exit_:
        simulate_study.main(['--out', str(tmp_path / 'o'), *argv])
    assert exit_.value.code == 2 and needle in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()


def _no_space(fd):
    raise OSError(errno.ENOSPC, 'No space left on device')


def test_a_full_disk_at_start_landing_leaves_no_landing_in_flight_and_a_retry_starts_it(tmp_path, monkeypatch):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    log = tmp_path / 'P01' / 'protocol.log'
    before = log.read_bytes()
    monkeypatch.setattr(os, 'fsync', _no_space)
    with pytest.raises(OSError) as err:
        s.start_landing(bag='practice_00')
    assert err.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert s.active is None and s.view()['in_flight'] is False
    assert log.read_bytes() == before                          # the partial line is taken back
    spec = s.start_landing(bag='practice_00')                  # space is back: the same landing starts
    assert spec.name == 'practice_00' and s.active == spec
    s.record_landing(landing(spec.goal_index), start_pad=None, episode=1, bag='practice_00')
    events = [json.loads(line)['event'] for line in log.read_text().splitlines()]
    assert events.count('landing_started') == 1 and events[-1] == 'landing_recorded'


def test_a_torn_protocol_line_does_not_swallow_the_event_after_it(tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    fly(s)
    log = tmp_path / 'P01' / 'protocol.log'
    with open(log, 'a') as fh:
        fh.write('{"t": "2024-01-01T00:00:00.000Z", "event": "landing_sta')       # a crash cut this event
    s.stop_practice()                                          # appended after the torn line (same store)
    assert s.phase == 'block1'
    fly(s)
    s2 = StudySession(CFG, TEXT, tmp_path, 'P01')              # restart: practice_done must still be read
    assert s2.phase == 'block1' and s2.next_landing().trial == 1
    lines = log.read_text().splitlines()
    torn = lines.index('{"t": "2024-01-01T00:00:00.000Z", "event": "landing_sta')     # on a line of its own
    assert json.loads(lines[torn + 1])['event'] == 'practice_done'


def test_an_event_already_glued_to_a_torn_line_is_read_and_a_torn_tail_is_dropped(tmp_path, caplog):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    fly(s)
    log = tmp_path / 'P01' / 'protocol.log'
    done = json.dumps({'t': '2024-01-01T00:00:01.000Z', 'event': 'practice_done', 'why': 'participant stopped'})
    glued, tail = '{"t": "2024-01-01T00:00:00.000Z", "event": "lan', '{"t": "2024-01-01T00:00:02.000Z", "ev'
    with open(log, 'a') as fh:
        fh.write(glued + done + '\n')            # what an appender that did not start a fresh line left
        fh.write(tail)                            # and a torn last line
    with caplog.at_level('WARNING', logger='assist_station.study'):
        s2 = StudySession(CFG, TEXT, tmp_path, 'P01')
    assert s2.phase == 'block1'
    warned = [r.getMessage() for r in caplog.records]
    assert any(f'skipped {len(glued)} bytes' in m for m in warned) and any(f'dropped {len(tail)} bytes' in m
                                                                           for m in warned)
    text = log.read_text()
    assert text.endswith('\n') and '"ev\n' not in text and '"ev{' not in text
    assert [json.loads(line)['event'] for line in text.splitlines()[-2:]] == ['torn_event_dropped', 'session_opened']


def test_a_saved_row_whose_log_line_fails_is_recorded_and_the_problem_reported(tmp_path, monkeypatch):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')
    s.consent()
    spec = s.start_landing()
    real_log = s.store.log

    def log_fails_for_recorded(event, **data):
        if event in ('landing_recorded', 'practice_done'):
            raise OSError(errno.ENOSPC, 'No space left on device')
        real_log(event, **data)
    monkeypatch.setattr(s.store, 'log', log_fails_for_recorded)
    row = s.record_landing(landing(spec.goal_index), start_pad=None, episode=4, bag=None)
    assert row['trial'] == '0' and s.active is None and s.next_landing().trial == 1
    problem = s.take_log_problem()
    assert 'landing_recorded not written (No space left on device)' in problem
    assert s.take_log_problem() is None
    assert len(rows(tmp_path / 'P01' / 'landings.csv')) == 1


@pytest.mark.parametrize('pid', ['S01\n', 'S01\r', ' S01', 'S01 '])
def test_ids_with_surrounding_whitespace_are_refused(tmp_path, pid):
    with pytest.raises(StudyError, match='participant ID'):
        StudySession(CFG, TEXT, tmp_path, pid)
    assert list(tmp_path.iterdir()) == []


def test_a_symlinked_participant_directory_is_refused(tmp_path):
    root, outside = tmp_path / 'study', tmp_path / 'elsewhere'
    root.mkdir()
    outside.mkdir()
    (root / 'P01').symlink_to(outside)
    with pytest.raises(StudyError, match='symbolic link'):
        StudySession(CFG, TEXT, root, 'P01')
    assert list(outside.iterdir()) == []


@pytest.mark.parametrize('name', ['protocol.log', 'landings.csv', 'survey.json', 'study.yaml', 'bags'])
def test_a_symlinked_file_in_a_participant_directory_is_refused(tmp_path, name):
    root, outside = tmp_path / 'study', tmp_path / 'elsewhere'
    s = StudySession(CFG, TEXT, root, 'P01')
    s.consent()
    fly(s)
    outside.mkdir()
    target = outside / name
    if name == 'bags':
        target.mkdir()
    else:
        target.write_text('outside\n')
    path = root / 'P01' / name
    if path.is_dir():
        path.rmdir()
    elif path.exists():
        path.unlink()
    path.symlink_to(target)
    with pytest.raises(StudyError, match='symbolic link'):
        StudySession(CFG, TEXT, root, 'P01').store.new_bag_path('block1_00')
    if name == 'bags':
        assert list(target.iterdir()) == []
    else:
        assert target.read_text() == 'outside\n'


def test_a_file_replaced_by_a_symlink_while_open_is_not_written_through(tmp_path):
    root, outside = tmp_path / 'study', tmp_path / 'elsewhere.log'
    s = StudySession(CFG, TEXT, root, 'P01')
    outside.write_text('outside\n')
    log = root / 'P01' / 'protocol.log'
    log.unlink()
    log.symlink_to(outside)
    with pytest.raises(StudyError, match='symbolic link'):
        s.consent()
    assert outside.read_text() == 'outside\n' and s.phase == 'consent'
