"""The user's cache: files the stack can always make again (exported models, generated textures).

One root for every package: `$ASSIST_CACHE_DIR` when set, else `$XDG_CACHE_HOME/assist` (an absolute
XDG_CACHE_HOME only, as the XDG base-directory specification says), else `~/.cache/assist`. Each user of
the cache has its own folder below the root. `ASSIST_CACHE_DIR=off` turns caching off: `cache_dir`
then returns None and its caller keeps what it makes in memory, or in `scratch_dir` when it needs files.
"""
from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path

_LOG = logging.getLogger(__name__)

CACHE_ENV = 'ASSIST_CACHE_DIR'
OFF = 'off'


def cache_root() -> Path | None:
    """The cache's root folder (None when ASSIST_CACHE_DIR is 'off')."""
    root = os.environ.get(CACHE_ENV, '')
    if root.lower() == OFF:
        return None
    if not root:
        xdg = os.environ.get('XDG_CACHE_HOME', '')
        root = os.path.join(xdg if os.path.isabs(xdg) else os.path.join(Path.home(), '.cache'), 'assist')
    return Path(root)


def cache_dir(name: str) -> Path | None:
    """The cache folder of one kind of file, `name` (e.g. 'onnx'); None when caching is off."""
    root = cache_root()
    return None if root is None else root / name


def scratch_dir(name: str) -> Path:
    """`cache_dir(name)`, or when caching is off a folder of this user's in the system's temporary directory
    (for files a library can only read from disk, such as pybullet's textures)."""
    folder = cache_dir(name)
    if folder is not None:
        return folder
    uid = os.getuid() if hasattr(os, 'getuid') else 0
    return Path(tempfile.gettempdir()) / f'assist-scratch-{uid}' / name


def file_key(path: str | Path, *parts: str) -> str:
    """A cache key for what is made from one file: a hash of `parts` (versions, settings) and the file's bytes."""
    h = hashlib.sha256('|'.join(parts).encode() + b'|')
    with open(path, 'rb') as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b''):
            h.update(chunk)
    return h.hexdigest()[:32]


def store_entry(folder: Path, key: str, files: dict[str, bytes], keep: int, what: str) -> bool:
    """Write one cache entry, files `key + suffix` (atomic each, in the order given: write the file that marks the
    entry complete last), then drop the oldest entries beyond `keep` in `folder` (an entry: the files of one key).
    A failure (read-only or full disk) is logged as a warning naming `what`, not raised. True when stored."""
    from .atomic import write_bytes_atomic
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for suffix, data in files.items():
            write_bytes_atomic(folder / f'{key}{suffix}', data)
        entries: dict[str, float] = {}
        for f in folder.iterdir():
            if f.is_file() and not f.name.startswith('.'):
                k = f.name.split('.', 1)[0]
                entries[k] = max(entries.get(k, 0.0), f.stat().st_mtime)
        for old in sorted(entries, key=entries.get, reverse=True)[keep:]:
            for f in folder.glob(f'{old}.*'):
                f.unlink(missing_ok=True)
        return True
    except OSError as exc:
        _LOG.warning('could not cache %s in %s (%s): it is made again at every start', what, folder, exc)
        return False


def touch(path: Path) -> None:
    """Mark a cache file as just used (store_entry's pruning keeps the newest); a failure is only debug-logged."""
    try:
        os.utime(path)
    except OSError as exc:
        _LOG.debug('could not mark %s as used (%s)', path, exc)
