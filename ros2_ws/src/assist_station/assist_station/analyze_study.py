"""analyze_study: the paper's user-study analysis (Table I, tests, regressions, SUS, Figs. 6-8) of participant dirs.

    analyze_study study_data/* --out study_analysis
    analyze_study study_sim/S01 study_sim/S02 --out /tmp/a --trajectories 4

Reads each participant directory the station (or simulate_study) wrote: landings.csv, survey.json and
bags/. Landings of the two blocks count (practice does not); a landing that ended on the pad the
vehicle started above (``started_on_pad``, the paper's "immediately landing on the starting
platform") is excluded and counted per condition.

* Table I, specified and nearest platform: success rate (specified: all legs on the goal pad;
  nearest: all legs on any pad, i.e. the pad nearest to where it landed), median and mean error, and
  variance (sample variance, m^2) of the horizontal error to the goal pad's centre (nearest: to the
  nearest pad's centre), unassisted vs assisted.
* Two-sample tests at the 99 % level (statistic and p for each; * in the table where p < 0.01):
  McNemar on success, paired by participant and trial (statsmodels; exact binomial when fewer than 25
  discordant pairs), Mood's median test (scipy), Welch's t-test on the mean (scipy), and the F-test
  of equal variances (variance ratio against scipy's F distribution, two-sided).
* The multivariable regression (statsmodels OLS) of a landing's error on three binary variables:
  assisted, first half (block 1) and experienced (a participant's mean self-rating on experience
  questions 2, 3, 5 and 6 at or above the threshold that makes a third of the participants
  experienced): coefficients and p-values.
* The experience level of the paper's Fig. 8: a linear regression (statsmodels OLS) of each
  participant's mean unassisted error on their answers to questions 2, 3, 5 and 6 predicts the error
  expected for that experience; the prediction scaled to 0..1 and inverted is the experience level
  (0 novice, 1 expert). With fewer participants than the regression has terms plus two, the mean
  rating scaled to 0..1 stands in (said in summary.json). Each condition's per-participant median
  error is then fitted against it (one line per condition, slope reported).
* SUS: mean score per condition and its percentile on the Sauro-Lewis curved grading scale (linear
  between the grade boundaries; 68 is the 50th percentile).
* Goal inference (assisted landings): the share that ended nearest to the goal pad, and the share
  of those that succeeded (the paper: 79.34 % and 93.34 %).

Writes OUT/summary.json, OUT/table.txt, OUT/table.md, OUT/violin.png (Fig. 6), OUT/experience.png
(Fig. 8) and OUT/trajectories.png (Fig. 7: chosen landings' /odom tracks from their bags, both
conditions of the same trials). Existing outputs in OUT are never overwritten (the tool refuses).
"""
from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from assist_common.frames import heading, rotate_xy
from assist_policy.cli import add_dataclass_args, parse_dataclass_args, setting

from .study import CONDITIONS, EXPERIENCE_QUESTIONS, LANDING_COLUMNS, StudyError

log = logging.getLogger('analyze_study')
ALPHA = 0.01
OUTPUTS = ('summary.json', 'table.txt', 'table.md', 'violin.png', 'experience.png', 'trajectories.png')
# Sauro & Lewis curved grading scale: (SUS score, percentile rank) at the grade boundaries, F .. A+
SUS_PERCENTILES = ((0.0, 0.0), (51.6, 14.0), (51.7, 15.0), (62.6, 34.0), (62.7, 35.0), (64.9, 40.0), (65.0, 41.0),
                   (71.0, 59.0), (71.1, 60.0), (72.5, 64.0), (72.6, 65.0), (74.0, 69.0), (74.1, 70.0), (77.1, 79.0),
                   (77.2, 80.0), (78.8, 84.0), (78.9, 85.0), (80.7, 89.0), (80.8, 90.0), (84.0, 95.0), (84.1, 96.0),
                   (100.0, 100.0))
JUMP_M = 1.0          # an /odom step longer than this between two messages is a reset (teleport)
COLORS = {'unassisted': '#1f77b4', 'assisted': '#2ca02c'}


