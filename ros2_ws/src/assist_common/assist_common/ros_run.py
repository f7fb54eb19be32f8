"""Running a node process: the executor, the spin off the main thread, stop signals, and a bounded teardown
(``run_node``, ``exit_process``)."""
from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import gc
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping

import rclpy
import rclpy.logging
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from .console import exit_now
from .ros_io import forward_logging
from .ros_params import Param, StartupError, check_overrides, console_request

EXECUTORS = ('single', 'multi', 'events')
EXECUTOR_PARAM = 'executor'


class EventsExecutorLoop:
    """rclpy.experimental.EventsExecutor (C++ event queue: no Python wait-set rebuild per wake-up),
    spun with spin_once (spin_until_stopped): in the rclpy 7.1.6 wheel its spin() dispatches nothing
    and busy-loops (a 10 Hz timer never fired in 2 s at ~60 % of a core), while spin_once delivers
    timers (steady and sim time), subscriptions and services."""

    def __init__(self, context=None) -> None:
        from rclpy.experimental import EventsExecutor
        self._context = context or rclpy.get_default_context()
        self._executor = EventsExecutor(context=self._context)

    def add_node(self, node: Node) -> None:
        """Serve `node`'s callbacks."""
        self._executor.add_node(node)

    def spin_once(self, timeout_sec: float | None = None) -> None:
        """Dispatch what is ready, waiting up to `timeout_sec` for something."""
        self._executor.spin_once(timeout_sec=timeout_sec)

    def shutdown(self) -> None:
        """Stop serving; spin returns after its current callback."""
        self._executor.shutdown()


REALTIME_PARAM = 'realtime_priority'


def realtime_priority_param(default: int = 0) -> Param:
    """The `realtime_priority` node parameter that run_node honours (one definition for every node)."""
    return Param(default, 'SCHED_FIFO priority (1-99) for every thread of this node\'s process (executor, '
                          'inference, middleware), as ros2_control does for its control loop; 0 = the normal '
                          'scheduler. Needs root, CAP_SYS_NICE or an rtprio limit (/etc/security/limits.conf); '
                          'without the right the node logs a warning and runs normally.', min=0, max=99)


def set_realtime_priority(priority: int, pid: int | None = None) -> int:
    """Put every thread of process `pid` (default: this one) under SCHED_FIFO `priority`, or back
    under SCHED_OTHER for 0; threads started later inherit it (so no SCHED_RESET_ON_FORK: it applies to
    new threads too). Returns the number of threads changed; raises PermissionError without the right, ValueError for
    a priority outside 0-99."""
    if not 0 <= int(priority) <= 99:
        raise ValueError(f'realtime priority must be 0-99, got {priority}')
    pid = os.getpid() if pid is None else int(pid)
    if priority > 0:
        policy, param = os.SCHED_FIFO, os.sched_param(int(priority))
    else:
        policy, param = os.SCHED_OTHER, os.sched_param(0)
    changed = 0
    for tid in os.listdir(f'/proc/{pid}/task'):
        try:
            os.sched_setscheduler(int(tid), policy, param)
        except ProcessLookupError:      # the thread ended meanwhile
            continue
        changed += 1
    return changed


def _apply_realtime_priority(node: Node) -> None:
    """Honour the node's `realtime_priority` parameter (if it declares one); never fails the node."""
    if not node.has_parameter(REALTIME_PARAM):
        return
    prio = int(node.get_parameter(REALTIME_PARAM).value)
    if prio <= 0:
        return
    try:
        n = set_realtime_priority(prio)
    except PermissionError:
        node.get_logger().warning(f'realtime_priority {prio}: no right to use SCHED_FIFO (run as root, give the '
                                  'binary CAP_SYS_NICE, or set an rtprio limit); running with the normal scheduler')
        return
    node.get_logger().info(f'realtime_priority: SCHED_FIFO {prio} on {n} threads')


def executor_param(default: str = 'events') -> Param:
    """The `executor` node parameter that run_node honours (one definition for every node)."""
    return Param(default, 'rclpy executor: events (rclpy.experimental.EventsExecutor: a C++ event queue, least '
                          'CPU and latency), single (SingleThreadedExecutor) or multi (MultiThreadedExecutor).',
                 choices=EXECUTORS)


