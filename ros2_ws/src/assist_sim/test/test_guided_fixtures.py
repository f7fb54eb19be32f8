"""The recorded ArduCopter GUIDED fixtures (test/fixtures/guided, made by sitl_identify against real SITL):
every file is there, well formed and consistent with the sequences sitl_identify defines. No SITL needed."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from assist_sim import sitl_identify as si

FIXTURES = Path(__file__).parent / 'fixtures' / 'guided'
SEQUENCES = si.build_sequences(20.0)
TRACES = sorted(p.name for p in FIXTURES.glob('touchdown_*.csv'))
MAX_BYTES = 300_000


def header_value(header: list[str], key: str) -> str:
    values = [h.split(':', 1)[1].strip() for h in header if h.startswith(key + ':')]
    assert len(values) == 1, f'header needs one {key!r} line'
    return values[0]


def test_every_sequence_and_the_touchdown_series_is_recorded():
    names = {p.name for p in FIXTURES.glob('*.csv')}
    assert {f'{n}.csv' for n in SEQUENCES} <= names
    assert 'touchdown.csv' in names and TRACES
    assert (FIXTURES / 'README.md').is_file()


@pytest.mark.parametrize('name', [f'{n}.csv' for n in SEQUENCES] + TRACES)
def test_fixture_format(name):
    path = FIXTURES / name
    assert path.stat().st_size < MAX_BYTES
    header, cols, data = si.read_fixture(path)
    assert cols[:len(si.COLUMNS)] == list(si.COLUMNS)
    assert header_value(header, 'sequence') == path.stem
    assert header_value(header, 'ardupilot_commit').startswith(si.ARDUPILOT_COMMIT)
    for key in ('sitl_defaults', 'ardupilot_params', 'sitl_speedup', 'date_utc', 'command'):
        assert header_value(header, key)
    assert 'WPNAV_ACCEL=' in header_value(header, 'ardupilot_params')
    assert len(data) > 200 and np.all(np.isfinite(data))
    t = data[:, 0]
    assert t[0] == 0.0
    dt = np.diff(t)
    assert np.all(dt > 0)                                         # monotonic
    assert np.allclose(dt, 0.02, atol=0.0015)                     # 50 Hz on physics time
    pos, vel = data[:, 7:10], data[:, 4:7]
    assert np.all(pos[:, 2] > 0.05) and np.abs(vel).max() < 5.0   # above the floor, plausible speeds


@pytest.mark.parametrize('name', sorted(SEQUENCES))
def test_commands_are_the_sequence_sent_at_20_hz(name):
    seq = SEQUENCES[name]
    _, _, data = si.read_fixture(FIXTURES / f'{name}.csv')
    t, cmd = data[:, 0], data[:, 1:4]
    k = np.floor(t * 20 + 1e-6).astype(int)
    inside = k < seq.n
    assert inside.sum() > 0.9 * len(t) and t[-1] >= (seq.n - 1) / 20
    assert np.allclose(cmd[inside], seq.commands[k[inside]], atol=1e-4)
    first = data[:int(si.PRE_ROLL_S * 50)]
    assert np.abs(first[:, 4:7]).max() < 0.3                      # starts from a steady hover


def test_touchdown_summary():
    lines = (FIXTURES / 'touchdown.csv').read_text().splitlines()
    head = [line[1:].strip() for line in lines if line.startswith('#')]
    assert header_value(head, 'ardupilot_commit').startswith(si.ARDUPILOT_COMMIT)
    body = [line.split(',') for line in lines if not line.startswith('#')]
    cols, rows = body[0], body[1:]
    assert cols[:8] == ['trial', 'lateral_cmd_mps', 'lateral_released_at_contact', 'descent_cmd_mps', 't_contact_s',
                        't_on_ground_s', 'delay_s', 'on_ground_came']
    assert {f'touchdown_{r[0]}.csv' for r in rows} == set(TRACES)
    for r in rows:
        rec = dict(zip(cols, r))
        assert float(rec['t_contact_s']) > 0
        if rec['on_ground_came'] == '1':
            assert float(rec['delay_s']) == pytest.approx(float(rec['t_on_ground_s']) - float(rec['t_contact_s']),
                                                          abs=2e-3)
            assert 0 < float(rec['delay_s']) < 30
        else:
            assert rec['delay_s'] == 'nan'
    assert any(float(dict(zip(cols, r))['lateral_cmd_mps']) == 0 for r in rows)
