"""Where parallel landings run: local worker processes or a Ray cluster (evaluate, train_td3's collection).

Ray is an optional dependency (requirements.txt installs it; ``pip install "ray==2.60.0"`` elsewhere),
imported only when a command is given ``--ray``.

Also what a run on workers needs around them: one run per output directory (`hold_directory`), workers that
end with the process that started them, even when it is SIGKILLed (`exit_with_parent`), and one line, not a
traceback, when a worker dies (`WorkerDied`).
"""
from __future__ import annotations

import ctypes
import fcntl
import logging
import multiprocessing
import multiprocessing.connection
import multiprocessing.context
import os
import signal
import socket
import sys
import threading
import time
import typing
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any

from assist_common.console import exit_now

log = logging.getLogger(__name__)

RAY_PIN = 'ray==2.60.0'
#: The main process's longest uninterrupted wait for its workers: a Ctrl-C is raised within this (completed_in_turn).
WAIT_POLL_S = 0.1
#: How long the address of --ray has to accept a connection, and then to answer as a gRPC server does.
RAY_PROBE_TIMEOUT_S = 5.0
#: How long a dead worker's exit status may take to be known (worker_died).
EXIT_STATUS_WAIT_S = 2.0
#: A worker whose parent is gone notices within this, where the kernel does not end it at once (exit_with_parent).
PARENT_POLL_S = 1.0


def cpu_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else (os.cpu_count() or 1)


class _CtrlCBlockedProcess(multiprocessing.context.SpawnProcess):
    """A spawned process born with SIGINT blocked (the mask survives fork and exec).

    A worker leaves Ctrl-C to its parent (ignore_ctrl_c), but only from its initializer on: a pool starts workers
    when work is first submitted, and a Ctrl-C while one was still importing raised KeyboardInterrupt in it (a
    traceback on the terminal). Blocking SIGINT in the starting thread, not ignoring it, loses no Ctrl-C for the
    parent: the kernel hands it to another thread or keeps it pending for this one until the mask is restored."""

    @staticmethod
    def _Popen(process_obj):
        if not hasattr(signal, 'pthread_sigmask'):
            return multiprocessing.context.SpawnProcess._Popen(process_obj)
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return multiprocessing.context.SpawnProcess._Popen(process_obj)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _WorkerContext(multiprocessing.context.SpawnContext):
    """The spawn start method with _CtrlCBlockedProcess."""
    Process = _CtrlCBlockedProcess


def process_context() -> multiprocessing.context.BaseContext:
    """The start method for worker processes: spawn (a fresh interpreter: no forked torch or pybullet state), each
    worker born deaf to Ctrl-C (_CtrlCBlockedProcess)."""
    return _WorkerContext()


class DirectoryBusy(RuntimeError):
    """Another run holds the directory (hold_directory)."""


class WorkerDied(RuntimeError):
    """A worker process of a local pool died (killed, out of memory, crashed): the run cannot go on."""


class RayUnreachable(ValueError):
    """--ray names an address where no Ray cluster can be reached (or Ray is missing, or cannot start)."""


def _holder(fd: int) -> str:
    """The pid a lock file holds, as text ('unknown' when it holds none yet)."""
    try:
        text = os.pread(fd, 32, 0).decode('ascii', 'replace').strip()
    except OSError:
        return 'unknown'
    return text if text.isdigit() else 'unknown'


