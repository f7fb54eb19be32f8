"""analyze_study on a small fixed data set, every figure recomputed here by hand (numpy, math; not the tool's code)."""
import csv
import json
import math

import numpy as np
import pytest
from scipy import stats

from assist_station import analyze_study as an
from assist_station.study import LANDING_COLUMNS, SURVEY

# (participant, first condition, experience answers for questions 2, 3, 5, 6, SUS unassisted, SUS assisted)
PEOPLE = (('P01', 'unassisted', (1, 2, 1, 1), 40.0, 70.0),
          ('P02', 'assisted', (5, 4, 5, 5), 60.0, 80.0),
          ('P03', 'unassisted', (2, 2, 3, 2), 50.0, 75.0))
# per participant and condition: (error_m, nearest_error_m, outcome, nearest_index) of trials 0..3
DATA = {
    ('P01', 'unassisted'): [(1.8, 0.6, 'crash', 1), (0.9, 0.2, 'wrong_pad', 1), (2.5, 1.1, 'crash', 3),
                            (0.3, 0.3, 'success', 0)],
    ('P01', 'assisted'): [(0.1, 0.1, 'success', 2), (0.2, 0.2, 'success', 1), (3.9, 0.1, 'wrong_pad', 4),
                          (0.15, 0.15, 'success', 0)],
    ('P02', 'unassisted'): [(0.4, 0.4, 'success', 2), (0.5, 0.5, 'edge', 1), (0.35, 0.35, 'success', 3),
                            (1.2, 0.7, 'crash', 1)],
    ('P02', 'assisted'): [(0.05, 0.05, 'success', 2), (0.12, 0.12, 'success', 1), (0.08, 0.08, 'success', 3),
                          (4.1, 0.2, 'wrong_pad', 1)],
    ('P03', 'unassisted'): [(1.5, 0.9, 'crash', 2), (0.7, 0.7, 'edge', 4), (1.9, 0.4, 'wrong_pad', 2),
                            (0.6, 0.6, 'crash', 0)],
    ('P03', 'assisted'): [(0.2, 0.2, 'success', 2), (0.1, 0.1, 'success', 1), (0.3, 0.3, 'success', 3),
                          (0.25, 0.25, 'success', 0)],
}
GOALS = (2, 1, 3, 0)
STUDY_YAML = 'sequence: [2, 1, 3, 0]\npractice_landings: 1\n'      # the study file as run, in each directory
EXCLUDED = ('P03', 'unassisted', 3)        # ended on the starting platform


def write_participants(root):
    dirs = []
    for pid, first, exp, sus_un, sus_as in PEOPLE:
        d = root / pid
        d.mkdir()
        (d / 'study.yaml').write_text(STUDY_YAML)
        second = 'assisted' if first == 'unassisted' else 'unassisted'
        with open(d / 'landings.csv', 'w', newline='') as fh:
            w = csv.DictWriter(fh, fieldnames=LANDING_COLUMNS, lineterminator='\n')
            w.writeheader()
            w.writerow({'participant': pid, 'block': 0, 'condition': first, 'order': f'{first}_first', 'trial': 0,
                        'goal_index': 1, 'error_m': 9.0, 'nearest_error_m': 9.0, 'success': 'false',
                        'crash': 'true', 'outcome': 'crash', 'started_on_pad': 'false'})       # practice: not counted
            for block, cond in ((1, first), (2, second)):
                for t, (err, nerr, outcome, nearest) in enumerate(DATA[(pid, cond)]):
                    w.writerow({'participant': pid, 'block': block, 'condition': cond, 'order': f'{first}_first',
                                'trial': t, 'goal_index': GOALS[t], 'nearest_index': nearest,
                                'landed_index': GOALS[t] if outcome == 'success' else '', 'error_m': err,
                                'nearest_error_m': nerr, 'success': str(outcome == 'success').lower(),
                                'crash': str(outcome == 'crash').lower(), 'outcome': outcome,
                                'started_on_pad': str((pid, cond, t) == EXCLUDED).lower()})
        survey = {str(q['id']): ([] if q['kind'] == 'multi' else 1) for q in SURVEY}
        for q, a in zip((2, 3, 5, 6), exp):
            survey[str(q)] = a
        (d / 'survey.json').write_text(json.dumps({
            'participant': pid, 'survey': survey,
            'sus': {'1': {'condition': first, 'score': sus_un if first == 'unassisted' else sus_as},
                    '2': {'condition': second, 'score': sus_as if first == 'unassisted' else sus_un}}}))
        dirs.append(d)
    return dirs