class PoolWaitingExecutor(MultiThreadedExecutor):
    """MultiThreadedExecutor whose shutdown waits for the callbacks still running in its thread pool.

    rclpy 7.1's Executor.shutdown tests `_is_shutdown` right after setting it, so it never waits for
    outstanding work; spin returns at context shutdown while pool threads are mid-callback, and a node
    destroyed then has callbacks running into a dead node.
    """

    def shutdown(self, timeout_sec: float | None = None) -> bool:
        """Stop taking callbacks, then wait until the pool's running ones have returned."""
        done = super().shutdown(timeout_sec)
        self._executor.shutdown(wait=True)      # rclpy's ThreadPoolExecutor of this executor
        return done


def make_executor(kind: str, num_threads: int = 2, context=None):
    """An executor by name: single (SingleThreadedExecutor), multi (MultiThreadedExecutor with
    `num_threads`, at least 2; a PoolWaitingExecutor), events (EventsExecutorLoop); ValueError for any
    other name."""
    if kind == 'single':
        return SingleThreadedExecutor(context=context)
    if kind == 'multi':
        return PoolWaitingExecutor(num_threads=max(2, int(num_threads)), context=context)
    if kind == 'events':
        return EventsExecutorLoop(context=context)
    raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}, got {kind!r}")


def freeze_startup_heap() -> int:
    """Collect garbage once, then freeze every object alive now (imports, models, the node) out of
    the cyclic collector's view: a full collection then scans only what the running node allocates
    (unfrozen, one took 40-250 ms in sim_node, encoder_node and policy_node: a stalled frame).
    Returns the number of frozen objects."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


SHUTDOWN_GRACE_S = 1.0


def _context_going_down(grace_s: float) -> bool:
    """True once rclpy's default context is shut down, waiting up to `grace_s` for it."""
    end = time.monotonic() + grace_s
    while rclpy.ok():
        if time.monotonic() >= end:
            return False
        time.sleep(0.02)
    return True


SPIN_STOP_TIMEOUT_S = 5.0
#: A node still going down this long after a stop signal writes every thread's stack to stderr (see _going_down).
SHUTDOWN_STACKS_S = 8.0
#: exit_process: flushing and exiting taking this long writes every thread's stack and exits with code 1.
EXIT_STACKS_S = 5.0
#: After a stop signal, the node's destruction (rcl_node_fini, which deletes the middleware's participant) and the
#: context's shutdown taking this long write every thread's stack and end the process with run_node's exit code
#: (TeardownDeadline): 10x a slow destruction on a loaded machine (0.1-0.3 s), and with the stop and close()
#: before it still inside launch's 5 s from SIGINT to SIGTERM.
TEARDOWN_DEADLINE_S = 3.0
#: TeardownDeadline: time between the stack dump and the exit, for the dump to be written first.
TEARDOWN_DUMP_LEAD_S = 0.5
STOP_POLL_S = 0.1
#: The main thread's longest uninterrupted wait while a node spins: a stop signal taken by another thread is
#: acted on within this (spin_off_main_thread).
SIGNAL_POLL_S = 0.1


def spin_until_stopped(spinner, stop: threading.Event, context=None, poll_s: float = STOP_POLL_S) -> None:
    """Dispatch `spinner`'s callbacks (spin_once) until `stop` is set or `context` (default: rclpy's
    default context) shuts down; returns after the callback in progress has finished."""
    context = context or rclpy.get_default_context()
    try:
        while not stop.is_set() and context.ok():
            spinner.spin_once(timeout_sec=poll_s)
    except ExternalShutdownException:
        if context.ok():            # raised while the context is up: not the shutdown this loop ends on
            raise


