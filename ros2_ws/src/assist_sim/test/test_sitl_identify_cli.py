"""sitl_identify without SITL: argument checks, refusal to overwrite, the sequences it flies, the CSV format."""
from __future__ import annotations

import math

import numpy as np
import pytest

from assist_sim import sitl_identify as si


def run_main(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        si.main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    return exc.value.code, err


@pytest.mark.parametrize('argv, words', [
    ([], '--out is required'),
    (['--out', 'x', '--sequences', 'step_x_pos,nope'], 'unknown nope'),
    (['--out', 'x', '--sequences', 'step_x_pos,step_x_pos'], 'twice'),
    (['--out', 'x', '--altitude-m', '0.5'], '--altitude-m must be >= 1.5'),
    (['--out', 'x', '--altitude-m', 'nan'], "--altitude-m: not a finite number: 'nan'"),
    (['--out', 'x', '--json-port', '70000'], '--json-port must be <= 65535'),
    (['--out', 'x', '--command-hz', '50', '--log-hz', '20'], '--log-hz must be >= --command-hz'),
])
def test_bad_arguments_end_with_one_error_line(argv, words, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(argv, capsys)
    assert code == 2
    errors = [line for line in err if 'error:' in line]
    assert len(errors) == 1 and words in errors[0], err
    assert not (tmp_path / 'x').exists()


def test_out_that_is_a_file_is_refused(capsys, tmp_path):
    f = tmp_path / 'file'
    f.write_text('keep')
    code, err = run_main(['--out', str(f)], capsys)
    assert code == 2 and 'not a folder' in err[-1]
    assert f.read_text() == 'keep'


def test_existing_fixtures_are_not_overwritten_without_force(capsys, tmp_path):
    old = tmp_path / 'step_z.csv'
    old.write_text('old data\n')
    code, err = run_main(['--out', str(tmp_path), '--sequences', 'step_z', '--touchdown-trials', '0',
                          '--touchdown-lateral-mps', '0'], capsys)
    assert code == 2 and 'step_z.csv' in err[-1] and '--force' in err[-1]
    assert old.read_text() == 'old data\n'


def test_output_files_follow_the_selection():
    cfg = si.IdentifyConfig(out='o', sequences='step_x_pos,chirp_x', touchdown_trials=1, touchdown_lateral_mps=0.5)
    assert si.output_files(cfg) == ['step_x_pos.csv', 'chirp_x.csv', 'touchdown_vertical_1.csv',
                                    'touchdown_lateral.csv', 'touchdown_lateral_release.csv', 'touchdown.csv']
    none = si.IdentifyConfig(out='o', sequences='step_z', touchdown_trials=0, touchdown_lateral_mps=0.0)
    assert si.output_files(none) == ['step_z.csv']


def test_sequences_start_in_hover_stay_in_the_envelope_and_come_to_rest():
    seqs = si.build_sequences(20.0)
    assert {'step_x_pos', 'step_y_pos', 'step_z', 'ramp_x', 'square_x_0p25', 'square_x_1', 'chirp_x',
            'step_diag', 'random_a', 'random_b', 'random_c'} <= set(seqs)
    pre = int(si.PRE_ROLL_S * 20)
    for s in seqs.values():
        c = s.commands
        assert 10.0 <= s.n / 20 <= 25.0, s.name
        assert np.all(c[:pre] == 0) and np.any(c[pre:pre + 10] != 0), s.name   # steady hover, then moves
        assert np.all(c[-20:] == 0), s.name                        # ends at rest
        assert np.abs(c[:, :2]).max() <= 1.5 and -1.5 <= c[:, 2].min() and c[:, 2].max() <= 1.0, s.name
        path = np.cumsum(c, axis=0) / 20                           # commanded displacement
        # open floor: the identification scene has walls 10 m and pads 15 m from the start spot
        assert np.abs(path[:, :2] + s.start_xy).max() <= 5.0 and np.abs(path[:, 2]).max() <= 2.5, s.name
    sq = seqs['square_x_0p25'].commands[pre:pre + 20, 0]
    assert list(sq[:10]) == [1, 1, 1, 1, 1, -1, -1, -1, -1, -1]     # 0.25 s = 5 setpoints per half-period


def test_random_sequences_are_fixed_by_their_seeds_and_differ():
    a, b = si.build_sequences(20.0), si.build_sequences(20.0)
    for name in si.RANDOM_SEEDS:
        assert np.array_equal(a[name].commands, b[name].commands)
        holds = np.flatnonzero(np.any(np.diff(a[name].commands, axis=0) != 0, axis=1))
        assert np.diff(holds).min() >= 4                           # holds of at least 0.2 s
    assert not np.array_equal(a['random_a'].commands[:400], a['random_b'].commands[:400])


def test_fixture_text_round_trips():
    rows = [(0.0, 1.0, 0.0, -0.5, 0.123456, -0.0000001, 2.0, 1.5, 2.5, 3.0), (0.02, 1, 0, 0, 0, 0, 0, 0, 0, math.nan)]
    text = si.fixture_text(['sequence: s', 'ardupilot_commit: abc'], si.COLUMNS, rows)
    assert text.splitlines()[:3] == ['# sequence: s', '# ardupilot_commit: abc', ','.join(si.COLUMNS)]
    assert text.splitlines()[3].startswith('0,1.0000,0,-0.5000,0.1235,0,')
    p = __import__('pathlib').Path
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        f = p(d) / 'f.csv'
        f.write_text(text)
        header, cols, data = si.read_fixture(f)
    assert header == ['sequence: s', 'ardupilot_commit: abc'] and cols == list(si.COLUMNS)
    assert data.shape == (2, 10) and data[0, 4] == pytest.approx(0.1235) and math.isnan(data[1, 9])
