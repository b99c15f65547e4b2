"""Real processes on loopback DDS (random non-zero domain, ROS_LOCALHOST_ONLY=1): the
`event_publisher` executable, a subscriber process and `evdnerf echo`; SIGINT / SIGTERM
during publishing leave a valid bag, read back by the independent mcap reader."""

import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ros_domain

from evdnerf_ros.events.codecs import make_decoder, quantize_to_us
from evdnerf_ros.io import event_messages as em
from evdnerf_ros.io.rosbag2 import open_bag, read_events
from evdnerf_ros.io.typestore import ros2_typestore
from evdnerf_ros.nodes.echo import format_report, run_echo
from test_ros_publisher import offline_events

EXE = Path(sys.executable).parent / "event_publisher"
EVENTS, INFO = "/event_publisher/events", "/event_publisher/camera_info"

SUBSCRIBER = r"""
import pickle, sys, time
from evdnerf_ros.ros.transport import DdsContext, DdsSubscription
ctx = DdsContext()
from evdnerf_ros.ros.qos import profile
subs = {"/event_publisher/camera_info": DdsSubscription(ctx, "/event_publisher/camera_info",
                                                        "sensor_msgs/msg/CameraInfo", profile("default", 100)),
        "/event_publisher/events": DdsSubscription(ctx, "/event_publisher/events",
                                                   "event_camera_msgs/msg/EventPacket", profile("default", 2000))}
got = {t: [] for t in subs}
start = time.monotonic(); last = None
while time.monotonic() - start < 60 and (last is None or time.monotonic() - last < 2.0):
    for t, s in subs.items():
        if s.wait(0.05):
            items = s.take_raw(1000)
            if items:
                got[t] += [d for d, _ in items]
                last = time.monotonic()
pickle.dump(got, open(sys.argv[1], "wb"))
"""


@pytest.fixture
def dds_env(monkeypatch):
    domain = str(ros_domain())
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    return dict(os.environ)


def _publisher(args, env, **kw):
    return subprocess.Popen([str(EXE), "--ros-args", *args], env=env, stderr=subprocess.PIPE, text=True, **kw)


def test_publisher_and_subscriber_processes(tmp_path, dds_env):
    sub = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, str(tmp_path / "got.pkl")], env=dds_env)
    offset = 150_000_000
    bag = tmp_path / "bag"
    pub = _publisher(["-p", "camera.width:=24", "-p", "camera.height:=24", "-p", "duration:=0.06",
                      "-p", f"scene_time_offset:={offset / 1e9}", "-p", "adaptive:=false", "-p", "chunk:=0.02",
                      "-p", "realtime_factor:=0.0", "-p", "wait_for_subscribers:=2", "-p", f"bag:={bag}",
                      "-r", "__node:=event_publisher"], dds_env)
    # idle counts from the start until the first message: long enough for the publisher process
    # to start (a 2 s idle ended the echo just as the publisher began, 0 of 48 messages, in CI)
    rep = run_echo(EVENTS, count=0, idle=8.0, duration=60, png=tmp_path / "echo.png", npz=tmp_path / "echo.npz",
                   print_fn=lambda *_: None)
    _, err = pub.communicate(timeout=60)
    assert pub.returncode == 0, err
    assert sub.wait(timeout=60) == 0
    got = pickle.load(open(tmp_path / "got.pkl", "rb"))
    ts = ros2_typestore()

    # field for field against the publisher's own bag recording of the same messages
    with open_bag(bag) as b:
        recorded = {t: [bytes(m.data) for m in b.messages(t)] for t in (EVENTS, INFO)}
    assert len(got[EVENTS]) == len(recorded[EVENTS]) > 5 and 1 <= len(got[INFO]) <= len(recorded[INFO]) <= 2
    # CameraInfo is sent at the start and again when a subscriber appears: the wire holds the last ones
    pairs = {EVENTS: zip(got[EVENTS], recorded[EVENTS]), INFO: zip(got[INFO], recorded[INFO][-len(got[INFO]):])}
    for topic, msgtype in ((EVENTS, "event_camera_msgs/msg/EventPacket"), (INFO, "sensor_msgs/msg/CameraInfo")):
        for k, (wire, rec) in enumerate(pairs[topic]):
            assert wire[:len(rec)] == rec
            a, b_ = ts.deserialize_cdr(wire, msgtype), ts.deserialize_cdr(rec, msgtype)
            for name in ("header", "height", "width"):
                assert getattr(a, name) == getattr(b_, name)
            if topic == EVENTS:
                assert (a.seq, a.encoding, a.is_bigendian, a.header.frame_id) == (k, "evt3", False, "event_camera")
                assert a.time_base == b_.time_base and np.array_equal(a.events, b_.events)
            else:
                assert (a.width, a.height, a.distortion_model) == (24, 24, "plumb_bob")
                np.testing.assert_array_equal(a.k, b_.k)
    # the event stream on the wire equals the offline generator's (evt3: whole microseconds)
    fields = [em.parse_event_packet(w, what="wire") for w in got[EVENTS]]
    dec = make_decoder("evt3", time_base_ns=fields[0].time_base)
    parts = [dec.feed(f.events).events for f in fields] + [dec.close().events]
    wire_events = np.concatenate([p for p in parts if p.size])
    ref = quantize_to_us(offline_events(24, 24, 60_000_000, offset), time_base_ns=0)
    np.testing.assert_array_equal(wire_events, ref)
    # and what `evdnerf echo` (a second subscriber) saw
    assert rep.messages == len(got[EVENTS]) and rep.events == ref.size
    assert (rep.width, rep.height, rep.encoding) == (24, 24, "evt3")
    assert rep.size_min <= rep.size_mean <= rep.size_max and rep.rate_hz > 0
    assert "+" in rep.ascii and "-" in rep.ascii and len(rep.ascii.splitlines()) == 12
    saved = np.load(tmp_path / "echo.npz")
    np.testing.assert_array_equal(saved["t"], ref["t"])
    import matplotlib.image

    assert matplotlib.image.imread(tmp_path / "echo.png").shape[:2] == (24, 24)
    assert "real-time factor" in err and "publishing anyway" not in err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_publishing_leaves_valid_bag(tmp_path, dds_env, sig):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    bag = tmp_path / "bag"
    pub = _publisher(["-p", "camera.width:=16", "-p", "camera.height:=16", "-p", "duration:=30.0",
                      "-p", "scene_time_offset:=0.1", "-p", "realtime_factor:=1.0", "-p", "chunk:=0.005",
                      "-p", "encoding:=mono", "-p", f"bag:={bag}"], dds_env)
    deadline = time.monotonic() + 30
    started = []
    while time.monotonic() < deadline:
        line = pub.stderr.readline()
        started.append(line)
        if "publishing" in line:
            break
    time.sleep(1.5)
    pub.send_signal(sig)
    _, err = pub.communicate(timeout=30)
    err = "".join(started) + err
    assert pub.returncode == 0, err
    assert f"{signal.Signals(sig).name}: stopping" in err and "stopped:" in err
    mcaps = list(bag.glob("*.mcap"))
    assert len(mcaps) == 1 and not list(tmp_path.glob(".*partial"))
    counts = {}
    with open(mcaps[0], "rb") as f:
        for _, channel, message, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if channel.topic == EVENTS:
                assert decoded.encoding == "mono" and decoded.width == 16 and message.log_time > 0
    assert counts[INFO] >= 1 and counts[EVENTS] > 10
    ev = read_events(bag, EVENTS).events
    assert ev.size > 0 and np.all(np.diff(ev["t"]) >= 0)


