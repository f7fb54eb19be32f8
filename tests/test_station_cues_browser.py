"""The assistant's intent cues on the pilot station page, in a real browser (headless Chromium + Selenium).

pilot_station runs as a subprocess on a private domain; the test's node stands in for the rest of the graph: it
publishes a fixed scene (/sim/scene), the vehicle hovering (/odom), a plain camera image, and the assistant's
topics (/assist/agent_cmd, /assist/goal_estimate, /assist/descent_ok, /cmd_vel) at 20 Hz, each switchable. The
checks read the canvases' own pixels where the test projects the pads itself (the chase camera of the page's
hello, the downward camera of ARCHITECTURE.md), and the page's window.stationStats.
"""
from __future__ import annotations

import math
import re
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped, TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import Bool
from visualization_msgs.msg import Marker, MarkerArray

from assist_common.ros_io import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS
from assist_station import testing
from assist_station.testing import Proc, wait_for

pytestmark = pytest.mark.graph
BIN = Path(sys.executable).parent

# three pads ahead of the vehicle: box centre, size (box top = centre + size z / 2), colour; yellow tops
PADS = [((4.0, 1.5, 0.4), (1.2, 1.2, 0.8)), ((7.5, -1.5, 0.5), (1.2, 1.2, 1.0)), ((11.0, 1.0, 0.3), (1.2, 1.2, 0.6))]
TOPS = [(c[0], c[1], c[2] + s[2] / 2) for c, s in PADS]
PAD_RGB = (0.85, 0.75, 0.2)
HOVER = (0.0, 0.0, 3.0)               # the vehicle in the chase-view checks (yaw 0): the pads lie ahead of it
ABOVE_PAD0 = (3.5, 1.0, 2.5)          # the vehicle in the inset check: pad 0's top is in the camera's view
CAMERA_GRAY = 40
SURE_VAR, UNSURE_VAR = 0.01, 1.0      # m^2: sigma 0.1 m and 1 m (cue_max_sigma_m 0.5 by default)
BETWEEN_PADS = (5.75, 0.0, 0.9)      # on no pad


