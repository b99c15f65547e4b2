"""``evdnerf echo TOPIC``: subscribe over DDS and show what is on the wire — message rate,
bandwidth, message size, events per second, and an event image (ASCII on the terminal,
optionally a PNG; the decoded events can be saved as .npz).

Event topics (EventPacket evt3 / evt2 / mono, dvs EventArray) are decoded with the same
code as bags (one streaming decoder per topic); other types are only counted and their
first message printed.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import InputError
from ..io.typestore import DVS_EVENT_ARRAY, EVENT_PACKET, ros2_typestore
from ..options import option
from ..ros.node import Node


@dataclass(frozen=True)
class EchoOptions:
    """Every knob of `evdnerf echo` (flags, --config keys and library defaults)."""

    type: str = option(EVENT_PACKET, "message type (e.g. dvs_msgs/msg/EventArray)")
    qos: str = option("default", "subscriber QoS profile ('default' is reliable)",
                      choices=("default", "sensor_data", "transient_local"))
    depth: int = option(1000, "subscriber history (keep-last) depth; deep so a slow start loses nothing",
                        low=1, high=1_000_000)
    count: int = option(0, "stop after this many messages (0: no limit)", low=0, high=10**12)
    duration: float = option(0.0, "stop after this many seconds (0: no limit)", low=0, high=4e9)
    idle: float = option(0.0, "stop when nothing arrives for this many seconds, counted from the start until "
                              "the first message (0: no limit)", low=0, high=4e9)
    png: str | None = option(None, "write the event image of everything received", kind=str)
    save_events: str | None = option(None, "write the decoded events and trigger events (.npz)", kind=str)
    overwrite: bool = option(False, "replace existing --png / --save-events files")


@dataclass
class EchoReport:
    topic: str
    msgtype: str
    messages: int = 0
    bytes: int = 0
    events: int = 0
    triggers: int = 0          # external-trigger events (EXT_TRIGGER edges), both edges
    trigger_rising: int = 0
    seconds: float = 0.0
    rate_hz: float = 0.0
    mbytes_per_s: float = 0.0
    size_min: int = 0
    size_mean: float = 0.0
    size_max: int = 0
    width: int = 0
    height: int = 0
    encoding: str = ""
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    ascii: str = ""
    png: str | None = None
    npz: str | None = None
    lines: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return asdict(self)


class _LiveTopic:
    """What the bag decoder needs to know about a topic, for live messages."""

    ros1 = False

    def __init__(self, topic: str, msgtype: str):
        from ..io.rosbag2 import TopicSummary

        self.path = "DDS"
        self._summary = TopicSummary(topic, msgtype, 0)

    def topic(self, name: str):
        return self._summary


def ascii_image(events: np.ndarray, width: int, height: int, cols: int = 64) -> str:
    """Net polarity per cell: '+' more ON, '-' more OFF, '.' none, '~' balanced."""
    if not width or not height:
        return ""
    cw = max(1, -(-width // cols))
    ch = 2 * cw                          # terminal cells are about twice as tall as wide
    gw, gh = -(-width // cw), -(-height // ch)
    net = np.zeros((gh, gw), np.int64)
    seen = np.zeros((gh, gw), bool)
    if events.size:
        gy, gx = events["y"] // ch, events["x"] // cw
        np.add.at(net, (gy, gx), events["p"].astype(np.int64))
        seen[gy, gx] = True
    chars = np.where(net > 0, "+", np.where(net < 0, "-", np.where(seen, "~", ".")))
    return "\n".join("".join(row) for row in chars)


class Echo(Node):
    NAME = "evdnerf_echo"

    def __init__(self, topic: str, msgtype: str = EchoOptions.type, *, qos: str = EchoOptions.qos,
                 depth: int = EchoOptions.depth, fast: bool = True, **kw):
        """`depth`: the subscriber's keep-last history; deep, so that a slow first decode loses nothing."""
        super().__init__((), **kw)
        self.sub = self.create_subscription(topic, msgtype, qos, depth=depth, fast=fast)
        self.sub.qos_fix = "subscribe with `evdnerf echo TOPIC --qos sensor_data` to hear a best-effort publisher"
        self.msgtype = msgtype

    def run(self, *, count: int = EchoOptions.count, duration: float = EchoOptions.duration,
            idle: float = EchoOptions.idle, png=None, npz=None, overwrite: bool = False, print_fn=print,
            keep_events: bool = True) -> EchoReport:
        """Listen until `count` messages, `duration` seconds, or `idle` seconds without a message
        (counted from the start while none has come), or SIGINT / SIGTERM.

        The output paths are checked before listening, so a bad path costs no recording."""
        from ..atomic import check_output

        for path in (png, npz):
            if path:
                check_output(path, overwrite=overwrite)
        from ..io.bag_reader import BagMessage, TopicDecoder

        is_events = self.msgtype in (EVENT_PACKET, DVS_EVENT_ARRAY)
        dec = TopicDecoder(_LiveTopic(self.sub.topic, self.msgtype), self.sub.topic) if is_events else None
        rep = EchoReport(self.sub.topic, self.msgtype)
        sizes, chunks, trigger_chunks = [], [], []
        t_start = time.monotonic()
        t_first = t_last = None
        window = [t_start, 0, 0, 0]          # start, messages, bytes, events
        while self.ok():
            now = time.monotonic()
            if duration and now - t_start >= duration:
                break
            if idle and now - (t_start if t_last is None else t_last) >= idle:
                break
            if count and rep.messages >= count:
                break
            if not self.sub.wait(0.1):
                self.check_qos()
                continue
            # never take past --count: a batch may hold more (a peer repeating a packet must not be decoded twice)
            for data, _ in self.sub.take_raw(count - rep.messages if count else 1024):
                now = time.monotonic()
                t_first = t_first or now
                t_last = now
                rep.messages += 1
                rep.bytes += len(data)
                sizes.append(len(data))
                window[1] += 1
                window[2] += len(data)
                if dec is not None:
                    pk = dec.packet(BagMessage(self.sub.topic, self.msgtype, 0, data))
                    rep.width, rep.height, rep.encoding = pk.width, pk.height, pk.encoding
                    rep.first_stamp_ns = pk.stamp_ns if rep.first_stamp_ns is None else rep.first_stamp_ns
                    rep.last_stamp_ns = pk.stamp_ns
                    if pk.triggers.size:
                        trigger_chunks.append(pk.triggers)
                    if pk.events.size:
                        rep.events += int(pk.events.size)
                        window[3] += int(pk.events.size)
                        if keep_events:
                            chunks.append(pk.events)
                elif rep.messages == 1:
                    print_fn(f"first message: {ros2_typestore().deserialize_cdr(data, self.msgtype)}")
            if now - window[0] >= 1.0:
                dt = now - window[0]
                line = (f"{self.sub.topic}: {window[1] / dt:.1f} msg/s, {window[2] / dt / 1e6:.3f} MB/s, "
                        f"mean {window[2] / max(window[1], 1):.0f} B/msg" +
                        (f", {window[3] / dt:.0f} events/s" if is_events else ""))
                rep.lines.append(line)
                print_fn(line)
                window = [now, 0, 0, 0]
        if dec is not None and dec.stream is not None:
            from ..io.bag_reader import decoded_parts

            tail, tail_triggers = decoded_parts(dec.stream.close())
            if tail.size:
                rep.events += int(tail.size)
                chunks.append(tail)
            if tail_triggers.size:
                trigger_chunks.append(tail_triggers)
        rep.seconds = (t_last - t_first) if t_first is not None and t_last is not None else 0.0
        if sizes:
            rep.size_min, rep.size_mean, rep.size_max = min(sizes), float(np.mean(sizes)), max(sizes)
        if rep.seconds > 0:
            rep.rate_hz = (rep.messages - 1) / rep.seconds
            rep.mbytes_per_s = rep.bytes / rep.seconds / 1e6
        if is_events:
            from ..events.types import empty_events, empty_triggers

            ev = np.concatenate(chunks) if chunks else empty_events()
            trig = np.concatenate(trigger_chunks) if trigger_chunks else empty_triggers()
            rep.triggers, rep.trigger_rising = int(trig.size), int(np.count_nonzero(trig["value"] == 1))
            rep.ascii = ascii_image(ev, rep.width, rep.height)
            if png and rep.width:
                from ..events import event_image, save_png

                save_png(png, event_image(ev, rep.width, rep.height), overwrite=overwrite)
                rep.png = str(png)
            if npz:
                from ..atomic import atomic_output

                with atomic_output(npz, overwrite=overwrite) as tmp:
                    with open(tmp, "wb") as f:
                        np.savez(f, t=ev["t"], x=ev["x"], y=ev["y"], p=ev["p"], width=rep.width, height=rep.height,
                                 trigger_t=trig["t"], trigger_id=trig["id"], trigger_value=trig["value"])
                rep.npz = str(npz)
        return rep