def _in_process_publisher(log, **params):
    from evdnerf_ros.nodes.event_publisher import EventPublisher
    from evdnerf_ros.ros.qos import LOOPBACK_XML

    return EventPublisher((), overrides={"camera.width": 16, "camera.height": 16, "realtime_factor": 0.0,
                                         "adaptive": False, "scene_time_offset": 0.15, **params},
                          domain_id=int(os.environ["ROS_DOMAIN_ID"]), dds_config=LOOPBACK_XML, log_stream=log)


def test_qos_mismatch_with_a_subscriber_is_warned(dds_env):
    import io

    from evdnerf_ros.ros.qos import LOOPBACK_XML, profile
    from evdnerf_ros.ros.transport import DdsContext, DdsSubscription

    ctx = DdsContext(int(dds_env["ROS_DOMAIN_ID"]), config=LOOPBACK_XML)
    sub = DdsSubscription(ctx, EVENTS, "event_camera_msgs/msg/EventPacket", profile("default"))   # reliable
    log = io.StringIO()
    node = _in_process_publisher(log, qos="sensor_data", duration=0.02, wait_for_subscribers=1, wait_timeout=1.5)
    with node:
        rep = node.run()
    text = log.getvalue()
    assert rep.events > 0 and sub.take_raw() == []
    assert "[WARN]" in text and f"topic {EVENTS}: a subscriber has incompatible QoS (RELIABILITY)" in text
    assert "best_effort" in text and "publishing anyway" in text
    ctx.close()


def test_echo_shows_other_message_types(dds_env):
    import io
    import threading

    log = io.StringIO()
    node = _in_process_publisher(log, duration=0.03, chunk=0.01, camera_info_period=0.01, wait_for_subscribers=0)
    lines = []
    result = {}
    th = threading.Thread(target=lambda: result.update(rep=run_echo(
        INFO, "sensor_msgs/msg/CameraInfo", count=2, duration=20, print_fn=lines.append)))
    th.start()
    time.sleep(1.0)                       # let the echo's subscription be discovered first
    with node:
        node.run()
    th.join(30)
    rep = result["rep"]
    assert rep.messages == 2 and rep.events == 0 and rep.msgtype == "sensor_msgs/msg/CameraInfo"
    assert any(line.startswith("first message: ") and "CameraInfo(" in line and "width=16" in line for line in lines)
    assert rep.size_min == rep.size_max > 300     # 9 + 9 + 12 + 5 doubles and the header


