"""bag_play: publishes a bag's messages with their original timing (rate, start offset, loop, topics, remaps, /clock).

    bag_play flights/run1                                   # everything, real time
    bag_play flights/run1 --rate 2 --start-offset-s 5 --topics /camera/color/image_raw /odom
    bag_play flights/run1 --remap /cmd_vel:=/recorded/cmd_vel --clock true --loop true

Messages go out as the CDR bytes recorded (no re-serialisation) with QoS derived from the offered
profiles in the bag (best effort if any publisher offered it; transient local if all did, so /sim/goal
and /sim/scene stay latched). With clock:=true, /clock follows the bag's timestamps (scaled by the rate)
for graphs run with use_sim_time. Topics whose message type this install lacks are skipped with one
warning each. A missing, corrupt or truncated bag, an empty topic selection, a bag recorded with other
message definitions, or nothing to play (the selected topics hold no messages at or after the start
offset; with loop:=true too, which would otherwise spin) ends the node with one `error:` line and exit code 1.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock

from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import run_node

from .bagio import BagError, BagReader
from .play_core import PlayClock, parse_remaps
from .rosutil import cli_to_ros_args, message_class, ros_qos

log = logging.getLogger('bag_play')

PARAMS = {
    'bag': Param('', 'Bag to play: a rosbag2 directory (metadata.yaml + data) or one .mcap/.db3 file.'),
    'rate': Param(1.0, 'Playback speed factor (2.0: twice as fast).', min=0.0, min_exclusive=True, max=1000.0),
    'start_offset_s': Param(0.0, 'Skip this many seconds from the start of the bag.', min=0.0, max=1e9),
    'loop': Param(False, 'Start again from the (offset) start after the last message.'),
    'topics': Param(Parameter.Type.STRING_ARRAY, 'Topics to play; empty or unset: every topic in the bag.'),
    'remap': Param(Parameter.Type.STRING_ARRAY, 'Topic renames, each /from:=/to (applied to what is published).'),
    'clock': Param(False, 'Publish /clock from the bag timestamps (for use_sim_time graphs).'),
    'clock_rate_hz': Param(100.0, '/clock messages per second of wall time while playing.', min=1.0, max=10000.0),
    'wait_for_subscribers': Param(0, 'Before playing, wait (after delay_s) until the played topics have this many '
                                     'subscriptions in all (0: do not wait).', min=0, max=1000),
    'delay_s': Param(1.0, 'Wait this long after start-up (discovery) before the first message.', min=0.0,
                     max=3600.0),
}


class BagPlayNode(Node):
    """Plays a bag on a thread of its own; the executor only watches for the end."""

    def __init__(self, **kwargs):
        super().__init__('bag_play', **kwargs)
        self.p = declare_parameters(self, PARAMS)
        if not self.p['bag']:
            raise StartupError('bag_play: no bag given (bag_play BAG, or -p bag:=BAG)')
        try:
            remaps = parse_remaps(list(self.p['remap'] or []))
        except ValueError as exc:
            raise StartupError(f'bag_play: {exc}') from exc
        requested = self.p['topics']
        if requested is not None and list(requested) and not [t for t in requested if t]:
            raise StartupError('bag_play: the topic selection is empty')
        try:
            self.reader = BagReader(self.p['bag'])
        except BagError as exc:
            raise StartupError(f'bag_play: {exc}') from exc
        try:
            self.reader.open()
            topics = self.reader.select([t for t in requested if t] if requested else None)
            self.reader.check_definitions(topics)
        except BagError as exc:
            self.reader.close()
            raise StartupError(f'bag_play: {exc}') from exc
        self.pubs = {}
        for topic in topics:
            info = self.reader.topics[topic]
            cls = message_class(info.msgtype)
            if cls is None:
                self.get_logger().warning(f'bag_play: skipping {topic}: type {info.msgtype} is not installed here')
                continue
            self.pubs[topic] = self.create_publisher(cls, remaps.get(topic, topic), ros_qos(info.qos))
        if not self.pubs:
            self.reader.close()
            raise StartupError(f'bag_play: none of the selected topics has a type installed here ({topics})')
        first = self.reader.start_ns + int(self.p['start_offset_s'] * 1e9)
        if not sum(self.reader.topics[t].count for t in self.pubs):
            self.reader.close()
            raise StartupError(f'bag_play: {self.p["bag"]}: nothing to play: the selected topics '
                               f'{sorted(self.pubs)} hold no messages')
        if first > self.reader.end_ns:
            self.reader.close()
            raise StartupError(f'bag_play: {self.p["bag"]}: nothing to play: start offset {self.p["start_offset_s"]} s '
                               f'is past the end of the bag '
                               f'({(self.reader.end_ns - self.reader.start_ns) * 1e-9:.3f} s long)')
        self.pub_clock = self.create_publisher(Clock, '/clock', 10) if self.p['clock'] else None
        self.exit_code: int | None = None
        self.error: str | None = None      # why playback failed (main prints it as the error: line)
        self.published = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play, daemon=True)
        self._thread.start()
        self.create_timer(0.1, self._check_done)
        self.get_logger().info(f'bag_play: {self.p["bag"]}: {len(self.pubs)} topics, '
                               f'{self.reader.message_count} messages, rate {self.p["rate"]}')

    # ------------------------------------------------------------------ playback thread
    def _publish_clock(self, t_ns: int) -> None:
        if self.pub_clock is not None:
            msg = Clock()
            msg.clock.sec, msg.clock.nanosec = int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000)
            self.pub_clock.publish(msg)

    def _wait_until(self, clock: PlayClock, due: float) -> bool:
        """Sleep until `due`, ticking /clock; False when asked to stop."""
        period = 1.0 / float(self.p['clock_rate_hz'])
        while True:
            now = time.monotonic()
            if now >= due:
                return not self._stop.is_set()
            if self.pub_clock is not None:
                self._publish_clock(clock.bag_time(now))
            if self._stop.wait(min(due - now, period) if self.pub_clock is not None else due - now):
                return False

    def _play(self) -> None:
        try:
            if self._stop.wait(float(self.p['delay_s'])):
                return
            need = int(self.p['wait_for_subscribers'])
            while need and sum(p.get_subscription_count() for p in self.pubs.values()) < need:
                if self._stop.wait(0.05):
                    return
            first = self.reader.start_ns + int(self.p['start_offset_s'] * 1e9)
            while not self._stop.is_set():
                clock = PlayClock(first, time.monotonic(), float(self.p['rate']))
                played = 0
                for topic, t, raw in self.reader.messages(list(self.pubs), start_ns=first):
                    if not self._wait_until(clock, clock.due(t)):
                        return
                    self._publish_clock(t)
                    self.pubs[topic].publish(raw)
                    self.published += 1
                    played += 1
                if not played:        # a loop over nothing would spin at full speed
                    self._fail(f'{self.p["bag"]}: nothing to play: the selected topics {sorted(self.pubs)} hold no '
                               f'messages at or after the start offset ({self.p["start_offset_s"]} s)')
                    return
                if not self.p['loop']:
                    break
            self.exit_code = 0
        except BagError as exc:
            self._fail(str(exc))
        except Exception as exc:  # noqa: BLE001 - reported as one line, the node then exits non-zero
            self._fail(f'playback failed: {type(exc).__name__}: {exc}')

    def _fail(self, text: str) -> None:
        """End playback with an error (exit code 1)."""
        log.error('bag_play: %s', text)
        self.error = text
        self.exit_code = 1

    def _check_done(self) -> None:
        if self.exit_code is not None:
            if self.exit_code == 0:
                self.get_logger().info(f'bag_play: done, {self.published} messages published')
            raise SystemExit(self.exit_code)

    def close(self) -> None:
        """Stop the playback thread and close the bag (run_node calls this on every exit)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.reader.close()


def main(args=None):
    """Console entry point (flags map to the node parameters; --help lists them)."""
    argv = sys.argv[1:] if args is None else list(args)
    ros_args = cli_to_ros_args('bag_play', __doc__, PARAMS, argv, positional='bag')
    nodes: list[BagPlayNode] = []

    def make() -> BagPlayNode:
        nodes.append(BagPlayNode())
        return nodes[-1]
    try:
        code = run_node(make, ros_args)
    except SystemExit as exc:
        code = int(exc.code or 0)
    if nodes and nodes[0].error is not None:
        sys.stderr.write(f'error: bag_play: {nodes[0].error}\n')
        code = code or 1
    sys.exit(code)


if __name__ == '__main__':
    main()