class Feed:
    """The graph around the station, from the test's node: what it publishes is set through `state`."""

    def __init__(self, node):
        self.node, self.lock = node, threading.Lock()
        self.state = {'pose': HOVER, 'agent': False, 'goal': None, 'stamp_offset_s': 0.0, 'descent': None,
                      'blended': None}
        self.diag: dict[str, str] = {}
        self.pubs = {'scene': node.create_publisher(MarkerArray, '/sim/scene', LATCHED_QOS),
                     'odom': node.create_publisher(Odometry, '/odom', SENSOR_QOS),
                     'image': node.create_publisher(Image, '/camera/color/image_raw', SENSOR_QOS),
                     'agent': node.create_publisher(TwistStamped, '/assist/agent_cmd', RELIABLE_QOS),
                     'goal': node.create_publisher(PoseWithCovarianceStamped, '/assist/goal_estimate', RELIABLE_QOS),
                     'descent': node.create_publisher(Bool, '/assist/descent_ok', RELIABLE_QOS),
                     'blended': node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)}
        self.sub = node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.params = node.create_client(SetParameters, '/pilot_station/set_parameters')
        self.pubs['scene'].publish(self._scene())
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def set(self, **kw) -> None:
        with self.lock:
            self.state.update(kw)

    def _on_diag(self, msg):
        for st in msg.status:
            if st.name.endswith('pilot_station'):
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}

    def counter(self, key: str) -> int:
        with self.lock:
            return int(self.diag.get(key, 0))

    def set_params(self, **values) -> None:
        assert self.params.wait_for_service(timeout_sec=20)
        req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        future = self.params.call_async(req)
        assert wait_for(future.done, 20) and all(r.successful for r in future.result().results)

    def _scene(self) -> MarkerArray:
        arr = MarkerArray()
        for i, (c, s) in enumerate(PADS):
            m = Marker(ns='platforms', id=i, type=Marker.CUBE, action=Marker.ADD)
            m.header.frame_id = 'odom'
            m.pose.position.x, m.pose.position.y, m.pose.position.z = c
            m.pose.orientation.w = 1.0
            m.scale.x, m.scale.y, m.scale.z = s
            m.color.r, m.color.g, m.color.b, m.color.a = (*PAD_RGB, 1.0)
            arr.markers.append(m)
        return arr

    def _stamped(self, msg, offset_s: float = 0.0):
        t = self.node.get_clock().now().nanoseconds * 1e-9 + offset_s
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), int((t % 1.0) * 1e9)
        return msg

    def _run(self) -> None:
        image = Image(height=64, width=64, encoding='rgb8', step=192, data=bytes([CAMERA_GRAY]) * (64 * 64 * 3))
        image.header.frame_id = 'camera_optical_frame'
        tick = 0
        while not self.stop.is_set():
            with self.lock:
                st = dict(self.state)
            od = Odometry()
            od.header.frame_id, od.child_frame_id = 'odom', 'base_link'
            od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = st['pose']
            od.pose.pose.orientation.w = 1.0
            self.pubs['odom'].publish(self._stamped(od))
            if tick % 2 == 0:
                self.pubs['image'].publish(self._stamped(image))
            if st['agent']:
                a = TwistStamped()
                a.header.frame_id = 'base_link'
                a.twist.linear.x = 0.1                           # live, below the blending threshold
                self.pubs['agent'].publish(self._stamped(a))
            if st['goal'] is not None:
                p, var = st['goal']
                g = PoseWithCovarianceStamped()
                g.header.frame_id = 'odom'
                g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z = p
                g.pose.pose.orientation.w = 1.0
                cov = [0.0] * 36
                cov[0] = cov[7] = cov[14] = var
                cov[21] = cov[28] = cov[35] = 1e6
                g.pose.covariance = cov
                self.pubs['goal'].publish(self._stamped(g, st['stamp_offset_s']))
            if st['descent'] is not None:
                self.pubs['descent'].publish(Bool(data=st['descent']))
            if st['blended'] is not None:
                v = TwistStamped()
                v.header.frame_id = 'base_link'
                v.twist.linear.x, v.twist.linear.y, v.twist.linear.z = st['blended']
                self.pubs['blended'].publish(self._stamped(v))
            tick += 1
            time.sleep(0.05)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        for p in self.pubs.values():
            self.node.destroy_publisher(p)
        self.node.destroy_subscription(self.sub)
        self.node.destroy_client(self.params)


@pytest.fixture(scope='module')
def page(ros, domain_id, tmp_path_factory):
    """pilot_station (free flight: no goal marker of its own) + the feed + one browser page."""
    tmp = tmp_path_factory.mktemp('cues')
    feed = Feed(ros)
    st = Proc('pilot_station', ['-p', 'port:=0', '-p', 'mode:=free'], domain_id, tmp / 'station.log')
    driver = None
    try:
        assert wait_for(lambda: 'open http://' in st.log(), 60), st.log()
        url = re.search(r'open (http://127\.0\.0\.1:\d+/)', st.log()).group(1)
        try:
            driver = testing.start_browser(tmp / 'chromium')
        except FileNotFoundError as exc:
            pytest.fail(str(exc))
        driver.get(url)
        assert wait_for(lambda: (s := testing.page_stats(driver)) and s['ws'] == 'open' and s['pose'] is not None
                        and s['scenePlatforms'] == 3 and s['cameraFrames'] > 0, 60), st.log()
        yield {'driver': driver, 'feed': feed, 'station': st, 'tmp': tmp}
    finally:
        if driver is not None:
            driver.quit()
        feed.close()
        st.stop()


# ---------------------------------------------------------------------- the test's own projections
def chase_pixel(hello: dict, canvas: list, pose: tuple, point) -> tuple[int, int]:
    """Where the page's chase camera (behind and above the vehicle, yaw 0) shows a world point: (col, row)."""
    W, H = canvas
    pos, fwd = np.array(pose, float), np.array([1.0, 0.0, 0.0])
    eye = pos - fwd * hello['back_m'] + np.array([0.0, 0.0, hello['up_m']])
    look = pos + 1.5 * fwd - eye
    fw = look / np.linalg.norm(look)
    rt = np.cross(fw, [0.0, 0.0, 1.0])
    rt /= np.linalg.norm(rt)
    up = np.cross(rt, fw)
    f = (H / 2) / math.tan(math.radians(hello['fov_deg']) / 2)
    d = np.asarray(point, float) - eye
    x, y, z = d @ rt, d @ up, d @ fw
    return round(W / 2 + f * x / z), round(H / 2 - f * y / z)


