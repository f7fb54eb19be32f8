"""landing_runner: fly landing episodes on an autopilot (ArduCopter SITL or the sim's MAVLink vehicle).

Thin rclpy shell over assist_bridge.landing_runner_core: for each episode announced by a new
/sim/goal it waits until /odom has been still for `settle_s` (an estimate still converging, as SITL's EKF
after the sim moved the vehicle to the next start spot, would misplace the takeoff and the approach), calls
/uav/guided and /uav/arm (retried while the autopilot refuses), then /uav/takeoff; the pilot (sim_pilot_node or a
person on teleop_keyboard / the pilot station) and the assistant then fly the landing; on the
result from /sim/landing it waits up to `autopilot_confirm_s` for /uav/landed_state ON_GROUND (the
autopilot's own landing verdict, recorded as `autopilot_landed`), then calls /uav/land (LAND disarms
on the ground, so the sim starts the next episode). Results are logged, optionally written to a CSV
(a file with other columns is refused at start-up, never appended to), and summarised; with
`episodes` > 0 the process exits 0 when they are flown (1 if the autopilot never arms).
"""
from __future__ import annotations

import csv
import json
import math
import time
from pathlib import Path

from geometry_msgs.msg import PointStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String, UInt8
from std_srvs.srv import Trigger

from assist_common.atomic import CsvLog
from assist_common.ros_io import LANDING_QOS, LATCHED_QOS, SENSOR_QOS, Diagnostics, forward_logging
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import exit_process, run_node

from .landing_runner_core import LandingRunnerCore, RunnerConfig, RunnerState
from .mavlink_bridge_node import LANDED_STATE_TOPIC

PARAMS = {
    'episodes': Param(0, 'Landings to fly; 0: until stopped. The process exits 0 when they are flown.',
                      min=0, max=1_000_000),
    'arm_retry_s': Param(5.0, 'Seconds between arming attempts while the autopilot refuses (steady clock).',
                         min=0.1, max=600.0),
    'arm_give_up_s': Param(300.0, 'Exit 1 when an episode has not armed and taken off after this many seconds.',
                           min=1.0, max=86400.0),
    'flight_timeout_s': Param(150.0, 'Request LAND when no landing result came this long after takeoff.',
                              min=1.0, max=86400.0),
    'call_timeout_s': Param(30.0, 'A /uav/* call not answered within this counts as failed.', min=0.5, max=600.0),
    'land_after_touchdown': Param(True, 'Call /uav/land after each landing result (disarms on the ground).'),
    'reboot_after_s': Param(120.0, 'Call /uav/reboot once when an episode has been refused arming this long (an '
                                   'EKF that did not recover from a crash); 0: never.', min=0.0, max=86400.0),
    'reboot_after_crash': Param(False, 'Call /uav/reboot before the episode that follows a crash (ArduCopter '
                                       "SITL's EKF may be corrupted by one, yet accept arming)."),
    'disarm_timeout_s': Param(20.0, 'No next episode this long after a landing (the autopilot never detected it, '
                                    'e.g. resting on a pad edge): call /uav/force_disarm (the bridge refuses '
                                    'unless its allow_force_disarm is set); 0: never.', min=0.0, max=3600.0),
    'autopilot_confirm_s': Param(RunnerConfig.autopilot_confirm_s, 'After a touchdown result, wait up to this '
                                 'long for /uav/landed_state ON_GROUND (the autopilot\'s land detector) before '
                                 'calling /uav/land; recorded as autopilot_landed true/false (empty for a timeout, '
                                 'a crash in the air, or no landed state heard); 0: do not wait.',
                                 min=0.0, max=60.0),
    'settle_s': Param(RunnerConfig.settle_s, 'Arm only once /odom has been still this long (speed at most '
                      'settle_speed_mps, position within settle_drift_m); 0: arm without /odom.', min=0.0, max=60.0),
    'settle_speed_mps': Param(RunnerConfig.settle_speed_mps, 'Fastest /odom speed that counts as still.',
                              min=0.001, max=1.0),
    'settle_drift_m': Param(RunnerConfig.settle_drift_m, 'Farthest /odom position change within settle_s that '
                            'counts as still.', min=0.001, max=1.0),
    'results_file': Param('', 'CSV file for the landing results (appended; empty: log only). An existing file '
                              'with other columns is refused.'),
}
_CALL_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
_CSV_FIELDS = ('episode', 'goal_index', 'landed_index', 'error_m', 'success', 'crash', 'outcome', 'reason',
               'duration_s', 'assisted', 'autopilot_landed')


