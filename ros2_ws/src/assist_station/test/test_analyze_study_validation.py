"""analyze_study on damaged or contradictory study data: every value is checked against the study file and the
protocol, what fails is left out and said (counts per reason in summary.json and the table), nothing ends in a
traceback, summary.json is strict JSON, outputs never go through a symbolic link; simulate_study's ID prefix."""
import csv
import json
import os
import shutil

import pytest

from assist_station import analyze_study as an
from assist_station import simulate_study as sim
from assist_station.study import LANDING_COLUMNS, SURVEY, StudyConfig, StudyError, StudySession

TEXT = 'sequence: [1, 3, 0, 2]\npractice_landings: 1\n'
CFG = StudyConfig.from_text(TEXT)
PIDS = ('S01', 'S02', 'S03', 'S04')
EXPERIENCE = {'S01': 1, 'S02': 5, 'S03': 2, 'S04': 3}        # answer to questions 2, 3, 5, 6


def landing(pid, spec):
    """A /sim/landing result for one study landing: errors that differ per participant, trial and condition."""
    k = PIDS.index(pid)
    err = round(0.1 + 0.07 * spec.trial + 0.05 * k + (0.6 if spec.condition == 'unassisted' else 0.0), 4)
    ok = err < 0.5
    return {'episode': spec.trial, 'goal_index': spec.goal_index, 'landed_index': spec.goal_index if ok else None,
            'nearest_index': spec.goal_index, 'error_m': err, 'nearest_error_m': err, 'success': ok,
            'crash': not ok, 'outcome': 'success' if ok else 'crash', 'duration_s': 20.0,
            'assisted': spec.condition == 'assisted'}


def make_study(root):
    """Four participants through the station's own protocol core (study.yaml, landings.csv, survey.json)."""
    for pid in PIDS:
        s = StudySession(CFG, TEXT, root, pid)
        s.consent()
        s.stop_practice()
        for sus in ([3, 3, 3, 3, 3, 3, 3, 3, 3, 3], [4, 2, 4, 2, 4, 2, 4, 2, 4, 1]):
            for _ in CFG.sequence:
                spec = s.start_landing()
                s.record_landing(landing(pid, spec), start_pad=None, episode=spec.trial, bag=None)
            s.submit_sus(sus)
        answers = {str(q['id']): ([] if q['kind'] == 'multi' else 1) for q in SURVEY}
        for q in (2, 3, 5, 6):
            answers[str(q)] = EXPERIENCE[pid]
        s.submit_survey(answers)
    return [root / pid for pid in PIDS]


@pytest.fixture(scope='module')
def clean(tmp_path_factory):
    """The undamaged study and its analysis (what a damaged copy must reproduce once the damage is left out)."""
    root = tmp_path_factory.mktemp('clean')
    dirs = make_study(root / 'data')
    return root / 'data', an.run(dirs, an.AnalyzeArgs(out=str(root / 'out'), plots=False))


@pytest.fixture
def data(clean, tmp_path):
    """A fresh copy of the clean study to damage."""
    shutil.copytree(clean[0], tmp_path / 'data')
    return tmp_path / 'data'


def analyse(data, tmp_path, pids=PIDS, **kw):
    return an.run([data / p for p in pids], an.AnalyzeArgs(out=str(tmp_path / 'out'), plots=False, **kw))


def read_rows(d):
    with open(d / 'landings.csv', newline='') as fh:
        return list(csv.DictReader(fh))


def write_rows(d, rows, tail=b''):
    with open(d / 'landings.csv', 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=LANDING_COLUMNS, lineterminator='\n')
        w.writeheader()
        w.writerows(rows)
    with open(d / 'landings.csv', 'ab') as fh:
        fh.write(tail)


def strict(path):
    """summary.json parsed as strict JSON (NaN/Infinity refused)."""
    def refuse(name):
        raise ValueError(f'{name} in {path}')
    return json.loads(path.read_text(), parse_constant=refuse)


def figures(s):
    return {k: s[k] for k in ('participants', 'landings', 'excluded', 'table', 'tests', 'tests_nearest',
                              'regression', 'sus', 'goal_inference')}


def row_index(rows, block, trial):
    return next(i for i, r in enumerate(rows) if r['block'] == str(block) and r['trial'] == str(trial))


