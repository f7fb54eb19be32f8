"""analyze_study on a three-condition study (unassisted, assisted, assisted_cues): the per-landing measures per
condition and their paired tests recomputed here by hand (plain Python: means, medians, the Wilcoxon signed-rank
statistic and its exact p by enumerating the sign patterns, McNemar's exact binomial p), Table I still unassisted
vs assisted, and what validation refuses: a wrong condition, order or block, an unknown condition, a malformed
measure, another study's participants. Files written before the measure columns are still read."""
import csv
import itertools
import json
import math
import statistics

import numpy as np
import pytest

from assist_station import analyze_study as an
from assist_station.study import (ALL_CONDITIONS, BASE_COLUMNS, LANDING_COLUMNS, SURVEY, condition_order,
                                  order_name)

GOALS = (2, 1, 3, 0)
STUDY_YAML = 'sequence: [2, 1, 3, 0]\npractice_landings: 1\nconditions: [unassisted, assisted, assisted_cues]\n'
PIDS = ('S01', 'S02', 'S03', 'S04')
# per participant and condition: (time to land s, path m, key presses, corrective presses) of the block's middle;
# trial t adds (t - 1.5) x (2 s, 0.4 m, 2 presses) and t - 1 corrective presses to them
BASE = {
    'S01': {'unassisted': (31.0, 14.2, 40, 11), 'assisted': (27.5, 12.1, 33, 7),
            'assisted_cues': (24.0, 11.3, 30, 5)},
    'S02': {'unassisted': (25.0, 12.9, 35, 9), 'assisted': (26.2, 12.0, 31, 8),
            'assisted_cues': (21.1, 10.2, 38, 10)},
    'S03': {'unassisted': (36.0, 16.4, 52, 15), 'assisted': (29.9, 13.6, 41, 12),
            'assisted_cues': (30.7, 14.1, 43, 13)},
    'S04': {'unassisted': (28.0, 9.5, 37, 11), 'assisted': (23.4, 11.7, 29, 6),
            'assisted_cues': (19.5, 9.9, 24, 3)},
}
# outcomes of trials 0..3 per participant and condition
OUTCOMES = {
    'S01': {'unassisted': ('crash', 'wrong_pad', 'success', 'wrong_pad'), 'assisted': ('success', 'success',
            'wrong_pad', 'success'), 'assisted_cues': ('success', 'success', 'success', 'success')},
    'S02': {'unassisted': ('success', 'edge', 'wrong_pad', 'crash'), 'assisted': ('success', 'wrong_pad',
            'success', 'success'), 'assisted_cues': ('success', 'success', 'wrong_pad', 'success')},
    'S03': {'unassisted': ('wrong_pad', 'crash', 'success', 'success'), 'assisted': ('success', 'success',
            'success', 'edge'), 'assisted_cues': ('success', 'edge', 'success', 'success')},
    'S04': {'unassisted': ('wrong_pad', 'success', 'crash', 'wrong_pad'), 'assisted': ('wrong_pad', 'success',
            'success', 'success'), 'assisted_cues': ('success', 'success', 'success', 'success')},
}
EXCLUDED = ('S02', 'assisted', 3)           # ended on the starting platform: left out of every figure


def error_of(pid, cond, t, outcome):
    return round(0.08 + 0.05 * t + 0.03 * PIDS.index(pid) + {'success': 0.0, 'edge': 0.3, 'wrong_pad': 1.9,
                                                               'crash': 0.8}[outcome] + 0.2 * (cond == 'unassisted'), 4)


