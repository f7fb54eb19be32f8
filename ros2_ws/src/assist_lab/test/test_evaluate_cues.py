"""evaluate --cues: the assistant's intent shown to the pilots; pilots who ignore it fly exactly as without it."""
import pytest

from assist_lab import evaluate
from assist_lab.episodes_plan import evaluation_plans
from assist_lab.evaluate import condition_name, cues_shown, rules_flying
from assist_lab.graph_eval import GraphEvalArgs, node_params

COMMON = ['--conditions', 'unassisted', 'oracle', '--betas', '0.3', '--landings', '2', '--pilot', 'mix',
          '--max-episode-s', '12', '--plot', 'false', '--workers', '1']


def rows(out, *extra):
    assert evaluate.main(['--out', str(out), *COMMON, *extra]) == 0
    return evaluate.read_landings(out / 'landings.csv')


def test_pilots_who_ignore_the_cues_fly_the_same_landings(tmp_path):
    plain = rows(tmp_path / 'plain')
    ignored = rows(tmp_path / 'ignored', '--cues', '--cue-trust', '0')
    assert sorted(plain) == ['oracle+guard', 'unassisted']
    assert sorted(ignored) == ['oracle+guard+cues', 'unassisted']      # never cues without an assistant
    assert ignored['unassisted'] == plain['unassisted']
    strip = [{k: v for k, v in r.items() if k != 'condition'} for r in ignored['oracle+guard+cues']]
    assert strip == [{k: v for k, v in r.items() if k != 'condition'} for r in plain['oracle+guard']]
    assert all(r['path_m'] > 0.5 and r['duration_s'] > 0.5 for r in plain['oracle+guard'])


def test_a_cue_trust_outside_zero_to_one_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        evaluate.main(['--out', str(tmp_path / 'x'), *COMMON, '--cues', '--cue-trust', '1.5'])
    assert stop.value.code == 2
    assert '--cue-trust must be <= 1, got 1.5' in capsys.readouterr().err
    assert not (tmp_path / 'x').exists()


def test_evaluate_graph_lets_the_simulated_pilot_read_the_cues_of_an_assistant():
    args = GraphEvalArgs(cues=True, cue_trust=0.7)
    plans = [p for _, p in evaluation_plans(args.seed, (0.5,), 2, args.pilot, args.alpha)]
    latent = node_params(args, 'latent', plans, rules_flying(args, 'latent'))
    assert latent['sim_pilot_node']['cue_trust'] == 0.7
    assert 'cue_trust' not in node_params(args, 'unassisted', plans, rules_flying(args, 'unassisted'))['sim_pilot_node']
    assert 'cue_trust' not in node_params(GraphEvalArgs(), 'latent', plans,
                                          rules_flying(args, 'latent'))['sim_pilot_node']
    assert condition_name('latent', rules_flying(args, 'latent'), cues_shown(args, 'latent')).endswith('+cues')
