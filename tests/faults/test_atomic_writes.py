"""Fault injection, the shared crash-safe writer (assist_common.atomic): failures at every point of a write
leave the old content or the new, never a mix; interrupted writers' temporaries are cleaned up;
resumed logs are truncated to what the checkpoint counted.
"""
from __future__ import annotations

import os

import pytest

from assist_common import atomic
from assist_common.atomic import (atomic_dir, atomic_path, committed_dir, remove_stale_temporaries, truncate_csv,
                                  write_text_atomic)


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / 'config.json'
    write_text_atomic(path, 'old')
    with pytest.raises(RuntimeError):
        with atomic_path(path) as tmp:
            tmp.write_text('half')
            raise RuntimeError('killed mid-write')
    assert path.read_text() == 'old' and sorted(p.name for p in tmp_path.iterdir()) == ['config.json']
    write_text_atomic(path, 'new')
    assert path.read_text() == 'new'


def test_temporary_keeps_the_suffix_and_is_hidden(tmp_path):
    with atomic_path(tmp_path / 'shard_00001.npz') as tmp:
        assert tmp.suffix == '.npz' and tmp.name.startswith('.') and tmp.parent == tmp_path
        assert not list(tmp_path.glob('shard_[0-9]*[0-9].npz'))
        tmp.write_bytes(b'x')


def _unit(d, step):
    (d / 'state.txt').write_text(str(step))
    (d / 'replay.txt').write_text(str(step))


def test_directory_unit_survives_a_crash_at_every_rename(tmp_path, monkeypatch):
    path = tmp_path / 'checkpoint'
    with atomic_dir(path) as d:
        _unit(d, 100)
    # crash while writing the second file of the next unit: the previous unit is untouched
    with pytest.raises(RuntimeError):
        with atomic_dir(path) as d:
            (d / 'state.txt').write_text('200')
            raise RuntimeError('killed between the two files')
    assert committed_dir(path) == path and (path / 'replay.txt').read_text() == '100'
    # crash between "current -> .old" and "new -> current": the .old unit is complete and found
    real_rename, calls = os.rename, []

    def rename(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise OSError('killed between renames')
        real_rename(src, dst)
    monkeypatch.setattr(atomic.os, 'rename', rename)
    with pytest.raises(OSError):
        with atomic_dir(path) as d:
            _unit(d, 300)
    monkeypatch.setattr(atomic.os, 'rename', real_rename)
    found = committed_dir(path)
    assert found.name == 'checkpoint.old' and (found / 'state.txt').read_text() == (found / 'replay.txt').read_text()
    # the next save must not delete that last good unit before the new one is in place
    with atomic_dir(path) as d:
        _unit(d, 400)
    assert committed_dir(path) == path and (path / 'state.txt').read_text() == '400'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['checkpoint']


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    dead = 2**22 + 12345          # above the default pid_max: no such process
    (tmp_path / f'.replay.tmp{dead}.npz').write_bytes(b'half')
    (tmp_path / f'.checkpoint.tmp{dead}').mkdir()
    (tmp_path / f'.landings.tmp{os.getppid()}.csv').write_text('live writer')   # a running process
    (tmp_path / 'metrics.csv').write_text('keep')
    gone = remove_stale_temporaries(tmp_path)
    assert sorted(p.name for p in gone) == sorted([f'.replay.tmp{dead}.npz', f'.checkpoint.tmp{dead}'])
    assert (tmp_path / 'metrics.csv').exists() and (tmp_path / f'.landings.tmp{os.getppid()}.csv').exists()


def test_truncate_csv_drops_rows_after_the_checkpoint_and_torn_lines(tmp_path):
    path = tmp_path / 'metrics.csv'
    path.write_text('episode,step\r\n1,10\r\n2,20\r\n3,30\r\n4,4')     # row 4 torn by a kill
    assert truncate_csv(path, lambda r: int(r['episode']) <= 2) == 2
    assert path.read_bytes() == b'episode,step\r\n1,10\r\n2,20\r\n'
    path.write_text('epis')                                            # torn header: start afresh
    truncate_csv(path, lambda r: True)
    assert not path.exists()
    assert truncate_csv(tmp_path / 'missing.csv', lambda r: True) == 0
