"""evaluate on a tiny grid: CSV of every landing, summary statistics, plot, pairing across conditions."""
import csv

import pytest

from assist_lab.evaluate import EvalArgs, evaluate, format_table, main, summarize

pytestmark = pytest.mark.slow(seconds=60)


def test_tiny_evaluation_writes_everything(tmp_path):
    args = EvalArgs(out=str(tmp_path), conditions=('unassisted', 'scripted_oracle', 'latent'),
                    betas=(0.0, 1.0), landings=2, latent_model=str(tmp_path / 'missing.pt'))
    summary = evaluate(args)
    assert set(summary) == {'unassisted', 'scripted_oracle+guard'}   # latent skipped: no model; the guard by default
    rows = list(csv.DictReader(open(tmp_path / 'landings.csv')))
    assert len(rows) == 8
    # paired: the same seeds and scenes in every condition
    by = {}
    for r in rows:
        by.setdefault(r['condition'], []).append((r['seed'], r['scene_seed'], r['goal_index']))
    assert by['unassisted'] == by['scripted_oracle+guard']
    assert (tmp_path / 'error_vs_beta.png').stat().st_size > 1000
    assert summary['scripted_oracle+guard']['error_mean'] < summary['unassisted']['error_mean']
    assert 'unassisted' in format_table(summary)
    # aimed_index: the pad nearest the pilot's first estimate, a real pad index
    assert all(0 <= int(r['aimed_index']) <= 4 for r in rows)
    # combining earlier runs' CSVs flies nothing and reproduces their statistics
    again = evaluate(EvalArgs(out=str(tmp_path / 'combined'), from_csv=(str(tmp_path / 'landings.csv'),)))
    assert set(again) == set(summary)
    for cond in summary:
        for key in ('n', 'error_mean', 'error_median', 'specified_success', 'crash_rate', 'misaimed'):
            assert again[cond][key] == pytest.approx(summary[cond][key], abs=1e-3), (cond, key)
    assert (tmp_path / 'combined' / 'error_vs_beta.png').stat().st_size > 1000
    # a condition split over two processes by beta (the second offsets --seed to keep the pairing)
    lo = evaluate(EvalArgs(out=str(tmp_path / 'lo'), conditions=('scripted_oracle',), betas=(0.0,), landings=2))
    hi = evaluate(EvalArgs(out=str(tmp_path / 'hi'), conditions=('scripted_oracle',), betas=(1.0,), landings=2,
                           seed=EvalArgs.seed + 1000))
    both = evaluate(EvalArgs(out=str(tmp_path / 'both'), from_csv=(str(tmp_path / 'lo' / 'landings.csv'),
                                                                   str(tmp_path / 'hi' / 'landings.csv'))))
    assert lo['scripted_oracle+guard']['n'] == hi['scripted_oracle+guard']['n'] == 2
    for key in ('n', 'error_mean', 'specified_success', 'nearest_success', 'landed_on_goal'):
        assert both['scripted_oracle+guard'][key] == pytest.approx(summary['scripted_oracle+guard'][key], abs=1e-3), key


def test_evaluate_flies_the_assistant_as_policy_node_does_by_default(tmp_path):
    """The rules policy_node runs in each mode are on unless set: the floor guard for every assisted condition,
    the override, recall and damper for latent (not the oracle, which knows the goal); all four off: the bare actor."""
    run = dict(conditions=('unassisted', 'latent', 'oracle', 'scripted_nearest_pad'), betas=(0.5,), landings=1,
               max_episode_s=1.0, plot=False)
    default = evaluate(EvalArgs(out=str(tmp_path / 'default'), **run))
    assert set(default) == {'unassisted', 'latent+guard+override+recall+damper', 'oracle+guard',
                            'scripted_nearest_pad+guard'}
    table = format_table(default).splitlines()
    assert len({line.index(' 1 ') for line in table[2:]}) == 1        # the long names keep the columns aligned
    assert table[3].startswith('latent+guard+override+recall+damper') and table[3].endswith('0.25 +- 0.15')
    assert set(evaluate(EvalArgs(out=str(tmp_path / 'bare'), safety=False, override=False, recall=False,
                                 damper=False, **run))) == {'unassisted', 'latent', 'oracle', 'scripted_nearest_pad'}
    assert main(['--out', str(tmp_path / 'cli'), '--conditions', 'latent', 'oracle', '--betas', '0.5',
                 '--landings', '1', '--max-episode-s', '1', '--plot', 'false', '--recall', 'false',
                 '--override', 'true']) == 0
    assert {r['condition'] for r in csv.DictReader(open(tmp_path / 'cli' / 'landings.csv'))} == {
        'latent+guard+override+damper', 'oracle+guard+override'}