# ----------------------------------------------------------------------------------------- wrong numbers
def test_clean_study_leaves_nothing_out(clean):
    _, s = clean
    assert s['landings'] == {'unassisted': 16, 'assisted': 16}
    assert s['validation']['rows_excluded_total'] == 0 and s['validation']['files_excluded'] == []
    assert s['tests']['mcnemar']['pairs'] == 16 and s['tests']['mcnemar']['unpaired'] == 0


def test_duplicated_rows_count_once_and_are_reported(clean, data, tmp_path):
    for pid in PIDS:
        rows = read_rows(data / pid)
        write_rows(data / pid, rows + [rows[3]])           # a study row written twice
    s = analyse(data, tmp_path)
    assert figures(s) == figures(clean[1])                 # 32 landings, not 36
    assert s['validation']['rows_excluded'] == {an.R_DUPLICATE: 4}
    table = (tmp_path / 'out' / 'table.txt').read_text()
    assert f'Left out as invalid: 4 rows (4 {an.R_DUPLICATE})' in table
    assert 'Left out as invalid: 4 rows' in (tmp_path / 'out' / 'table.md').read_text()


def test_two_different_rows_for_one_landing_both_left_out(data, tmp_path):
    rows = read_rows(data / 'S01')
    other = dict(rows[row_index(rows, 1, 2)], error_m='0.0100', nearest_error_m='0.0100')
    write_rows(data / 'S01', rows + [other])
    s = analyse(data, tmp_path)
    assert s['landings'] == {'unassisted': 15, 'assisted': 16}      # S01 flies unassisted in block 1
    assert s['validation']['rows_excluded'] == {an.R_CONFLICT: 2}
    assert s['tests']['mcnemar']['unpaired'] == 1


@pytest.mark.parametrize('value', ['1e300', 'inf', 'nan', '-0.5', '50.5'])
def test_errors_outside_the_arena_are_left_out_and_summary_is_strict_json(clean, data, tmp_path, value):
    rows = read_rows(data / 'S02')
    rows[row_index(rows, 2, 1)]['error_m'] = value
    write_rows(data / 'S02', rows)
    s = analyse(data, tmp_path)
    del rows[row_index(rows, 2, 1)]                          # the same as that row never having been written
    write_rows(data / 'S02', rows)
    without = an.run([data / p for p in PIDS], an.AnalyzeArgs(out=str(tmp_path / 'out2'), plots=False))
    assert figures(s) == figures(without)
    assert s['validation']['rows_excluded'] == {an.R_ERROR: 1}
    strict(tmp_path / 'out' / 'summary.json')
    assert s['table']['specified']['mean_error_m']['unassisted'] < 2.0


def test_arena_bound_is_a_setting(data, tmp_path):
    rows = read_rows(data / 'S02')
    rows[row_index(rows, 2, 1)]['error_m'] = '60.0'
    write_rows(data / 'S02', rows)
    assert analyse(data, tmp_path, max_error_m=100.0)['validation']['rows_excluded_total'] == 0


def test_undefined_statistics_are_null_in_strict_json(tmp_path):
    root = tmp_path / 'data'
    make_study(root)
    for pid in PIDS:                                         # every error the same: Welch's t is 0/0
        rows = read_rows(root / pid)
        for r in rows:
            r.update(error_m='0.2000', nearest_error_m='0.2000', success='true', crash='false', outcome='success',
                     landed_index=r['goal_index'])
        write_rows(root / pid, rows)
    s = analyse(root, tmp_path)
    data = strict(tmp_path / 'out' / 'summary.json')
    assert data['tests']['t']['statistic'] is None and s['tests']['t']['statistic'] is None


def set_survey(d, change):
    path = d / 'survey.json'
    survey = json.loads(path.read_text())
    change(survey)
    path.write_text(json.dumps(survey))


def test_absurd_sus_scores_are_left_out(clean, data, tmp_path):
    set_survey(data / 'S01', lambda s: s['sus']['1'].update(score=1e308))            # answers say 50
    set_survey(data / 'S02', lambda s: s['sus']['2'].pop('answers') and s['sus']['2'].update(score=1e308))
    set_survey(data / 'S03', lambda s: s['sus']['1'].update(answers=[9] * 10))
    s = analyse(data, tmp_path)
    # S01 block 1: unassisted, S02 block 2: unassisted, S03 block 1: unassisted; S04 (block 2: unassisted) stays
    s04 = clean[1]['per_participant']['S04']['sus']['unassisted']
    assert s['sus']['unassisted'] == {'mean': s04, 'percentile': an.sus_percentile(s04), 'n': 1}
    assert s['sus']['assisted'] == clean[1]['sus']['assisted']
    files = s['validation']['files_excluded']
    assert len(files) == 3 and all('sus block' in f for f in files), files
    strict(tmp_path / 'out' / 'summary.json')


