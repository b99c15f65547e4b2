"""The event publisher's /tf (robot pose along the trajectory), /tf_static (extrinsics,
latched for late subscribers) and /clock (trajectory time when not publishing in real time),
received over loopback DDS; the messages and QoS helpers on their own."""

import os
import time

import numpy as np
import pytest

from conftest import ros_domain

from evdnerf_ros.errors import InputError
from evdnerf_ros.ros import tf as rtf
from evdnerf_ros.ros import rostypes
from evdnerf_ros.ros.qos import LOOPBACK_XML, QosProfile
from evdnerf_ros.ros.transport import DdsContext, DdsSubscription

NS = 1_000_000_000


def test_transform_round_trip_and_bad_pose():
    from evdnerf_ros.io.poses import extrinsics

    T = extrinsics([0.1, -0.2, 0.3], [10, 20, 30])
    data = rtf.tf_message([rtf.transform_stamped(T, "base_link", "event_camera", 3 * NS + 5)])
    [(parent, child, stamp, back)] = rtf.decode_transforms(data)
    assert (parent, child, stamp) == ("base_link", "event_camera", 3 * NS + 5)
    np.testing.assert_allclose(back, T, atol=1e-12)
    clock = rostypes.deserialize(rtf.clock_message(7 * NS + 9), rtf.CLOCK_TYPE).clock
    assert (clock.sec, clock.nanosec) == (7, 9)
    with pytest.raises(InputError, match="finite 4x4"):
        rtf.transform_stamped(np.full((4, 4), np.nan), "a", "b", 0)
    # QoS as ROS 2's broadcasters and clock publishers
    assert rtf.TF_STATIC_QOS.durability == "transient_local" and rtf.TF_STATIC_QOS.depth == 1
    assert rtf.CLOCK_QOS.reliability == "best_effort" and rtf.TF_QOS.depth == 100


def _take(sub, n_min, timeout=5.0):
    got = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and len(got) < n_min:
        sub.wait(0.05)
        got += sub.take_raw(1000)
    return got


def test_publisher_sends_tf_tf_static_and_clock(tmp_path):
    from evdnerf_ros.nodes.event_publisher import EventPublisher

    domain = ros_domain()
    traj = tmp_path / "traj.csv"
    traj.write_text("t_ns,x,y,z,qx,qy,qz,qw\n0,0,0,0,0,0,0,1\n50000000,0.05,0,0,0,0,0,1\n"
                    "100000000,0.1,0,0,0,0,0.0499792,0.9987503\n")
    ctx = DdsContext(domain, config=LOOPBACK_XML)
    tf_sub = DdsSubscription(ctx, "/tf", rtf.TF_TYPE, rtf.TF_QOS)
    # best effort as ROS 2's time source, but deep enough to keep every tick for the check
    clock_sub = DdsSubscription(ctx, "/clock", rtf.CLOCK_TYPE, QosProfile("best_effort", "volatile", 100))
    events = DdsSubscription(ctx, "/event_publisher/events", "event_camera_msgs/msg/EventPacket", "default")
    node = EventPublisher((), overrides={"camera.width": 16, "camera.height": 16, "realtime_factor": 0.0,
                                         "adaptive": False, "trajectory": str(traj), "chunk": 0.02,
                                         "camera.xyz": [0.1, 0.0, 0.2], "camera.rpy_deg": [-90.0, 0.0, -90.0],
                                         "scene_time_offset": 0.15, "wait_for_subscribers": 1},
                          domain_id=domain, dds_config=LOOPBACK_XML)
    assert node._clock_pub is not None            # realtime_factor 0 is not real time
    with node:
        t_deadline = time.monotonic() + 10
        while node._tf_pubs[0].subscribers() < 1 and time.monotonic() < t_deadline:
            time.sleep(0.01)
        rep = node.run()
        tfs = _take(tf_sub, 5)
        clocks = _take(clock_sub, 5)
        # a subscriber that comes after the run still gets the extrinsics (transient local)
        static_sub = DdsSubscription(ctx, "/tf_static", rtf.TF_TYPE, rtf.TF_STATIC_QOS)
        statics = _take(static_sub, 1)
    ctx.close()
    assert rep.events > 0
    chunk_starts = [k * 20_000_000 for k in range(5)]
    poses = [rtf.decode_transforms(d)[0] for d, _ in tfs]
    assert [(p, c, s) for p, c, s, _ in poses] == [("world", "base_link", s) for s in chunk_starts]
    for (_, _, s, T) in poses:
        np.testing.assert_allclose(T, node.track(s), atol=1e-9)
    np.testing.assert_allclose([T[0, 3] for *_, T in poses], [0.0, 0.02, 0.04, 0.06, 0.08], atol=1e-6)
    [(parent, child, _, T_static)] = rtf.decode_transforms(statics[0][0])
    assert (parent, child) == ("base_link", "event_camera")
    np.testing.assert_allclose(T_static, node.T_robot_cam, atol=1e-12)
    np.testing.assert_allclose(T_static[:3, 3], [0.1, 0.0, 0.2])
    stamps = [rostypes.deserialize(d, rtf.CLOCK_TYPE).clock for d, _ in clocks]
    assert [c.sec * NS + c.nanosec for c in stamps] == chunk_starts


def test_clock_only_when_not_real_time_and_tf_switch():
    from evdnerf_ros.nodes.event_publisher import EventPublisher

    domain = ros_domain()
    common = {"camera.width": 8, "camera.height": 8, "duration": 0.01}
    with EventPublisher((), overrides={**common, "realtime_factor": 1.0}, domain_id=domain,
                        dds_config=LOOPBACK_XML) as node:
        assert node._clock_pub is None and node._tf_pubs is not None
    with EventPublisher((), overrides={**common, "realtime_factor": 1.0, "publish_clock": "true",
                                       "publish_tf": False}, domain_id=domain, dds_config=LOOPBACK_XML) as node:
        assert node._clock_pub is not None and node._tf_pubs is None
        assert "/clock" in node.publishers and "/tf" not in node.publishers
    with EventPublisher((), overrides=common, dds=False) as node:      # bag only: nothing extra
        assert node._clock_pub is None and node._tf_pubs is None and node.ros is None
