"""Shared rclpy plumbing for every node in the workspace (parameters, QoS, diagnostics, main)."""
from __future__ import annotations

import ctypes
import faulthandler
import gc
import importlib.metadata
import logging
import math
import os
import signal
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Iterable, Mapping, Sequence

import rclpy
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

SENSOR_QOS = qos_profile_sensor_data
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
LANDING_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)


class StartupError(RuntimeError):
    """A node cannot start (bad parameter, missing model, unreachable endpoint): one clear line."""


_NUMERIC = (int, float)


@dataclass(frozen=True)
class Param:
    """One declared node parameter: default, description, and the rule every value must pass.

    `min`/`max` bound numeric values (inclusive unless `min_exclusive`), `choices` lists the
    accepted strings, `dynamic` marks a parameter the node applies at run time (validated by the
    parameter callback); every other parameter is declared read-only, so `ros2 param set` is
    refused instead of accepted and ignored. A float parameter accepts an integer (`-p x:=2`).
    An array parameter has a list default and `item_type` (int, float or str): every item is
    checked against `min`/`max`/`choices` (rcl's parser wants one item type: write 0.0, not 0, in a
    float array).
    """

    default: Any
    description: str
    min: float | None = None
    max: float | None = None
    min_exclusive: bool = False
    choices: tuple[str, ...] | None = None
    dynamic: bool = False
    item_type: type | None = None

    def coerce(self, name: str, value: Any) -> Any:
        """Value converted to the parameter's type and checked; ValueError with a one-line reason."""
        if self.item_type is not None:
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"parameter '{name}' must be a list, got {value!r}")
            item = Param(self.item_type(), self.description, self.min, self.max, self.min_exclusive, self.choices)
            return [item.coerce(f'{name}[{i}]', v) for i, v in enumerate(value)]
        kind = type(self.default)
        if kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"parameter '{name}' must be true or false, got {value!r}")
            return value
        if kind in _NUMERIC:
            if isinstance(value, bool) or not isinstance(value, _NUMERIC):
                raise ValueError(f"parameter '{name}' must be a number, got {value!r}")
            if kind is int:
                if isinstance(value, float):
                    if not (math.isfinite(value) and value.is_integer()):
                        raise ValueError(f"parameter '{name}' must be an integer, got {value!r}")
                    value = int(value)
            else:
                value = float(value)
                if not math.isfinite(value):
                    raise ValueError(f"parameter '{name}' must be finite, got {value!r}")
            self._check_range(name, value)
            return value
        if kind is str:
            if not isinstance(value, str):
                raise ValueError(f"parameter '{name}' must be a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise ValueError(f"parameter '{name}' must be one of {', '.join(self.choices)}; got {value!r}")
            return value
        if isinstance(self.default, (list, tuple)):
            if not isinstance(value, (list, tuple)):
                raise ValueError(f"parameter '{name}' must be a list, got {value!r}")
            return list(value)
        return value

    def rule(self) -> str:
        """The accepted values in words ('> 0.0 and <= 10.0', 'one of a, b'); empty when unrestricted."""
        if self.choices is not None:
            return 'one of ' + ', '.join(self.choices)
        lo, hi = self.min, self.max
        lo_s = '' if lo is None else (f'> {lo}' if self.min_exclusive else f'>= {lo}')
        hi_s = '' if hi is None else f'<= {hi}'
        return ' and '.join(x for x in (lo_s, hi_s) if x)

    def _check_range(self, name: str, value: float) -> None:
        lo, hi = self.min, self.max
        below = lo is not None and (value <= lo if self.min_exclusive else value < lo)
        above = hi is not None and value > hi
        if below or above:
            raise ValueError(f"parameter '{name}' must be {self.rule()}, got {value!r}")


_ARRAY_TYPES = {int: Parameter.Type.INTEGER_ARRAY, float: Parameter.Type.DOUBLE_ARRAY,
                str: Parameter.Type.STRING_ARRAY}


class ParamValues(dict):
    """The node's current (validated, coerced) parameter values; dynamic ones follow run-time sets."""


def declare_parameters(node: Node, spec: Mapping[str, Param],
                       on_change: Callable[[dict[str, Any]], None] | None = None) -> ParamValues:
    """Declare every parameter in `spec`, validate the start-up values and return them (live).

    A bad start-up value raises StartupError (one line naming the node and parameter). Parameters
    with `dynamic=True` may be set at run time: each set is validated with the same rule and then
    passed to `on_change(changed)` (which may raise ValueError to refuse it); the others are
    read-only. The returned dict is updated in place when a set is accepted.
    """
    from rcl_interfaces.msg import SetParametersResult

    values = ParamValues()
    for name, p in spec.items():
        rule = p.rule()
        text = p.description + (f' Accepted: {rule}.' if rule else '') + ('' if p.dynamic else ' Read-only.')
        desc = ParameterDescriptor(description=text, read_only=not p.dynamic,
                                   dynamic_typing=(isinstance(p.default, (int, float))
                                                   and not isinstance(p.default, bool)))
        try:
            if p.item_type is not None:      # typed array (an empty default has no type of its own)
                desc.type = _ARRAY_TYPES[p.item_type].value
                raw = node.declare_parameter(name, _ARRAY_TYPES[p.item_type], desc).value
                raw = list(p.default) if raw is None else raw
            else:
                raw = node.declare_parameter(name, p.default, desc).value
        except Exception as exc:  # rclpy raises its own type errors for e.g. a string for a bool
            raise StartupError(f'{node.get_name()}: parameter {name!r}: {exc}') from exc
        try:
            values[name] = p.coerce(name, raw)
        except ValueError as exc:
            raise StartupError(f'{node.get_name()}: {exc}') from exc

    def _on_set(params) -> SetParametersResult:
        changed = {}
        for prm in params:
            p = spec.get(prm.name)
            if p is None:
                continue  # use_sim_time and other rclpy-owned parameters
            try:
                changed[prm.name] = p.coerce(prm.name, prm.value)
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        if changed:
            old = {k: values[k] for k in changed}
            values.update(changed)
            if on_change is not None:
                try:
                    on_change(changed)
                except ValueError as exc:
                    values.update(old)
                    return SetParametersResult(successful=False, reason=str(exc))
            node.get_logger().info('parameters set: ' + ', '.join(f'{k}={v!r}' for k, v in changed.items()))
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(_on_set)
    return values


def check_overrides(node: Node) -> None:
    """StartupError (one line) when the node was given a parameter it does not declare (a misspelt name in a
    parameter file or a ``-p``), naming the closest declared one: rclpy would otherwise ignore it silently."""
    import difflib
    given = node._parameter_overrides      # rclpy keeps a node's start-up overrides only here (no public getter)
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if not unknown:
        return
    declared = sorted(node._parameters)
    hints = []
    for name in unknown:
        close = difflib.get_close_matches(name, declared, n=1)
        hints.append(f'{name!r}' + (f' (did you mean {close[0]!r}?)' if close else ''))
    raise StartupError(f'{node.get_name()}: unknown parameter{"s" if len(unknown) > 1 else ""} {", ".join(hints)}; '
                       'its --help lists the parameters')


def stamp_to_sec(stamp) -> float:
    """builtin_interfaces/Time -> float seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def sec_to_stamp(t: float, stamp=None):
    """Float seconds >= 0 -> builtin_interfaces/Time (into `stamp` if given), rounded to the nanosecond.

    Rounds the whole time, not the fraction alone: 6.9999999999 s is 7 s 0 ns, never 6 s 0 ns."""
    from builtin_interfaces.msg import Time
    stamp = Time() if stamp is None else stamp
    sec, nanosec = divmod(int(round(float(t) * 1e9)), 1_000_000_000)
    stamp.sec, stamp.nanosec = int(sec), int(nanosec)
    return stamp


STAMP_TOLERANCE_S = 0.25    # default: a header stamp this far ahead of the node's clock is still accepted


def stamp_problem(stamp_s: float | None, now_s: float, max_age_s: float,
                  tolerance_s: float = STAMP_TOLERANCE_S) -> tuple[str, str] | None:
    """Why a message's header stamp makes it unusable at `now_s` (the node's clock, sim or wall), else None.

    (reason key, text): ``future_stamp`` when the stamp lies more than `tolerance_s` ahead, ``stale_stamp``
    when it is older than `max_age_s`. An unset stamp (None: 0 in the message) is judged by arrival: None.
    """
    if stamp_s is None:
        return None
    if stamp_s - now_s > tolerance_s:
        return 'future_stamp', f'stamped {stamp_s - now_s:.3f} s ahead of the clock (tolerance {tolerance_s:g} s)'
    if now_s - stamp_s > max_age_s:
        return 'stale_stamp', f'stamped {now_s - stamp_s:.3f} s ago (older than {max_age_s:g} s)'
    return None


def twist_to_array(msg: TwistStamped):
    """Linear part of a TwistStamped as a 3-vector (numpy), without validation."""
    import numpy as np
    v = msg.twist.linear
    return np.array([v.x, v.y, v.z], dtype=float)


def fill_twist(msg: TwistStamped, v: Sequence[float]) -> TwistStamped:
    """Write a 3-vector into the linear part of a TwistStamped (angular left at zero)."""
    msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z = (float(x) for x in v[:3])
    return msg


def all_finite(values: Iterable[float]) -> bool:
    """True when every value is a finite float."""
    return all(math.isfinite(float(x)) for x in values)


class Diagnostics:
    """Thread-safe counters and key/values published as one DiagnosticStatus on /diagnostics."""

    def __init__(self, node: Node, name: str | None = None, period_s: float = 1.0,
                 topic: str = '/diagnostics'):
        self._node = node
        self._name = name or node.get_fully_qualified_name()
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._values: dict[str, str] = {}
        self._level = 0  # DiagnosticStatus.OK
        self._message = 'ok'
        self._pub = node.create_publisher(DiagnosticArray, topic, 10)
        # a steady timer: the status keeps coming when sim time stalls or races (stamps: node clock)
        self._timer = node.create_timer(period_s, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def count(self, key: str, n: int = 1) -> None:
        """Increment counter `key`."""
        with self._lock:
            self._counts[key] += n

    def get(self, key: str) -> int:
        """Current value of counter `key`."""
        with self._lock:
            return self._counts[key]

    def set(self, key: str, value: Any) -> None:
        """Set a key/value shown in the status."""
        with self._lock:
            self._values[key] = str(value)

    def status(self, level: int, message: str) -> None:
        """Set the overall level (DiagnosticStatus.OK/WARN/ERROR/STALE) and message."""
        with self._lock:
            self._level = level if isinstance(level, int) else int.from_bytes(level, 'little')
            self._message = message

    def publish(self) -> None:
        """Publish the current status now."""
        with self._lock:
            st = DiagnosticStatus()
            st.level = bytes([self._level])
            st.name = self._name
            st.message = self._message
            st.hardware_id = self._node.get_name()
            kv = [KeyValue(key=k, value=str(v)) for k, v in sorted(self._counts.items())]
            kv += [KeyValue(key=k, value=v) for k, v in sorted(self._values.items())]
            st.values = kv
        arr = DiagnosticArray()
        arr.header.stamp = self._node.get_clock().now().to_msg()
        arr.status = [st]
        self._pub.publish(arr)


class RosLogHandler(logging.Handler):
    """Forwards Python `logging` records (cores, libraries) to a node's rclpy logger.

    Each Python logger becomes a child of the node's logger (`sim_node.assist_sim.mavlink_vehicle`),
    so the messages get rclpy's timestamps and console format and reach /rosout. Without a node
    (before it exists, after it is destroyed) records go to an rclpy logger of the same name:
    console only.
    """

    def __init__(self) -> None:
        super().__init__(level=logging.DEBUG)
        self.setFormatter(logging.Formatter('%(message)s'))
        self._node: Node | None = None
        self._loggers: dict[str, Any] = {}
        self._map_lock = threading.Lock()

    def attach(self, node: Node | None) -> None:
        """Forward to `node`'s logger from now on (None: console only)."""
        with self._map_lock:
            self._node = node
            self._loggers = {}

    def _logger(self, name: str):
        with self._map_lock:
            logger = self._loggers.get(name)
            if logger is None:
                if self._node is not None:
                    logger = self._node.get_logger().get_child(name or 'python')
                else:
                    logger = rclpy.logging.get_logger(name or 'python')
                self._loggers[name] = logger
            return logger

    def emit(self, record: logging.LogRecord) -> None:
        """Send one record at the matching rclpy severity (debug for anything below INFO)."""
        try:
            text = self.format(record)
            logger = self._logger(record.name)
            # one call site per severity: rclpy ties a call site to one severity
            if record.levelno >= logging.CRITICAL:
                logger.fatal(text)
            elif record.levelno >= logging.ERROR:
                logger.error(text)
            elif record.levelno >= logging.WARNING:
                logger.warning(text)
            elif record.levelno >= logging.INFO:
                logger.info(text)
            else:
                logger.debug(text)
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