def landing_rows(pid):
    """(block, condition, trial, row dict) of participant `pid`'s study landings, as the station writes them."""
    order = condition_order(pid, ALL_CONDITIONS)
    out = []
    for block, cond in enumerate(order, start=1):
        base = BASE[pid][cond]
        for t, outcome in enumerate(OUTCOMES[pid][cond]):
            err = error_of(pid, cond, t, outcome)
            out.append((block, cond, t, {
                'participant': pid, 'block': block, 'condition': cond, 'order': order_name(pid, ALL_CONDITIONS),
                'trial': t, 'goal_index': GOALS[t], 'landed_index': GOALS[t] if outcome == 'success' else '',
                'nearest_index': GOALS[t], 'error_m': f'{err:.4f}', 'nearest_error_m': f'{err:.4f}',
                'success': str(outcome == 'success').lower(), 'crash': str(outcome == 'crash').lower(),
                'outcome': outcome, 'duration_s': f'{base[0] + (t - 1.5) * 2:.4f}',
                'started_on_pad': str((pid, cond, t) == EXCLUDED).lower(),
                'assist_live': str(cond != 'unassisted').lower(),
                'path_length_m': f'{base[1] + (t - 1.5) * 0.4:.4f}', 'key_presses': int(base[2] + (t - 1.5) * 2),
                'corrective_keys': base[3] + t - 1}))
    return out


def write_study(root, pids=PIDS, study_yaml=STUDY_YAML, columns=LANDING_COLUMNS, rows_of=landing_rows):
    dirs = []
    for pid in pids:
        d = root / pid
        d.mkdir(parents=True)
        (d / 'study.yaml').write_text(study_yaml)
        order = condition_order(pid, ALL_CONDITIONS)
        with open(d / 'landings.csv', 'w', newline='') as fh:
            w = csv.DictWriter(fh, fieldnames=columns, lineterminator='\n', extrasaction='ignore')
            w.writeheader()
            w.writerow({'participant': pid, 'block': 0, 'condition': order[0], 'order': order_name(pid, ALL_CONDITIONS),
                        'trial': 0, 'goal_index': 4, 'error_m': 9.0, 'nearest_error_m': 9.0, 'success': 'false',
                        'crash': 'true', 'outcome': 'crash', 'started_on_pad': 'false'})    # practice: not counted
            for *_, row in rows_of(pid):
                w.writerow(row)
        survey = {str(q['id']): ([] if q['kind'] == 'multi' else 2) for q in SURVEY}
        sus = {str(b): {'condition': c, 'answers': [3 + (c == 'assisted_cues')] + [3] * 9,
                        'score': 50.0 + 2.5 * (c == 'assisted_cues')} for b, c in enumerate(order, start=1)}
        (d / 'survey.json').write_text(json.dumps({'participant': pid, 'sus': sus, 'survey': survey}))
        dirs.append(d)
    return dirs


def counted():
    """Every analysed landing: (pid, condition, trial, block, row)."""
    return [(pid, c, t, b, r) for pid in PIDS for b, c, t, r in landing_rows(pid) if (pid, c, t) != EXCLUDED]


def exact_wilcoxon(d):
    """(min(W+, W-), two-sided exact p) of paired differences `d` (no zeros, no tied magnitudes)."""
    order = sorted(range(len(d)), key=lambda i: abs(d[i]))
    rank = {i: k + 1 for k, i in enumerate(order)}
    w_plus = sum(rank[i] for i in range(len(d)) if d[i] > 0)
    w_minus = sum(rank[i] for i in range(len(d)) if d[i] < 0)
    stat = min(w_plus, w_minus)
    total = len(d) * (len(d) + 1) // 2
    sums = [sum(k for k, s in zip(range(1, len(d) + 1), signs) if s) for signs in
            itertools.product((0, 1), repeat=len(d))]
    low = sum(1 for s in sums if min(s, total - s) <= stat)
    return stat, min(1.0, low / 2 ** len(d))


def exact_mcnemar(pairs):
    b = sum(x and not y for x, y in pairs)
    c = sum(y and not x for x, y in pairs)
    n = b + c
    return min(b, c), min(1.0, 2 * sum(math.comb(n, k) for k in range(min(b, c) + 1)) / 2 ** n)


@pytest.fixture(scope='module')
def result(tmp_path_factory):
    root = tmp_path_factory.mktemp('cues')
    dirs = write_study(root)
    return root, an.run(dirs, an.AnalyzeArgs(out=str(root / 'out'), plots=True, trajectories=0))


