"""Parameter services (rcl_interfaces over rq/ / rr/ topics, rmw_cyclonedds' request header),
/parameter_events and /rosout, against a node on loopback DDS; the event publisher's live
parameters. The client is ours (what `ros2 param` sends); the Fast DDS peer in
test_ros_graph.py calls the same services from an independent DDS implementation."""

import io
import os
import threading
import time

import numpy as np
import pytest

from conftest import ros_domain

from evdnerf_ros.errors import InputError
from evdnerf_ros.ros import rostypes
from evdnerf_ros.ros.node import Node
from evdnerf_ros.ros.param_services import (DOUBLE, INTEGER, STRING, ParameterClient, join_reply, split_request,
                                            to_parameter_value)
from evdnerf_ros.ros.parameters import ParameterSpec as P
from evdnerf_ros.ros.parameters import Parameters
from evdnerf_ros.ros.qos import LOOPBACK_XML, PROFILES
from evdnerf_ros.ros.transport import DdsContext, DdsPublisher, DdsSubscription


def _domain() -> int:
    return ros_domain()


class Talker(Node):
    NAME = "talker"
    PARAMETERS = [
        P("gain", 1.0, "a live gain", dynamic=True, min=0.0, max=10.0),
        P("count", 3, "a live count", dynamic=True, min=0),
        P("mode", "a", "a live choice", dynamic=True, choices=("a", "b")),
        P("label", "x", "start-up only"),
        P("path", "", "read-only", read_only=True),
        P("camera.xyz", [0.0, 0.0, 0.0], "a nested list", dynamic=True),
    ]


@pytest.fixture
def served():
    domain = _domain()
    log = io.StringIO()
    node = Talker(domain_id=domain, dds_config=LOOPBACK_XML, log_stream=log, namespace="/robot")
    ctx = DdsContext(domain, config=LOOPBACK_XML)
    events = DdsSubscription(ctx, "/parameter_events", "rcl_interfaces/msg/ParameterEvent", PROFILES["parameters"])
    rosout = DdsSubscription(ctx, "/rosout", "rcl_interfaces/msg/Log", PROFILES["parameters"])
    client = ParameterClient(ctx, "/robot/talker")
    assert client.wait_for_service(10.0)
    yield node, client, events, rosout, log
    node.shutdown()
    ctx.close()


def _events(sub, timeout=2.0):
    out = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sub.wait(0.05)
        out += [rostypes.deserialize(d, "rcl_interfaces/msg/ParameterEvent") for d, _ in sub.take_raw()]
        if out and time.monotonic() > deadline - timeout + 0.3:
            break
    return out


def test_get_list_types_describe(served):
    node, client, *_ = served
    assert client.get("gain", "label", "camera.xyz", "nope") == [1.0, "x", [0.0, 0.0, 0.0], None]
    assert client.list() == ["gain", "count", "mode", "label", "path", "camera.xyz", "use_sim_time"]
    assert client.list(prefixes=["camera"]) == ["camera.xyz"]
    assert client.list(depth=1) == ["gain", "count", "mode", "label", "path", "use_sim_time"]
    assert client.types("gain", "count", "label", "camera.xyz", "nope") == [DOUBLE, INTEGER, STRING, 8, 0]
    gain, label, path, mode = client.describe("gain", "label", "path", "mode")
    assert (gain.type, gain.read_only, gain.description) == (DOUBLE, False, "a live gain")
    assert (gain.floating_point_range[0].from_value, gain.floating_point_range[0].to_value) == (0.0, 10.0)
    assert label.read_only and "start-up only" in label.additional_constraints
    assert path.read_only and "one of ['a', 'b']" in mode.additional_constraints


def test_set_takes_effect_or_refuses_with_the_reason(served):
    node, client, events, rosout, log = served
    seen = []
    node.params.listeners.append(seen.append)
    first = _events(events)           # the initial values (new_parameters), transient for late joiners: none
    assert client.set(gain=2.5, count=7) == [(True, ""), (True, "")]
    assert node.params["gain"] == 2.5 and node.params["count"] == 7 and seen == [{"gain": 2.5}, {"count": 7}]
    refused = {
        "gain": (20.0, "outside its range [0.0, 10.0]"),
        "count": (1.5, "Wrong parameter type, parameter {count} is of type {integer}, setting it to {double}"),
        "mode": ("c", "is not one of ['a', 'b']"),
        "label": ("y", "read-only while the node runs; set it at start-up"),
        "path": ("/x", "read-only while the node runs"),
        "ghost": (1, "cannot be set because it was not declared"),
    }
    for name, (value, reason) in refused.items():
        [(ok, why)] = client.set(**{name: value})
        assert not ok and reason in why, (name, why)
    ok, why = client.set_typed("gain", 3, INTEGER)       # ROS 2 does not turn an integer into a double
    assert not ok and "setting it to {integer} is not allowed" in why
    assert node.params["gain"] == 2.5 and node.params["label"] == "x"
    # each value on its own: the good one applies, the bad one is refused
    assert [ok for ok, _ in client.set(gain=4.0, count=-1)] == [True, False]
    assert client.set(**{"camera.xyz": [0.1, 0.2, 0.3]}) == [(True, "")]
    assert client.get("gain", "count", "camera.xyz") == [4.0, 7, [0.1, 0.2, 0.3]]
    evs = first + _events(events)
    changed = [(p.name, to_py(p.value)) for e in evs for p in e.changed_parameters]
    assert changed == [("gain", 2.5), ("count", 7), ("gain", 4.0), ("camera.xyz", [0.1, 0.2, 0.3])]
    assert all(e.node == "/robot/talker" for e in evs)
    # refusals are logged, and every log line is also on /rosout
    lines = [rostypes.deserialize(d, "rcl_interfaces/msg/Log") for d, _ in rosout.take_raw(1000)]
    assert any(ln.level == 30 and "outside its range" in ln.msg and ln.name == "robot.talker" for ln in lines)
    assert "[WARN]" in log.getvalue() and "outside its range" in log.getvalue()