@dataclass
class AnalyzeArgs:
    """Command-line arguments of analyze_study (besides the participant directories)."""

    out: str = setting('study_analysis', nonempty=True)
    trajectories: int = setting(3, ge=0, le=50)
    plots: bool = True


HELP = {'out': 'directory for summary.json, the tables and the figures (created; existing outputs are refused)',
        'trajectories': 'participants whose landings Fig. 7 draws (both conditions of one trial each; 0: no figure)',
        'plots': 'draw the figures'}


# ----------------------------------------------------------------------------------------- loading
def _bool(text: str) -> bool | None:
    return {'true': True, 'false': False}.get(text.strip().lower())


def _float(text: str) -> float | None:
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _int(text: str) -> int | None:
    try:
        return int(text)
    except (TypeError, ValueError):
        return None


@dataclass
class Participant:
    """One participant's landings (study blocks only) and answers."""

    pid: str
    dir: Path
    rows: list[dict[str, Any]]
    sus: dict[str, float]                 # condition -> score
    survey: dict[str, Any] | None


def load_participant(path: Path) -> Participant:
    """Read a participant directory; StudyError (one line) when it is not one."""
    lpath = path / 'landings.csv'
    if not lpath.is_file():
        raise StudyError(f'{path}: no landings.csv (not a participant directory)')
    with open(lpath, encoding='utf-8', newline='') as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or not set(LANDING_COLUMNS) <= set(reader.fieldnames):
            raise StudyError(f'{lpath}: missing columns {sorted(set(LANDING_COLUMNS) - set(reader.fieldnames or []))}')
        raw = list(reader)
    rows, pid = [], None
    for i, r in enumerate(raw, start=2):
        block = _int(r['block'])
        if block not in (1, 2):
            continue
        err, nerr = _float(r['error_m']), _float(r['nearest_error_m'])
        success, trial = _bool(r['success']), _int(r['trial'])
        if r['condition'] not in CONDITIONS or err is None or success is None or trial is None:
            log.warning('%s line %d: unusable row skipped', lpath, i)
            continue
        pid = pid or r['participant']
        rows.append({'pid': r['participant'], 'block': block, 'condition': r['condition'], 'trial': trial,
                     'goal_index': _int(r['goal_index']), 'landed_index': _int(r['landed_index']),
                     'nearest_index': _int(r['nearest_index']), 'error_m': err,
                     'nearest_error_m': nerr if nerr is not None else err, 'success': success,
                     'crash': bool(_bool(r['crash'])), 'outcome': r['outcome'],
                     'started_on_pad': bool(_bool(r['started_on_pad'])), 'bag': r.get('bag') or ''})
    sus: dict[str, float] = {}
    survey = None
    spath = path / 'survey.json'
    if spath.is_file():
        try:
            data = json.loads(spath.read_text(encoding='utf-8'))
        except ValueError as exc:
            raise StudyError(f'{spath}: not JSON ({exc})') from None
        for entry in (data.get('sus') or {}).values():
            ok = isinstance(entry, dict) and entry.get('condition') in CONDITIONS
            if ok and _float(entry.get('score')) is not None:
                sus[entry['condition']] = float(entry['score'])
        survey = data.get('survey') if isinstance(data.get('survey'), dict) else None
    return Participant(pid or path.name, path, rows, sus, survey)


# ----------------------------------------------------------------------------------------- statistics
def sus_percentile(score: float) -> float:
    """Percentile rank of a SUS score (Sauro-Lewis curved grading scale, linear between boundaries)."""
    xs, ys = zip(*SUS_PERCENTILES)
    return float(np.interp(score, xs, ys))


def describe(errors: np.ndarray, success: np.ndarray) -> dict[str, float | None]:
    """Success rate, median, mean and sample variance of one condition's landings."""
    if errors.size == 0:
        return {'success_rate': None, 'median_error_m': None, 'mean_error_m': None, 'variance_m2': None}
    return {'success_rate': float(np.mean(success)), 'median_error_m': float(np.median(errors)),
            'mean_error_m': float(np.mean(errors)),
            'variance_m2': float(np.var(errors, ddof=1)) if errors.size > 1 else None}