def spin_off_main_thread(spinner, teardown: Callable[[], None] | None = None, context=None) -> None:
    """Spin `spinner` on a worker thread while the main thread only waits for it; returns when it stops.

    Python runs signal handlers on the main thread, between two bytecodes of whatever it is doing:
    spun there, a Ctrl-C raised KeyboardInterrupt inside a callback halfway through its work (seen
    in CI: policy_node's history push, which the events executor then logged as FATAL). Here it is
    raised in this wait, and the shutdown is ordered: the worker is told to stop dispatching, the
    callback it is in finishes, the executor is shut down and `teardown` (run_node: the node's
    close()) runs on the worker, the thread its callbacks ran on (sqlite connections, for one, refuse
    any other); all of it while the context is still valid, so a callback or close() that logs or
    publishes then still reaches /rosout (rclpy's own SIGINT handler shut the context down at once,
    under a running callback: CI saw "Failed to publish log message to rosout: publisher's context
    is invalid" from a timer's log line). The caller shuts the context down afterwards. Should the
    worker not come back within SPIN_STOP_TIMEOUT_S (a callback blocked on something that never
    comes), the context is shut down to release it. An exception that ends spin or teardown on the
    worker is re-raised here.
    """
    failure: list[BaseException] = []
    finished = threading.Event()
    stop = threading.Event()

    def spin() -> None:
        try:
            spin_until_stopped(spinner, stop, context)
        except ExternalShutdownException:
            pass
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread, re-raised below
            failure.append(exc)
        try:
            spinner.shutdown()          # waits for callbacks still running (MultiThreadedExecutor's pool)
            if teardown is not None:
                teardown()
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread, re-raised below
            failure.append(exc)
        finally:
            finished.set()

    worker = threading.Thread(target=spin, name='rclpy_spin', daemon=True)
    try:
        worker.start()
        # A timed wait, again and again: the kernel hands a process-wide signal (Ctrl-C, launch's SIGINT) to
        # any thread that does not block it (the middleware's, the node's own), and then Python's C handler
        # only raises a flag; the main thread runs the Python handler at its next bytecode, which a wait
        # without a timeout never reaches (sim_node ignored a Ctrl-C until launch's SIGKILL).
        while not finished.wait(SIGNAL_POLL_S):
            pass
    finally:
        # Not worker.join()/is_alive(): a join interrupted by Ctrl-C marks the running thread as
        # stopped (CPython's bpo-45274 fix releases its lock), and the node was then closed twice,
        # under a live executor (CI: pybullet "Not connected to physics server").
        if not finished.is_set():       # interrupted: stop dispatching, let the running callback finish
            _going_down()               # a second Ctrl-C must not cut this short
            stop.set()
            if not finished.wait(SPIN_STOP_TIMEOUT_S):
                logging.getLogger(__name__).warning(
                    'executor still in a callback %.0f s after Ctrl-C; shutting the context down', SPIN_STOP_TIMEOUT_S)
                rclpy.try_shutdown(context=context)
                if not finished.wait(SPIN_STOP_TIMEOUT_S):
                    logging.getLogger(__name__).warning('executor still in a callback; cleaning up anyway')
        faulthandler.cancel_dump_traceback_later()
    if failure:
        raise failure[0]


