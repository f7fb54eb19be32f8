"""compare_landings (assist_lab.compare): two evaluate runs paired landing by landing."""
import csv

import pytest

from assist_lab.compare import load_side, main, paired_stats, report
from assist_lab.evaluate import write_landings


def row(cond, beta, seed, err, outcome='success', pilot='ignorer'):
    """A landings.csv row as evaluate writes it."""
    return {'condition': cond, 'beta': beta, 'seed': seed, 'goal_index': 1, 'landed_index': 1 if outcome in (
        'success', 'edge') else None, 'nearest_index': 1, 'aimed_index': 1, 'error_m': err,
        'nearest_error_m': err, 'outcome': outcome, 'success': outcome == 'success', 'crash': outcome == 'crash',
        'duration_s': 20.0, 'active_fraction': 0.5, 'pilot': pilot}


@pytest.fixture
def runs(tmp_path):
    old, new = tmp_path / 'old', tmp_path / 'new'
    old.mkdir()
    new.mkdir()
    a = [row('latent', 0.0, 7, 0.10), row('latent', 0.0, 8, 0.70, 'edge'), row('latent', 0.5, 9, 0.60, 'crash'),
         row('latent', 1.0, 10, 0.08, pilot='keyboard'), row('latent', 1.0, 11, 0.09, pilot='keyboard')]
    b = [row('latent+x', 0.0, 7, 0.12), row('latent+x', 0.0, 8, 0.05), row('latent+x', 0.5, 9, 0.06),
         row('latent+x', 1.0, 10, 0.40, 'edge', pilot='keyboard'), row('latent+x', 2.0, 99, 0.1)]
    write_landings(old / 'landings.csv', {'unassisted': [row('unassisted', 0.0, 7, 1.0, 'crash')], 'latent': a})
    write_landings(new / 'landings.csv', {'latent+x': b})
    return old, new


def test_pairs_on_beta_and_seed_and_counts_flips(runs):
    old, new = runs
    a, b = load_side([str(old)], None), load_side([str(new / 'landings.csv')], None)
    assert (a.condition, b.condition) == ('latent', 'latent+x') and len(a.rows) == 5
    text, pairs = report(a, b, 0.25)
    assert len(pairs) == 4 and '(1 only in A, 1 only in B)' in text
    s = paired_stats(pairs)
    assert s['delta_error'] == pytest.approx((0.02 - 0.65 - 0.54 + 0.32) / 4)
    assert (s['success_gained'], s['success_lost'], s['crash_gained'], s['crash_lost']) == (2, 1, 0, 1)
    assert s['success_mcnemar_p'] == pytest.approx(1.0)          # 2 vs 1 discordant: no evidence
    assert 'changed (outcome, or error moved > 0.25 m): 3' in text
    assert 'crash 0.600 -> success 0.060' in text and 'keyboard' in text   # per family rows and landings


def test_cli_writes_pairs_and_refuses_bad_input_in_one_line(runs, tmp_path, capsys):
    old, new = runs
    out = tmp_path / 'pairs.csv'
    assert main(['--a', str(old), '--condition-a', 'unassisted', '--b', str(new), '--out', str(out)]) == 0
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 1 and rows[0]['outcome_a'] == 'crash' and float(rows[0]['delta_error']) == -0.88
    assert main(['--a', str(old), '--condition-a', 'nope', '--b', str(new)]) == 2
    assert "no condition 'nope'" in capsys.readouterr().err
    bad = tmp_path / 'bad.csv'
    bad.write_text('a,b\n1,2\n')
    assert main(['--a', str(bad), '--b', str(new)]) == 2
    assert 'not a landings.csv' in capsys.readouterr().err
    assert main(['--a', str(tmp_path / 'missing'), '--b', str(new)]) == 2
    two = tmp_path / 'two'
    two.mkdir()
    write_landings(two / 'landings.csv', {'x': [row('x', 0.0, 7, 0.1)], 'y': [row('y', 0.0, 7, 0.1)]})
    assert main(['--a', str(two), '--b', str(new)]) == 2
    assert 'name one with --condition-a/-b' in capsys.readouterr().err
    assert main(['--a', str(old), '--b', str(old)]) == 0                   # a run against itself: all equal
    assert 'changed (outcome, or error moved > 0.25 m): 0' in capsys.readouterr().out


def test_cli_draws_the_paired_comparison(runs, tmp_path):
    old, new = runs
    png = tmp_path / 'pairs.png'
    assert main(['--a', str(old), '--condition-a', 'unassisted', '--b', str(new), '--plot', str(png)]) == 0
    assert png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and png.stat().st_size > 10_000


def test_time_path_and_wrong_pad_are_compared_pair_by_pair(tmp_path):
    a = [dict(row('latent', 0.0, s, 0.1), duration_s=20.0 + s, path_m=10.0 + s) for s in range(4)]
    a[0].update(outcome='wrong_pad', success=False)
    a[1].update(outcome='wrong_pad', success=False)
    b = [dict(row('latent+cues', 0.0, s, 0.1), duration_s=15.0 + s, path_m=9.0 + s) for s in range(4)]
    b[1].update(outcome='wrong_pad', success=False)
    b[3].pop('path_m')                                     # an older table's row: compared where both have it
    write_landings(tmp_path / 'a.csv', {'latent': a})
    write_landings(tmp_path / 'b.csv', {'latent+cues': b})
    text, pairs = report(load_side([str(tmp_path / 'a.csv')], None), load_side([str(tmp_path / 'b.csv')], None))
    s = paired_stats(pairs)
    assert s['duration_s']['n'] == 4 and s['duration_s']['a'] == pytest.approx(21.5)
    assert s['duration_s']['change'] == pytest.approx(16.5 / 21.5 - 1.0)
    assert s['path_m']['n'] == 3 and s['path_m']['b'] == pytest.approx(10.0)
    assert (s['wrong_pad_a'], s['wrong_pad_b'], s['wrong_pad_gained'], s['wrong_pad_lost']) == (2, 1, 0, 1)
    assert 'time to land (s)      4  A 21.50  B 16.50  (-23.3 %)' in text
    assert 'wrong pad             4  A 2  B 1  (+0/-1, McNemar p 1)' in text