def mcnemar_test(pairs: list[tuple[bool, bool]]) -> dict[str, float | None]:
    """McNemar's test on paired successes (unassisted, assisted): exact binomial below 25 discordant pairs."""
    from statsmodels.stats.contingency_tables import mcnemar
    if not pairs:
        return {'statistic': None, 'p': None, 'pairs': 0}
    a = np.array(pairs, dtype=bool)
    table = [[int(np.sum(a[:, 0] & a[:, 1])), int(np.sum(a[:, 0] & ~a[:, 1]))],
             [int(np.sum(~a[:, 0] & a[:, 1])), int(np.sum(~a[:, 0] & ~a[:, 1]))]]
    discordant = table[0][1] + table[1][0]
    exact = discordant < 25
    res = mcnemar(table, exact=exact, correction=True)
    return {'statistic': float(res.statistic), 'p': float(res.pvalue), 'pairs': len(pairs),
            'discordant': discordant, 'exact': exact, 'table': table}


def two_sample_tests(un: np.ndarray, asd: np.ndarray) -> dict[str, dict[str, float | None]]:
    """Mood's median test, Welch's t-test and the two-sided F-test of equal variances."""
    from scipy import stats
    none = {'statistic': None, 'p': None}
    out = {'mood_median': dict(none), 't': dict(none), 'f': dict(none)}
    if un.size < 2 or asd.size < 2:
        return out
    try:
        stat, p, _, _ = stats.median_test(un, asd)
        out['mood_median'] = {'statistic': float(stat), 'p': float(p)}
    except ValueError as exc:            # every value on one side of the grand median
        log.warning("Mood's median test not defined here: %s", exc)
    t = stats.ttest_ind(un, asd, equal_var=False)
    out['t'] = {'statistic': float(t.statistic), 'p': float(t.pvalue)}
    v_un, v_as = np.var(un, ddof=1), np.var(asd, ddof=1)
    if v_as > 0 and v_un > 0:
        f = v_un / v_as
        d1, d2 = un.size - 1, asd.size - 1
        p = 2.0 * min(stats.f.cdf(f, d1, d2), stats.f.sf(f, d1, d2))
        out['f'] = {'statistic': float(f), 'p': float(min(1.0, p))}
    return out


def experience_ratings(parts: list[Participant]) -> dict[str, np.ndarray]:
    """Each participant's answers to the experience questions (2, 3, 5, 6), for those who answered."""
    out = {}
    for p in parts:
        if p.survey is None:
            continue
        vals = [_float(p.survey.get(str(q))) for q in EXPERIENCE_QUESTIONS]
        if all(v is not None for v in vals):
            out[p.pid] = np.array(vals, dtype=float)
    return out


def experienced_set(ratings: dict[str, np.ndarray]) -> tuple[set[str], float | None]:
    """Participants rated experienced: mean rating at or above the threshold that makes the number experienced
    closest to a third (ratings tie, so it is rarely exactly a third)."""
    if not ratings:
        return set(), None
    means = {pid: float(np.mean(r)) for pid, r in ratings.items()}
    target = len(means) / 3.0            # ratings tie: the threshold whose count comes closest to a third

    def miss(c: float) -> tuple[float, float]:
        return abs(sum(m >= c for m in means.values()) - target), -c
    threshold = min(set(means.values()), key=miss)
    return {pid for pid, m in means.items() if m >= threshold}, threshold