def test_from_csv_rejects_a_file_that_is_not_a_landings_csv(tmp_path):
    bad = tmp_path / 'bad.csv'
    bad.write_text('a,b\n1,2\n')
    with pytest.raises(ValueError, match='not a landings.csv'):
        evaluate(EvalArgs(out=str(tmp_path / 'o'), from_csv=(str(bad),)))
    assert main(['--from-csv', str(bad), '--out', str(tmp_path / 'o')]) == 1


def test_summary_statistics():
    rows = [{'error_m': 0.1, 'success': True, 'crash': False, 'outcome': 'success', 'landed_index': 2,
             'nearest_index': 2, 'goal_index': 2, 'active_fraction': 0.5, 'aimed_index': 1},
            {'error_m': 4.0, 'success': False, 'crash': False, 'outcome': 'wrong_pad', 'landed_index': 3,
             'nearest_index': 3, 'goal_index': 2, 'active_fraction': 0.5, 'aimed_index': 3},
            {'error_m': 1.0, 'success': False, 'crash': True, 'outcome': 'crash', 'landed_index': None,
             'nearest_index': 2, 'goal_index': 2, 'active_fraction': 0.0, 'aimed_index': 2}]
    s = summarize(rows)
    assert s['error_mean'] == pytest.approx(5.1 / 3)
    assert s['error_median'] == pytest.approx(1.0)
    assert s['specified_success'] == pytest.approx(1 / 3)
    assert s['nearest_success'] == pytest.approx(2 / 3)
    assert s['crash_rate'] == pytest.approx(1 / 3)
    assert s['landed_on_goal'] == pytest.approx(1 / 3)
    assert s['misaimed'] == pytest.approx(2 / 3)           # rows 0 and 1 set off for pads 1 and 3
    assert s['misaimed_success'] == pytest.approx(1 / 2)   # row 0 still landed on its goal


@pytest.mark.parametrize('flags', [['--landings', '0'], ['--landings', '-1'], ['--betas'], ['--seed', '-1'],
                                   ['--max-episode-s', '0'], ['--max-episode-s', 'nan'], ['--conditions'],
                                   ['--alpha', '2']])
def test_bad_values_exit_2_and_never_replace_results(flags, tmp_path, capsys):
    out = tmp_path / 'ev'
    out.mkdir()
    (out / 'landings.csv').write_text('condition,beta,seed\nlatent,0.5,2024\n')
    with pytest.raises(SystemExit) as exc:
        main(['--out', str(out), *flags])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) >= 1 and err[-1].startswith('evaluate: error:') and 'Traceback' not in '\n'.join(err)
    assert (out / 'landings.csv').read_text() == 'condition,beta,seed\nlatent,0.5,2024\n'    # untouched
    assert sorted(p.name for p in out.iterdir()) == ['landings.csv']
    with pytest.raises(ValueError):                      # the library call refuses them too
        evaluate(EvalArgs(out=str(out), landings=0))


