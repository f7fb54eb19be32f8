"""/sim/scene: the pure scene_markers core and sim_node publishing it (latched, on every reset)."""
import math
import threading

import numpy as np
import pytest
from geometry_msgs.msg import PointStamped
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from assist_sim.core.config import SceneConfig
from assist_sim.core.scene import generate_scene
from assist_sim.core.scene_markers import GOAL_NS, PLATFORMS_NS, material_rgba, scene_markers
from assist_common.ros_io import LATCHED_QOS


def test_scene_markers_are_one_box_per_pad_plus_the_goal():
    scene = generate_scene(7, SceneConfig())
    boxes = scene_markers(scene, goal_index=3)
    pads = [b for b in boxes if b.ns == PLATFORMS_NS]
    assert [b.id for b in pads] == [0, 1, 2, 3, 4]
    for b, pad in zip(pads, scene.pads, strict=True):
        assert b.center == pytest.approx((pad.center[0], pad.center[1], pad.height / 2))
        assert b.size == pytest.approx((pad.length, pad.width, pad.height))
        qx, qy, qz, qw = b.quaternion
        assert (qx, qy) == (0.0, 0.0) and 2 * math.atan2(qz, qw) == pytest.approx(pad.yaw)
        assert b.rgba == material_rgba(pad.material) and b.rgba[3] == 1.0
        assert b.center[2] + b.size[2] / 2 == pytest.approx(pad.top_center[2])   # top = the contract's goal point
    goal = [b for b in boxes if b.ns == GOAL_NS]
    assert len(goal) == 1 and goal[0].id == 3 and goal[0].center == pads[3].center
    assert [b.ns for b in scene_markers(scene, None)] == [PLATFORMS_NS] * 5
    with pytest.raises(ValueError):
        scene_markers(scene, 5)


def test_material_colours_differ_between_materials():
    colours = {material_rgba(i)[:3] for i in range(52)}
    assert len(colours) == 52 and all(0.0 <= c <= 1.0 for rgb in colours for c in rgb)


@pytest.mark.graph
def test_sim_node_publishes_the_scene_latched_and_again_on_reset(ros, start_node, wait):
    lock = threading.Lock()
    scenes, goals = [], []

    def keep(store):
        def cb(msg):
            with lock:
                store.append(msg)
        return cb
    sim = start_node('sim_node', {'seed': 5, 'camera_rate_hz': 0.0})
    assert wait(lambda: 'sim_node up' in sim.log(), 60), sim.log()
    # subscribe only after the node is up: a latched topic still delivers the current scene
    subs = [ros.create_subscription(MarkerArray, '/sim/scene', keep(scenes), LATCHED_QOS),
            ros.create_subscription(PointStamped, '/sim/goal', keep(goals), LATCHED_QOS)]
    try:
        assert wait(lambda: len(scenes) >= 1 and len(goals) >= 1, 20), sim.log()

        def check(arr: MarkerArray, goal: PointStamped):
            assert all(m.action == Marker.ADD for m in arr.markers)   # the contract: CUBEs only
            cubes = list(arr.markers)
            assert len(cubes) == 6
            assert all(m.type == Marker.CUBE and m.header.frame_id == 'odom' for m in cubes)
            pads = [m for m in cubes if m.ns == 'platforms']
            assert [m.id for m in pads] == [0, 1, 2, 3, 4]
            assert all(m.scale.x > 0 and m.scale.y > 0 and m.scale.z > 0 for m in pads)
            (g,) = [m for m in cubes if m.ns == 'goal']
            top = np.array([g.pose.position.x, g.pose.position.y, g.pose.position.z + g.scale.z / 2])
            np.testing.assert_allclose(top, [goal.point.x, goal.point.y, goal.point.z], atol=1e-6)
            return [(m.pose.position.x, m.pose.position.y) for m in pads]
        with lock:
            first = check(scenes[-1], goals[-1])
        n = len(scenes)
        client = ros.create_client(Trigger, '/sim/reset')
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert wait(lambda: future.done(), 10) and future.result().success
        assert wait(lambda: len(scenes) > n and len(goals) >= 2, 10)
        with lock:
            second = check(scenes[-1], goals[-1])
        assert second != first          # a new scene after the reset
        ros.destroy_client(client)
    finally:
        for s in subs:
            ros.destroy_subscription(s)
