"""Silence what C libraries print on the process's stdout/stderr (pybullet's banner and `argv[0]=`)."""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import sys
from collections.abc import Iterator

_LIBC = ctypes.CDLL(ctypes.util.find_library('c'))


@contextlib.contextmanager
def quiet_output(stderr: bool = True) -> Iterator[None]:
    """Point file descriptor 1 (and 2 unless stderr=False) at /dev/null for the block.

    C stdio is flushed on both sides, so nothing the block buffered comes out after it.
    """
    streams = [sys.stdout] + ([sys.stderr] if stderr else [])
    saved: list[tuple[int, int]] = []
    for stream in streams:
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):  # no real file (e.g. captured by a test runner)
            continue
        stream.flush()
        saved.append((fd, os.dup(fd)))
    _LIBC.fflush(None)
    try:
        with open(os.devnull, 'wb') as null:
            for fd, _ in saved:
                os.dup2(null.fileno(), fd)
        yield
    finally:
        _LIBC.fflush(None)
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