def test_two_worker_processes_fly_the_rows_of_one(tmp_path):
    """Landings are independent tasks keyed by (condition, beta, seed): two processes give byte-identical rows."""
    flags = ['--conditions', 'unassisted', 'oracle', '--betas', '0', '1', '--landings', '2', '--max-episode-s', '12',
             '--plot', 'false']
    assert main(['--out', str(tmp_path / 'one'), '--workers', '1', *flags]) == 0
    assert main(['--out', str(tmp_path / 'two'), '--workers', '2', *flags]) == 0
    one = (tmp_path / 'one' / 'landings.csv').read_text()
    assert one == (tmp_path / 'two' / 'landings.csv').read_text()
    assert len(one.splitlines()) == 1 + 8


def test_auto_workers_scale_with_the_plan(monkeypatch):
    from assist_lab import evaluate as ev
    monkeypatch.setattr(ev, 'cpu_cores', lambda: 4)
    assert ev.worker_count(0, 5) == 1            # a short run stays in this process
    assert ev.worker_count(0, 16) == 2
    assert ev.worker_count(0, 840) == 4          # one per core
    assert ev.worker_count(3, 2) == 2 and ev.worker_count(3, 100) == 3


@pytest.mark.scale
def test_a_local_ray_instance_flies_the_rows_of_one_process(tmp_path, local_ray):
    """--ray auto: the landings as Ray tasks on a local instance, byte-identical rows."""
    flags = ['--conditions', 'unassisted', 'oracle', '--betas', '0', '1', '--landings', '1', '--max-episode-s', '12',
             '--plot', 'false']
    assert main(['--out', str(tmp_path / 'one'), '--workers', '1', *flags]) == 0
    assert main(['--out', str(tmp_path / 'ray'), '--ray', 'auto', *flags]) == 0
    assert local_ray.is_initialized() and local_ray.cluster_resources().get('CPU', 0) >= 1
    assert (tmp_path / 'one' / 'landings.csv').read_text() == (tmp_path / 'ray' / 'landings.csv').read_text()
    from assist_lab.cluster import probe_ray
    host, _, port = local_ray.get_runtime_context().gcs_address.rpartition(':')
    probe_ray(host, int(port))                  # Ray's own GCS answers the probe that refuses a port that is not Ray


def test_ray_at_an_address_nobody_serves_is_one_error_line(tmp_path, capsys):
    pytest.importorskip('ray', reason='ray is in requirements.txt; this runs wherever make test installed it')
    code = main(['--out', str(tmp_path / 'x'), '--ray', '127.0.0.1:1', '--conditions', 'unassisted', '--betas', '0',
                 '--landings', '1', '--plot', 'false'])
    assert code == 2 and 'cannot start or reach Ray' in capsys.readouterr().err


def test_a_second_run_into_the_same_out_keeps_the_first_runs_other_conditions(tmp_path):
    # adding a condition to a finished run (evaluate_graph's SITL series do this) replaced its landings.csv,
    # losing the first run's landings; a condition flown again replaces only its own rows
    run = dict(out=str(tmp_path), betas=(0.5,), landings=2, max_episode_s=2.0, plot=False)
    evaluate(EvalArgs(conditions=('unassisted', 'scripted_oracle'), **run))
    first = {r['condition']: r for r in csv.DictReader(open(tmp_path / 'landings.csv'))}
    summary = evaluate(EvalArgs(conditions=('scripted_nearest_pad', 'scripted_oracle'), **run))
    rows = list(csv.DictReader(open(tmp_path / 'landings.csv')))
    assert sorted({r['condition'] for r in rows}) == ['scripted_nearest_pad+guard', 'scripted_oracle+guard',
                                                      'unassisted']
    assert len(rows) == 6                                   # scripted_oracle's two landings once, not twice
    assert {r['condition']: r for r in rows}['unassisted'] == first['unassisted']
    assert set(summary) == {'unassisted', 'scripted_oracle+guard', 'scripted_nearest_pad+guard'}
    assert 'unassisted' in (tmp_path / 'summary.csv').read_text()
