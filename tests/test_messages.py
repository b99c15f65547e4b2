"""ROS message builders / readers: exact stamps, CameraInfo, PoseStamped, JointState,
TimeReference, through CDR, a bag, and the independent MCAP reader."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from evdnerf_ros.errors import FormatError, InputError
from evdnerf_ros.geometry.poses import check_rigid
from evdnerf_ros.geometry.rotations import quat_from_ros, quat_to_matrix
from evdnerf_ros.io.messages import (K_from_camera_info, camera_info, intrinsics_from_camera_info,
                                     joint_state, ns_to_sec_nanosec, ns_to_stamp, pose_from_pose_stamped,
                                     pose_stamped, stamp_to_ns, time_reference, time_reference_ns)
from evdnerf_ros.io.rosbag2 import BagWriter, open_bag
from evdnerf_ros.io.typestore import ros2_typestore

K = np.array([[512.5, 0.0, 320.25], [0.0, 511.0, 240.75], [0.0, 0.0, 1.0]])
INT32_NS = (-(2**31) * 10**9, (2**31) * 10**9 - 1)


def cdr_round_trip(msg):
    ts = ros2_typestore()
    return ts.deserialize_cdr(ts.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


# --------------------------------------------------------------------------- stamps


@given(st.integers(*INT32_NS))
def test_stamp_round_trip_exact(ns):
    s = ns_to_stamp(ns)
    assert 0 <= s.nanosec < 10**9
    assert stamp_to_ns(s) == ns
    assert stamp_to_ns(cdr_round_trip(pose_stamped(np.eye(4), ns)).header.stamp) == ns


def test_stamp_edge_cases():
    assert ns_to_sec_nanosec(-1) == (-1, 999_999_999)
    assert ns_to_sec_nanosec(INT32_NS[1]) == (2**31 - 1, 999_999_999)
    assert ns_to_sec_nanosec(2**32 * 10**9 - 1, ros1=True) == (2**32 - 1, 999_999_999)
    assert stamp_to_ns((2**33, 5)) == 2**33 * 10**9 + 5  # wider than int32 sec, still exact
    assert stamp_to_ns((1, 1_500_000_000)) == 2_500_000_000  # non-normalised nanosec carried exactly
    with pytest.raises(InputError, match="int32 seconds"):
        ns_to_stamp(INT32_NS[1] + 1)
    with pytest.raises(InputError, match="uint32 seconds"):
        ns_to_sec_nanosec(-1, ros1=True)
    with pytest.raises(InputError, match="int64"):
        stamp_to_ns((2**34, 0))
    with pytest.raises(InputError, match="integer number of nanoseconds"):
        ns_to_stamp(1.5)
    with pytest.raises(InputError, match="bool"):
        ns_to_stamp(True)
    assert stamp_to_ns(ns_to_stamp(np.int64(-123456789012))) == -123456789012


# --------------------------------------------------------------------------- CameraInfo


def test_camera_info_round_trip():
    D = [0.1, -0.2, 0.001, 0.002, 0.05]
    msg = cdr_round_trip(camera_info(640, 480, K, D, frame_id="cam", stamp_ns=1_700_000_000_000_000_123))
    assert np.array_equal(K_from_camera_info(msg), K)
    info = intrinsics_from_camera_info(msg)
    assert (info["width"], info["height"], info["distortion_model"], info["frame_id"], info["stamp_ns"]) == \
        (640, 480, "plumb_bob", "cam", 1_700_000_000_000_000_123)
    assert np.array_equal(info["D"], D) and np.array_equal(info["R"], np.eye(3))
    assert np.array_equal(info["P"], np.hstack([K, np.zeros((3, 1))]))
    eq = cdr_round_trip(camera_info(10, 10, K, [0, 0, 0, 0], distortion_model="equidistant"))
    assert list(eq.d) == [0, 0, 0, 0]


def test_camera_info_rejects_bad_input():
    with pytest.raises(InputError, match=r"expected shape \(3, 3\)"):
        camera_info(640, 480, np.eye(4))
    with pytest.raises(InputError, match="plumb_bob' takes 5"):
        camera_info(640, 480, K, [0.1, 0.2])
    with pytest.raises(InputError, match="pinhole"):
        camera_info(640, 480, -K)
    with pytest.raises(InputError, match="NaN"):
        camera_info(640, 480, K, [np.nan, 0, 0, 0, 0])
    with pytest.raises(InputError, match="width"):
        camera_info(0, 480, K)


# --------------------------------------------------------------------------- poses


def random_pose(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(quat_from_ros(q))
    T[:3, 3] = rng.normal(size=3) * 3
    return T


def test_pose_round_trip(rng):
    specials = [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)]
    poses = [random_pose(rng) for _ in range(200)]
    for R in specials:
        T = np.eye(4)
        T[:3, :3] = R
        poses.append(T)
    for i, T in enumerate(poses):
        got, stamp, frame = pose_from_pose_stamped(cdr_round_trip(pose_stamped(T, 1000 + i, "world")))
        assert np.allclose(got, T, atol=1e-12, rtol=0) and stamp == 1000 + i and frame == "world"
        assert got[3].tolist() == [0, 0, 0, 1]


def test_non_rigid_pose_is_refused():
    T = np.eye(4)
    T[0, 0] = 1.01
    with pytest.raises(InputError, match="not a proper rotation"):
        pose_stamped(T, 0)
    with pytest.raises(InputError, match="det = -1"):
        pose_stamped(np.diag([1.0, 1.0, -1.0, 1.0]), 0)
    bad = np.eye(4)
    bad[3, 0] = 0.5
    with pytest.raises(InputError, match="last row"):
        check_rigid(bad)
    with pytest.raises(InputError, match="shape"):
        pose_stamped(np.eye(3), 0)
    msg = pose_stamped(np.eye(4), 0)
    msg.pose.orientation.w = 0.0
    with pytest.raises(FormatError, match="not a valid rigid pose"):
        pose_from_pose_stamped(msg)


# --------------------------------------------------------------------------- JointState / TimeReference


def test_joint_state_and_time_reference_round_trip():
    js = cdr_round_trip(joint_state(["servo"], [math.radians(30)], [0.5], stamp_ns=77))
    assert list(js.name) == ["servo"] and list(js.position) == [math.radians(30)] and list(js.velocity) == [0.5]
    assert list(js.effort) == [] and stamp_to_ns(js.header.stamp) == 77
    js2 = cdr_round_trip(joint_state(["a", "b"], [1.0, 2.0], stamp_ns=-5))
    assert list(js2.velocity) == [] and stamp_to_ns(js2.header.stamp) == -5
    with pytest.raises(InputError, match="expected 2 values"):
        joint_state(["a", "b"], [1.0], stamp_ns=0)
    with pytest.raises(InputError, match="duplicates"):
        joint_state(["a", "a"], [1.0, 2.0], stamp_ns=0)
    tr = cdr_round_trip(time_reference(1_700_000_000_000_000_001, 123_456_789, "arduino"))
    assert time_reference_ns(tr) == (1_700_000_000_000_000_001, 123_456_789, "arduino")


# --------------------------------------------------------------------------- through a bag


def test_messages_through_bag_and_independent_reader(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.3]
    t = 1_700_000_000_000_000_000
    path = tmp_path / "view_00"
    with BagWriter(path) as w:
        w.write_camera_info("/event_camera/camera_info", 640, 480, K, stamp_ns=t)
        w.write("/rig/camera_pose", "geometry_msgs/msg/PoseStamped", pose_stamped(T, t, "world"), t)
        w.write("/rig/servo/joint_states", "sensor_msgs/msg/JointState", joint_state(["servo"], [0.25], stamp_ns=t + 1),
                t + 1)
        w.write("/rig/servo/trigger", "sensor_msgs/msg/TimeReference", time_reference(t + 2, 42_000, "START"), t + 2)
    with open_bag(path) as bag:
        (_, ci), = bag.read_messages("/event_camera/camera_info")
        (_, ps), = bag.read_messages("/rig/camera_pose")
        (_, js), = bag.read_messages("/rig/servo/joint_states")
        (_, tr), = bag.read_messages("/rig/servo/trigger")
    assert np.array_equal(K_from_camera_info(ci), K)
    assert np.allclose(pose_from_pose_stamped(ps)[0], T, atol=1e-15)
    assert list(js.position) == [0.25] and time_reference_ns(tr) == (t + 2, 42_000, "START")
    with open(next(path.glob("*.mcap")), "rb") as f:
        got = {ch.topic: (m.log_time, msg) for _, ch, m, msg in
               make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()}
    log, ci2 = got["/event_camera/camera_info"]
    assert log == t and list(ci2.k) == K.reshape(-1).tolist() and ci2.distortion_model == "plumb_bob"
    _, ps2 = got["/rig/camera_pose"]
    assert (ps2.pose.position.x, ps2.pose.position.y, ps2.pose.position.z) == (0.1, -0.2, 0.3)
    assert (ps2.pose.orientation.w, ps2.header.frame_id) == (1.0, "world")
    assert got["/rig/servo/joint_states"][1].name == ["servo"]
    tr2 = got["/rig/servo/trigger"][1]
    assert (tr2.time_ref.sec, tr2.time_ref.nanosec, tr2.source) == (0, 42_000, "START")
