"""Zenoh transport with rmw_zenoh's conventions, against a SEPARATE process that uses only the
`zenoh` package and rosbags (not our code): it subscribes with rmw_zenoh's key expressions and
checks the attachment and the CDR, queries our liveliness tokens, and publishes in rmw_zenoh's
format (with malformed samples in between) to our echo. Peer mode on loopback, no router, no
multicast: our side listens on a free port, the peer connects to it; a random ROS domain."""

import importlib.util
import io
import json
import os
import pickle
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ros_domain

from evdnerf_ros.io.typestore import ros2_typestore
from evdnerf_ros.ros import zenoh_transport as zt
from evdnerf_ros.ros.transport import TransportError

HAVE_ZENOH = importlib.util.find_spec("zenoh") is not None
needs_zenoh = pytest.mark.skipif(not HAVE_ZENOH, reason="eclipse-zenoh is not installed "
                                 "(.venv/bin/pip install -e '.[zenoh]')")

EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
MSG_DIR = Path(zt.__file__).resolve().parents[1] / "io" / "msg"

PEER = r"""
import json, pickle, struct, sys, time
from pathlib import Path
import zenoh
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

mode, port, domain, path, msgdir = sys.argv[1:6]
ts = get_typestore(Stores.ROS2_HUMBLE)
ts.register(get_types_from_msg((Path(msgdir) / "event_camera_msgs/msg/EventPacket.msg").read_text(),
                               "event_camera_msgs/msg/EventPacket"))
EV, CI = "event_camera_msgs/msg/EventPacket", "sensor_msgs/msg/CameraInfo"

def dds(name):
    pkg, _, t = name.split("/")
    return f"{pkg}::msg::dds_::{t}_"

def key(topic, name):          # rmw_zenoh: <domain>/<topic without leading slash>/<DDS type>/<RIHS01 hash>
    return f"{domain}/{topic.strip('/')}/{dds(name)}/{ts.hash_rihs01(name)}"

cfg = zenoh.Config()
cfg.insert_json5("mode", '"peer"')
cfg.insert_json5("scouting/multicast/enabled", "false")
cfg.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
s = zenoh.open(cfg)
zid = str(s.info.zid())

def token(eid, kind, node, topic=None, name=None, qos="::,10:,:,:,,"):
    k = f"@ros2_lv/{domain}/{zid}/0/{eid}/{kind}/%/%/{node}"
    if topic:
        k += f"/{topic.replace('/', '%')}/{dds(name)}/{ts.hash_rihs01(name)}/{qos}"
    return s.liveliness().declare_token(k)

def tokens():
    return sorted(str(r.ok.key_expr) for r in s.liveliness().get(f"@ros2_lv/{domain}/**", timeout=2.0)
                  if r.ok is not None)

out = {}
if mode == "listen":
    got = {EV: [], CI: []}
    def cb(name):
        return lambda smp: got[name].append((str(smp.key_expr), smp.payload.to_bytes(),
                                             None if smp.attachment is None else smp.attachment.to_bytes(),
                                             time.time_ns()))
    subs = [s.declare_subscriber(key("/event_publisher/events", EV), cb(EV)),
            s.declare_subscriber(key("/event_publisher/camera_info", CI), cb(CI))]
    toks = [token(0, "NN", "zenoh_peer"), token(1, "MS", "zenoh_peer", "/event_publisher/events", EV),
            token(2, "MS", "zenoh_peer", "/event_publisher/camera_info", CI)]
    start, last, n = time.monotonic(), None, 0
    while time.monotonic() - start < 40 and (last is None or time.monotonic() - last < 1.5):
        time.sleep(0.05)
        if len(got[EV]) + len(got[CI]) != n:
            n, last = len(got[EV]) + len(got[CI]), time.monotonic()
    out["tokens"] = tokens()            # the publisher node is still up: the test keeps it open
    out["decoded"] = {}
    for name, items in got.items():
        dec = []
        for _, payload, _, _ in items:   # rosbags decodes and re-encodes byte for byte
            msg = ts.deserialize_cdr(payload, name)
            assert bytes(ts.serialize_cdr(msg, name)) == payload
            dec.append((msg.width, msg.height) if name == CI else
                       (msg.width, msg.height, msg.encoding, msg.seq, len(msg.events)))
        out["decoded"][name] = dec
    out["got"] = got
else:                                      # talk: rmw_zenoh-format publisher, with malformed samples
    payloads = pickle.load(open(path, "rb"))
    toks = [token(0, "NN", "zenoh_peer"), token(1, "MP", "zenoh_peer", "/peer/events", EV)]
    pub = s.declare_publisher(key("/peer/events", EV), reliability=zenoh.Reliability.RELIABLE,
                              congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 20
    seen = []
    while time.monotonic() < deadline:       # our echo's subscription token, queried
        seen = [t for t in tokens() if "/MS/" in t and "/%peer%events/" in t]
        if seen:
            break
        time.sleep(0.1)
    out["seen"] = seen
    time.sleep(0.3)
    gid = bytes(range(16))
    att = lambda seq: struct.pack("<qqB", seq, time.time_ns(), 16) + gid
    good = payloads[0]
    bad = [(good, None), (good, att(1)[:10]), (b"\x07\x07garbage!", att(1)),
           (good[:13], att(1)), (good, struct.pack("<qqB", 1, 2, 8) + gid[:8])]
    for i, p in enumerate(payloads):
        pub.put(bad[i % len(bad)][0], **({} if bad[i % len(bad)][1] is None else {"attachment": bad[i % len(bad)][1]}))
        pub.put(p, attachment=att(i + 1))
    time.sleep(1.0)
pickle.dump(out, open(path + ".out", "wb"))
s.close()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listen(port: int) -> str:
    return json.dumps({"mode": "peer", "scouting": {"multicast": {"enabled": False}},
                       "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})


def _domain() -> int:
    return ros_domain()


def _peer(mode, port, domain, path):
    return subprocess.Popen([sys.executable, "-c", PEER, mode, str(port), str(domain), str(path), str(MSG_DIR)])


# ----------------------------------------------------------------------------- no network
def test_selection_follows_rmw_implementation(monkeypatch):
    assert zt.selected_rmw(env={}) == "dds"
    assert zt.selected_rmw(env={"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"}) == "zenoh"
    assert zt.selected_rmw(env={"RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}) == "dds"
    assert zt.selected_rmw("rmw_zenoh_cpp", env={"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}) == "zenoh"
    with pytest.raises(Exception, match="RMW_IMPLEMENTATION='rmw_zneoh_cpp'.*rmw_zenoh_cpp"):
        zt.selected_rmw(env={"RMW_IMPLEMENTATION": "rmw_zneoh_cpp"})


def test_names_follow_rmw_zenoh_design():
    h = ros2_typestore().hash_rihs01("std_msgs/msg/String")
    # the examples of rmw_zenoh's docs/design.md
    assert zt.topic_keyexpr(0, "/chatter", "std_msgs/msg/String", h) == (
        "0/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert zt.topic_keyexpr(0, "/robot1/chatter", "std_msgs/msg/String", h).startswith("0/robot1/chatter/")
    assert zt.qos_keyexpr("default") == "::,10:,:,:,,"
    assert zt.qos_keyexpr(zt._qos.QosProfile("reliable", "volatile", 7)) == "::,7:,:,:,,"
    assert zt.qos_keyexpr("sensor_data") == "2::,5:,:,:,,"
    assert zt.qos_keyexpr("transient_local") == ":1:,1:,:,:,,"
    att = zt.make_attachment(5, 1_700_000_000_123_456_789, bytes(range(16)))
    assert len(att) == 33 and att[16] == 16
    assert zt.parse_attachment(att) == (5, 1_700_000_000_123_456_789, bytes(range(16)))
    assert zt.parse_attachment(att[:-1]) is None and zt.parse_attachment(None) is None
    assert zt.parse_liveliness("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener")["node"] == "listener"
    lv = zt.parse_liveliness("@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                             "std_msgs::msg::dds_::String_/RIHS01_df66/::,7:,:,:,,")
    assert lv["kind"] == "MP" and lv["topic"] == "/chatter" and lv["namespace"] == "/"
    assert zt.parse_liveliness("@ros2_lv/2/x/0/0/XX/%/%/n") is None
    assert zt.parse_liveliness("@ros2_lv/2/x/0/1/MP/%/%/n") is None       # a publisher needs its topic


def test_missing_package_names_the_extra(monkeypatch):
    from evdnerf_ros.ros.node import Node

    monkeypatch.setitem(sys.modules, "zenoh", None)
    with pytest.raises(TransportError, match=r"pip install 'rig\[zenoh\]'"):
        Node(name="n", rmw="rmw_zenoh_cpp")


# ----------------------------------------------------------------------------- against a zenoh peer
@needs_zenoh
def test_publisher_to_independent_zenoh_peer(tmp_path):
    from rosbags.rosbag2 import Reader

    from evdnerf_ros.nodes.event_publisher import EventPublisher

    port, domain = _free_port(), _domain()
    peer = _peer("listen", port, domain, tmp_path / "peer")
    bag = tmp_path / "bag"
    log = io.StringIO()
    node = EventPublisher((), overrides={"camera.width": 24, "camera.height": 24, "duration": 0.06, "chunk": 0.02,
                                         "adaptive": False, "realtime_factor": 0.0, "scene_time_offset": 0.15,
                                         "wait_for_subscribers": 1, "wait_timeout": 20.0, "bag": str(bag)},
                          domain_id=domain, dds_config=_listen(port), rmw="rmw_zenoh_cpp", log_stream=log)
    t_start = time.time_ns()
    with node:
        ctx = node.dds
        assert isinstance(ctx, zt.ZenohContext)
        rep = node.run()
        topics = sorted(node.publishers)
        peer.wait(60)                      # the node stays up while the peer queries its tokens
    assert peer.returncode == 0
    out = pickle.load(open(str(tmp_path / "peer") + ".out", "rb"))
    assert rep.events > 0
    # byte for byte what the node published (the bag holds the same serialised messages)
    with Reader(bag) as r:
        sent = {c.topic: [] for c in r.connections}
        for conn, _, raw in r.messages():
            sent[conn.topic].append(bytes(raw))
    for topic, name in (("/event_publisher/events", EVENT_PACKET), ("/event_publisher/camera_info", CAMERA_INFO)):
        got = out["got"][name]
        # the node waits for the events' subscriber only: on a loaded machine the peer may match
        # camera_info a message late, so that topic's got is the tail of what was sent
        first = 0 if name == EVENT_PACKET else len(sent[topic]) - len(got)
        assert [p for _, p, _, _ in got] == sent[topic][first:] and len(got) >= 1
        h = ros2_typestore().hash_rihs01(name)
        assert {k for k, _, _, _ in got} == {f"{domain}{topic}/{name.replace('/msg/', '::msg::dds_::')}_/{h}"}
        atts = [zt.parse_attachment(a) for _, _, a, _ in got]
        assert all(len(a) == 33 for _, _, a, _ in got)
        assert [a[0] for a in atts] == list(range(first + 1, first + len(got) + 1))   # sequence numbers from 1
        assert all(t_start <= a[1] <= recv for a, (_, _, _, recv) in zip(atts, got))   # source time, UNIX ns
        assert len({a[2] for a in atts}) == 1                                   # one 16-byte GID per publisher
        token = next(t for t in out["tokens"] if f"/MP/%/%/event_publisher/{topic.replace('/', '%')}/" in t)
        assert atts[0][2] == zt.gid_of(token)
    dec = out["decoded"][EVENT_PACKET]
    assert all(d[:3] == (24, 24, "evt3") and d[4] > 0 for d in dec)
    assert [d[3] for d in dec] == list(range(dec[0][3], dec[0][3] + len(dec)))     # EventPacket.seq
    assert all(d == (24, 24) for d in out["decoded"][CAMERA_INFO])
    # graph presence: the node and its two publishers, in rmw_zenoh's token format
    base = f"@ros2_lv/{domain}/{ctx.zid}/0"
    assert f"{base}/0/NN/%/%/event_publisher" in out["tokens"]
    h = ros2_typestore().hash_rihs01(EVENT_PACKET)
    assert (f"{base}/1/MP/%/%/event_publisher/%event_publisher%events/event_camera_msgs::msg::dds_::EventPacket_/"
            f"{h}/::,10:,:,:,,") in out["tokens"]
    ours = sorted(zt.parse_liveliness(t)["topic"] for t in out["tokens"] if f"{base}/" in t and "/MP/" in t)
    assert ours == topics and "/event_publisher/camera_info" in ours      # one MP token per publisher


@needs_zenoh
def test_independent_zenoh_peer_to_echo_drops_malformed(tmp_path, monkeypatch, capsys):
    from evdnerf_ros.events import make_events
    from evdnerf_ros.io.packetizer import Packetizer
    from evdnerf_ros.nodes.echo import run_echo

    port, domain = _free_port(), _domain()
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_zenoh_cpp")
    t = np.arange(300, dtype=np.int64) * 1_000_000 + 3_000_000_000
    ev = make_events(t, np.arange(300) % 16, np.arange(300) // 16 % 16, np.where(np.arange(300) % 3, 1, -1))
    packets = []
    Packetizer(lambda topic, msgtype, data, stamp: packets.append(bytes(data))).write_events(
        "/peer/events", ev, width=16, height=16, packet_ns=20_000_000)
    assert len(packets) >= 10
    pickle.dump(packets, open(tmp_path / "peer", "wb"))
    result, npz = {}, tmp_path / "echo.npz"
    th = threading.Thread(target=lambda: result.update(rep=run_echo(
        "/peer/events", count=len(packets), duration=30, npz=npz, domain_id=domain, dds_config=_listen(port),
        print_fn=lambda *_: None)))
    th.start()
    peer = _peer("talk", port, domain, tmp_path / "peer")
    th.join(40)
    peer.wait(30)
    assert peer.returncode == 0
    out = pickle.load(open(str(tmp_path / "peer") + ".out", "rb"))
    assert len(out["seen"]) == 1 and "/MS/%/%/evdnerf_echo/%peer%events/" in out["seen"][0]
    rep = result["rep"]
    assert rep.messages == len(packets) and rep.events == 300         # every malformed sample dropped
    with np.load(npz) as z:
        np.testing.assert_array_equal(z["t"], t)
        np.testing.assert_array_equal(z["x"], ev["x"])
        np.testing.assert_array_equal(z["p"], ev["p"])
    err = capsys.readouterr().err
    assert "topic /peer/events: ignored a malformed Zenoh sample" in err


@needs_zenoh
def test_rendezvous_without_config_and_domains_do_not_cross_talk(monkeypatch):
    """No config: the first session listens on the rendezvous port, the next connects there;
    a subscription in another ROS domain hears nothing."""
    from evdnerf_ros.ros.qos import profile

    monkeypatch.delenv("ZENOH_SESSION_CONFIG_URI", raising=False)
    monkeypatch.delenv("ZENOH_CONFIG_OVERRIDE", raising=False)
    rv = f"tcp/127.0.0.1:{_free_port()}"
    d = _domain()
    a = zt.ZenohContext(d, node_name="a", rendezvous=rv)
    b = zt.ZenohContext(d, node_name="b", rendezvous=rv)
    c = zt.ZenohContext(d + 1, node_name="c", rendezvous=rv)
    try:
        sub = zt.ZenohSubscription(b, "/x", "std_msgs/msg/String", profile("default"))
        other = zt.ZenohSubscription(c, "/x", "std_msgs/msg/String", profile("default"))
        pub = zt.ZenohPublisher(a, "/x", "std_msgs/msg/String", profile("default"))
        assert pub.wait_for_subscribers(1, 5.0)
        deadline = time.monotonic() + 5
        while sub.matched() < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert sub.matched() == 1 and other.matched() == 0
        S = ros2_typestore().types["std_msgs/msg/String"]
        pub.publish(S(data="hello"))
        assert sub.wait(5.0)
        (msg,) = sub.take()
        assert msg.data == "hello"
        time.sleep(0.2)
        assert other.take() == []
    finally:
        for ctx in (a, b, c):
            ctx.close()


@needs_zenoh
def test_bad_configs_are_refused(monkeypatch):
    with pytest.raises(Exception, match="Cyclone DDS XML"):
        zt.ZenohContext(0, config="<CycloneDDS/>")
    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", "mode")
    with pytest.raises(Exception, match="ZENOH_CONFIG_OVERRIDE item 'mode'"):
        zt.ZenohContext(0, config=_listen(_free_port()))