def inset_pixel(pose: tuple, point, size: int = 192, vfov_deg: float = 58.0, offset_m: float = 0.05):
    """Where the downward camera (level vehicle, yaw 0; image top = body forward, optical x = body -y) shows a
    world point on the square inset canvas: (col, row)."""
    b = np.asarray(point, float) - np.asarray(pose, float) + np.array([0.0, 0.0, offset_m])
    xo, yo, zo = -b[1], -b[0], -b[2]
    f = (size / 2) / math.tan(math.radians(vfov_deg) / 2)
    return round(size / 2 + f * xo / zo), round(size / 2 + f * yo / zo)


def view(d, canvas='view') -> np.ndarray:
    return testing.png_to_rgb(testing.canvas_png(d, canvas)).astype(int)


def patch(img: np.ndarray, px, r: int = 2) -> np.ndarray:
    """Median colour of the (2r+1)^2 pixels around px = (col, row)."""
    c, rr = px
    return np.median(img[rr - r:rr + r + 1, c - r:c + r + 1].reshape(-1, 3), axis=0)


def cyan(rgb) -> bool:
    return rgb[1] - rgb[0] > 50 and rgb[2] - rgb[0] > 50


def saturation(rgb) -> float:
    return float(max(rgb) - min(rgb))


def magenta_count(img: np.ndarray) -> int:
    return int(((img[..., 0] > 200) & (img[..., 2] > 200) & (img[..., 1] < 120)).sum())


def stats(d) -> dict:
    return testing.page_stats(d)


def goal_drawn(d):
    return stats(d)['cueDrawn']['goal']


@pytest.fixture(scope='module')
def geometry(page):
    """Pad centres in the chase view (the test's projection) and each pad's plain colour there (no cue)."""
    d, feed = page['driver'], page['feed']
    feed.set(pose=HOVER, agent=False)
    assert wait_for(lambda: stats(d)['pose']['p'] == list(HOVER), 10)
    canvas, chase = stats(d)['canvas'], stats(d)['chase']
    centres = [chase_pixel(chase, canvas, HOVER, t) for t in TOPS]
    img = view(d)
    plain = [patch(img, c) for c in centres]
    for rgb in plain:       # a yellow pad top, lit: the colour the scene gave it
        assert rgb[0] > 150 and rgb[1] > 130 and rgb[2] < 100 and not cyan(rgb), plain
    return {'canvas': canvas, 'chase': chase, 'centres': centres, 'plain': plain}


def plain_at(img, geometry, i) -> bool:
    """Pad i looks as it does without a cue (within a few levels per channel)."""
    return bool(np.abs(patch(img, geometry['centres'][i]) - geometry['plain'][i]).max() <= 12)


def assisting(feed, **kw):
    feed.set(**dict({'pose': HOVER, 'agent': True, 'goal': (TOPS[0], SURE_VAR), 'stamp_offset_s': 0.0,
                     'descent': True, 'blended': None}, **kw))


# ---------------------------------------------------------------------- tests
def test_the_goal_pad_is_highlighted_where_the_estimate_lies_and_follows_it(page, geometry):
    d, feed = page['driver'], page['feed']
    assisting(feed, goal=(TOPS[0], SURE_VAR))
    assert wait_for(lambda: (g := goal_drawn(d)) and g['pad'] == 0 and g['state'] == 'sure', 10), stats(d)
    # the page draws the cue where the test's own projection puts pad 0's top centre
    assert np.abs(np.array(goal_drawn(d)['view']) - geometry['centres'][0]).max() <= 3, (goal_drawn(d), geometry)
    assert wait_for(lambda: cyan(patch(view(d), geometry['centres'][0])), 10), patch(view(d), geometry['centres'][0])
    img = view(d)
    assert plain_at(img, geometry, 1) and plain_at(img, geometry, 2)
    feed.set(goal=(TOPS[1], SURE_VAR))                                # the estimate moves to pad 1
    assert wait_for(lambda: goal_drawn(d)['pad'] == 1, 10), stats(d)
    assert wait_for(lambda: cyan(patch(img := view(d), geometry['centres'][1])) and plain_at(img, geometry, 0), 10)
    assert plain_at(view(d), geometry, 2)


