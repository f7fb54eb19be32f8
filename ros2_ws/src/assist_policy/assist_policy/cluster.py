"""Where parallel landings run: local worker processes or a Ray cluster (evaluate, train_td3's collection).

Ray is an optional dependency (requirements.txt installs it; ``pip install "ray==2.60.0"`` elsewhere),
imported only when a command is given ``--ray``.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import socket
from collections.abc import Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, wait
from types import ModuleType

log = logging.getLogger(__name__)

RAY_PIN = 'ray==2.60.0'
#: The main process's longest uninterrupted wait for its workers: a Ctrl-C is raised within this (completed_in_turn).
WAIT_POLL_S = 0.1


def cpu_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)


def process_context() -> multiprocessing.context.BaseContext:
    """The start method for worker processes: spawn (a fresh interpreter: no forked torch or pybullet state)."""
    return multiprocessing.get_context('spawn')


def ignore_ctrl_c() -> None:
    """In a worker process: leave Ctrl-C to the parent, which stops the pool (a terminal signals the whole
    process group, and a worker interrupted while it waits for work would print a traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def completed_in_turn(futures: Iterable[Future]) -> Iterator[Future]:
    """concurrent.futures.as_completed, waking every WAIT_POLL_S.

    The kernel hands a process-wide SIGINT to any thread that does not block it (the pool's own), and
    Python runs the handler on the main thread at its next bytecode: an untimed wait slept through a
    Ctrl-C until the next landing ended. The order is completion order, as as_completed's.
    """
    pending = set(futures)
    while pending:
        done, pending = wait(pending, timeout=WAIT_POLL_S, return_when=FIRST_COMPLETED)
        yield from done


def result_of(future: Future):
    """future.result(), waking every WAIT_POLL_S so that a Ctrl-C is raised at once (see completed_in_turn)."""
    while not future.done():
        wait([future], timeout=WAIT_POLL_S)
    return future.result()


_CONNECTED: list[str] = []         # the address this process initialised Ray with


def connect_ray(address: str) -> ModuleType:
    """The ray module, initialised for `address` ('auto': a local instance; HOST:6379 or ray://HOST:10001: an
    existing cluster); ValueError (one line) when ray is missing, the cluster cannot be started or reached, or
    this process already uses Ray at another address (a Ray instance already up for `address` is reused)."""
    try:
        import ray
    except ImportError as exc:
        raise ValueError(f'--ray needs the ray package ({exc}); pip install "{RAY_PIN}"') from None
    if address != 'auto':
        host, _, port = address.removeprefix('ray://').rpartition(':')
        try:                          # Ray retries an unreachable address for minutes: ask the socket first
            socket.create_connection((host or '127.0.0.1', int(port)), timeout=5.0).close()
        except (OSError, ValueError) as exc:
            raise ValueError(f'--ray {address}: cannot start or reach Ray: {exc}') from None
    if ray.is_initialized():
        if _CONNECTED and _CONNECTED[-1] != address:
            raise ValueError(f'--ray {address}: this process already uses Ray at {_CONNECTED[-1]}')
        return ray
    try:
        ray.init(address=None if address == 'auto' else address, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ValueError(f'--ray {address}: cannot start or reach Ray: {exc}') from None
    _CONNECTED.append(address)
    return ray


def ray_cpus(ray: ModuleType) -> int:
    """CPUs the connected Ray cluster offers (at least 1)."""
    return max(1, int(ray.cluster_resources().get('CPU', 0)))