def regression(rows: list[dict], experienced: set[str]) -> dict[str, dict[str, float | None]]:
    """OLS of error_m on assisted, first_half and experienced (binary); coefficient and p-value of each."""
    import pandas as pd
    import statsmodels.formula.api as smf
    df = pd.DataFrame({'error_m': [r['error_m'] for r in rows],
                       'assisted': [int(r['condition'] == 'assisted') for r in rows],
                       'first_half': [int(r['block'] == 1) for r in rows],
                       'experienced': [int(r['pid'] in experienced) for r in rows]})
    out: dict[str, dict[str, float | None]] = {}
    terms = [t for t in ('assisted', 'first_half', 'experienced') if df[t].nunique() > 1]
    design = np.column_stack([np.ones(len(df))] + [df[t].to_numpy(float) for t in terms]) if terms else None
    if not terms or len(df) <= len(terms) + 1 or np.linalg.matrix_rank(design) < design.shape[1]:
        why = 'too few landings, or the variables are collinear in these data (e.g. one order only)'
        return {t: {'coef': None, 'p': None, 'note': why} for t in ('assisted', 'first_half', 'experienced')}
    fit = smf.ols('error_m ~ ' + ' + '.join(terms), data=df).fit()
    for t in ('assisted', 'first_half', 'experienced'):
        out[t] = ({'coef': float(fit.params[t]), 'p': float(fit.pvalues[t])} if t in terms
                  else {'coef': None, 'p': None, 'note': 'constant in these data'})
    out['intercept'] = {'coef': float(fit.params['Intercept']), 'p': float(fit.pvalues['Intercept'])}
    out['n'] = {'coef': float(len(df)), 'p': None}
    return out


def experience_levels(parts: list[Participant], ratings: dict[str, np.ndarray]) -> tuple[dict[str, float], str]:
    """Fig. 8's experience level per participant (0 novice .. 1 expert) and how it was obtained."""
    import statsmodels.api as sm
    pids = [p.pid for p in parts if p.pid in ratings]
    mean_err = {}
    for p in parts:
        errs = [r['error_m'] for r in p.rows if r['condition'] == 'unassisted' and not r['started_on_pad']]
        if p.pid in ratings and errs:
            mean_err[p.pid] = float(np.mean(errs))
    pids = [pid for pid in pids if pid in mean_err]
    if not pids:
        return {}, 'no participant with both survey answers and unassisted landings'
    X = np.array([ratings[pid] for pid in pids])
    y = np.array([mean_err[pid] for pid in pids])
    if len(pids) >= X.shape[1] + 3:
        fit = sm.OLS(y, sm.add_constant(X, has_constant='add')).fit()
        pred = fit.predict(sm.add_constant(X, has_constant='add'))
        span = pred.max() - pred.min()
        level = 1.0 - (pred - pred.min()) / span if span > 0 else np.full(len(pids), 0.5)
        how = 'regression of mean unassisted error on questions 2, 3, 5, 6 (prediction scaled to 0..1, inverted)'
    else:
        m = X.mean(axis=1)
        level = (m - 1.0) / 4.0
        how = 'mean rating of questions 2, 3, 5, 6 scaled to 0..1 (too few participants for the regression)'
    return {pid: float(v) for pid, v in zip(pids, level)}, how


def line_fit(x: np.ndarray, y: np.ndarray) -> dict[str, float | None]:
    """Least-squares line y = intercept + slope x (statsmodels OLS)."""
    import statsmodels.api as sm
    if x.size < 2 or np.ptp(x) == 0:
        return {'slope': None, 'intercept': None}
    fit = sm.OLS(y, sm.add_constant(x, has_constant='add')).fit()
    return {'slope': float(fit.params[1]), 'intercept': float(fit.params[0]),
            'p': float(fit.pvalues[1]) if x.size > 2 else None}


