"""Build and read the contract's messages as rosbags objects (no rclpy): numpy <-> Image, Odometry, ..."""
from __future__ import annotations

import json
from typing import Any

import numpy as np

from assist_common.frames import quat_to_matrix

from .bagio import typestore


def T(msgtype: str) -> Any:
    """Message class of a Jazzy type, e.g. T('geometry_msgs/msg/TwistStamped')."""
    return typestore().types[msgtype]


def stamp(t_ns: int) -> Any:
    """builtin_interfaces/Time from nanoseconds."""
    return T('builtin_interfaces/msg/Time')(sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))


def stamp_ns(st: Any) -> int:
    """Nanoseconds of a builtin_interfaces/Time."""
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def header(t_ns: int, frame: str) -> Any:
    """std_msgs/Header."""
    return T('std_msgs/msg/Header')(stamp=stamp(t_ns), frame_id=frame)


def _vec3(v) -> Any:
    return T('geometry_msgs/msg/Vector3')(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def twist_stamped(t_ns: int, v, frame: str = 'base_link') -> Any:
    """geometry_msgs/TwistStamped with linear velocity v (3,)."""
    return T('geometry_msgs/msg/TwistStamped')(
        header=header(t_ns, frame), twist=T('geometry_msgs/msg/Twist')(linear=_vec3(v), angular=_vec3((0, 0, 0))))


def twist_linear(msg: Any) -> np.ndarray:
    """Linear part of a TwistStamped as (3,) float."""
    lin = msg.twist.linear
    return np.array([lin.x, lin.y, lin.z], dtype=float)


def point_stamped(t_ns: int, p, frame: str = 'odom') -> Any:
    """geometry_msgs/PointStamped."""
    return T('geometry_msgs/msg/PointStamped')(
        header=header(t_ns, frame), point=T('geometry_msgs/msg/Point')(x=float(p[0]), y=float(p[1]), z=float(p[2])))


def point(msg: Any) -> np.ndarray:
    """PointStamped -> (3,)."""
    return np.array([msg.point.x, msg.point.y, msg.point.z], dtype=float)


def odometry(t_ns: int, position, quaternion, velocity_world, odom_frame: str = 'odom',
             base_frame: str = 'base_link') -> Any:
    """nav_msgs/Odometry as sim_node publishes it (twist in base_link, REP-105)."""
    rot = quat_to_matrix(quaternion)
    v_body = rot.T @ np.asarray(velocity_world, dtype=float)
    Pose, Quat = T('geometry_msgs/msg/Pose'), T('geometry_msgs/msg/Quaternion')
    pose = Pose(position=T('geometry_msgs/msg/Point')(x=float(position[0]), y=float(position[1]),
                                                      z=float(position[2])),
                orientation=Quat(x=float(quaternion[0]), y=float(quaternion[1]), z=float(quaternion[2]),
                                 w=float(quaternion[3])))
    return T('nav_msgs/msg/Odometry')(
        header=header(t_ns, odom_frame), child_frame_id=base_frame,
        pose=T('geometry_msgs/msg/PoseWithCovariance')(pose=pose, covariance=np.zeros(36)),
        twist=T('geometry_msgs/msg/TwistWithCovariance')(
            twist=T('geometry_msgs/msg/Twist')(linear=_vec3(v_body), angular=_vec3((0, 0, 0))),
            covariance=np.zeros(36)))


def odom_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Odometry -> (position (3,), quaternion xyzw (4,), twist linear in base_link (3,))."""
    p, q, v = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear
    return (np.array([p.x, p.y, p.z], dtype=float), np.array([q.x, q.y, q.z, q.w], dtype=float),
            np.array([v.x, v.y, v.z], dtype=float))


def image(t_ns: int, array: np.ndarray, frame: str = 'camera_optical_frame') -> Any:
    """sensor_msgs/Image from uint8 HxWx3 (rgb8) or float32 HxW metres (32FC1)."""
    a = np.ascontiguousarray(array)
    if a.ndim == 3 and a.shape[2] == 3 and a.dtype == np.uint8:
        enc, step = 'rgb8', a.shape[1] * 3
    elif a.ndim == 2:
        a = a.astype(np.float32)
        enc, step = '32FC1', a.shape[1] * 4
    else:
        raise ValueError(f'image: unsupported array {a.shape} {a.dtype}')
    return T('sensor_msgs/msg/Image')(header=header(t_ns, frame), height=a.shape[0], width=a.shape[1], encoding=enc,
                                      is_bigendian=0, step=step, data=np.frombuffer(a.tobytes(), np.uint8))


def image_array(msg: Any) -> np.ndarray:
    """sensor_msgs/Image (rgb8, 32FC1, 16UC1) -> uint8 HxWx3 or float32 metres HxW; ValueError otherwise."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8).tobytes()
    if len(data) < h * step:
        raise ValueError(f'image data has {len(data)} bytes, {h}x{step} expected')
    if msg.encoding == 'rgb8':
        return np.frombuffer(data, np.uint8)[:h * step].reshape(h, step)[:, :w * 3].reshape(h, w, 3).copy()
    if msg.encoding == '32FC1':
        return np.frombuffer(data, np.float32, count=h * step // 4).reshape(h, step // 4)[:, :w].copy()
    if msg.encoding == '16UC1':
        return (np.frombuffer(data, np.uint16, count=h * step // 2).reshape(h, step // 2)[:, :w]
                .astype(np.float32) / 1000.0)
    raise ValueError(f'unsupported image encoding {msg.encoding!r}')


def float_array(values) -> Any:
    """std_msgs/Float32MultiArray with a 1-D layout."""
    data = np.asarray(values, dtype=np.float32).reshape(-1)
    dim = T('std_msgs/msg/MultiArrayDimension')(label='latent', size=int(data.size), stride=int(data.size))
    return T('std_msgs/msg/Float32MultiArray')(layout=T('std_msgs/msg/MultiArrayLayout')(dim=[dim], data_offset=0),
                                               data=data)


def pose_with_covariance(t_ns: int, p, covariance, frame: str = 'odom') -> Any:
    """geometry_msgs/PoseWithCovarianceStamped at position p (3,), identity orientation, 6x6 row-major covariance."""
    pose = T('geometry_msgs/msg/Pose')(position=T('geometry_msgs/msg/Point')(x=float(p[0]), y=float(p[1]),
                                                                             z=float(p[2])),
                                        orientation=T('geometry_msgs/msg/Quaternion')(x=0.0, y=0.0, z=0.0, w=1.0))
    cov = np.asarray(covariance, dtype=np.float64).reshape(36)
    return T('geometry_msgs/msg/PoseWithCovarianceStamped')(
        header=header(t_ns, frame), pose=T('geometry_msgs/msg/PoseWithCovariance')(pose=pose, covariance=cov))


def pose_position(msg: Any) -> np.ndarray:
    """PoseWithCovarianceStamped -> its position (3,)."""
    p = msg.pose.pose.position
    return np.array([p.x, p.y, p.z], dtype=float)


def boolean(value: bool) -> Any:
    """std_msgs/Bool."""
    return T('std_msgs/msg/Bool')(data=bool(value))


def string(text: str) -> Any:
    """std_msgs/String."""
    return T('std_msgs/msg/String')(data=text)


def landing_json(msg: Any) -> dict:
    """/sim/landing String -> dict; ValueError when not a JSON object."""
    obj = json.loads(msg.data)
    if not isinstance(obj, dict):
        raise ValueError('landing message is not a JSON object')
    return obj


def scene_markers(t_ns: int, boxes, frame: str = 'odom') -> Any:
    """/sim/scene MarkerArray (rosbags object) from assist_sim's BoxMarker list, as sim_node publishes it."""
    Marker = T('visualization_msgs/msg/Marker')
    empty_image = T('sensor_msgs/msg/CompressedImage')(header=header(0, ''), format='', data=np.zeros(0, np.uint8))
    out = []
    for b in boxes:
        qx, qy, qz, qw = b.quaternion
        pose = T('geometry_msgs/msg/Pose')(
            position=T('geometry_msgs/msg/Point')(x=float(b.center[0]), y=float(b.center[1]), z=float(b.center[2])),
            orientation=T('geometry_msgs/msg/Quaternion')(x=qx, y=qy, z=qz, w=qw))
        r, g, bl, a = (float(c) for c in b.rgba)
        out.append(Marker(header=header(t_ns, frame), ns=b.ns, id=int(b.id), type=Marker.CUBE, action=Marker.ADD,
                          pose=pose, scale=_vec3(b.size), color=T('std_msgs/msg/ColorRGBA')(r=r, g=g, b=bl, a=a),
                          lifetime=T('builtin_interfaces/msg/Duration')(sec=0, nanosec=0), frame_locked=False,
                          points=[], colors=[], texture_resource='', texture=empty_image, uv_coordinates=[],
                          text='', mesh_resource='',
                          mesh_file=T('visualization_msgs/msg/MeshFile')(filename='', data=np.zeros(0, np.uint8)),
                          mesh_use_embedded_materials=False))
    return T('visualization_msgs/msg/MarkerArray')(markers=out)


def pads_from_markers(msg: Any) -> tuple[list[dict], int | None]:
    """/sim/scene MarkerArray -> (pads by index: centre, size, yaw), goal index (ns 'goal') or None."""
    pads: dict[int, dict] = {}
    goal = None
    for m in msg.markers:
        q = m.pose.orientation
        yaw = float(np.arctan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)))
        pad = {'centre': (m.pose.position.x, m.pose.position.y, m.pose.position.z),
               'size': (m.scale.x, m.scale.y, m.scale.z), 'yaw': yaw}
        if m.ns == 'platforms':
            pads[int(m.id)] = pad
        elif m.ns == 'goal':
            goal = int(m.id)
    return [pads[i] for i in sorted(pads)], goal