def to_py(pv):
    from evdnerf_ros.ros.param_services import from_parameter_value

    return from_parameter_value(pv)[1]


def test_set_atomically_is_all_or_nothing(served):
    node, client, events, *_ = served
    [(ok, why)] = client.set(atomically=True, gain=5.0, count=2.5)
    assert not ok and "{count} is of type {integer}" in why
    [(ok, why)] = client.set(atomically=True, gain=5.0, label="z")
    assert not ok and "read-only" in why
    assert node.params["gain"] == 1.0 and node.params["count"] == 3
    assert client.set(atomically=True, gain=5.0, count=9) == [(True, "")]
    assert (node.params["gain"], node.params["count"]) == (5.0, 9)


def test_validators_refuse_the_whole_set():
    params = Parameters([P("lo", 1, "", dynamic=True), P("hi", 5, "", dynamic=True)])
    params.validators.append(lambda ch: "lo must stay below hi" if {**params.as_dict(), **ch}["lo"] >=
                             {**params.as_dict(), **ch}["hi"] else None)
    assert params.set_runtime([("lo", 7)], "t", atomically=True) == ["lo must stay below hi"]
    assert params.set_runtime([("lo", 7), ("hi", "x")], "t", atomically=True)[0].startswith("t: parameter 'hi'")
    assert params.as_dict() == {"lo": 1, "hi": 5}
    assert params.set_runtime([("lo", 7), ("hi", 9)], "t", atomically=True) == [None, None]
    assert params.as_dict() == {"lo": 7, "hi": 9}
    # one by one: each value is judged against the values before it
    assert params.set_runtime([("lo", 20), ("hi", 30)], "t") == ["lo must stay below hi", None]
    assert params.as_dict() == {"lo": 7, "hi": 30}


def test_a_bool_value_names_a_true_false_choice():
    """``-p per_pixel:=false`` reads as a bool; a string parameter offering "true" / "false" takes it
    as that choice, and refuses it otherwise."""
    spec = P("mode", "auto", "", choices=("auto", "true", "false"))
    assert spec.coerce(False, "t") == "false" and spec.coerce(True, "t") == "true"
    assert spec.coerce("auto", "t") == "auto"
    with pytest.raises(InputError, match="is a string, got bool"):
        P("world", "auto", "", choices=("auto", "field")).coerce(True, "t")
    with pytest.raises(InputError, match="is a string, got bool"):
        P("name", "x", "").coerce(False, "t")


def test_malformed_requests_are_logged_and_ignored(served):
    """Cyclone drops samples that are not valid CDR for the topic's type before they reach us
    (test_ros_graph.py sends such bytes from Fast DDS); what arrives can still be nonsense:
    parameter values of no ParameterType, requests of the wrong shape. Logged, ignored, and
    the service keeps answering."""
    from evdnerf_ros.ros.param_services import _msg

    node, client, *_, log = served
    srv = "rcl_interfaces/srv/SetParameters"
    bad = DdsPublisher(client.ctx, "/robot/talker/set_parameters", srv + "_Request", PROFILES["parameters"],
                       dds_name="rq/robot/talker/set_parametersRequest",
                       idl=rostypes.idl_struct(srv + "_Request", True))
    assert bad.wait_for_subscribers(1, 5.0)
    value = to_parameter_value(2.0)
    value.type = 77                                        # no such rcl_interfaces/msg/ParameterType
    body = rostypes.serialize(rostypes.message(srv + "_Request", parameters=[_msg("Parameter", name="gain",
                                                                                  value=value)]), srv + "_Request")
    bad.publish_raw(join_reply(5, 1, body))
    bad.publish_raw(body)                                  # no request header: the body is read as one
    deadline = time.monotonic() + 5
    while node.ros.params.malformed < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert node.ros.params.malformed == 2
    assert client.get("gain") == [1.0]              # nothing applied, still serving
    assert log.getvalue().count("ignored a malformed request") == 2