# ----------------------------------------------------------------------------------------- analysis
def analyze(parts: list[Participant]) -> dict[str, Any]:
    """Every figure of the paper's study analysis as summary.json's dictionary."""
    rows_all = [r for p in parts for r in p.rows]
    excluded = {c: sum(1 for r in rows_all if r['condition'] == c and r['started_on_pad']) for c in CONDITIONS}
    rows = [r for r in rows_all if not r['started_on_pad']]
    by = {c: [r for r in rows if r['condition'] == c] for c in CONDITIONS}
    table: dict[str, dict[str, dict[str, float | None]]] = {}
    nearest_ok = {'success', 'wrong_pad'}
    for kind in ('specified', 'nearest'):
        stats = {}
        for c in CONDITIONS:
            err = np.array([r['error_m' if kind == 'specified' else 'nearest_error_m'] for r in by[c]], dtype=float)
            ok = np.array([r['success'] if kind == 'specified' else r['outcome'] in nearest_ok for r in by[c]],
                          dtype=bool)
            stats[c] = describe(err, ok)
        table[kind] = {m: {c: stats[c][m] for c in CONDITIONS} for m in stats[CONDITIONS[0]]}
    tests: dict[str, dict[str, Any]] = {}
    tests_nearest: dict[str, dict[str, Any]] = {}
    for kind, dest in (('specified', tests), ('nearest', tests_nearest)):
        key = 'error_m' if kind == 'specified' else 'nearest_error_m'
        succ = (lambda r: r['success']) if kind == 'specified' else (lambda r: r['outcome'] in nearest_ok)
        index = {(r['pid'], r['trial'], r['condition']): succ(r) for r in rows}
        pairs = [(index[(pid, t, 'unassisted')], index[(pid, t, 'assisted')])
                 for (pid, t, c) in index if c == 'unassisted' and (pid, t, 'assisted') in index]
        dest['mcnemar'] = mcnemar_test(pairs)
        dest.update(two_sample_tests(np.array([r[key] for r in by['unassisted']], dtype=float),
                                     np.array([r[key] for r in by['assisted']], dtype=float)))
    ratings = experience_ratings(parts)
    experienced, threshold = experienced_set(ratings)
    reg = regression(rows, experienced)
    levels, how = experience_levels(parts, ratings)
    per_participant = {}
    for p in parts:
        entry: dict[str, Any] = {'experience_level': levels.get(p.pid), 'experienced': p.pid in experienced}
        for c in CONDITIONS:
            errs = [r['error_m'] for r in p.rows if r['condition'] == c and not r['started_on_pad']]
            entry[f'median_error_m_{c}'] = float(np.median(errs)) if errs else None
            entry[f'landings_{c}'] = len(errs)
        entry['sus'] = p.sus
        per_participant[p.pid] = entry
    fig8 = {}
    for c in CONDITIONS:
        pts = [(v['experience_level'], v[f'median_error_m_{c}']) for v in per_participant.values()
               if v['experience_level'] is not None and v[f'median_error_m_{c}'] is not None]
        x, y = (np.array([a for a, _ in pts]), np.array([b for _, b in pts])) if pts else (np.zeros(0), np.zeros(0))
        fig8[c] = line_fit(x, y)
    sus = {}
    for c in CONDITIONS:
        scores = [p.sus[c] for p in parts if c in p.sus]
        mean = float(np.mean(scores)) if scores else None
        sus[c] = {'mean': mean, 'percentile': None if mean is None else sus_percentile(mean), 'n': len(scores)}
    assisted = by['assisted']
    inferred = [r for r in assisted if r['nearest_index'] is not None and r['nearest_index'] == r['goal_index']]
    goal_inference = {'rate': len(inferred) / len(assisted) if assisted else None,
                      'success_given_inferred': (sum(r['success'] for r in inferred) / len(inferred)
                                                 if inferred else None),
                      'landings': len(assisted)}
    return {'participants': len(parts), 'landings': {c: len(by[c]) for c in CONDITIONS}, 'excluded': excluded,
            'table': table, 'tests': tests, 'tests_nearest': tests_nearest, 'alpha': ALPHA,
            'regression': reg, 'experienced': {'threshold_mean_rating': threshold, 'n': len(experienced),
                                               'participants': sorted(experienced)},
            'experience_level': {'method': how, 'fits': fig8}, 'sus': sus, 'goal_inference': goal_inference,
            'per_participant': per_participant}


# ----------------------------------------------------------------------------------------- tables
def _fmt(metric: str, v: float | None) -> str:
    if v is None:
        return '-'
    if metric == 'success_rate':
        return f'{100 * v:.2f}%'
    return f'{v:.2f}m' if metric != 'variance_m2' else f'{v:.2f}m^2'