def landings():
    """Every counted landing as (pid, cond, trial, block, error, nearest error, outcome, nearest index)."""
    out = []
    for pid, first, *_ in PEOPLE:
        for cond in ('unassisted', 'assisted'):
            block = 1 if cond == first else 2
            for t, (err, nerr, outcome, nearest) in enumerate(DATA[(pid, cond)]):
                if (pid, cond, t) != EXCLUDED:
                    out.append((pid, cond, t, block, err, nerr, outcome, nearest))
    return out


@pytest.fixture(scope='module')
def result(tmp_path_factory):
    root = tmp_path_factory.mktemp('study')
    dirs = write_participants(root)
    summary = an.run(dirs, an.AnalyzeArgs(out=str(root / 'out'), plots=True, trajectories=0))
    return root, summary


def test_table_one_and_exclusions(result):
    _, s = result
    assert s['participants'] == 3 and s['excluded'] == {'unassisted': 1, 'assisted': 0}
    rows = landings()
    for cond in ('unassisted', 'assisted'):
        err = np.array([r[4] for r in rows if r[1] == cond])
        nerr = np.array([r[5] for r in rows if r[1] == cond])
        ok = [r[6] == 'success' for r in rows if r[1] == cond]
        near_ok = [r[6] in ('success', 'wrong_pad') for r in rows if r[1] == cond]
        spec, near = s['table']['specified'], s['table']['nearest']
        assert spec['success_rate'][cond] == pytest.approx(sum(ok) / len(ok))
        srt, n = sorted(err), len(err)
        median = srt[n // 2] if n % 2 else (srt[n // 2 - 1] + srt[n // 2]) / 2
        assert spec['median_error_m'][cond] == pytest.approx(median)
        assert spec['mean_error_m'][cond] == pytest.approx(err.sum() / len(err))
        assert spec['variance_m2'][cond] == pytest.approx(((err - err.mean()) ** 2).sum() / (len(err) - 1))
        assert near['success_rate'][cond] == pytest.approx(sum(near_ok) / len(near_ok))
        assert near['mean_error_m'][cond] == pytest.approx(nerr.mean())
    assert s['landings'] == {'unassisted': 11, 'assisted': 12}


def test_mcnemar_exact_on_pairs_by_participant_and_trial(result):
    _, s = result
    by = {(r[0], r[1], r[2]): r[6] == 'success' for r in landings()}
    pairs = [(by[(p, 'unassisted', t)], by[(p, 'assisted', t)]) for (p, c, t) in by
             if c == 'unassisted' and (p, 'assisted', t) in by]
    b = sum(u and not a for u, a in pairs)
    c = sum(a and not u for u, a in pairs)
    n = b + c
    p = min(1.0, 2 * sum(math.comb(n, k) for k in range(min(b, c) + 1)) / 2 ** n)
    m = s['tests']['mcnemar']
    assert m['pairs'] == 11 and m['exact'] and m['statistic'] == min(b, c)
    assert m['p'] == pytest.approx(p)


def test_mood_median_t_and_f_tests(result):
    _, s = result
    un = np.array([r[4] for r in landings() if r[1] == 'unassisted'])
    asd = np.array([r[4] for r in landings() if r[1] == 'assisted'])
    grand = np.median(np.concatenate([un, asd]))
    table = np.array([[np.sum(un > grand), np.sum(asd > grand)], [np.sum(un <= grand), np.sum(asd <= grand)]])
    expected = table.sum(1, keepdims=True) * table.sum(0, keepdims=True) / table.sum()
    chi2 = (((np.abs(table - expected) - 0.5) ** 2) / expected).sum()          # Yates
    assert s['tests']['mood_median']['statistic'] == pytest.approx(chi2)
    assert s['tests']['mood_median']['p'] == pytest.approx(math.erfc(math.sqrt(chi2 / 2)))
    v1, v2 = un.var(ddof=1) / len(un), asd.var(ddof=1) / len(asd)
    t = (un.mean() - asd.mean()) / math.sqrt(v1 + v2)
    dof = (v1 + v2) ** 2 / (v1 ** 2 / (len(un) - 1) + v2 ** 2 / (len(asd) - 1))
    assert s['tests']['t']['statistic'] == pytest.approx(t)
    assert s['tests']['t']['p'] == pytest.approx(2 * stats.t.sf(abs(t), dof))
    f = un.var(ddof=1) / asd.var(ddof=1)
    assert s['tests']['f']['statistic'] == pytest.approx(f)
    one_sided = stats.f.sf(f, len(un) - 1, len(asd) - 1) if f > 1 else stats.f.cdf(f, len(un) - 1, len(asd) - 1)
    assert s['tests']['f']['p'] == pytest.approx(2 * one_sided)


def test_regression_coefficients_and_p_values(result):
    _, s = result
    assert s['experienced'] == {'threshold_mean_rating': 4.75, 'n': 1, 'participants': ['P02']}
    rows = landings()
    X = np.array([[1, r[1] == 'assisted', r[3] == 1, r[0] == 'P02'] for r in rows], dtype=float)
    y = np.array([r[4] for r in rows])
    beta = np.linalg.solve(X.T @ X, X.T @ y)
    resid = y - X @ beta
    dof = len(y) - X.shape[1]
    se = np.sqrt(np.diag(resid @ resid / dof * np.linalg.inv(X.T @ X)))
    for i, name in enumerate(('assisted', 'first_half', 'experienced'), start=1):
        assert s['regression'][name]['coef'] == pytest.approx(beta[i])
        assert s['regression'][name]['p'] == pytest.approx(2 * stats.t.sf(abs(beta[i] / se[i]), dof))


def test_sus_percentiles_reproduce_the_papers(result):
    _, s = result
    assert s['sus']['unassisted']['mean'] == pytest.approx(50.0)
    assert s['sus']['assisted']['mean'] == pytest.approx(75.0)
    assert an.sus_percentile(68.0) == pytest.approx(50.0)
    assert abs(an.sus_percentile(60.91) - 32) <= 1.5       # the paper: 60.91 -> 32nd percentile
    assert abs(an.sus_percentile(73.41) - 68) <= 1.5       # 73.41 -> 68th
    assert s['sus']['assisted']['percentile'] == pytest.approx(an.sus_percentile(75.0))


def test_goal_inference_and_experience_fits(result):
    _, s = result
    assisted = [r for r in landings() if r[1] == 'assisted']
    inferred = [r for r in assisted if r[7] == GOALS[r[2]]]
    assert s['goal_inference']['rate'] == pytest.approx(len(inferred) / len(assisted))
    assert s['goal_inference']['success_given_inferred'] == pytest.approx(
        sum(r[6] == 'success' for r in inferred) / len(inferred))
    levels = {pid: (np.mean(e) - 1) / 4 for pid, _, e, *_ in PEOPLE}     # 3 participants: the mean-rating fallback
    assert 'mean rating' in s['experience_level']['method']
    for cond in ('unassisted', 'assisted'):
        x = np.array([levels[p] for p, *_ in PEOPLE])
        y = np.array([np.median([r[4] for r in landings() if r[0] == p and r[1] == cond]) for p, *_ in PEOPLE])
        slope = np.polyfit(x, y, 1)[0]
        assert s['experience_level']['fits'][cond]['slope'] == pytest.approx(slope)


def test_outputs_and_summary_shape(result):
    root, s = result
    out = root / 'out'
    data = json.loads((out / 'summary.json').read_text())
    assert set(data['table']) == {'specified', 'nearest'}
    for kind in ('specified', 'nearest'):
        assert set(data['table'][kind]) == {'success_rate', 'median_error_m', 'mean_error_m', 'variance_m2'}
    assert set(data['tests']) >= {'mcnemar', 'mood_median', 't', 'f'}
    assert all(set(data['regression'][k]) >= {'coef', 'p'} for k in ('assisted', 'first_half', 'experienced'))
    assert set(data['sus']['assisted']) >= {'mean', 'percentile'}
    assert (out / 'violin.png').stat().st_size > 5000 and (out / 'experience.png').stat().st_size > 5000
    md = (out / 'table.md').read_text()
    assert '| Success rate |' in md and 'McNemar' in md
    with pytest.raises(an.StudyError, match='not overwriting'):
        an.run([root / 'P01'], an.AnalyzeArgs(out=str(out)))


def test_experienced_is_the_third_closest_to_a_third_with_ties():
    r = {f'P{i}': np.full(4, v) for i, v in enumerate((5, 4, 4, 4, 3, 3, 2, 2, 1, 1, 1, 1))}
    chosen, threshold = an.experienced_set(r)
    assert threshold == 4 and len(chosen) == 4            # 4 of 12 (>= 5 alone: 1; >= 3: 6)
    assert an._ordinal(22.4) == '22nd' and an._ordinal(31) == '31st' and an._ordinal(13) == '13th'


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert an.main([str(tmp_path), '--out', str(tmp_path / 'o')]) == 1
    assert 'nothing to analyse' in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        an.main([str(tmp_path), '--trajectories', '-1'])
    assert exit_.value.code == 2
