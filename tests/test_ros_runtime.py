"""The rclpy-free node runtime: names, --ros-args, typed parameters and YAML files, QoS
profiles and the ROS environment, logging, Node construction."""

import io
import os
import re

import pytest

from evdnerf_ros.errors import InputError
from evdnerf_ros.ros import names, qos
from evdnerf_ros.ros.args import parse_ros_args
from evdnerf_ros.ros.logging import RosLogger
from evdnerf_ros.ros.node import Node
from evdnerf_ros.ros.parameters import ParameterSpec, Parameters, load_params_file


# ----------------------------------------------------------------------------- names

@pytest.mark.parametrize("name,ns,node,full", [
    ("events", "/", "pub", "/events"),
    ("events", "/robot", "pub", "/robot/events"),
    ("/abs/x", "/robot", "pub", "/abs/x"),
    ("~/events", "/", "pub", "/pub/events"),
    ("~/events", "/robot/cam", "pub", "/robot/cam/pub/events"),
    ("~", "/robot", "pub", "/robot/pub"),
    ("a/b", "robot", "pub", "/robot/a/b"),
])
def test_resolve_topic(name, ns, node, full):
    assert names.resolve_topic(name, ns, node) == full


@pytest.mark.parametrize("bad", ["", "/a//b", "/a/", "/1abc", "/a b", "/a/__x", "~events", "/a-b"])
def test_bad_topic_names_are_refused(bad):
    with pytest.raises(InputError, match="topic name"):
        names.resolve_topic(bad, "/", "pub")


def test_dds_names():
    assert names.dds_topic("/event_publisher/events") == "rt/event_publisher/events"
    assert names.dds_type("event_camera_msgs/msg/EventPacket") == "event_camera_msgs::msg::dds_::EventPacket_"
    with pytest.raises(InputError):
        names.dds_type("EventPacket")
    with pytest.raises(InputError, match="node name"):
        names.validate_node_name("9lives")


def test_remaps_resolve_both_sides():
    remaps = {"~/events": "/camera/events", "other": "x"}
    assert names.apply_remaps("/ns/pub/events", remaps, "/ns", "pub") == "/camera/events"
    assert names.apply_remaps("/ns/other", remaps, "/ns", "pub") == "/ns/x"
    assert names.apply_remaps("/ns/kept", remaps, "/ns", "pub") == "/ns/kept"


# ----------------------------------------------------------------------------- --ros-args