_LOG_HANDLER: RosLogHandler | None = None


def forward_logging(node: Node | None) -> RosLogHandler:
    """Route the root Python logger (level INFO) to `node`'s rclpy logger; returns the one handler.

    run_node calls it with the node it built; a node may call it first thing in __init__ so that
    messages logged while it starts up reach /rosout too.
    """
    global _LOG_HANDLER
    root = logging.getLogger()
    if _LOG_HANDLER is None:
        _LOG_HANDLER = RosLogHandler()
    if _LOG_HANDLER not in root.handlers:
        for h in list(root.handlers):   # e.g. a basicConfig stream handler: one console line per message
            if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler):
                root.removeHandler(h)
        root.addHandler(_LOG_HANDLER)
    if root.level == logging.NOTSET or root.level > logging.INFO:
        root.setLevel(logging.INFO)
    _LOG_HANDLER.attach(node)
    return _LOG_HANDLER


def release_logging() -> None:
    """Undo forward_logging: the handler forgets its node and leaves the root logger (a process that built nodes
    in turn, e.g. a test run, must not log one's records under the name of a node destroyed before)."""
    if _LOG_HANDLER is not None:
        _LOG_HANDLER.attach(None)
        logging.getLogger().removeHandler(_LOG_HANDLER)


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