def run_echo(topic: str, msgtype: str = EchoOptions.type, *, qos: str = EchoOptions.qos,
             depth: int = EchoOptions.depth, domain_id=None, dds_config=None, **run_kw) -> EchoReport:
    if not isinstance(topic, str) or not topic.startswith("/"):
        raise InputError(f"topic {topic!r}: give the absolute topic name, e.g. /event_publisher/events")
    node = Echo(topic, msgtype, qos=qos, depth=depth, domain_id=domain_id, dds_config=dds_config)
    node.install_signal_handlers()
    with node:
        return node.run(**run_kw)


def format_report(rep: EchoReport) -> str:
    lines = [f"{rep.topic} [{rep.msgtype}]: {rep.messages} messages, {rep.bytes} bytes in {rep.seconds:.2f} s "
             f"({rep.rate_hz:.1f} msg/s, {rep.mbytes_per_s:.3f} MB/s); message size min {rep.size_min} / mean "
             f"{rep.size_mean:.0f} / max {rep.size_max} B"]
    if rep.msgtype in (EVENT_PACKET, DVS_EVENT_ARRAY):
        lines.append(f"{rep.events} events, {rep.width}x{rep.height}, encoding {rep.encoding or '-'}" +
                     (f"; {rep.triggers} trigger events ({rep.trigger_rising} rising, "
                      f"{rep.triggers - rep.trigger_rising} falling)" if rep.triggers else ""))
        if rep.ascii:
            lines.append(rep.ascii)
    if rep.png:
        lines.append(f"event image: {rep.png}")
    if rep.npz:
        lines.append(f"events: {rep.npz}")
    return "\n".join(lines)