TEST_OF = {'success_rate': 'mcnemar', 'median_error_m': 'mood_median', 'mean_error_m': 't', 'variance_m2': 'f'}
ROW_NAMES = {'success_rate': 'Success rate', 'median_error_m': 'Median error', 'mean_error_m': 'Mean error',
             'variance_m2': 'Variance'}


def table_rows(summary: dict[str, Any]) -> list[list[str]]:
    """Table I as rows of cells (* marks the more favourable value where the test's p < alpha)."""
    out = []
    for metric, name in ROW_NAMES.items():
        cells = [name]
        for kind, tests in (('specified', summary['tests']), ('nearest', summary['tests_nearest'])):
            vals = summary['table'][kind][metric]
            p = tests[TEST_OF[metric]].get('p')
            best = None
            if p is not None and p < ALPHA and None not in vals.values():
                better = max if metric == 'success_rate' else min
                best = better(CONDITIONS, key=lambda c: vals[c])
            for c in CONDITIONS:
                cells.append(_fmt(metric, vals[c]) + ('*' if c == best else ''))
        out.append(cells)
    return out


def render_tables(summary: dict[str, Any]) -> tuple[str, str]:
    """(plain text, Markdown) of Table I plus the tests, regression, SUS and goal inference."""
    head = ['', 'Specified: unassisted', 'Specified: assisted', 'Nearest: unassisted', 'Nearest: assisted']
    rows = table_rows(summary)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    text = [f"User study: {summary['participants']} participants, {summary['landings']['unassisted']} unassisted and "
            f"{summary['landings']['assisted']} assisted landings (excluded: {summary['excluded']['unassisted']} "
            f"unassisted, {summary['excluded']['assisted']} assisted, ended on the starting platform)"]
    text += ['  '.join(c.ljust(w) for c, w in zip(r, widths)) for r in [head] + rows]
    md = [text[0], '', '| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    md += ['| ' + ' | '.join(r) + ' |' for r in rows]
    notes = ['* significantly more favourable (p < 0.01)']
    for name, key in (('McNemar (success)', 'mcnemar'), ("Mood's median test", 'mood_median'),
                      ("Welch's t-test", 't'), ('F-test (variance)', 'f')):
        t = summary['tests'][key]
        notes.append(f'{name}: statistic {_num(t["statistic"])}, p {_num(t["p"], 4)}')
    reg = summary['regression']
    notes.append('Regression of error (m): ' + ', '.join(
        f"{k} {_num(reg[k]['coef'])} (p {_num(reg[k]['p'], 4)})" for k in ('assisted', 'first_half', 'experienced')))
    fits = summary['experience_level']['fits']
    notes.append('Median error vs experience level, slope: ' + ', '.join(
        f"{c} {_num(fits[c]['slope'])}" for c in CONDITIONS))
    sus = summary['sus']
    notes.append('SUS: ' + ', '.join(f"{c} {_num(sus[c]['mean'])} ({_ordinal(sus[c]['percentile'])} percentile)"
                                     for c in CONDITIONS))
    gi = summary['goal_inference']
    notes.append(f"Goal inferred (assisted landings ended nearest the goal pad): {_pct(gi['rate'])}; of those "
                 f"successful: {_pct(gi['success_given_inferred'])}")
    return '\n'.join(text + [''] + notes) + '\n', '\n'.join(md + [''] + [f'- {n}' for n in notes]) + '\n'


def _num(v: float | None, digits: int = 2) -> str:
    return '-' if v is None else f'{v:.{digits}f}'


def _ordinal(v: float | None) -> str:
    """31 -> '31st', 22 -> '22nd', 13 -> '13th' (rounded); '-' for None."""
    if v is None:
        return '-'
    n = int(round(v))
    suffix = 'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')
    return f'{n}{suffix}'


def _pct(v: float | None) -> str:
    return '-' if v is None else f'{100 * v:.2f} %'