def test_sus_labelled_with_the_wrong_condition_is_left_out(data, tmp_path):
    set_survey(data / 'S01', lambda s: s['sus']['1'].update(condition='assisted'))    # S01 flies unassisted first
    s = analyse(data, tmp_path)
    assert s['sus']['assisted']['n'] == 4 and s['sus']['unassisted']['n'] == 3
    assert 'S01 flies unassisted in block 1' in s['validation']['files_excluded'][0]


def test_experience_answers_outside_the_scale_are_left_out(clean, data, tmp_path):
    set_survey(data / 'S02', lambda s: s['survey'].update({'2': 1e9}))
    s = analyse(data, tmp_path)
    assert s['per_participant']['S02']['experience_level'] is None
    assert clean[1]['per_participant']['S02']['experience_level'] is not None
    assert any('question 2' in f for f in s['validation']['files_excluded'])


def test_block_contradicting_the_counterbalanced_order_is_left_out(data, tmp_path):
    rows = read_rows(data / 'S03')                       # S03: odd, unassisted first; its file says otherwise
    for r in rows:
        if r['block'] == '1':
            r['condition'], r['assist_live'] = 'assisted', 'true'
        elif r['block'] == '2':
            r['condition'], r['assist_live'] = 'unassisted', 'false'
    write_rows(data / 'S03', rows)
    s = analyse(data, tmp_path)
    assert s['landings'] == {'unassisted': 12, 'assisted': 12} and s['tests']['mcnemar']['pairs'] == 12
    assert s['validation']['rows_excluded'] == {an.R_CONDITION: 8}


def test_assist_live_contradicting_the_condition_is_left_out(data, tmp_path):
    rows = read_rows(data / 'S04')
    rows[row_index(rows, 1, 0)]['assist_live'] = 'false'         # S04 flies assisted first: the graph did not
    write_rows(data / 'S04', rows)
    s = analyse(data, tmp_path)
    assert s['landings'] == {'unassisted': 16, 'assisted': 15}
    assert s['validation']['rows_excluded'] == {an.R_LIVE: 1}


def test_rows_of_another_participant_and_trials_outside_the_sequence_are_said(data, tmp_path):
    rows = read_rows(data / 'S01')
    rows[row_index(rows, 1, 0)]['participant'] = 'S02'
    rows[row_index(rows, 2, 1)]['trial'] = '99'
    rows[row_index(rows, 2, 2)]['goal_index'] = '4'              # the sequence's trial 2 is pad 0
    write_rows(data / 'S01', rows)
    s = analyse(data, tmp_path)
    assert s['tests']['mcnemar']['pairs'] == 13 and s['tests']['mcnemar']['unpaired'] == 3
    assert s['validation']['rows_excluded'] == {an.R_PARTICIPANT: 1, an.R_TRIAL: 1, an.R_GOAL: 1}
    assert '3 landings without their pair' in (tmp_path / 'out' / 'table.txt').read_text()
    assert any('S01/landings.csv line' in line and "'S02'" in line for line in s['validation']['rows_listed'])


def test_integers_must_be_written_as_the_station_writes_them(data, tmp_path):
    rows = read_rows(data / 'S01')
    rows[row_index(rows, 2, 3)]['trial'] = '0_3'                 # int() would take it as 3
    rows[row_index(rows, 2, 2)]['nearest_index'] = ' 0'
    write_rows(data / 'S01', rows)
    s = analyse(data, tmp_path)
    assert s['validation']['rows_excluded'] == {an.R_TRIAL: 1, an.R_VALUE: 1}


def test_directory_not_named_after_its_participant_is_left_out(data, tmp_path):
    (data / 'S04').rename(data / 'S06')                          # S04's files under S06's name
    s = an.run([data / p for p in ('S01', 'S02', 'S03', 'S06')],
               an.AnalyzeArgs(out=str(tmp_path / 'out'), plots=False))
    assert s['participants'] == 3 and 'S06' not in s['per_participant']
    assert s['validation']['rows_excluded'] == {an.R_PARTICIPANT: 8}
    assert any(line.startswith(str(data / 'S06')) for line in s['validation']['participants_excluded'])