FIELDS = {'time_to_land_s': 'duration_s', 'path_length_m': 'path_length_m', 'key_presses': 'key_presses',
          'corrective_keys': 'corrective_keys'}


def test_per_condition_measures(result):
    _, s = result
    m = s['measures']
    assert m['conditions'] == list(ALL_CONDITIONS)
    assert m['excluded'] == {'unassisted': 0, 'assisted': 1, 'assisted_cues': 0}
    for cond in ALL_CONDITIONS:
        rows = [r for _, c, _, _, r in counted() if c == cond]
        per = m['per_condition'][cond]
        assert per['landings'] == len(rows)
        assert per['success_rate'] == pytest.approx(sum(r['outcome'] == 'success' for r in rows) / len(rows))
        assert per['wrong_pad_rate'] == pytest.approx(sum(r['outcome'] == 'wrong_pad' for r in rows) / len(rows))
        for key, column in FIELDS.items():
            vals = [float(r[column]) for r in rows]
            assert per[key]['mean'] == pytest.approx(sum(vals) / len(vals)), (cond, key)
            assert per[key]['median'] == pytest.approx(statistics.median(vals)), (cond, key)
            assert per[key]['n'] == len(vals)


@pytest.mark.parametrize('a, b', [('unassisted', 'assisted'), ('unassisted', 'assisted_cues'),
                                  ('assisted', 'assisted_cues')])
def test_paired_tests_between_each_pair(result, a, b):
    _, s = result
    t = s['measures']['tests'][f'{a} vs {b}']
    assert t['conditions'] == [a, b]
    for key, column in FIELDS.items():
        means = {}
        for pid in PIDS:
            for c in (a, b):
                vals = [float(r[column]) for p, cc, _, _, r in counted() if p == pid and cc == c]
                means[(pid, c)] = sum(vals) / len(vals)
        d = [means[(pid, a)] - means[(pid, b)] for pid in PIDS]
        stat, p = exact_wilcoxon(d)
        assert t[key]['pairs'] == 4
        assert t[key]['statistic'] == pytest.approx(stat), key
        assert t[key]['p'] == pytest.approx(p), key
        assert t[key]['median_difference'] == pytest.approx(statistics.median(d))
    for rate, hit in (('success', 'success'), ('wrong_pad', 'wrong_pad')):
        index = {(pid, tr, c): r['outcome'] == hit for pid, c, tr, _, r in counted()}
        pairs = [(index[(pid, tr, a)], index[(pid, tr, b)]) for pid in PIDS for tr in range(4)
                 if (pid, tr, a) in index and (pid, tr, b) in index]
        stat, p = exact_mcnemar(pairs)
        assert t[rate]['pairs'] == len(pairs) and t[rate]['exact']
        assert t[rate]['statistic'] == stat and t[rate]['p'] == pytest.approx(p), rate
        assert t[rate]['unpaired'] == sum(1 for k in index if k[2] in (a, b)) - 2 * len(pairs)


def test_table_one_and_the_regression_stay_unassisted_vs_assisted(result):
    _, s = result
    rows = [x for x in counted() if x[1] in ('unassisted', 'assisted')]
    assert s['landings'] == {'unassisted': 16, 'assisted': 15}
    for cond in ('unassisted', 'assisted'):
        errs = [float(r['error_m']) for _, c, _, _, r in rows if c == cond]
        ok = [r['outcome'] == 'success' for _, c, _, _, r in rows if c == cond]
        assert s['table']['specified']['mean_error_m'][cond] == pytest.approx(sum(errs) / len(errs))
        assert s['table']['specified']['success_rate'][cond] == pytest.approx(sum(ok) / len(ok))
    # first half: the earlier of the participant's unassisted and assisted blocks (S03: cues, unassisted, ...)
    first = {pid: 1 + min(condition_order(pid, ALL_CONDITIONS).index(c) for c in ('unassisted', 'assisted'))
             for pid in PIDS}
    assert first == {'S01': 1, 'S02': 1, 'S03': 2, 'S04': 2}
    X = np.array([[1.0, c == 'assisted', b == first[pid]] for pid, c, _, b, _ in rows], dtype=float)
    y = np.array([float(r['error_m']) for *_, r in rows])
    beta = np.linalg.solve(X.T @ X, X.T @ y)      # experienced is constant here (every rating 2): not a term
    assert s['regression']['assisted']['coef'] == pytest.approx(beta[1])
    assert s['regression']['first_half']['coef'] == pytest.approx(beta[2])
    assert s['regression']['experienced']['coef'] is None
    assert set(s['sus']) == set(ALL_CONDITIONS) and s['sus']['assisted_cues']['mean'] == pytest.approx(52.5)
    assert s['per_participant']['S03']['landings_assisted_cues'] == 4


