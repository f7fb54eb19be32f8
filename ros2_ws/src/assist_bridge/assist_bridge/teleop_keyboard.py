"""teleop_keyboard: the pilot's keyboard -> /pilot/cmd_vel (TwistStamped, base_link) at a fixed rate.

W/S forward/back, A/D left/right, arrow up/down climb/descend, space stop, q (or Ctrl-C) quit.
Needs a real terminal: the terminal is put in non-canonical, no-echo mode (restored on every
exit) and a zero command is published before the node goes away. Under the status line a second
line shows the assistant's intent from /assist/goal_estimate, /assist/descent_ok and /odom (where
its goal pad lies in body terms, whether to descend), empty while none has arrived in time.
"""
from __future__ import annotations

import os
import select
import shutil
import signal
import sys
import termios
import threading
import time

from geometry_msgs.msg import PoseWithCovarianceStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from std_msgs.msg import Bool

from assist_common.ros_io import (RELIABLE_QOS, SENSOR_QOS, STAMP_TOLERANCE_S, Diagnostics, fill_twist,
                                  forward_logging, stamp_to_sec)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import exit_process, run_node

from .teleop_core import HELP, IntentConfig, IntentError, IntentLine, KeyDecoder, TeleopConfig, TeleopCore

PARAMS = {
    'speed': Param(1.0, 'Horizontal speed for W/S/A/D (m/s; settable at run time).', min=0.0, max=5.0,
                   min_exclusive=True, dynamic=True),
    'speed_z': Param(0.5, 'Vertical speed for the up/down arrows (m/s; settable at run time).', min=0.0, max=3.0,
                     min_exclusive=True, dynamic=True),
    'rate_hz': Param(20.0, 'Publish rate of /pilot/cmd_vel (Hz); published continuously, not only on key events.',
                     min=1.0, max=200.0),
    'initial_hold_s': Param(0.6, 'A key counts as held this long after its first event (longer than the '
                            "terminal's auto-repeat delay; settable at run time).", min=0.0, max=60.0,
                            min_exclusive=True, dynamic=True),
    'repeat_timeout_s': Param(0.15, 'A repeating key counts as released when its repeats stop this long '
                                    '(settable at run time).', min=0.0, max=2.0, min_exclusive=True, dynamic=True),
    'frame_id': Param('base_link', 'frame_id of the published commands (body FLU).'),
    'status_line': Param(True, 'Show a live status line in the terminal, cut to its width, and under it the '
                               'assistant\'s intent (settable at run time).', dynamic=True),
    'intent_timeout_s': Param(IntentConfig.timeout_s, 'The intent line shows a goal estimate stamped, and /odom or '
                              '/assist/descent_ok received, within this long (s, the node\'s clock); with neither '
                              'estimate nor descent_ok that recent it is empty.', min=0.0, max=10.0,
                              min_exclusive=True),
    'intent_max_sigma_m': Param(IntentConfig.max_sigma_m, 'A goal estimate whose sqrt(max(var x, var y)) exceeds '
                                'this is shown as unsure (m).', min=0.0, max=100.0, min_exclusive=True),
}
# TeleopConfig fields that a run-time parameter set changes in place
LIVE_CONFIG = ('speed', 'speed_z', 'initial_hold_s', 'repeat_timeout_s')