def results_header_problem(path: str | Path, fields: tuple[str, ...] = _CSV_FIELDS) -> str | None:
    """Why rows with `fields` cannot be appended to the CSV at `path` (its header differs); None if they can."""
    path = Path(path)
    if not path.exists() or path.stat().st_size == 0:
        return None
    with path.open(newline='', encoding='utf-8') as fh:
        header = next(csv.reader(fh), [])
    if tuple(header) == tuple(fields):
        return None
    return (f"results_file {str(path)!r} has the columns {','.join(header)}; landing_runner writes "
            f"{','.join(fields)}: give a new file (nothing was written)")


class LandingRunner(Node):
    """Arms, takes off and lands the vehicle once per episode so a pilot can fly each landing."""

    def __init__(self, **kwargs):
        super().__init__('landing_runner', **kwargs)
        forward_logging(self)
        self.p = declare_parameters(self, PARAMS)
        try:
            cfg = RunnerConfig(episodes=int(self.p['episodes']), arm_retry_s=float(self.p['arm_retry_s']),
                               arm_give_up_s=float(self.p['arm_give_up_s']),
                               flight_timeout_s=float(self.p['flight_timeout_s']),
                               land_after_touchdown=bool(self.p['land_after_touchdown']),
                               reboot_after_s=float(self.p['reboot_after_s']),
                               reboot_after_crash=bool(self.p['reboot_after_crash']),
                               disarm_timeout_s=float(self.p['disarm_timeout_s']),
                               autopilot_confirm_s=float(self.p['autopilot_confirm_s']),
                               settle_s=float(self.p['settle_s']),
                               settle_speed_mps=float(self.p['settle_speed_mps']),
                               settle_drift_m=float(self.p['settle_drift_m']))
        except ValueError as exc:
            raise StartupError(str(exc)) from exc
        self.core = LandingRunnerCore(cfg)
        if self.p['results_file'] and (problem := results_header_problem(self.p['results_file'])):
            raise StartupError(f'landing_runner: {problem}')
        self.csv = CsvLog(self.p['results_file'], list(_CSV_FIELDS)) if self.p['results_file'] else None
        self._written = 0               # results handed to the CSV so far
        self.diag = Diagnostics(self)
        self.exit_code: int | None = None
        self._future = None
        self._call_name = ''
        self._call_started = 0.0
        self.uav = {n: self.create_client(Trigger, f'/uav/{n}', qos_profile=_CALL_QOS)
                    for n in ('guided', 'arm', 'takeoff', 'land', 'reboot', 'force_disarm')}
        self.create_subscription(PointStamped, '/sim/goal', self._on_goal, LATCHED_QOS)
        self.create_subscription(String, '/sim/landing', self._on_landing, LANDING_QOS)
        self.create_subscription(UInt8, LANDED_STATE_TOPIC, self._on_landed_state, LATCHED_QOS)
        self.create_subscription(Odometry, '/odom', self._on_odometry, SENSOR_QOS)
        self.create_timer(0.1, self._tick)
        self.get_logger().info(f"landing_runner: {cfg.episodes or 'unlimited'} episodes; waiting for /sim/goal")

    def _on_goal(self, msg: PointStamped) -> None:
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.point.x, msg.point.y, msg.point.z)
        if not all(math.isfinite(v) for v in key[2:]):
            self.diag.count('rejected_goal')
            self.get_logger().warning('rejected non-finite /sim/goal')
            return
        self.core.on_goal(key, time.monotonic())

    def _on_landing(self, msg: String) -> None:
        try:
            result = json.loads(msg.data)
            if not isinstance(result, dict):
                raise ValueError('not a JSON object')
        except ValueError as exc:
            self.diag.count('rejected_landing')
            self.get_logger().warning(f'rejected /sim/landing ({exc}): {msg.data[:80]!r}')
            return
        self.core.on_landing(result, time.monotonic())
        self._write_results()

    def _on_odometry(self, msg: Odometry) -> None:
        p, v = msg.pose.pose.position, msg.twist.twist.linear
        self.core.on_odometry((p.x, p.y, p.z), (v.x, v.y, v.z), time.monotonic())

    def _on_landed_state(self, msg: UInt8) -> None:
        self.core.on_landed_state(int(msg.data), time.monotonic())
        self._write_results()

    def _write_results(self) -> None:
        """Hand the results recorded since the last call (with the autopilot's verdict) to the CSV."""
        results = self.core.stats.results
        for result in results[self._written:]:
            if self.csv is not None:
                self.csv.write({k: result.get(k, '') for k in _CSV_FIELDS})
            if isinstance(result.get('autopilot_landed'), bool):
                self.diag.count('autopilot_landed' if result['autopilot_landed'] else 'autopilot_not_landed')
        self._written = len(results)
        self.diag.set('landings', str(self._written))

    def close(self) -> None:
        """Record a result still waiting for its verdict, close the results file (run_node calls this)."""
        self.core.flush(time.monotonic())
        self._write_results()
        if self.csv is not None:
            self.csv.close()

    def _tick(self) -> None:
        now = time.monotonic()
        if self._future is not None:
            if self._future.done():
                exc = self._future.exception()
                res = None if exc is not None else self._future.result()
                ok, text = (False, f'call failed: {exc}') if res is None else (bool(res.success), res.message)
                self._future = None
                self.core.on_answer(self._call_name, ok, text, now)
            elif now - self._call_started > self.p['call_timeout_s']:
                self.uav[self._call_name].remove_pending_request(self._future)   # a late answer is dropped
                self._future = None
                self.diag.count('call_timeouts')
                self.core.on_answer(self._call_name, False, f"no answer in {self.p['call_timeout_s']:.0f} s", now)
            else:
                return
        missing = [n for n, c in self.uav.items()
                   if n not in ('reboot', 'force_disarm') and not c.service_is_ready()]
        if missing:                     # wait for the bridge rather than time a call out
            self.get_logger().warning(f"waiting for /uav/{', /uav/'.join(missing)} (is mavlink_bridge_node up?)",
                                      throttle_duration_sec=10.0)
            return
        name = self.core.poll(now)
        self._write_results()           # a verdict that timed out in poll
        if name is not None and not self.uav[name].service_is_ready():
            self.core.on_answer(name, False, f'/uav/{name} not offered by the bridge', now)
        elif name is not None:
            self._call_name, self._call_started = name, now
            self._future = self.uav[name].call_async(Trigger.Request())
        self.diag.set('state', self.core.state.value)
        if self.core.state == RunnerState.FAILED and self.exit_code is None:
            self.exit_code = 1
            self.get_logger().error(f'landing_runner: {self.core.failure}; {self.core.stats.summary()}')
            self.context.try_shutdown()
        elif self.core.finished and self.exit_code is None:
            self.exit_code = 0
            self.get_logger().info(f'landing_runner done: {self.core.stats.summary()}')
            self.context.try_shutdown()


def main(args=None):
    """Console entry point."""
    holder: dict = {}

    def make() -> LandingRunner:
        holder['node'] = LandingRunner()
        return holder['node']
    code = run_node(make, args, params=PARAMS)
    node = holder.get('node')
    exit_process(code if code or node is None else (node.exit_code or 0))


if __name__ == '__main__':
    main()