def _interrupt(signum, frame) -> None:
    """SIGTERM handler: stop the node as a Ctrl-C does (rclpy's own handler is not installed)."""
    raise KeyboardInterrupt(f'signal {signum}')


HELP_FLAGS = ('-h', '--help')
VERSION_FLAG = '--version'


def package_version(package: str) -> str:
    """Version of an installed package: its Python distribution's, else its package.xml's in the ament index."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        from ament_index_python.packages import get_package_share_directory
        version = ET.parse(os.path.join(get_package_share_directory(package), 'package.xml')).findtext('version')
    except (ImportError, LookupError, OSError, ValueError, ET.ParseError):
        version = None
    return (version or 'unknown').strip()


def _param_type(p: Param) -> str:
    """ROS type name of a parameter's values (bool, integer, double, string, or an array of one)."""
    names = {bool: 'bool', int: 'integer', float: 'double', str: 'string'}
    if p.item_type is not None:
        return names[p.item_type] + '[]'
    return names.get(type(p.default), type(p.default).__name__)


def parameter_help(params: Mapping[str, Param]) -> str:
    """One entry per parameter: name, type, default, accepted values, run-time or read-only, description."""
    lines = []
    for name, p in params.items():
        rule = p.rule()
        facts = [_param_type(p), f'default {p.default!r}'] + ([rule] if rule else [])
        facts.append('run-time' if p.dynamic else 'read-only')
        lines.append(f'  {name} ({"; ".join(facts)})')
        lines.append(f'      {p.description}')
    return '\n'.join(lines)