# ----------------------------------------------------------------------------------------- figures
def _save(fig: Any, path: Path, dpi: int = 120) -> None:
    """Write a figure as PNG and free it."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def plot_violin(parts: list[Participant], path: Path) -> None:
    """Fig. 6: the distribution of landing errors per condition."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    data = [[r['error_m'] for p in parts for r in p.rows if r['condition'] == c and not r['started_on_pad']]
            for c in CONDITIONS]
    fig, ax = plt.subplots(figsize=(5, 4))
    shown = [(c, d) for c, d in zip(CONDITIONS, data) if len(d) > 1]
    if shown:
        parts_ = ax.violinplot([d for _, d in shown], showmedians=True)
        for body, (c, _) in zip(parts_['bodies'], shown):
            body.set_facecolor(COLORS[c])
            body.set_alpha(0.6)
        ax.set_xticks(range(1, len(shown) + 1), [c for c, _ in shown])
    ax.set_ylabel('error to the goal pad centre (m)')
    ax.set_title('Landing error per condition')
    _save(fig, path)


def plot_experience(summary: dict[str, Any], path: Path) -> None:
    """Fig. 8: per-participant median error against experience level, a fitted line per condition."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 4))
    for c in CONDITIONS:
        pts = [(v['experience_level'], v[f'median_error_m_{c}']) for v in summary['per_participant'].values()
               if v['experience_level'] is not None and v[f'median_error_m_{c}'] is not None]
        if not pts:
            continue
        x, y = np.array(pts).T
        ax.scatter(x, y, color=COLORS[c], label=c)
        fit = summary['experience_level']['fits'][c]
        if fit['slope'] is not None:
            xs = np.linspace(0, 1, 2)
            ax.plot(xs, fit['intercept'] + fit['slope'] * xs, color=COLORS[c],
                    label=f"{c} fit (slope {fit['slope']:.2f})")
    ax.set_xlabel('experience level (0 novice, 1 expert)')
    ax.set_ylabel('median error (m)')
    ax.legend(fontsize=8)
    _save(fig, path)


def bag_track(bag: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(N x 3 /odom positions from the episode's start, pad boxes as rows of cx, cy, sx, sy, yaw, or None) of a
    landing's bag."""
    from assist_policy.bags.bagio import BagReader
    pts, pads = [], None
    with BagReader(bag) as reader:
        topics = [t for t in ('/odom', '/sim/scene') if t in reader.select(None)]
        for conn_topic, _t, raw in reader.messages(topics):
            msg = reader.deserialize(raw, conn_topic)
            if conn_topic == '/odom':
                p = msg.pose.pose.position
                pts.append((p.x, p.y, p.z))
            else:
                boxes = []
                for m in msg.markers:
                    if m.ns == 'platforms' and m.action == 0:
                        q = m.pose.orientation
                        yaw = heading((q.x, q.y, q.z, q.w))
                        boxes.append((m.pose.position.x, m.pose.position.y, m.scale.x, m.scale.y, yaw))
                if boxes:
                    pads = np.array(boxes)
    track = np.array(pts).reshape(-1, 3)
    if len(track) > 1:      # the bag opens before /sim/reset: keep the flight after the last teleport
        jumps = np.flatnonzero(np.linalg.norm(np.diff(track, axis=0), axis=1) > JUMP_M)
        if jumps.size:
            track = track[jumps[-1] + 1:]
    return track, pads


