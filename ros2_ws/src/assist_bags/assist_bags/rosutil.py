"""Small rclpy helpers shared by bag_record and bag_play (type lookup, QoS <-> bag metadata, CLI front end)."""
from __future__ import annotations

import argparse
import importlib
import sys
from typing import Any
from collections.abc import Mapping

from rclpy.duration import Duration
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from assist_common.ros_params import HELP_FLAGS, VERSION_FLAG, Param, node_help, version_text


def message_class(msgtype: str) -> Any | None:
    """The installed Python class of 'pkg/msg/Type' (or 'pkg/Type'); None when this install lacks it."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        return None
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{parts[1]}'), parts[2])
    except (ImportError, AttributeError, ValueError):
        return None


def _qtime(d: Duration | Any) -> QosTime:
    ns = int(getattr(d, 'nanoseconds', 0))
    if ns <= 0 or ns >= 2**63 - 1:
        return QosTime(9223372036, 854775807)
    return QosTime(ns // 1_000_000_000, ns % 1_000_000_000)


def bag_qos(q: QoSProfile) -> Qos:
    """rclpy QoSProfile (e.g. a publisher's offered profile) -> rosbags Qos for bag metadata."""
    def enum(cls, value, default):
        try:
            return cls(int(value))
        except (ValueError, TypeError):
            return default
    return Qos(enum(QosHistory, q.history, QosHistory.KEEP_LAST), int(q.depth),
               enum(QosReliability, q.reliability, QosReliability.RELIABLE),
               enum(QosDurability, q.durability, QosDurability.VOLATILE),
               _qtime(q.deadline), _qtime(q.lifespan), enum(QosLiveliness, q.liveliness, QosLiveliness.AUTOMATIC),
               _qtime(q.liveliness_lease_duration), bool(q.avoid_ros_namespace_conventions))


def ros_qos(profiles: list[Qos], depth: int = 10) -> QoSProfile:
    """A publisher QoS for replaying a topic recorded with these offered profiles (like ros2 bag play)."""
    reliable = not profiles or all(p.reliability != QosReliability.BEST_EFFORT for p in profiles)
    latched = bool(profiles) and all(p.durability == QosDurability.TRANSIENT_LOCAL for p in profiles)
    d = max([depth] + [int(p.depth) for p in profiles if p.history == QosHistory.KEEP_LAST])
    return QoSProfile(depth=d, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


def cli_to_ros_args(prog: str, description: str, params: Mapping[str, Param], argv: list[str],
                    positional: str | None = None) -> list[str]:
    """argparse front end for a node: --flag per parameter -> rclpy args with -p name:=value.

    `--help` and `--version` (before any --ros-args) answer as every node executable does (the parameter table;
    the package's version) and exit 0 without starting the node.
    """
    ros_tail: list[str] = []
    if '--ros-args' in argv:
        i = argv.index('--ros-args')
        argv, ros_tail = argv[:i], argv[i:]
    if any(a in HELP_FLAGS for a in argv):
        summary = description.strip().splitlines()[0] if description.strip() else ''
        flags = (f'Each parameter is also a --flag (--{next(iter(params)).replace("_", "-")} VALUE sets '
                 f'{next(iter(params))})' + (f'; the first argument sets {positional}' if positional else '') + '.')
        sys.stdout.write(node_help(prog, summary, params) + '\n' + flags + '\n')
        raise SystemExit(0)
    if VERSION_FLAG in argv:
        sys.stdout.write(version_text(prog, __name__.split('.')[0]))
        raise SystemExit(0)
    parser = argparse.ArgumentParser(prog=prog, description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog='Any --ros-args ... after the flags go to rclpy unchanged.')
    if positional:
        parser.add_argument(positional, nargs='?', help=params[positional].description)
    for name, p in params.items():
        if name == positional:
            continue
        flag = '--' + name.replace('_', '-')
        if isinstance(p.default, bool):
            parser.add_argument(flag, choices=('true', 'false'), help=f'{p.description} (default: {p.default})')
        elif isinstance(p.default, (list, tuple)) or p.default == Parameter.Type.STRING_ARRAY:
            parser.add_argument(flag, nargs='*', help=f'{p.description}')
        else:
            parser.add_argument(flag, help=f'{p.description} (default: {p.default!r})')
    ns = parser.parse_args(argv)
    sets = []
    for name in params:
        v = getattr(ns, name, None)
        if v is None:
            continue
        if isinstance(v, list):
            if not v:
                continue
            v = '[' + ','.join(f"'{x}'" for x in v) + ']'
        elif isinstance(params[name].default, str):
            v = f"'{v}'"
        sets += ['-p', f'{name}:={v}']
    if not sets:
        return ros_tail
    if ros_tail:
        return ros_tail + sets
    return ['--ros-args'] + sets