@contextlib.contextmanager
def _stop_signals_deferred():
    """A SIGINT/SIGTERM arriving inside the block is acted on (KeyboardInterrupt) when the block ends.

    rclpy's Executor.__init__ interrupted half-way leaves an object whose __del__ fails (CI: "Exception
    ignored in Executor.__del__ ... no attribute '_sigint_gc'" after a Ctrl-C during start-up), so an
    executor is built whole or not at all. From the main thread only (signal handlers live there).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum, frame) -> None:
        received.append(signum)
    previous = {sig: signal.signal(sig, hold) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if received:
        raise KeyboardInterrupt(f'signal {received[0]}')


def _interrupt(signum, frame) -> None:
    """SIGTERM handler: stop the node as a Ctrl-C does (rclpy's own handler is not installed)."""
    raise KeyboardInterrupt(f'signal {signum}')



def run_node(factory: Callable[[], Node], args: list[str] | None = None,
             num_threads: int = 1, executor: str | None = None,
             params: Mapping[str, Param] | None = None) -> int:
    """Init rclpy, build the node, spin it, always clean up; returns the process exit code.

    `-h`/`--help` (parameter table `params`: name, type, default, range, run-time or read-only,
    description) and `--version` (the package's version) before any `--ros-args` are answered on
    stdout with exit code 0, without starting rclpy or building the node; the program name and
    package come from the module that defines `factory`.

    num_threads 1 (default) spins a SingleThreadedExecutor: nodes keep heavy work on their own
    threads, and rclpy 7.1's MultiThreadedExecutor burns a core on its bookkeeping at ~100
    callbacks/s. A node whose callbacks would otherwise queue behind each other (sim_node's
    /cmd_vel behind its GIL-heavy sim thread) asks for more threads; blocking waits belong in
    coroutine callbacks (see mavlink_bridge_node's services). `executor` names the kind
    (make_executor); a node that declares the parameter `executor` chooses it at run time. Once
    the node is built, its threads get the SCHED_FIFO priority of its `realtime_priority` parameter
    (if declared and > 0) and the start-up heap is frozen out of the garbage collector's way. The
    executor spins off the main thread (spin_off_main_thread), so a Ctrl-C never lands inside a
    callback, and the node's close() (if it has one) runs on the thread its callbacks ran on.
    SIGINT and SIGTERM stop the executor first and shut the context down last (rclpy's own signal
    handlers are not installed), so what a callback or close() logs meanwhile still reaches /rosout.
    After a stop signal the node's destruction and the context's shutdown run under a TeardownDeadline:
    should the middleware's teardown hang (it holds the GIL), every thread's stack goes to stderr and
    the process ends with the code run_node would return, TEARDOWN_DEADLINE_S after the destruction
    began, instead of waiting for launch's SIGKILL; the node then leaves the graph only when its peers'
    discovery lease on it runs out. A
    StartupError raised by `factory` (nodes wrap bad parameters, missing models and unreachable
    endpoints in it) is reported as one clear line on stderr and gives exit code 1, no traceback.
    Python `logging` records go to the node's logger (/rosout).
    """
    answer = console_request(factory, args, params)
    if answer is not None:
        sys.stdout.write(answer)
        return 0
    # rclpy's SIGINT/SIGTERM handler would shut the context down at once, under a running callback;
    # spin_off_main_thread stops the executor first and the context goes down last (below).
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, _interrupt)
    handler = forward_logging(None)
    node = None
    code = 0
    stop_signal = False                 # SIGINT/SIGTERM ended the node: the process is going down
    deadline: TeardownDeadline | None = None
    closed = threading.Event()

    def close_node() -> None:
        try:
            close = getattr(node, 'close', None)
            if callable(close):
                close()
        finally:
            closed.set()
    try:
        node = factory()
        handler.attach(node)
        check_overrides(node)
        kind = executor or ('single' if num_threads <= 1 else 'multi')
        if node.has_parameter(EXECUTOR_PARAM):
            kind = node.get_parameter(EXECUTOR_PARAM).value
        with _stop_signals_deferred():
            spinner = make_executor(kind, num_threads)
            spinner.add_node(node)
        _apply_realtime_priority(node)
        freeze_startup_heap()
        spin_off_main_thread(spinner, teardown=close_node)
    except StartupError as exc:
        sys.stderr.write(f'error: {exc}\n')
        code = 1
    except KeyboardInterrupt:           # SIGINT or SIGTERM (the handlers installed above)
        stop_signal = True
    except ExternalShutdownException:
        pass
    except RuntimeError:                # RCLError is one too
        # A Ctrl-C that lands while rclpy is inside C++ (take_message, the events executor) surfaces
        # as RCLError or as pybind11's RuntimeError "Unable to convert call argument '0' to Python
        # object" (seen in CI, any executor), sometimes just before rclpy's handler has shut the
        # context down. Not a failure if the context goes down within a second; otherwise re-raised.
        if not _context_going_down(SHUTDOWN_GRACE_S):
            raise
    finally:
        # Going down: another Ctrl-C (a second key press, or launch's SIGINT/SIGTERM to a node that is
        # already exiting) must not interrupt the clean-up with a KeyboardInterrupt traceback.
        _going_down()
        try:
            if node is not None:
                if not closed.is_set():     # never spun (start-up failed), or the executor never came back
                    close_node()
                handler.attach(None)
                if stop_signal:
                    deadline = TeardownDeadline.arm(TEARDOWN_DEADLINE_S, code)
                node.destroy_node()
            if rclpy.ok():
                rclpy.try_shutdown()
        finally:
            if deadline is not None:
                deadline.cancel()
            faulthandler.cancel_dump_traceback_later()
    return code


def exit_process(code: int) -> None:
    """End a node process after run_node: flush output and exit without interpreter finalization.

    Everything of the node is cleaned up by then (threads stopped, node destroyed, rclpy shut
    down); tearing down torch's and the middleware's modules at interpreter exit takes another
    2-4 s on a loaded machine, which makes `ros2 launch` escalate a Ctrl-C to SIGTERM.
    """
    _going_down()
    faulthandler.dump_traceback_later(EXIT_STACKS_S, exit=True, file=sys.stderr)
    exit_now(code)


def _going_down() -> None:
    """The process is going down: further stop signals are not obeyed, and a hang says where it is.

    SIGINT is ignored; SIGTERM (launch's escalation 5 s after its SIGINT) and SHUTDOWN_STACKS_S
    without an exit write the stack of every thread to stderr. Both are faulthandler's: its signal
    handler and its watchdog thread run in C without the GIL, so they report even a process in which
    no Python code can run any more (a thread stuck in an extension while holding the GIL), where a
    log line would never come. From the main thread only (signal handlers live there).
    """
    if threading.current_thread() is not threading.main_thread():
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        faulthandler.register(signal.SIGTERM, file=sys.stderr, all_threads=True, chain=False)
        faulthandler.dump_traceback_later(SHUTDOWN_STACKS_S, file=sys.stderr)
    except (AttributeError, ValueError, OSError, RuntimeError) as exc:   # no usable stderr (closed, replaced)
        logging.getLogger(__name__).debug('no stack dump on a stuck shutdown: %s', exc)


