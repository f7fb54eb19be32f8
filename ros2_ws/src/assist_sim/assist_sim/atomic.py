"""Crash-safe file writing: a reader (or a resumed run) sees the old content or the new, never half.

Every writer of results and checkpoints in the workspace goes through these helpers:

* ``atomic_path(path)``: yields a temporary path beside `path` (same directory, same suffix, a
  hidden name that no ``shard_*`` / ``*.csv`` glob matches); when the block ends without an
  exception the file is fsynced, renamed over `path` and the directory fsynced; on an exception
  the temporary file is removed and `path` is untouched.
* ``write_text_atomic`` / ``write_bytes_atomic``: the same for an in-memory payload.
* ``atomic_dir(path)``: the same for a whole directory (e.g. a training checkpoint made of several
  files): written under a temporary name, every file fsynced, then renamed into place in one step.
"""
from __future__ import annotations

import os
import re
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

TMP_MARK = '.tmp'


def _tmp_name(path: Path) -> Path:
    """Hidden temporary sibling of `path` that keeps its suffix (np.savez appends .npz otherwise)."""
    return path.with_name(f'.{path.stem}{TMP_MARK}{os.getpid()}{path.suffix}')


def fsync_file(path: str | Path) -> None:
    """Flush a file's data to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: str | Path) -> None:
    """Flush a directory's entries (renames, new files) to disk; a no-op where unsupported."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, 'O_DIRECTORY', 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass        # some filesystems refuse fsync on directories
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces `path` (fsync, rename, fsync dir)."""
    path = Path(path)
    tmp = _tmp_name(path)
    _remove(tmp)
    try:
        yield tmp
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        _remove(tmp)
        raise
    fsync_dir(path.parent)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Replace `path` with `data` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str, encoding: str = 'utf-8') -> None:
    """Replace `path` with `text` atomically."""
    write_bytes_atomic(path, text.encode(encoding))


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield an empty temporary directory; on success it becomes `path` in one rename.

    `path` must not exist yet (directories cannot be renamed over non-empty ones atomically): give
    each unit its own name (e.g. ``ckpt-000400``) and delete older units after this returns.
    """
    path = Path(path)
    if path.exists():
        raise FileExistsError(f'{path} exists')
    tmp = path.with_name(f'.{path.name}{TMP_MARK}{os.getpid()}')
    _remove(tmp)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        for f in tmp.rglob('*'):
            if f.is_file():
                fsync_file(f)
        fsync_dir(tmp)
        os.rename(tmp, path)
    except BaseException:
        _remove(tmp)
        raise
    fsync_dir(path.parent)


_TMP_RE = re.compile(r'^\..+' + re.escape(TMP_MARK) + r'(\d+)(\.[^.]+)?$')


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(directory: str | Path) -> list[Path]:
    """Delete temporaries that killed writers left in `directory`; returns what was removed.

    Only names these helpers create (hidden, ``.tmp<pid>``) whose writing process is gone.
    """
    gone = []
    for p in sorted(Path(directory).glob(f'.*{TMP_MARK}*')):
        m = _TMP_RE.match(p.name)
        if m is None or (int(m.group(1)) != os.getpid() and _alive(int(m.group(1)))):
            continue
        _remove(p)
        gone.append(p)
    return gone