def test_tables_show_every_condition_and_pair(result):
    root, s = result
    text = (root / 'out' / 'table.txt').read_text()
    md = (root / 'out' / 'table.md').read_text()
    assert text.splitlines()[0].endswith('; 16 assisted_cues landings (0 excluded)')
    head = next(line for line in text.splitlines() if line.strip().startswith('unassisted'))
    assert head.split() == list(ALL_CONDITIONS)
    for pair in ('unassisted vs assisted:', 'unassisted vs assisted_cues:', 'assisted vs assisted_cues:'):
        assert sum(line.startswith(pair) for line in text.splitlines()) == 1
        assert f'- {pair}' in md
    assert '|  | unassisted | assisted | assisted_cues |' in md
    assert (root / 'out' / 'violin.png').stat().st_size > 5000


def test_a_two_condition_study_gets_the_measures_of_its_two(tmp_path):
    def two(pid):
        order = condition_order(pid)
        out = []
        for _, c, t, r in landing_rows(pid):
            if c == 'assisted_cues':
                continue
            block = order.index(c) + 1
            out.append((block, c, t, dict(r, block=block, order=order_name(pid))))
        return out
    dirs = write_study(tmp_path, study_yaml='sequence: [2, 1, 3, 0]\npractice_landings: 1\n', rows_of=two)
    for d in dirs:                                  # the two-block study's survey: blocks 1 and 2
        survey = json.loads((d / 'survey.json').read_text())
        order = condition_order(d.name)
        survey['sus'] = {str(b): dict(survey['sus']['1'], condition=c, answers=[3] * 10, score=50.0)
                         for b, c in enumerate(order, start=1)}
        (d / 'survey.json').write_text(json.dumps(survey))
    s = an.run(dirs, an.AnalyzeArgs(out=str(tmp_path / 'out'), plots=False))
    assert s['validation']['rows_excluded_total'] == 0
    assert s['measures']['conditions'] == ['unassisted', 'assisted'] and list(s['measures']['tests']) == [
        'unassisted vs assisted']
    assert set(s['sus']) == {'unassisted', 'assisted'}
    assert 'assisted_cues' not in json.dumps(s)
    assert not (tmp_path / 'out' / 'table.txt').read_text().splitlines()[0].endswith('excluded)')


# ----------------------------------------------------------------------------------------- validation
def rewrite(d, change):
    with open(d / 'landings.csv', newline='') as fh:
        reader = csv.DictReader(fh)
        header, rows = reader.fieldnames, list(reader)
    change(rows)
    with open(d / 'landings.csv', 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=header, lineterminator='\n')
        w.writeheader()
        w.writerows(rows)


def at(rows, block, trial):
    return next(r for r in rows if r['block'] == str(block) and r['trial'] == str(trial))


def analyse(tmp_path, dirs):
    return an.run(dirs, an.AnalyzeArgs(out=str(tmp_path / 'out'), plots=False))