def plot_trajectories(parts: list[Participant], n: int, path: Path) -> int:
    """Fig. 7: top views of chosen landings (both conditions of one trial) from their bags; returns panels drawn."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon
    chosen = []
    for p in parts:
        if len(chosen) >= n:
            break
        trials = {}
        for r in p.rows:
            if r['bag'] and (p.dir / 'bags' / r['bag']).is_dir():
                trials.setdefault(r['trial'], {})[r['condition']] = r
        both = sorted(t for t, d in trials.items() if len(d) == 2)
        if both:
            chosen.append((p, trials[both[len(both) // 2]]))
    if not chosen:
        return 0
    fig, axes = plt.subplots(len(chosen), 1, figsize=(10, 2.6 * len(chosen)), squeeze=False)   # long scenes: rows
    drawn = 0
    for ax, (p, pair) in zip(axes[:, 0], chosen):
        for c in CONDITIONS:
            r = pair[c]
            try:
                track, pads = bag_track(p.dir / 'bags' / r['bag'])
            except Exception as exc:  # noqa: BLE001 - a damaged bag costs its panel line, not the analysis
                log.warning('%s: bag %s unreadable (%s); not drawn', p.pid, r['bag'], exc)
                continue
            if pads is not None and c == CONDITIONS[0]:
                for k, (cx, cy, sx, sy, yaw) in enumerate(pads):
                    corners = [np.array([cx, cy]) + rotate_xy((dx, dy), yaw)
                               for dx, dy in ((-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2),
                                              (-sx / 2, sy / 2))]
                    ax.add_patch(Polygon(corners, closed=True, fill=k == r['goal_index'], alpha=0.35,
                                         color='orange' if k == r['goal_index'] else 'gray'))
            if len(track):
                ax.plot(track[:, 0], track[:, 1], color=COLORS[c], label=f"{c}: {r['outcome']}")
                ax.plot(track[-1, 0], track[-1, 1], 'o', color=COLORS[c])
                drawn += 1
        ax.set_title(f"{p.pid}, trial {pair[CONDITIONS[0]]['trial'] + 1}")
        ax.set_aspect('equal')
        ax.set_xlabel('x (m)')
        ax.set_ylabel('y (m)')
        ax.legend(fontsize=7)
    _save(fig, path)
    return drawn


# ----------------------------------------------------------------------------------------- main
def run(dirs: list[Path], args: AnalyzeArgs) -> dict[str, Any]:
    """Analyse the participant directories into args.out; returns the summary."""
    out = Path(args.out)
    taken = [name for name in OUTPUTS if (out / name).exists()]
    if taken:
        raise StudyError(f'{out}: {", ".join(taken)} exist already; not overwriting (use another --out)')
    parts = []
    for d in dirs:
        if not d.is_dir():
            log.warning('%s: not a directory, skipped', d)
            continue
        if not (d / 'landings.csv').exists():
            log.warning('%s: no landings.csv, skipped', d)
            continue
        parts.append(load_participant(d))
    if not parts:
        raise StudyError('no participant directory with landings.csv among the arguments')
    pids = [p.pid for p in parts]
    if len(set(pids)) != len(pids):
        raise StudyError(f'a participant appears twice: {sorted({p for p in pids if pids.count(p) > 1})}')
    summary = analyze(parts)
    text, md = render_tables(summary)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'table.txt').write_text(text, encoding='utf-8')
    (out / 'table.md').write_text(md, encoding='utf-8')
    if args.plots:
        plot_violin(parts, out / 'violin.png')
        plot_experience(summary, out / 'experience.png')
        if args.trajectories:
            summary['trajectory_panels'] = plot_trajectories(parts, args.trajectories, out / 'trajectories.png')
    (out / 'summary.json').write_text(json.dumps(summary, indent=1) + '\n', encoding='utf-8')
    return summary


def main(argv: list[str] | None = None) -> int:
    """Console entry point: analyse, print the table."""
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    parser = argparse.ArgumentParser(prog='analyze_study', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('dirs', nargs='+', type=Path, help='participant directories (e.g. study_data/*)')
    add_dataclass_args(parser, AnalyzeArgs, HELP)
    ns_argv = sys.argv[1:] if argv is None else list(argv)
    pre, _ = parser.parse_known_args(ns_argv)
    args, _ = parse_dataclass_args(parser, AnalyzeArgs, ns_argv)
    try:
        summary = run(pre.dirs, args)
    except (StudyError, OSError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    text, _ = render_tables(summary)
    print(text, end='')
    print(f'written to {args.out}/ (summary.json, table.txt, table.md' + (', figures)' if args.plots else ')'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