def test_an_unsure_estimate_is_outlined_not_filled(page, geometry):
    d, feed = page['driver'], page['feed']
    assisting(feed, goal=(TOPS[2], UNSURE_VAR))
    assert wait_for(lambda: (g := goal_drawn(d)) and g['pad'] == 2 and g['state'] == 'unsure', 10), stats(d)
    c = geometry['centres'][2]

    def outlined_only():
        img = view(d)
        box = img[c[1] - 40:c[1] + 40, c[0] - 60:c[0] + 60]
        ring = int(((box[..., 1] - box[..., 0] > 50) & (box[..., 2] - box[..., 0] > 50)).sum())
        return plain_at(img, geometry, 2) and ring > 20
    assert wait_for(outlined_only, 10)
    assisting(feed, goal=(TOPS[2], SURE_VAR))
    assert wait_for(lambda: cyan(patch(view(d), c)), 10)


@pytest.mark.parametrize('trouble, counter', [
    ({'goal': None}, 'cue_goal_unknown'),                                     # the estimate stops coming
    ({'goal': ((math.nan, 1.5, 0.8), SURE_VAR)}, 'goal_estimate_rejected_nonfinite'),
    ({'stamp_offset_s': -2.0}, 'goal_estimate_rejected_stale_stamp'),        # stamped 2 s ago
    ({'goal': (BETWEEN_PADS, SURE_VAR)}, 'goal_estimate_rejected_unknown_pad'),
])
def test_a_stale_or_bad_estimate_turns_the_cue_grey_and_is_counted(page, geometry, trouble, counter):
    d, feed = page['driver'], page['feed']
    c = geometry['centres'][0]
    assisting(feed)
    assert wait_for(lambda: (g := goal_drawn(d)) and g['pad'] == 0 and g['state'] == 'sure'
                    and cyan(patch(view(d), c)), 10), stats(d)
    before = feed.counter(counter)
    feed.set(**trouble)
    assert wait_for(lambda: (g := goal_drawn(d)) and g['state'] == 'unknown' and g['pad'] == 0, 10), stats(d)

    def grey():
        rgb = patch(view(d), c)
        return not cyan(rgb) and saturation(rgb) < 0.6 * saturation(geometry['plain'][0])
    assert wait_for(grey, 10), (patch(view(d), c), geometry['plain'][0])
    assert wait_for(lambda: feed.counter(counter) > before, 10), (counter, feed.diag)
    assisting(feed)                                                   # good estimates again: solid again
    assert wait_for(lambda: goal_drawn(d)['state'] == 'sure' and cyan(patch(view(d), c)), 10)


def test_the_descent_light(page):
    d, feed = page['driver'], page['feed']
    light = lambda: (d.find_element('id', 'descent').get_attribute('class'),        # noqa: E731
                     d.find_element('id', 'descent').text)
    assisting(feed, descent=True)
    assert wait_for(lambda: light() == ('go', 'descend'), 10), light()
    feed.set(descent=False)
    assert wait_for(lambda: light() == ('stop', 'hold'), 10), light()
    feed.set(descent=None)                                            # silent for longer than cue_timeout_s
    assert wait_for(lambda: light() == ('unknown', 'descend ?'), 10), light()
    assert d.find_element('id', 'descent').is_displayed()