def parameter_table(params: Mapping[str, Param]) -> str:
    """The parameters as a Markdown table (name, type, default, accepted, run-time, description): docs/nodes.md."""
    def cell(text: str) -> str:
        return str(text).replace('|', '\\|').replace('\n', ' ')
    rows = ['| parameter | type | default | accepted | run-time | description |',
            '| --- | --- | --- | --- | --- | --- |']
    for name, p in params.items():
        rows.append(f'| `{name}` | {_param_type(p)} | `{p.default!r}` | {cell(p.rule() or "any")} | '
                    f'{"yes" if p.dynamic else "no"} | {cell(p.description)} |')
    return '\n'.join(rows)


def node_help(prog: str, summary: str, params: Mapping[str, Param] | None) -> str:
    """The --help text of node executable `prog`: usage, `summary`, and its parameter table."""
    text = [f'usage: {prog} [-h] [--version] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] ...]', '']
    if summary:
        text += [summary, '']
    if params:
        text += ['parameters (-p NAME:=VALUE; run-time ones also by `ros2 param set`):', parameter_help(params)]
    else:
        text += ['parameters: see `ros2 param describe` on the running node']
    return '\n'.join(text) + '\n'


def console_request(factory: Callable[[], Node], args: list[str] | None,
                    params: Mapping[str, Param] | None) -> str | None:
    """The text --help or --version asks for (flags before --ros-args only), else None: the node should start."""
    argv = sys.argv[1:] if args is None else list(args)
    own = argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
    if not any(a in HELP_FLAGS or a == VERSION_FLAG for a in own):
        return None
    module = getattr(factory, '__module__', None) or __name__
    package, prog = module.split('.')[0], module.rsplit('.', 1)[-1]
    if any(a in HELP_FLAGS for a in own):
        doc = (getattr(sys.modules.get(module), '__doc__', None) or '').strip()
        return node_help(prog, doc.splitlines()[0] if doc else '', params)
    return version_text(prog, package)


def version_text(prog: str, package: str) -> str:
    """The --version answer of executable `prog` of `package`: 'prog (package) version'."""
    return f'{prog} ({package}) {package_version(package)}\n'


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
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


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
