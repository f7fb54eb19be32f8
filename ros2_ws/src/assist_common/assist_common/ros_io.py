"""What nodes share on the wire: QoS profiles, header stamps, twists, /diagnostics, and Python logging sent to
/rosout."""
from __future__ import annotations

import logging
import math
import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from typing import Any

import rclpy
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TwistStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

SENSOR_QOS = qos_profile_sensor_data
RELIABLE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          history=HistoryPolicy.KEEP_LAST)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
LANDING_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)

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
