"""Shared rclpy plumbing for every node in the workspace (parameters, QoS, diagnostics, main)."""
from __future__ import annotations

import logging
import math
import sys
import threading
from collections import Counter
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Mapping, Sequence

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TwistStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy._rclpy_pybind11 import RCLError
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
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


@dataclass(frozen=True)
class Param:
    """One declared node parameter: default value and a human description."""

    default: Any
    description: str


def declare_parameters(node: Node, spec: Mapping[str, Param]) -> dict[str, Any]:
    """Declare every parameter in `spec` with a descriptor and return the current values."""
    values = {}
    for name, p in spec.items():
        node.declare_parameter(name, p.default, ParameterDescriptor(description=p.description))
        values[name] = node.get_parameter(name).value
    return values


def stamp_to_sec(stamp) -> float:
    """builtin_interfaces/Time -> float seconds."""
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


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
        self._timer = node.create_timer(period_s, self.publish)

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


def run_node(factory: Callable[[], Node], args: list[str] | None = None,
             num_threads: int = 1) -> int:
    """Init rclpy, build the node, spin it, always clean up; returns the process exit code.

    num_threads 1 (default) spins a SingleThreadedExecutor: nodes keep heavy work on their own
    threads, and rclpy 7.1's MultiThreadedExecutor burns a core on its bookkeeping at ~100
    callbacks/s. A node whose callbacks would otherwise queue behind each other (sim_node's
    /cmd_vel behind its GIL-heavy sim thread) asks for more threads; blocking waits belong in
    coroutine callbacks (see mavlink_bridge_node's services). A StartupError raised by `factory` (nodes wrap bad parameters, missing
    models and unreachable endpoints in it) is reported as one clear line on stderr and gives
    exit code 1, no traceback.
    """
    logging.basicConfig(level=logging.INFO, format='[%(levelname)s] [%(name)s]: %(message)s')
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = factory()
        executor = (SingleThreadedExecutor() if num_threads <= 1
                    else MultiThreadedExecutor(num_threads=num_threads))
        executor.add_node(node)
        executor.spin()
    except StartupError as exc:
        sys.stderr.write(f'error: {exc}\n')
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        if rclpy.ok():      # a real failure, not the context going away under SIGINT
            raise
    finally:
        if node is not None:
            close = getattr(node, 'close', None)
            if callable(close):
                close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return code
