"""Re-encode the event topic of a bag into another bag (another encoding, storage or ROS version).

:func:`reencode_bag` copies ``src`` to ``dst`` message by message in bag-time order. The event
topic's messages are decoded and encoded again one for one: each keeps its bag time, header
stamp, ``seq`` (EventPacket.seq, ROS 1 header.seq) and ``frame_id``; every other topic is
copied byte for byte. Options: ``repacketize=True`` cuts the events into new packets instead
(``packet_ns``; stamps = each packet's first event time), ``other_topics=False`` writes the
event topic alone. Times follow :mod:`evdnerf_ros.io.packetizer`: reading the output gives the
same event times as reading the input (evt3 / evt2 outputs keep metavision_driver's
``time_base = 0`` when the first stamp is the first event's time, which holds for
metavision_driver recordings and our own bags; otherwise ``time_base`` carries the origin).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from .bag_reader import TopicDecoder, open_bag, pick_event_topic
from .packetizer import DEFAULT_PACKET_NS, STREAM_ENCODINGS
from .typestore import EVENT_PACKET, LEGACY_EVENT_PACKET


def _writer_for(dst: Path, storage: str | None):
    if dst.suffix.lower() == ".bag":
        if storage not in (None, "rosbag1"):
            raise InputError(f"{dst}: a .bag output is a ROS 1 bag; storage {storage!r} does not apply")
        from .rosbag1 import Rosbag1Writer

        return Rosbag1Writer(dst)
    from .rosbag2 import BagWriter

    if storage is None:
        storage = "sqlite3" if dst.suffix.lower() == ".db3" else "mcap"
    return BagWriter(dst, storage=storage)


def reencode_bag(src, dst, *, encoding: str | None = None, storage: str | None = None, topic: str | None = None,
                 repacketize: bool = False, packet_ns: int = DEFAULT_PACKET_NS, other_topics: bool = True) -> dict:
    """Write ``src``'s event topic (``topic``, default the bag's only event topic) re-encoded as
    ``encoding`` (default: evt3 for rosbag2, array for ROS 1) into the new bag ``dst`` (module
    doc). Returns {"topic", "encoding", "messages", "events", "copied": {topic: messages}}."""
    src, dst = Path(src), Path(dst)
    with open_bag(src) as bag:
        topic = pick_event_topic(bag, topic)
        dec = TopicDecoder(bag, topic)
        writer = _writer_for(dst, storage)
        encoding = encoding or writer.default_encoding
        if other_topics and writer.ros1 != bag.ros1:
            others = sorted(n for n in bag.topics if n != topic)
            if others:
                raise InputError(f"{src}: its other topics {others} cannot be copied between a ROS 1 bag and a "
                                 "ROS 2 bag byte for byte; re-encode the event topic alone (other_topics=False)")
        copied: dict[str, int] = {}
        n_msg = n_ev = 0
        with writer:
            for name in bag.topics if other_topics else (topic,):  # list every topic, also the empty ones
                if name != topic:
                    writer.add_topic(name, bag.topics[name].msgtype)
                    copied[name] = 0
            held = []
            for m in bag.messages(None if other_topics else topic):
                if m.topic != topic:
                    writer.write_raw(m.topic, m.msgtype, m.data, m.t_ns)
                    copied[m.topic] += 1
                    continue
                pk = dec.packet(m)
                if pk.triggers.size and encoding not in STREAM_ENCODINGS:
                    raise InputError(f"{src}: topic {topic} carries {pk.triggers.size} trigger events in message "
                                     f"{pk.index}, which encoding {encoding!r} cannot carry; use encoding 'evt3'")
                n_ev += pk.events.size
                if repacketize:
                    held.append(pk)
                    if sum(p.events.size for p in held) >= 1 << 20:
                        n_msg += _repack(writer, topic, held, encoding, packet_ns)
                        held = []
                    continue
                seq = pk.seq if (m.msgtype in (EVENT_PACKET, LEGACY_EVENT_PACKET) or bag.ros1) else None
                n_msg += writer.write_packet(topic, pk.events, triggers=pk.triggers, width=pk.width,
                                             height=pk.height, encoding=encoding, stamp_ns=pk.stamp_ns,
                                             seq=seq, frame_id=pk.frame_id, t_ns=m.t_ns)
            tail_ev, tail_tr = dec.close()
            if tail_ev.size or tail_tr.size:
                raise FormatError(f"topic {topic}: {tail_ev.size} events came out only at the end of the stream; "
                                  "re-encode with repacketize=True", source=str(src))
            if held:
                n_msg += _repack(writer, topic, held, encoding, packet_ns)
    return {"topic": topic, "encoding": encoding, "messages": n_msg, "events": n_ev, "copied": copied}


def _repack(writer, topic, held, encoding, packet_ns) -> int:
    ev = np.concatenate([p.events for p in held])
    tr = np.concatenate([p.triggers for p in held])
    first = held[0]
    return writer.write_events(topic, ev, width=first.width, height=first.height, encoding=encoding,
                               triggers=tr if tr.size else None, packet_ns=packet_ns, frame_id=first.frame_id)