def test_the_push_arrow_points_from_the_vehicle_along_v_minus_u(page, geometry):
    d, feed = page['driver'], page['feed']
    assisting(feed, blended=(0.0, 0.8, 0.0))                          # u = 0 (no key held): push = V, to the left
    assert wait_for(lambda: stats(d)['cueDrawn']['push'] is not None, 10), stats(d)
    start = chase_pixel(geometry['chase'], geometry['canvas'], HOVER, HOVER)
    tip = chase_pixel(geometry['chase'], geometry['canvas'], HOVER, (HOVER[0], HOVER[1] + 0.8, HOVER[2]))
    drawn = stats(d)['cueDrawn']['push']
    assert np.abs(np.array(drawn['from']) - start).max() <= 3 and np.abs(np.array(drawn['to']) - tip).max() <= 3
    img = view(d)
    mid = ((start[0] + tip[0]) // 2, (start[1] + tip[1]) // 2)
    seg = img[mid[1] - 3:mid[1] + 4, mid[0] - 3:mid[0] + 4]
    assert magenta_count(seg) > 10 and magenta_count(img) > 100       # the arrow's own pixels
    feed.set(blended=None)                                            # /cmd_vel stops: no push shown
    assert wait_for(lambda: stats(d)['cueDrawn']['push'] is None and magenta_count(view(d)) == 0, 10)


def test_a_cue_switched_off_by_parameter_disappears(page, geometry):
    d, feed = page['driver'], page['feed']
    c = geometry['centres'][0]
    assisting(feed, blended=(0.5, 0.0, 0.0))
    assert wait_for(lambda: goal_drawn(d) is not None and cyan(patch(view(d), c)) and magenta_count(view(d)) > 50
                    and d.find_element('id', 'descent').is_displayed(), 10)
    try:
        feed.set_params(cue_goal=False)
        assert wait_for(lambda: goal_drawn(d) is None and plain_at(view(d), geometry, 0), 10), stats(d)
        assert d.find_element('id', 'descent').is_displayed() and magenta_count(view(d)) > 50     # the others stay
        feed.set_params(cue_push=False, cue_descent=False)
        assert wait_for(lambda: magenta_count(view(d)) == 0 and not d.find_element('id', 'descent').is_displayed(),
                        10)
    finally:
        feed.set_params(cue_goal=True, cue_push=True, cue_descent=True)
    assert wait_for(lambda: cyan(patch(view(d), c)) and magenta_count(view(d)) > 50, 10)


def test_nothing_is_shown_while_assistance_is_off(page, geometry):
    d, feed = page['driver'], page['feed']
    assisting(feed, blended=(0.5, 0.0, 0.0))
    assert wait_for(lambda: cyan(patch(view(d), geometry['centres'][0])), 10)
    feed.set(agent=False)                           # /assist/agent_cmd stops; the intent topics keep coming
    assert wait_for(lambda: d.find_element('id', 'assist').text == 'unassisted', 10)

    def nothing():
        img = view(d)
        s = stats(d)
        return (s['cues'] == {'goal': None, 'descent': None, 'push': None} and s['cueDrawn']['goal'] is None
                and plain_at(img, geometry, 0) and magenta_count(img) == 0
                and not d.find_element('id', 'descent').is_displayed())
    assert wait_for(nothing, 10), stats(d)['cues']
    end = time.monotonic() + 1.0                     # and it stays so while the intent keeps arriving
    while time.monotonic() < end:
        assert nothing()
    feed.set(agent=True)
    assert wait_for(lambda: cyan(patch(view(d), geometry['centres'][0])), 10)


def test_the_camera_inset_marks_the_estimate(page):
    d, feed = page['driver'], page['feed']
    assisting(feed, pose=ABOVE_PAD0, goal=(TOPS[0], SURE_VAR))
    geom = stats(d)['cameraGeom']
    expected = inset_pixel(ABOVE_PAD0, TOPS[0], vfov_deg=geom['vfov_deg'], offset_m=geom['offset_m'])
    assert 20 < expected[0] < 172 and 20 < expected[1] < 172      # well inside the image
    assert wait_for(lambda: (g := goal_drawn(d)) and g.get('inset') is not None
                    and np.abs(np.array(g['inset']) - expected).max() <= 2, 10), (goal_drawn(d), expected)

    def marked():
        img = view(d, 'inset')
        inside = patch(img, (expected[0] + 8, expected[1] + 8), 1)       # the pad top's fill, off the cross
        far = patch(img, (180, 180), 1)                                    # the image, away from the pad
        return cyan(patch(img, expected, 0)) and cyan(inside) and np.abs(far - CAMERA_GRAY).max() <= 3
    assert wait_for(marked, 10)
    feed.set(goal=(TOPS[1], SURE_VAR))              # pad 1 is outside the camera's view: nothing marked
    assert wait_for(lambda: (g := goal_drawn(d)) and g['pad'] == 1 and g.get('inset') is None
                    and not cyan(patch(view(d, 'inset'), expected, 0)), 10)
    feed.set(pose=HOVER)