@pytest.mark.parametrize('change, reason', [
    (lambda rows: at(rows, 3, 0).update(condition='assisted'), an.R_CONDITION),          # S01 block 3 is cues
    (lambda rows: at(rows, 3, 1).update(condition='magic'), an.R_CONDITION),
    (lambda rows: at(rows, 2, 2).update(order='unassisted_first'), an.R_CONDITION),       # a two-block order
    (lambda rows: at(rows, 1, 3).update(order='assisted-unassisted-assisted_cues'), an.R_CONDITION),
    (lambda rows: at(rows, 3, 2).update(block='4'), an.R_BLOCK),
    (lambda rows: at(rows, 1, 0).update(path_length_m='twelve'), an.R_VALUE),
    (lambda rows: at(rows, 1, 1).update(path_length_m='-1.0'), an.R_VALUE),
    (lambda rows: at(rows, 2, 0).update(key_presses='3.5'), an.R_VALUE),
    (lambda rows: at(rows, 2, 1).update(corrective_keys='99'), an.R_VALUE),              # more than its presses
    (lambda rows: at(rows, 3, 3).update(assist_live='false'), an.R_LIVE),                # cues fly assisted
])
def test_wrong_condition_order_block_or_measure_is_left_out_with_its_reason(tmp_path, change, reason):
    dirs = write_study(tmp_path / 'data')
    rewrite(dirs[0], change)
    s = analyse(tmp_path, dirs)
    assert s['validation']['rows_excluded'] == {reason: 1}
    assert len(s['validation']['rows_listed']) == 1 and 'S01/landings.csv line' in s['validation']['rows_listed'][0]
    kept = sum(per['landings'] for per in s['measures']['per_condition'].values())
    assert kept == len(counted()) - 1


def test_a_malformed_measure_is_named_in_its_line(tmp_path):
    dirs = write_study(tmp_path / 'data')
    rewrite(dirs[1], lambda rows: at(rows, 1, 2).update(key_presses='many'))
    s = analyse(tmp_path, dirs)
    line, = s['validation']['rows_listed']
    assert "key_presses 'many' (an integer" in line and line.startswith('S02/landings.csv line')


def test_an_unknown_condition_in_a_study_file_and_another_studys_participant_are_left_out(tmp_path):
    dirs = write_study(tmp_path / 'data')
    (dirs[2] / 'study.yaml').write_text(STUDY_YAML.replace('assisted_cues]', 'assisted_hints]'))
    (dirs[3] / 'study.yaml').write_text('sequence: [2, 1, 3, 0]\npractice_landings: 1\n')   # the two-block study
    s = analyse(tmp_path, dirs)
    assert s['participants'] == 2
    bad, other = s['validation']['participants_excluded']
    assert 'conditions items must be one of unassisted, assisted, assisted_cues' in bad and '\n' not in bad
    assert 'conditions differ' in other


def test_sus_of_a_wrong_condition_or_block_is_left_out(tmp_path):
    dirs = write_study(tmp_path / 'data')
    path = dirs[0] / 'survey.json'
    survey = json.loads(path.read_text())
    survey['sus']['3']['condition'] = 'assisted'              # S01 flies assisted_cues in block 3
    survey['sus']['4'] = dict(survey['sus']['2'])
    path.write_text(json.dumps(survey))
    s = analyse(tmp_path, dirs)
    files = s['validation']['files_excluded']
    assert len(files) == 2 and any('S01 flies assisted_cues in block 3' in f for f in files)
    assert any('block 1, 2 or 3 only' in f for f in files)
    assert s['sus']['assisted_cues']['n'] == 3 and s['sus']['assisted']['n'] == 4


def test_files_written_before_the_measure_columns_are_read(tmp_path):
    dirs = write_study(tmp_path / 'data', columns=BASE_COLUMNS)
    s = analyse(tmp_path, dirs)
    assert s['validation']['rows_excluded_total'] == 0
    per = s['measures']['per_condition']['assisted_cues']
    assert per['landings'] == 16 and per['time_to_land_s']['n'] == 16
    assert per['path_length_m'] == {'mean': None, 'median': None, 'n': 0}
    t = s['measures']['tests']['assisted vs assisted_cues']
    assert t['path_length_m']['statistic'] is None and t['path_length_m']['pairs'] == 0
    assert t['time_to_land_s']['pairs'] == 4
