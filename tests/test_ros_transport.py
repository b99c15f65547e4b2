"""Cyclone DDS transport on loopback (random non-zero domain, localhost only): the raw-CDR
fast path (cyclonedds' private ddspy_write / ddspy_take, pinned 11.0.1) carries rosbags'
CDR byte for byte, the IdlStruct types have ROS 2's names and layout, and a QoS mismatch
is reported."""

import os
import time

import numpy as np
import pytest

from conftest import ros_domain

from evdnerf_ros.io import messages
from evdnerf_ros.io.typestore import ros2_typestore
from evdnerf_ros.ros.idl import idl_type, to_idl
from evdnerf_ros.ros.qos import LOOPBACK_XML
from evdnerf_ros.ros.transport import DdsContext, DdsPublisher, DdsSubscription


def _domain() -> int:
    return ros_domain()


@pytest.fixture
def ctx():
    c = DdsContext(_domain(), config=LOOPBACK_XML)
    yield c
    c.close()


def _samples():
    ts = ros2_typestore()
    T = ts.types
    hdr = messages.header(1_234_567_890_123, "cam")
    packet = T["event_camera_msgs/msg/EventPacket"](
        header=hdr, height=260, width=346, seq=7, time_base=1_000, encoding="evt3", is_bigendian=False,
        events=np.arange(4099, dtype=np.uint32).astype(np.uint8))
    Ev = T["dvs_msgs/msg/Event"]
    arr = T["dvs_msgs/msg/EventArray"](header=hdr, height=4, width=5, events=[
        Ev(x=1, y=2, ts=messages.ns_to_stamp(5), polarity=True), Ev(x=3, y=0, ts=messages.ns_to_stamp(9),
                                                                   polarity=False)])
    info = messages.camera_info(64, 48, [[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]], stamp_ns=77)
    pose = messages.pose_stamped(np.eye(4), 5, "world")
    return [(m, m.__msgtype__) for m in (packet, arr, info, pose)]


def _receive(sub, n, timeout=5.0):
    got, deadline = [], time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        if sub.wait(0.2):
            got += sub.take_raw()
    return got


@pytest.mark.parametrize("fast_pub", [True, False])
def test_raw_cdr_round_trip_is_rosbags_cdr(ctx, fast_pub):
    ts = ros2_typestore()
    for msg, msgtype in _samples():
        topic = f"/t/{msgtype.split('/')[-1].lower()}_{int(fast_pub)}"
        sub = DdsSubscription(ctx, topic, msgtype)
        pub = DdsPublisher(ctx, topic, msgtype, fast=fast_pub)
        assert pub.wait_for_subscribers(1, 5.0)
        pub.publish(msg)
        (data, stamp), = _receive(sub, 1)
        want = bytes(ts.serialize_cdr(msg, msgtype))
        assert len(data) % 4 == 0 and len(data) - len(want) < 4
        assert data[:len(want)] == want              # byte for byte what a ROS 2 node sends
        assert set(data[len(want):]) <= {0}
        back = ts.deserialize_cdr(data, msgtype)
        assert bytes(ts.serialize_cdr(back, msgtype)) == want
        assert stamp > 0


def test_idl_types_have_ros_names_and_layout(ctx):
    ts = ros2_typestore()
    for msg, msgtype in _samples():
        pkg, _, name = msgtype.split("/")
        cls = idl_type(msgtype)
        assert cls.__idl_typename__.replace(".", "::") == f"{pkg}::msg::dds_::{name}_"
        want = bytes(ts.serialize_cdr(msg, msgtype))
        assert to_idl(msg, msgtype).serialize(use_version_2=False)[:len(want)] == want
    top = ctx.topic("/event_publisher/events", "event_camera_msgs/msg/EventPacket")
    assert top.name == "rt/event_publisher/events"


def test_qos_mismatch_is_reported_on_both_sides(ctx):
    logs = []
    log = lambda level, msg: logs.append((level, msg))  # noqa: E731
    sub = DdsSubscription(ctx, "/mismatch", "std_msgs/msg/Header", "default", log=log)         # reliable
    pub = DdsPublisher(ctx, "/mismatch", "std_msgs/msg/Header", "sensor_data", log=log)       # best effort
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and not (pub.check_qos() or logs):
        time.sleep(0.05)
    sub.check_qos()
    assert pub.matched() == 0
    assert any(level == "warn" and "/mismatch" in m and "RELIABILITY" in m and "subscriber" in m for level, m in logs)
    assert any("publisher has incompatible QoS" in m for _, m in logs)
    pub.publish(messages.header(1, "x"))
    assert _receive(sub, 1, timeout=0.5) == []       # DDS delivers nothing: hence the warning


def test_reliable_publisher_reaches_best_effort_subscriber(ctx):
    sub = DdsSubscription(ctx, "/compatible", "std_msgs/msg/Header", "sensor_data")
    pub = DdsPublisher(ctx, "/compatible", "std_msgs/msg/Header", "default")
    assert pub.wait_for_subscribers(1, 5.0)
    pub.publish(messages.header(5, "x"))
    assert len(_receive(sub, 1)) == 1
    assert not pub.check_qos() and not sub.check_qos()