def _echo_of(pub, packets, **echo_kw):
    """The report of an echo of EVENTS that ``pub`` sends ``packets`` to once both ends have matched.

    Both ends, not just the writer: a writer can see the reader before the reader has discovered the
    writer, and a volatile reader drops what arrives in between (a loaded machine widens that gap)."""
    import threading

    from evdnerf_ros.nodes.echo import Echo

    result = {}
    node = Echo(EVENTS)
    try:
        deadline = time.monotonic() + 20
        while not (pub.matched() and node.sub.matched()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.matched() and node.sub.matched(), "the echo and the publisher never discovered each other"
        th = threading.Thread(target=lambda: result.update(rep=node.run(duration=30, print_fn=lambda *_: None,
                                                                        **echo_kw)))
        th.start()
        for data in packets:
            pub.publish_raw(data)
        th.join(40)
    finally:
        node.shutdown()
    return result["rep"]


def test_echo_reports_and_saves_trigger_events(dds_env, tmp_path):
    """EXT_TRIGGER edges inside EventPackets: counted, shown and saved with the events."""
    from evdnerf_ros.events import make_events, make_triggers
    from evdnerf_ros.io.packetizer import Packetizer
    from evdnerf_ros.ros.qos import LOOPBACK_XML, profile
    from evdnerf_ros.ros.transport import DdsContext, DdsPublisher

    ctx = DdsContext(int(dds_env["ROS_DOMAIN_ID"]), config=LOOPBACK_XML)
    pub = DdsPublisher(ctx, EVENTS, "event_camera_msgs/msg/EventPacket", profile("default"))
    t = np.arange(200, dtype=np.int64) * 1_000_000 + 3_000_000_000
    ev = make_events(t, np.arange(200) % 16, np.arange(200) // 16 % 16, np.where(np.arange(200) % 2, 1, -1))
    trig = make_triggers(np.array([t[10], t[11] + 500_000, t[150]]), np.zeros(3), np.array([1, 0, 1]))
    packets = []
    Packetizer(lambda topic, msgtype, data, stamp: packets.append(data)).write_events(
        EVENTS, ev, width=16, height=16, triggers=trig, packet_ns=20_000_000)
    out = tmp_path / "echo.npz"
    rep = _echo_of(pub, packets, count=len(packets), npz=out)
    assert rep.events == 200 and rep.triggers == 3 and rep.trigger_rising == 2
    assert "3 trigger events (2 rising, 1 falling)" in format_report(rep)
    with np.load(out) as z:
        np.testing.assert_array_equal(z["trigger_t"], trig["t"])
        np.testing.assert_array_equal(z["trigger_value"], [1, 0, 1])
        np.testing.assert_array_equal(z["t"], t)
    ctx.close()


def test_echo_count_stops_inside_a_batch(dds_env):
    """--count N shows exactly N messages even when more arrived in one take (here 10 back-to-back packets)."""
    from evdnerf_ros.events import make_events
    from evdnerf_ros.io.packetizer import Packetizer
    from evdnerf_ros.ros.qos import LOOPBACK_XML, profile
    from evdnerf_ros.ros.transport import DdsContext, DdsPublisher

    ctx = DdsContext(int(dds_env["ROS_DOMAIN_ID"]), config=LOOPBACK_XML)
    pub = DdsPublisher(ctx, EVENTS, "event_camera_msgs/msg/EventPacket", profile("default"))
    t = np.arange(100, dtype=np.int64) * 1_000_000 + 3_000_000_000
    ev = make_events(t, np.arange(100) % 16, np.arange(100) // 16 % 16, np.where(np.arange(100) % 2, 1, -1))
    packets = []
    Packetizer(lambda topic, msgtype, data, stamp: packets.append(data)).write_events(
        EVENTS, ev, width=16, height=16, packet_ns=10_000_000)
    assert len(packets) == 10
    rep = _echo_of(pub, packets, count=3)
    assert rep.messages == 3 and rep.events == 30
    ctx.close()


def test_echo_qos_hint_names_its_own_flag(dds_env, capsys):
    """A reliable echo cannot hear a best-effort publisher: the warning says which flag fixes it."""
    import io
    import threading

    lines = []
    result = {}
    th = threading.Thread(target=lambda: result.update(rep=run_echo(EVENTS, idle=2.5, print_fn=lines.append)))
    log = io.StringIO()
    th.start()
    time.sleep(1.0)
    node = _in_process_publisher(log, qos="sensor_data", duration=0.02, wait_for_subscribers=1, wait_timeout=1.0)
    with node:
        node.run()
    th.join(30)
    assert result["rep"].messages == 0
    err = capsys.readouterr().err
    assert "publisher has incompatible QoS (RELIABILITY)" in err and "evdnerf echo TOPIC --qos sensor_data" in err
