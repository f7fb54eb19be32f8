"""Crash-safe file writing: a reader (or a resumed run) sees the old content or the new, never half.

Every writer of results and checkpoints in the workspace goes through these helpers:

* ``atomic_path(path)``: yields a temporary path beside `path` (same directory, same suffix, a
  hidden name that no ``shard_*`` / ``*.csv`` glob matches); when the block ends without an
  exception the file is fsynced, renamed over `path` and the directory fsynced; on an exception
  the temporary file is removed and `path` is untouched.
* ``write_text_atomic`` / ``write_bytes_atomic``: the same for an in-memory payload.
* ``atomic_dir(path)``: the same for a whole directory (e.g. a training checkpoint made of several
  files): written under a temporary name, every file fsynced, then renamed into place;
  ``committed_dir(path)`` finds the last complete one after a crash.
"""
from __future__ import annotations

import csv
import io
import os
import re
import shutil
from contextlib import contextmanager
from pathlib import Path
from collections.abc import Callable, Iterator

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


OLD_SUFFIX = '.old'


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield an empty temporary directory; on success it replaces `path` as one unit.

    Every file is fsynced, then the previous `path` (if any) is renamed to ``<path>.old``, the new
    directory renamed to `path` and the old one deleted. A crash at any point leaves a complete
    unit at `path` or at ``<path>.old``: read it back with ``committed_dir(path)``.
    """
    path = Path(path)
    old = path.with_name(path.name + OLD_SUFFIX)
    tmp = path.with_name(f'.{path.name}{TMP_MARK}{os.getpid()}')
    _remove(tmp)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        for f in tmp.rglob('*'):
            if f.is_file():
                fsync_file(f)
        fsync_dir(tmp)
        if path.exists():          # only then is <path>.old stale; otherwise it may be the last good unit
            _remove(old)
            os.rename(path, old)
        os.rename(tmp, path)
    except BaseException:
        _remove(tmp)
        raise
    fsync_dir(path.parent)
    _remove(old)


def committed_dir(path: str | Path) -> Path | None:
    """The last complete unit written by ``atomic_dir(path)``: `path`, else ``<path>.old``, else None."""
    path = Path(path)
    if path.is_dir():
        return path
    old = path.with_name(path.name + OLD_SUFFIX)
    return old if old.is_dir() else None


_TMP_RE = re.compile(r'\..+' + re.escape(TMP_MARK) + r'(\d+)(\.[^.]+)?')     # fullmatch: the whole name


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
        m = _TMP_RE.fullmatch(p.name)
        if m is None or (int(m.group(1)) != os.getpid() and _alive(int(m.group(1)))):
            continue
        _remove(p)
        gone.append(p)
    return gone


def truncate_csv(path: str | Path, keep: Callable[[dict], bool]) -> int:
    """Atomically rewrite a CSV keeping its header and the rows for which `keep(row)` is true.

    Used on resume to drop rows written after the checkpoint being resumed (they would be written
    again). A torn last line (a writer killed mid-row) or any row `keep` cannot judge is dropped.
    Returns how many rows were dropped; a missing file is left alone (0).
    """
    path = Path(path)
    if not path.exists():
        return 0
    with open(path, newline='', encoding='utf-8') as fh:
        text = fh.read()
    lines = text.splitlines(keepends=True)
    dropped = 0
    if lines and not lines[-1].endswith('\n'):
        lines, dropped = lines[:-1], 1          # torn final row
    reader = csv.DictReader(lines)
    fields = reader.fieldnames or []
    kept = []
    for row in reader:
        try:
            ok = None not in row and None not in row.values() and keep(row)
        except (KeyError, TypeError, ValueError):
            ok = False
        if ok:
            kept.append(row)
        else:
            dropped += 1
    if not fields:              # not even a complete header: let the writer start the file afresh
        path.unlink()
        fsync_dir(path.parent)
        return dropped
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator='\r\n' if '\r\n' in text else '\n')
    w.writeheader()
    w.writerows(kept)
    write_text_atomic(path, buf.getvalue())
    return dropped


class CsvLog:
    """Append-only CSV with a fixed header (survives resumes: run truncate_csv on it first)."""

    def __init__(self, path: str | Path, fields: list[str]):
        path = Path(path)
        self.path, self.fields = path, fields
        new = not path.exists()
        self.fh = open(path, 'a', newline='', encoding='utf-8')
        self.w = csv.DictWriter(self.fh, fieldnames=fields, extrasaction='ignore')
        if new:
            self.w.writeheader()

    def write(self, row: dict) -> None:
        """Write one row and flush (so tail -f shows progress)."""
        self.w.writerow(row)
        self.fh.flush()

    def sync(self) -> None:
        """Make the rows written so far durable (before a checkpoint that counts them)."""
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def close(self) -> None:
        """Close the file."""
        self.fh.close()
