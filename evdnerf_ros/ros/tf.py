"""``/tf``, ``/tf_static`` (tf2_msgs/msg/TFMessage) and ``/clock`` (rosgraph_msgs/msg/Clock).

QoS as ROS 2's broadcasters: ``/tf`` reliable, volatile, keep-last 100
(tf2_ros::DynamicBroadcasterQoS); ``/tf_static`` reliable, transient local, keep-last 1
(StaticBroadcasterQoS: a late listener still gets the extrinsics); ``/clock`` best effort,
keep-last 1 (rclcpp::ClockQoS, what ``ros2 bag play --clock`` and simulators publish;
a node with ``use_sim_time:=true`` subscribes with that QoS). Poses are 4x4 homogeneous
T_parent_child; quaternions go out in ROS order (x, y, z, w). Stamps are int64 ns.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from . import rostypes
from .qos import BEST_EFFORT, RELIABLE, TRANSIENT_LOCAL, VOLATILE, QosProfile

TF_TYPE = "tf2_msgs/msg/TFMessage"
CLOCK_TOPIC = "/clock"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"
TF_QOS = QosProfile(RELIABLE, VOLATILE, 100)
TF_STATIC_QOS = QosProfile(RELIABLE, TRANSIENT_LOCAL, 1)
CLOCK_QOS = QosProfile(BEST_EFFORT, VOLATILE, 1)


def _time(stamp_ns: int):
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return rostypes.message("builtin_interfaces/msg/Time", sec=sec, nanosec=nsec)


def transform_stamped(T, parent: str, child: str, stamp_ns: int):
    """geometry_msgs/msg/TransformStamped of the 4x4 pose T_parent_child."""
    from ..geometry.rotations import matrix_to_quat, quat_to_ros

    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"transform {parent} -> {child}: expected a finite 4x4 pose, got shape {T.shape}")
    q = quat_to_ros(matrix_to_quat(T[:3, :3]))
    m = rostypes.message
    return m("geometry_msgs/msg/TransformStamped",
             header=m("std_msgs/msg/Header", stamp=_time(stamp_ns), frame_id=parent), child_frame_id=child,
             transform=m("geometry_msgs/msg/Transform",
                         translation=m("geometry_msgs/msg/Vector3", x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                         rotation=m("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                    w=float(q[3]))))


def tf_message(transforms) -> bytes:
    """CDR of a TFMessage of the given TransformStamped objects."""
    return rostypes.serialize(rostypes.message(TF_TYPE, transforms=list(transforms)), TF_TYPE)


def clock_message(stamp_ns: int) -> bytes:
    return rostypes.serialize(rostypes.message(CLOCK_TYPE, clock=_time(stamp_ns)), CLOCK_TYPE)


def clock_stamp_ns(data) -> int:
    """A rosgraph_msgs/msg/Clock CDR -> its time in int64 ns."""
    st = rostypes.deserialize(bytes(data), CLOCK_TYPE).clock
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def decode_transforms(data) -> list[tuple[str, str, int, np.ndarray]]:
    """TFMessage CDR -> [(parent, child, stamp ns, 4x4 T_parent_child)]."""
    from ..geometry.rotations import quat_from_ros, quat_to_matrix

    out = []
    for tr in rostypes.deserialize(data, TF_TYPE).transforms:
        r, t = tr.transform.rotation, tr.transform.translation
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(quat_from_ros([r.x, r.y, r.z, r.w]))
        T[:3, 3] = [t.x, t.y, t.z]
        st = tr.header.stamp
        out.append((tr.header.frame_id, tr.child_frame_id, int(st.sec) * 1_000_000_000 + int(st.nanosec), T))
    return out