def test_parse_ros_args_all_forms(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("x: {ros__parameters: {}}\n")
    ros, rest = parse_ros_args(
        ["positional", "--ros-args", "-p", "a:=3", "--param", "b:=[1.5, 2]", "-p", "c:='007'",
         "-p", "other_node:d:=1", "-p", "pub:e:=true", "--params-file", str(f), "-r", "__node:=renamed",
         "-r", "__ns:=/robot", "-r", "~/events:=/cam/events", "-r", "other_node:x:=y", "--log-level", "debug",
         "--enclave", "/e", "--disable-rosout-logs", "--", "tail"], "pub")
    assert rest == ["positional", "tail"]
    assert ros.params == {"a": 3, "b": [1.5, 2], "c": "007", "e": True}
    assert ros.params_files == [f]
    assert ros.node_name == "renamed" and ros.namespace == "/robot"
    assert ros.remaps == {"~/events": "/cam/events"}
    assert ros.log_level == "debug"


@pytest.mark.parametrize("argv,match", [
    (["--ros-args", "-p", "novalue"], "name:=value"),
    (["--ros-args", "-p"], "missing"),
    (["--ros-args", "--params-file", "/no/such.yaml"], "no such file"),
    (["--ros-args", "--log-level", "loud"], "log-level"),
    (["--ros-args", "--bogus"], "unknown argument"),
    (["--ros-args", "-p", "a:=[1,"], "not valid YAML"),
])
def test_parse_ros_args_errors(argv, match):
    with pytest.raises(InputError, match=match):
        parse_ros_args(argv, "pub")


# ----------------------------------------------------------------------------- parameters

SPECS = [ParameterSpec("rate", 1.0, "rate", min=0.0, max=10.0), ParameterSpec("n", 3, "count"),
         ParameterSpec("mode", "a", "mode", choices=("a", "b")), ParameterSpec("on", True, "flag"),
         ParameterSpec("cam.width", 64, "width", read_only=True), ParameterSpec("xyz", [0.0, 0.0, 0.0], "pos")]


def test_parameters_types_ranges_and_all_or_nothing():
    p = Parameters(SPECS)
    assert p["rate"] == 1.0 and p.cam__width == 64
    assert p.apply({"rate": 2, "n": 5}, "test") == []
    assert p["rate"] == 2.0 and isinstance(p["rate"], float) and p.source("n") == "test"
    for bad, match in [({"n": 1.5}, "is a integer"), ({"on": 1}, "is a bool"), ({"rate": 11.0}, "range"),
                       ({"mode": "c"}, "not one of"), ({"xyz": 3}, "is a array")]:
        with pytest.raises(InputError, match=match):
            p.apply({"n": 9, **bad}, "test")
        assert p["n"] == 5            # nothing applied when one value is bad
    with pytest.raises(InputError, match="read-only"):
        p.apply({"cam.width": 32}, "set", startup=False)
    assert p.apply({"typo": 1}, "t") == ["typo"]
    with pytest.raises(InputError, match="declared twice"):
        Parameters(SPECS + [SPECS[0]])


def test_params_file_wildcards_namespaces_and_nesting(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters: {n: 1, rate: 0.5}\n"
                 "pub:\n  ros__parameters: {n: 2, cam: {width: 32}}\n"
                 "/robot/pub:\n  ros__parameters: {mode: b}\n"
                 "other:\n  ros__parameters: {n: 99}\n")
    assert load_params_file(f, "pub", "/") == {"n": 2, "rate": 0.5, "cam.width": 32}
    assert load_params_file(f, "pub", "/robot") == {"n": 1, "rate": 0.5, "mode": "b"}
    assert load_params_file(f, "nobody") == {"n": 1, "rate": 0.5}
    bad = tmp_path / "bad.yaml"
    bad.write_text("pub:\n  n: 3\n")
    with pytest.raises(InputError, match="ros__parameters"):
        load_params_file(bad, "pub")
    bad.write_text("pub: [\n")
    with pytest.raises(InputError, match="not valid YAML"):
        load_params_file(bad, "pub")


class _Demo(Node):
    NAME = "demo_node"
    PARAMETERS = SPECS


def test_node_precedence_defaults_file_overrides_cli(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/r/renamed:\n  ros__parameters: {n: 2, rate: 0.5, unknown_key: 1}\n"
                 "renamed:\n  ros__parameters: {rate: 9.0}\n")  # root namespace only: not this node
    log = io.StringIO()
    node = _Demo(["--ros-args", "--params-file", str(f), "-p", "n:=7", "-r", "__node:=renamed", "-r", "__ns:=/r",
                  "-r", "~/out:=/remapped"], overrides={"n": 4, "mode": "b"}, dds=False, log_stream=log)
    assert node.name == "renamed" and node.namespace == "/r" and node.fully_qualified_name == "/r/renamed"
    assert (node.params["n"], node.params["rate"], node.params["mode"]) == (7, 0.5, "b")
    assert node.resolve("~/out") == "/remapped" and node.resolve("~/in") == "/r/renamed/in"
    assert "unknown_key" in log.getvalue()
    with pytest.raises(InputError, match="unexpected arguments"):
        _Demo(["stray"], dds=False)
    with pytest.raises(InputError, match="subscriptions need DDS"):
        node.create_subscription("x", "std_msgs/msg/Header")


def test_logger_format_and_threshold():
    out = io.StringIO()
    log = RosLogger("pub", "info", out)
    log.debug("hidden")
    log.info("shown")
    log.warn("careful")
    lines = out.getvalue().splitlines()
    assert len(lines) == 2
    assert re.fullmatch(r"\[INFO\] \[\d+\.\d{9}\] \[pub\]: shown", lines[0])
    assert lines[1].startswith("[WARN] ")


# ----------------------------------------------------------------------------- QoS and environment

def test_qos_profiles_map_to_cyclone():
    from cyclonedds.qos import Policy

    q = qos.profile("default").to_cyclone()
    assert Policy.Reliability.Reliable(max_blocking_time=qos.MAX_BLOCKING_NS) in q
    assert Policy.History.KeepLast(10) in q and Policy.Durability.Volatile in q
    q = qos.profile("sensor_data").to_cyclone()
    assert Policy.Reliability.BestEffort in q and Policy.History.KeepLast(5) in q
    q = qos.profile("transient_local", depth=3).to_cyclone()
    assert Policy.Durability.TransientLocal in q and Policy.History.KeepLast(3) in q
    with pytest.raises(InputError, match="QoS profile"):
        qos.profile("fast")
    with pytest.raises(InputError, match="depth"):
        qos.QosProfile(depth=0)


def test_ros_environment():
    assert qos.domain_id({}) == 0
    assert qos.domain_id({"ROS_DOMAIN_ID": "42"}) == 42
    for bad in ("233", "-1", "x"):
        with pytest.raises(InputError, match="ROS_DOMAIN_ID"):
            qos.domain_id({"ROS_DOMAIN_ID": bad})
    # rcl 9.2's precedence: ROS_LOCALHOST_ONLY=1 wins over the range Jazzy's setup.bash sets
    d = qos.discovery({"ROS_LOCALHOST_ONLY": "1", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
                       "ROS_STATIC_PEERS": "10.0.0.2"})
    assert (d.range, d.static_peers) == ("LOCALHOST", ())
    assert any("will be ignored" in w for w in d.warnings)
    assert qos.discovery({"ROS_LOCALHOST_ONLY": "0", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}).range == "SUBNET"
    assert qos.discovery({}).range == "SUBNET" and qos.discovery({}).warnings == ()
    assert qos.discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}).range == "LOCALHOST"
    bad = qos.discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "subnet"})     # rcl compares case-sensitively
    assert bad.range == "LOCALHOST" and "assuming localhost only" in bad.warnings[0]
    peers = qos.discovery({"ROS_STATIC_PEERS": "a.example;;10.0.0.2;" + "x" * 300})
    assert peers.static_peers == ("a.example", "10.0.0.2") and "too long" in peers.warnings[0]
    off = qos.discovery({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_STATIC_PEERS": "10.0.0.2"})
    assert off.static_peers == () and "will be ignored" in off.warnings[0]
    # rmw_cyclonedds_cpp 2.2's configuration for each
    assert qos.domain_config({"ROS_LOCALHOST_ONLY": "1"}) == qos.LOOPBACK_XML
    assert qos.domain_config({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"}) is None
    subnet = qos.domain_config({})
    assert "AllowMulticast" not in subnet and "<Peers>" not in subnet and "MaxAutoParticipantIndex>32" in subnet
    local_peer = qos.domain_config({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_STATIC_PEERS": "10.0.0.2"})
    assert '<Peer address="localhost"/><Peer address="10.0.0.2"/>' in local_peer
    assert "<AllowMulticast>false" in local_peer and 'name="lo"' not in local_peer
    assert '<Peer address="10.0.0.2"/>' in qos.domain_config({"ROS_STATIC_PEERS": "10.0.0.2"})
    assert f"ros_discovery_off_{os.getpid()}" in qos.domain_config({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"})
    assert qos.domain_config({"ROS_LOCALHOST_ONLY": "1", "CYCLONEDDS_URI": "file:///x.xml"}).endswith(
        "</CycloneDDS>,file:///x.xml")


def test_a_ctrl_c_delivered_twice_is_one_stop_request():
    """A terminal's Ctrl-C reaches `ros2 launch` and the node, and launch forwards it again: the
    repeat within REPEATED_SIGINT_S is not a second Ctrl-C; one a while later is."""
    import time

    from evdnerf_ros.ros.node import REPEATED_SIGINT_S, is_second_interrupt

    assert is_second_interrupt([])
    assert not is_second_interrupt([time.monotonic()])
    assert is_second_interrupt([time.monotonic() - REPEATED_SIGINT_S - 0.1])