def test_request_header_round_trip():
    body = rostypes.serialize(rostypes.message("rcl_interfaces/srv/GetParameters_Request", names=["a"]),
                              "rcl_interfaces/srv/GetParameters_Request")
    wire = join_reply(0x1122334455667788, -3, body)
    assert wire[4:20] == bytes.fromhex("8877665544332211") + (-3).to_bytes(8, "little", signed=True)
    assert split_request(wire) == (0x1122334455667788, -3, body)
    with pytest.raises(InputError, match="XCDR1 header"):
        split_request(b"\x00\x01\x00\x00abc")


def test_event_publisher_thresholds_and_noise_change_live():
    from evdnerf_ros.nodes.event_publisher import EventPublisher

    domain = _domain()
    log = io.StringIO()
    node = EventPublisher((), overrides={"camera.width": 16, "camera.height": 16, "realtime_factor": 1.0,
                                         "adaptive": False, "duration": 1.5, "chunk": 0.02,
                                         "scene_time_offset": 0.15},
                          domain_id=domain, dds_config=LOOPBACK_XML, log_stream=log)
    ctx = DdsContext(domain, config=LOOPBACK_XML)
    client = ParameterClient(ctx, "/event_publisher")
    assert client.wait_for_service(10.0)
    before = node.generator
    result = {}
    th = threading.Thread(target=lambda: result.update(rep=node.run()))
    with node:
        th.start()
        time.sleep(0.3)
        assert client.set(c_pos=0.5, shot_noise_hz=5.0) == [(True, ""), (True, "")]
        [(ok, why)] = client.set(scene="sky")
        [(ok2, why2)] = client.set(c_neg=-1.0)
        th.join(30)
    ctx.close()
    assert not ok and "read-only while the node runs" in why and not ok2 and "outside its range" in why2
    g = node.generator
    assert g is not before and (g.c_pos, g.c_neg, g.shot_noise_rate_hz) == (0.5, before.c_neg, 5.0)
    assert "applied at t = " in log.getvalue() and result["rep"].events > 0
    # the new generator went on from the old one's log image, not from scratch
    assert g.initialized and g.t_ns > node.t0
    np.testing.assert_array_equal(np.asarray(node.params["camera.xyz"]), [0.0, 0.0, 0.0])


def test_type_description_service(served):
    """~/get_type_description (REP 2011): the description whose JSON hashes to the type's RIHS01."""
    import hashlib
    import json

    _node, client, *_ = served
    name = "sensor_msgs/msg/CameraInfo"
    rep = client.call("get_type_description", type_name=name, type_hash=rostypes.type_hash(name),
                      include_type_sources=True)
    assert rep.successful and rep.failure_reason == ""
    got = rep.type_description
    assert got.type_description.type_name == name
    assert [f.name for f in got.type_description.fields][:3] == ["header", "height", "width"]
    as_dict = {"type_description": {"type_name": got.type_description.type_name, "fields": [
        {"name": f.name, "type": {"type_id": int(f.type.type_id), "capacity": int(f.type.capacity),
                                  "string_capacity": int(f.type.string_capacity),
                                  "nested_type_name": f.type.nested_type_name}} for f in got.type_description.fields]},
               "referenced_type_descriptions": [{"type_name": r.type_name, "fields": [
                   {"name": f.name, "type": {"type_id": int(f.type.type_id), "capacity": int(f.type.capacity),
                                             "string_capacity": int(f.type.string_capacity),
                                             "nested_type_name": f.type.nested_type_name}} for f in r.fields]}
                   for r in got.referenced_type_descriptions]}
    assert "RIHS01_" + hashlib.sha256(json.dumps(as_dict).encode()).hexdigest() == rostypes.type_hash(name)
    wrong = client.call("get_type_description", type_name=name, type_hash="RIHS01_" + "0" * 64,
                        include_type_sources=False)
    assert not wrong.successful and "hash" in wrong.failure_reason
    unknown = client.call("get_type_description", type_name="no_pkg/msg/Nothing", type_hash="",
                          include_type_sources=False)
    assert not unknown.successful and "not known" in unknown.failure_reason


def test_use_sim_time_follows_clock(served):
    """use_sim_time (every node's parameter): set live, the node's clock follows /clock."""
    from evdnerf_ros.ros import tf as rtf
    from evdnerf_ros.ros.transport import DdsPublisher

    node, client, *_ = served
    assert client.get("use_sim_time") == [False]
    assert abs(node.now_ns() - time.time_ns()) < 5_000_000_000
    assert client.set(use_sim_time=True) == [(True, "")]
    assert node.now_ns() == 0                        # no /clock yet, as rclpy's clock
    clock = DdsPublisher(client.ctx, "/clock", rtf.CLOCK_TYPE, rtf.CLOCK_QOS)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and node.now_ns() != 123_456_789_012:
        clock.publish_raw(rtf.clock_message(123_456_789_012))
        time.sleep(0.05)
    assert node.now_ns() == 123_456_789_012