class _SigEvent(ctypes.Structure):
    """glibc's struct sigevent (64 bytes): the fields SIGEV_THREAD uses, the rest of its union as padding."""

    _fields_ = [('sigev_value', ctypes.c_void_p), ('sigev_signo', ctypes.c_int), ('sigev_notify', ctypes.c_int),
                ('sigev_notify_function', ctypes.c_void_p), ('sigev_notify_attributes', ctypes.c_void_p),
                ('_pad', ctypes.c_byte * 32)]


class _TimeSpec(ctypes.Structure):
    _fields_ = [('tv_sec', ctypes.c_long), ('tv_nsec', ctypes.c_long)]


class _ITimerSpec(ctypes.Structure):
    _fields_ = [('it_interval', _TimeSpec), ('it_value', _TimeSpec)]


_SIGEV_THREAD = 2      # <signal.h>: the expiry calls sigev_notify_function(sigev_value) on a new thread


class TeardownDeadline:
    """Ends the process with a given exit code unless cancelled in time, even while a thread holds the GIL.

    rclpy's Node.destroy_node ends in rcl_node_fini, which for a process's last node deletes the
    middleware's participant (Fast DDS joins its threads there), all of it holding the GIL: should it
    never return (seen in CI: sim_node after launch's SIGINT, its main thread in destroy_node until
    launch's SIGKILL), no Python code of the process can run again, so neither a timed wait on another
    thread nor a signal handler can bound it. A POSIX timer whose expiry calls libc's _exit(code) on a
    thread of its own (SIGEV_THREAD) needs no GIL; faulthandler's watchdog writes every thread's stack
    TEARDOWN_DUMP_LEAD_S before. An _exit runs no clean-up: the caller flushes what it wrote (arm
    flushes sys.stdout and sys.stderr). Without timer_create (not glibc) only the stacks are written.
    """

    def __init__(self, timer: ctypes.c_void_p | None, libc: ctypes.CDLL | None) -> None:
        self._timer, self._libc = timer, libc

    @classmethod
    def arm(cls, seconds: float, code: int) -> TeardownDeadline:
        """Stacks to stderr after `seconds`, then _exit(`code`) TEARDOWN_DUMP_LEAD_S later, unless cancel()ed."""
        for stream in (sys.stdout, sys.stderr):     # an _exit flushes nothing
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        try:
            faulthandler.dump_traceback_later(seconds, file=sys.stderr)
        except (AttributeError, ValueError, OSError, RuntimeError) as exc:   # no usable stderr
            logging.getLogger(__name__).debug('no stack dump on a stuck teardown: %s', exc)
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            create, settime = libc.timer_create, libc.timer_settime
        except (OSError, AttributeError) as exc:
            logging.getLogger(__name__).debug('no exit deadline on a stuck teardown: %s', exc)
            return cls(None, None)
        create.argtypes = [ctypes.c_int, ctypes.POINTER(_SigEvent), ctypes.POINTER(ctypes.c_void_p)]
        settime.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.POINTER(_ITimerSpec), ctypes.c_void_p]
        libc.timer_delete.argtypes = [ctypes.c_void_p]
        event = _SigEvent(sigev_value=int(code), sigev_notify=_SIGEV_THREAD,
                          sigev_notify_function=ctypes.cast(libc._exit, ctypes.c_void_p).value)
        timer = ctypes.c_void_p()
        if create(time.CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
            logging.getLogger(__name__).debug('no exit deadline on a stuck teardown: timer_create errno %d',
                                              ctypes.get_errno())
            return cls(None, None)
        at = seconds + TEARDOWN_DUMP_LEAD_S
        spec = _ITimerSpec(it_value=_TimeSpec(int(at), int((at % 1.0) * 1e9)))
        if settime(timer, 0, ctypes.byref(spec), None) != 0:
            libc.timer_delete(timer)
            logging.getLogger(__name__).debug('no exit deadline on a stuck teardown: timer_settime errno %d',
                                              ctypes.get_errno())
            return cls(None, None)
        return cls(timer, libc)

    @property
    def armed(self) -> bool:
        """True while the exit is pending (False where the platform gave no timer, or once cancelled)."""
        return self._timer is not None

    def cancel(self) -> None:
        """The teardown finished: neither the stacks nor the exit."""
        faulthandler.cancel_dump_traceback_later()
        if self._timer is not None:
            self._libc.timer_delete(self._timer)
            self._timer = None