@contextmanager
def hold_directory(directory: str | Path, tool: str, instead: str) -> Iterator[Path]:
    """Hold `directory` (created if missing) for one run of `tool`: an exclusive lock (fcntl.flock) on the file
    .<tool>.lock in it, which names this process, for the block; the file is removed at the end (a SIGKILLed
    run leaves it unlocked: the kernel drops the lock with the process).

    DirectoryBusy (one line: the directory, the holder's pid and `instead`, what to do) when another process
    holds it: two runs writing the same files would each remove or overwrite what the other wrote.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    lock = directory / f'.{tool}.lock'
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise DirectoryBusy(f'{directory} is in use by another {tool} run (pid {holder}): {instead}') from None
        except BaseException:
            os.close(fd)
            raise
        try:           # the holder before us may have removed the file as we locked it: then lock the new one
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f'{os.getpid()}\n'.encode('ascii'), 0)
        yield directory
    finally:
        lock.unlink(missing_ok=True)        # while still held: a run that comes next locks a new file
        os.close(fd)


def _exit_status(code: int) -> str:
    """A process exit code in words."""
    if code < 0:
        try:
            return f'killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'killed by signal {-code}'
    return f'exit status {code}'


def _has_ended(process: multiprocessing.process.BaseProcess) -> bool:
    """Whether a process has ended (its sentinel is ready), without waiting."""
    try:
        return bool(multiprocessing.connection.wait([process.sentinel], timeout=0))
    except (OSError, ValueError):       # already closed
        return True


def any_worker_ended(pool: ProcessPoolExecutor) -> bool:
    """Whether one of `pool`'s worker processes has ended, read from the processes themselves: a worker killed while
    it writes a result can leave the executor's own manager thread waiting for the rest of that message, so the
    pool would never say it is broken."""
    return any(_has_ended(p) for p in list((getattr(pool, '_processes', None) or {}).values()))


def worker_died(pool: ProcessPoolExecutor) -> str:
    """'a worker process died (pid N, killed by SIGKILL)': which of `pool`'s workers ended and how, as far as the
    pool still knows (call before it is shut down)."""
    procs = dict(getattr(pool, '_processes', None) or {})      # the executor's own table of its workers
    # a process's sentinel fires as it exits, a moment before the kernel has its exit status to give
    deadline = time.monotonic() + EXIT_STATUS_WAIT_S
    while (any(p.exitcode is None and _has_ended(p) for p in procs.values())
           and time.monotonic() < deadline):
        time.sleep(0.01)
    ended = [(pid, p.exitcode) for pid, p in procs.items() if p.exitcode not in (None, 0)]
    # the pool SIGTERMs the others once one is gone: the first cause is the one that is not its SIGTERM
    ended.sort(key=lambda e: e[1] == -signal.SIGTERM)
    if not ended:
        return 'a worker process died (its exit status is unknown)'
    pid, code = ended[0]
    return f'a worker process died (pid {pid}, {_exit_status(code)})'


def exit_with_parent(parent_pid: int) -> None:
    """In a worker process: end it when its parent, `parent_pid`, dies, even by SIGKILL (nothing else would: a
    worker waiting for work sleeps forever). On Linux the kernel kills it at once (PR_SET_PDEATHSIG, sent when
    the parent's thread that started it ends: start a pool from a thread that outlives it); elsewhere, and as a
    fallback, a watchdog thread ends it within PARENT_POLL_S of being handed to another parent."""
    if sys.platform.startswith('linux'):
        pr_set_pdeathsig = 1
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0) != 0:
            log.warning('prctl(PR_SET_PDEATHSIG) failed (%s): this worker ends within %.0f s of its parent',
                        os.strerror(ctypes.get_errno()), PARENT_POLL_S)
    if os.getppid() != parent_pid:          # it died before the kernel was told
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name='parent-watchdog', daemon=True).start()


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


def ignore_ctrl_c() -> None:
    """In a worker process: leave Ctrl-C to the parent, which stops the pool (a terminal signals the whole
    process group, and a worker interrupted while it waits for work would print a traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def completed_in_turn(futures: Iterable[Future], pool: ProcessPoolExecutor | None = None) -> Iterator[Future]:
    """concurrent.futures.as_completed, waking every WAIT_POLL_S; BrokenProcessPool as soon as one of `pool`'s
    workers has ended while none of the futures left finished (any_worker_ended).

    The kernel hands a process-wide SIGINT to any thread that does not block it (the pool's own), and
    Python runs the handler on the main thread at its next bytecode: an untimed wait slept through a
    Ctrl-C until the next landing ended. The order is completion order, as as_completed's.
    """
    pending = set(futures)
    while pending:
        done, pending = wait(pending, timeout=WAIT_POLL_S, return_when=FIRST_COMPLETED)
        yield from done
        if pool is not None and pending and not done and any_worker_ended(pool):
            raise BrokenProcessPool('a worker process ended')


def result_of(future: Future, pool: ProcessPoolExecutor | None = None):
    """future.result(), waking every WAIT_POLL_S so that a Ctrl-C is raised at once (see completed_in_turn);
    BrokenProcessPool as soon as one of `pool`'s workers has ended (any_worker_ended)."""
    while not future.done():
        wait([future], timeout=WAIT_POLL_S)
        if pool is not None and not future.done() and any_worker_ended(pool):
            raise BrokenProcessPool('a worker process ended')
    return future.result()


_CONNECTED: list[str] = []         # the address this process initialised Ray with


# HTTP/2's client connection preface and an empty SETTINGS frame (RFC 9113, 3.4 and 6.5): a gRPC server, as Ray's
# GCS (HOST:6379) and its client server (ray://HOST:10001) are, answers with a SETTINGS frame of its own at once
_H2_PREFACE = b'PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n' + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
_H2_SETTINGS = 4


def probe_ray(host: str, port: int, timeout_s: float = RAY_PROBE_TIMEOUT_S) -> None:
    """Check that host:port is a gRPC server, as Ray's endpoints are, within about 2 x `timeout_s` (Ray itself
    retries an address that does not answer as Ray for minutes, deaf to Ctrl-C); RayUnreachable (the reason,
    one line) if not. Each wait is a socket timeout in this thread: a Ctrl-C interrupts it."""
    try:
        conn = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise RayUnreachable(f'{host}:{port}: {exc}') from None
    with conn:
        try:
            conn.sendall(_H2_PREFACE)
            head = b''
            while len(head) < 9:            # a frame header: length (3 bytes), type, flags, stream id (4)
                chunk = conn.recv(9 - len(head))
                if not chunk:
                    break
                head += chunk
        except TimeoutError:
            raise RayUnreachable(f'{host}:{port} accepts connections but is not a Ray cluster: no gRPC answer '
                                 f'within {timeout_s:g} s') from None
        except OSError as exc:
            raise RayUnreachable(f'{host}:{port} is not a Ray cluster: {exc}') from None
    if len(head) < 9 or head[3] != _H2_SETTINGS or int.from_bytes(head[5:9], 'big') & 0x7FFFFFFF:
        said = f'it answered {head[:40]!r}' if head else 'it closed the connection'
        raise RayUnreachable(f'{host}:{port} is not a Ray cluster: {said}, not gRPC')


def connect_ray(address: str) -> ModuleType:
    """The ray module, initialised for `address` ('auto': a local instance; HOST:6379 or ray://HOST:10001: an
    existing cluster); RayUnreachable (one line) when ray is missing, the cluster cannot be started or reached,
    the address answers but not as Ray does (probe_ray), or this process already uses Ray at another address (a
    Ray instance already up for `address` is reused)."""
    try:
        import ray
    except ImportError as exc:
        raise RayUnreachable(f'--ray needs the ray package ({exc}); pip install "{RAY_PIN}"') from None
    if address != 'auto':
        host, _, port = address.removeprefix('ray://').rpartition(':')
        try:
            port_number = int(port)
        except ValueError:
            raise RayUnreachable(f'--ray {address}: cannot start or reach Ray: expected HOST:PORT or '
                                 'ray://HOST:PORT') from None
        try:
            probe_ray(host or '127.0.0.1', port_number)
        except RayUnreachable as exc:
            raise RayUnreachable(f'--ray {address}: cannot start or reach Ray: {exc}') from None
    if ray.is_initialized():
        if _CONNECTED and _CONNECTED[-1] != address:
            raise RayUnreachable(f'--ray {address}: this process already uses Ray at {_CONNECTED[-1]}')
        return ray
    try:
        ray.init(address=None if address == 'auto' else address, include_dashboard=False, log_to_driver=False,
                 configure_logging=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise RayUnreachable(f'--ray {address}: cannot start or reach Ray: {exc}') from None
    _CONNECTED.append(address)
    return ray


def ray_cpus(ray: ModuleType) -> int:
    """CPUs the connected Ray cluster offers (at least 1)."""
    return max(1, int(ray.cluster_resources().get('CPU', 0)))


_WORKER = None      # in a pool's worker process: the object its tasks run on


def exit_worker_died(line: str) -> typing.NoReturn:
    """End a command whose worker process died: its one error `line` on stderr, then the process at once (status 1).

    The pool is closed by then and everything the run keeps is written; what is left are threads of the pool's
    machinery that a worker killed mid-message can leave waiting for ever (the executor's manager thread reading
    the rest of a result), which a normal interpreter exit would join.
    """
    sys.stderr.write(line.rstrip('\n') + '\n')
    exit_now(1)


def _start_worker(make: Callable[[], Any], parent_pid: int) -> None:
    """Worker process initialiser: gone with its parent `parent_pid`, Ctrl-C left to the parent, warnings logged,
    the worker object made."""
    global _WORKER
    exit_with_parent(parent_pid)
    ignore_ctrl_c()
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    _WORKER = make()


def _run_task(*args: Any) -> Any:
    return _WORKER.fly(*args)


class _Hosted:
    """A pool's worker object in a Ray actor."""

    def __init__(self, make: Callable[[], Any]) -> None:
        self.worker = make()

    def fly(self, *args: Any) -> Any:
        return self.worker.fly(*args)


class WorkerPool:
    """N workers in local processes (spawned) or Ray actors, each an object `make()` returns with a `fly(*args)`
    method; tasks submitted, results taken in order (`map`) or as they finish (`completed`).

    The one pool behind evaluate and train_td3's collection. `workers` 0: one per CPU core (local) or per CPU of the
    Ray cluster. RayUnreachable (a ValueError, one line) when Ray is asked for and cannot be reached; WorkerDied (one
    line) from submit or result once a local worker process has died; a task's own exception is raised by `result`.
    Local workers end with this process, even a SIGKILLed one (exit_with_parent). Use as a context manager, or call
    close(). `make` must pickle (a class or a functools.partial of one).
    """

    def __init__(self, make: Callable[[], Any], workers: int, ray_address: str = '', what: str = 'landings') -> None:
        self._ray = connect_ray(ray_address) if ray_address else None
        self.workers = workers or (ray_cpus(self._ray) if self._ray else cpu_cores())
        self._next = 0
        if self._ray is not None:
            remote = self._ray.remote(num_cpus=1)(_Hosted)
            self._actors = [remote.remote(make) for _ in range(self.workers)]
            self._pool = None
            where = f'Ray ({ray_address})'
        else:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=process_context(), initializer=_start_worker,
                                             initargs=(make, os.getpid()))
            where = 'local processes'
        log.info('flying %s on %d workers (%s)', what, self.workers, where)

    @property
    def ray(self) -> ModuleType | None:
        """The ray module when the workers are Ray actors, else None."""
        return self._ray

    def submit(self, *args: Any) -> Any:
        """Start `worker.fly(*args)` on the next worker; a handle for `result`."""
        if self._pool is not None:
            try:
                return self._pool.submit(_run_task, *args)
            except BrokenProcessPool:
                raise WorkerDied(worker_died(self._pool)) from None
        actor = self._actors[self._next % len(self._actors)]
        self._next += 1
        return actor.fly.remote(*args)

    def result(self, handle: Any) -> Any:
        """What the task `handle` names returned, once done (its exception is raised here)."""
        if isinstance(handle, Future):
            try:
                return result_of(handle, self._pool)
            except BrokenProcessPool:
                raise WorkerDied(worker_died(self._pool)) from None
        from ray.exceptions import RayTaskError
        try:
            return self._ray.get(handle)
        except RayTaskError as exc:
            raise exc.cause from None

    def completed(self, handles: Iterable[Any]) -> Iterator[Any]:
        """The handles in the order their tasks finish (a Ctrl-C is raised within WAIT_POLL_S)."""
        handles = list(handles)
        if self._pool is not None:
            try:
                yield from completed_in_turn(handles, self._pool)
            except BrokenProcessPool:
                raise WorkerDied(worker_died(self._pool)) from None
            return
        pending = list(handles)
        while pending:
            done, pending = self._ray.wait(pending, num_returns=1, timeout=WAIT_POLL_S)
            yield from done

    def cancel(self, handle: Any) -> None:
        """Drop a task not yet needed."""
        if isinstance(handle, Future):
            handle.cancel()
        else:
            self._ray.cancel(handle)

    def map(self, tasks: Iterable[Any], *extra: Any) -> Iterator[Any]:
        """`fly(task, *extra)` for every task (all submitted at once); results in the tasks' order."""
        pending = deque(self.submit(t, *extra) for t in tasks)
        try:
            while pending:
                yield self.result(pending[0])
                pending.popleft()
        finally:
            for handle in pending:
                self.cancel(handle)

    def close(self) -> None:
        """Stop the workers (tasks not started are dropped; after a worker died, the others are ended too)."""
        if self._pool is not None:
            if any_worker_ended(self._pool):             # (a dead worker stays ended: nothing to remember)
                procs = list((getattr(self._pool, '_processes', None) or {}).values())
                writer = getattr(getattr(self._pool, '_result_queue', None), '_writer', None)
                # tasks still queued for the dead workers: their feeder thread would block the exit on a full pipe
                call_queue = getattr(self._pool, '_call_queue', None)
                if call_queue is not None:
                    call_queue.cancel_join_thread()
                self._pool.shutdown(wait=False, cancel_futures=True)      # (drops the executor's references)
                for proc in procs:
                    if not _has_ended(proc):
                        proc.terminate()
                for proc in procs:
                    proc.join(EXIT_STATUS_WAIT_S)
                # With every worker gone, this process holds the last write end of the results pipe: closing it
                # ends (EOF) a read the executor's manager thread may be stuck in, on a result a killed worker
                # cut short, so the thread ends and the interpreter can exit.
                if writer is not None:
                    writer.close()
            else:
                self._pool.shutdown(wait=True, cancel_futures=True)
        else:
            for actor in self._actors:
                self._ray.kill(actor)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
