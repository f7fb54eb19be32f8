"""BoxMarker list (assist_sim.core.scene_markers) -> visualization_msgs/MarkerArray for /sim/scene."""
from __future__ import annotations

from collections.abc import Iterable

from visualization_msgs.msg import Marker, MarkerArray

from .core.scene_markers import BoxMarker


def scene_marker_array(boxes: Iterable[BoxMarker], frame_id: str, stamp) -> MarkerArray:
    """One CUBE per box, exactly as ARCHITECTURE.md's /sim/scene row (no other markers).

    The goal copy keeps id = pad index in ns 'goal', so after a reset a viewer that keeps markers
    (RViz) may still show the previous goal box; the pilot station replaces the whole array.
    """
    out = MarkerArray()
    for b in boxes:
        m = Marker()
        m.header.frame_id, m.header.stamp = frame_id, stamp
        m.ns, m.id, m.type, m.action = b.ns, int(b.id), Marker.CUBE, Marker.ADD
        m.pose.position.x, m.pose.position.y, m.pose.position.z = b.center
        q = b.quaternion
        m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = q
        m.scale.x, m.scale.y, m.scale.z = b.size
        m.color.r, m.color.g, m.color.b, m.color.a = b.rgba
        m.frame_locked = False
        out.markers.append(m)
    return out
