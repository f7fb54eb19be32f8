"""evaluate --cues: the assistant's intent shown to the pilots; pilots who ignore it fly exactly as without it."""
import pytest

from assist_lab import evaluate

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