def test_participant_of_another_study_file_is_left_out(data, tmp_path):
    (data / 'S04' / 'study.yaml').write_text('sequence: [4, 4, 4, 4]\npractice_landings: 1\n')
    s = analyse(data, tmp_path)
    assert s['participants'] == 3
    assert 'sequence differ' in s['validation']['participants_excluded'][0]


# ----------------------------------------------------------------------------------------- no tracebacks
@pytest.mark.parametrize('tail', [b'S01,2,assisted,unassisted_first,3,2,,2,0.4', b'S01,2,ass'])
def test_torn_last_row_is_skipped_and_said(clean, data, tmp_path, tail):
    rows = read_rows(data / 'S01')
    write_rows(data / 'S01', rows, tail=tail)
    s = analyse(data, tmp_path)
    assert s['validation']['rows_excluded'] == {an.R_TORN: 1} and figures(s) == figures(clean[1])
    assert 'S01/landings.csv line 10' in s['validation']['rows_listed'][0]


def test_short_row_in_the_middle_is_skipped(clean, data, tmp_path):
    rows = read_rows(data / 'S01')
    write_rows(data / 'S01', rows)
    with open(data / 'S01' / 'landings.csv', 'ab') as fh:
        fh.write(b'S01,2,assisted\n')
    assert analyse(data, tmp_path)['validation']['rows_excluded'] == {an.R_MALFORMED: 1}


def test_non_utf8_row_and_huge_field_are_skipped(clean, data, tmp_path):
    raw = (data / 'S02' / 'landings.csv').read_bytes().split(b'\n')
    raw[4] = raw[4].replace(b'crash', b'cr\xffsh').replace(b'success', b'succ\xffss')
    (data / 'S02' / 'landings.csv').write_bytes(b'\n'.join(raw))
    rows = read_rows(data / 'S03')
    rows[row_index(rows, 1, 1)]['bag'] = 'x' * 200_000
    write_rows(data / 'S03', rows)
    s = analyse(data, tmp_path)
    assert s['validation']['rows_excluded'] == {an.R_ENCODING: 1, an.R_MALFORMED: 1}
    assert s['landings']['unassisted'] + s['landings']['assisted'] == 30
    assert all(len(line) < 300 for line in s['validation']['rows_listed'])


@pytest.mark.parametrize('content, needle', [
    ('[1, 2, 3]', 'a JSON list'),
    ('{"participant": "S02", "sus": [1, 2], "survey": "yes"}', 'sus'),
    ('{"participant": "S02", "sus": {"1": 75}}', 'not an object'),
    ('{"participant": "S02", "sus": {"1": {"condition": "assisted", "score": NaN}}}', 'not JSON'),
    ('{"participant": "S07", "sus": {}}', "participant 'S07'"),
    (b'{"sus": {}, "x": "\xff"}', 'not UTF-8'),
])
def test_survey_of_another_shape_is_left_out(clean, data, tmp_path, content, needle):
    path = data / 'S02' / 'survey.json'
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    s = analyse(data, tmp_path)
    assert needle in s['validation']['files_excluded'][0]
    assert s['landings'] == clean[1]['landings'] and s['sus']['assisted']['n'] == 3


def test_names_from_files_and_directories_cannot_forge_lines(data, tmp_path):
    set_survey(data / 'S02', lambda s: s['survey'].update({'x\nERROR forged\udcff': 1}))
    odd = data / os.fsdecode(b'S\xff\nx')                     # a directory name that is not UTF-8
    shutil.copytree(data / 'S04', odd)
    s = an.run([data / p for p in PIDS] + [odd], an.AnalyzeArgs(out=str(tmp_path / 'out'), plots=False))
    lines = s['validation']['files_excluded'] + s['validation']['participants_excluded']
    assert len(lines) == 2 and all(line.isprintable() for line in lines), lines
    assert '\\n' in lines[0] and 'S\\udcff\\nx' in lines[1]
    assert (tmp_path / 'out' / 'table.txt').read_text().count('\n') == len(an.render_tables(s)[0].splitlines())