class TeleopKeyboard(Node):
    """Reads keys from the controlling terminal and publishes the pilot command."""

    def __init__(self, **kwargs):
        if not sys.stdin.isatty():
            raise StartupError('teleop_keyboard: stdin is not a terminal (TTY); run it in an interactive '
                               'terminal, e.g. `ros2 run assist_bridge teleop_keyboard` (not piped, not under launch '
                               'without a terminal prefix)')
        super().__init__('teleop_keyboard', **kwargs)
        forward_logging(self)
        self.lock = threading.Lock()
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        keys = set(TeleopConfig.__dataclass_fields__) & set(self.p)
        try:
            self.cfg = TeleopConfig(**{k: self.p[k] for k in keys})
        except (ValueError, TypeError) as exc:
            raise StartupError(f'teleop_keyboard: bad parameter: {exc}') from exc
        self.core = TeleopCore(self.cfg)
        self.decoder = KeyDecoder()
        self.intent = IntentLine(IntentConfig(timeout_s=self.p['intent_timeout_s'],
                                              max_sigma_m=self.p['intent_max_sigma_m'],
                                              stamp_tolerance_s=STAMP_TOLERANCE_S))
        self._logged: set[str] = set()
        self.diag = Diagnostics(self)
        self.pub = self.create_publisher(TwistStamped, '/pilot/cmd_vel', RELIABLE_QOS)
        self.create_subscription(Odometry, '/odom', self._on_odom, SENSOR_QOS)
        self.create_subscription(PoseWithCovarianceStamped, '/assist/goal_estimate', self._on_goal, RELIABLE_QOS)
        self.create_subscription(Bool, '/assist/descent_ok', self._on_descent, RELIABLE_QOS)
        self._fd = sys.stdin.fileno()
        self._saved = termios.tcgetattr(self._fd)
        self._restored = False
        self._closing = False
        mode = termios.tcgetattr(self._fd)
        mode[3] &= ~(termios.ICANON | termios.ECHO | termios.ISIG)   # keys one by one; Ctrl-C as a key
        mode[6][termios.VMIN], mode[6][termios.VTIME] = 1, 0
        termios.tcsetattr(self._fd, termios.TCSANOW, mode)
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, self._on_signal)
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read_keys, name='keyboard', daemon=True)
        self._reader.start()
        self.create_timer(1.0 / self.cfg.rate_hz, self._tick)
        self._out(f'teleop_keyboard: {HELP}\r\n')

    def _on_params(self, changed: dict) -> None:
        """Speeds and key timing apply from the next tick; status_line is read every tick."""
        with self.lock:
            for key in LIVE_CONFIG:
                if key in changed:
                    setattr(self.cfg, key, float(changed[key]))
        if changed.get('status_line') is False:
            self._out('\r\x1b[K\x1b[B\r\x1b[K\x1b[A')          # both rows: status and intent

    # ------------------------------------------------------------------ terminal
    def _out(self, text: str) -> None:
        sys.stdout.write(text)
        sys.stdout.flush()

    def _restore_terminal(self) -> None:
        if not self._restored:
            self._restored = True
            termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)
            if self.p['status_line']:
                self._out('\x1b[B\r\n')                         # below the intent row

    def _read_keys(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self._fd], [], [], 0.1)
            if not r:
                continue
            data = os.read(self._fd, 64)
            if not data:          # terminal closed
                self._request_quit('terminal closed')
                return
            now = time.monotonic()
            with self.lock:
                for tok in self.decoder.feed(data.decode('utf-8', 'replace')):
                    self.core.press(tok, now)
                quit_now = self.core.quit
            if quit_now:
                self._request_quit(f'key {self.core.last_key!r}')
                return

    # ------------------------------------------------------------------ the assistant's intent
    def _now_s(self) -> float:
        """The node's clock in seconds (sim time under use_sim_time)."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _reject(self, counter: str, text: str) -> None:
        """Count an unusable message and log it the first time its counter is seen."""
        self.diag.count(counter)
        if counter not in self._logged:
            self._logged.add(counter)
            self.get_logger().warning(f'{text} (further ones counted as {counter})')

    def _on_odom(self, msg: Odometry) -> None:
        """The vehicle's pose, for where the goal pad lies in body terms."""
        pp = msg.pose.pose
        with self.lock:
            ok = self.intent.note_odom((pp.position.x, pp.position.y, pp.position.z),
                                       (pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w),
                                       self._now_s())
        if not ok:
            self._reject('odom_rejected', '/odom rejected: non-finite pose or zero quaternion')

    def _on_goal(self, msg: PoseWithCovarianceStamped) -> None:
        """The assistant's goal pad estimate, validated by the core; a rejected one counted by reason."""
        pp, stamp = msg.pose.pose, stamp_to_sec(msg.header.stamp)
        try:
            with self.lock:
                self.intent.note_goal(msg.header.frame_id, stamp if stamp > 0 else None,
                                      (pp.position.x, pp.position.y, pp.position.z),
                                      (pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w),
                                      msg.pose.covariance, self._now_s())
        except IntentError as exc:
            self._reject(f'goal_estimate_rejected_{exc.kind}', f'/assist/goal_estimate rejected: {exc}')

    def _on_descent(self, msg: Bool) -> None:
        """The assistant's descent light (no header: dated by its arrival)."""
        with self.lock:
            self.intent.note_descent(bool(msg.data), self._now_s())

    # ------------------------------------------------------------------ publishing
    def _publish(self, v) -> None:
        msg = TwistStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.p['frame_id']
        self.pub.publish(fill_twist(msg, v))

    def _tick(self) -> None:
        if self._closing:
            return
        now = time.monotonic()
        width = shutil.get_terminal_size((80, 24)).columns
        with self.lock:
            v = self.core.velocity(now)
            line = self.core.status_line(now, width)
            intent = self.intent.line(self._now_s(), width)
        self._publish(v)
        if self.p['status_line']:   # two rows redrawn in place, status then intent; the cursor ends on the first
            self._out('\r' + line + '\x1b[K\r\n' + intent + '\x1b[K\x1b[A\r')

    def _send_zero(self) -> None:
        for _ in range(3):    # reliable QoS, but say it more than once on the way out
            self._publish((0.0, 0.0, 0.0))

    def _request_quit(self, why: str) -> None:
        self._closing = True
        self._send_zero()
        self._restore_terminal()
        self.get_logger().info(f'quit ({why}): zero command sent')
        self.context.try_shutdown()

    def _on_signal(self, signum, frame) -> None:
        self._closing = True
        self._send_zero()
        self._restore_terminal()
        raise KeyboardInterrupt

    def close(self) -> None:
        """Zero command (if the graph is still up), terminal restored, reader stopped."""
        self._stop.set()
        if self.context.ok():
            self._send_zero()
        self._restore_terminal()


def main(args=None):
    """Console entry point."""
    exit_process(run_node(lambda: TeleopKeyboard(), args, params=PARAMS))


if __name__ == '__main__':
    main()