def test_cli_goes_on_past_bad_files_and_exits_zero(data, tmp_path, capsys):
    (data / 'S02' / 'survey.json').write_text('[]')
    rows = read_rows(data / 'S01')
    write_rows(data / 'S01', rows, tail=b'S01,2,ass')
    (data / 'S03' / 'landings.csv').write_bytes(b'participant,block\n')              # not the station's columns
    assert an.main([str(data / p) for p in PIDS] + ['--out', str(tmp_path / 'o'), '--plots', 'false']) == 0
    captured = capsys.readouterr()
    assert 'User study: 3 participants' in captured.out
    assert 'Left out: ' + str(data / 'S03') in captured.out
    assert 'Traceback' not in captured.err
    strict(tmp_path / 'o' / 'summary.json')


def test_cli_exits_one_when_nothing_can_be_analysed(data, tmp_path, capsys):
    for pid in PIDS:
        (data / pid / 'landings.csv').write_bytes(b'\xff\xfe not a csv\n')
    assert an.main([str(data / p) for p in PIDS] + ['--out', str(tmp_path / 'o')]) == 1
    err = capsys.readouterr().err
    assert err.startswith('error: nothing to analyse') and err.count('\n') == 1
    assert not (tmp_path / 'o').exists()


# ----------------------------------------------------------------------------------------- output safety
def test_dangling_symlink_in_out_is_refused_before_any_work(clean, tmp_path):
    out = tmp_path / 'out'
    out.mkdir()
    outside = tmp_path / 'outside.md'
    os.symlink(outside, out / 'table.md')
    with pytest.raises(StudyError, match='table.md exist already'):
        an.run([clean[0] / p for p in PIDS], an.AnalyzeArgs(out=str(out), plots=False))
    assert not outside.exists() and sorted(p.name for p in out.iterdir()) == ['table.md']


def test_write_new_never_follows_or_replaces_what_stands(tmp_path):
    outside = tmp_path / 'outside.json'
    os.symlink(outside, tmp_path / 'summary.json')
    with pytest.raises(StudyError, match='not overwriting'):
        an.write_new(tmp_path / 'summary.json', b'{}')
    (tmp_path / 'kept.txt').write_text('results')
    with pytest.raises(StudyError, match='not overwriting'):
        an.write_new(tmp_path / 'kept.txt', b'other')
    an.write_new(tmp_path / 'new.txt', b'new')
    assert not outside.exists() and (tmp_path / 'kept.txt').read_text() == 'results'
    assert (tmp_path / 'new.txt').read_text() == 'new'
    assert (tmp_path / 'new.txt').stat().st_mode == (tmp_path / 'kept.txt').stat().st_mode    # the umask's mode
    assert sorted(p.name for p in tmp_path.iterdir()) == ['kept.txt', 'new.txt', 'summary.json']


@pytest.mark.parametrize('prefix', ['../x', 'a/b', '/tmp/x', '.', 'x y', 'S\n', 'P' * 31])
def test_simulate_study_refuses_an_id_prefix_that_is_no_participant_id(tmp_path, capsys, monkeypatch, prefix):
    def must_not_run(args):
        raise AssertionError('simulate() ran')
    monkeypatch.setattr(sim, 'simulate', must_not_run)
    with pytest.raises(SystemExit) as exit_:
        sim.main(['--out', str(tmp_path / 'o'), '--participants', '2', '--id-prefix', prefix])
    assert exit_.value.code == 2 and '--id-prefix' in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_simulate_refuses_a_path_prefix_before_writing(tmp_path, monkeypatch):
    def no_graph(*args, **kw):
        raise AssertionError('the graph was started')
    monkeypatch.setattr(sim, 'StudyGraph', no_graph)
    with pytest.raises(StudyError, match='participant ID'):
        sim.simulate(sim.SimulateArgs(out=str(tmp_path / 'o'), participants=1, id_prefix='../x'))
    assert list(tmp_path.iterdir()) == []


def test_simulate_study_max_landing_s_is_sim_node_s_episode_timeout(tmp_path, capsys):
    cfg, path = sim.study_file(sim.SimulateArgs(out=str(tmp_path)), tmp_path)
    for given, timeout in ((0.0, 0.0), (20.0, 20.0)):           # 0: the sim's own limit
        args = sim.SimulateArgs(out=str(tmp_path), max_landing_s=given)
        assert sim.graph_params(cfg, args, path, tmp_path, 8080)['sim_node']['episode_timeout_s'] == timeout
    with pytest.raises(SystemExit) as exit_:
        sim.main(['--out', str(tmp_path / 'o'), '--max-landing-s', '-1'])
    assert exit_.value.code == 2 and '--max-landing-s' in capsys.readouterr().err
