"""`evdnerf info`: what an event file or bag holds."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..units import format_ns
from .event_files import DEFAULT_TOPIC, container_kind, read_event_file
from .packetizer import EVENT_TYPES



def describe(path, *, topic: str | None = None, time_unit: str | None = None,
             geometry: tuple[int, int] | None = None, strict: bool = False) -> dict:
    """A JSON-ready summary: container, topics (bags), and the event stream's statistics."""
    path = Path(path)
    kind = container_kind(path)
    info: dict = {"path": str(path), "container": kind}
    if kind in ("rosbag1", "rosbag2"):
        from .rosbag2 import bag_info

        bag = bag_info(path, decode_events=False)  # events are decoded once, below
        info["storage"] = bag.storage
        info["topics"] = [{"topic": t.name, "type": t.msgtype, "messages": t.message_count}
                          for t in bag.topics.values()]
        event_topics = [t.name for t in bag.topics.values() if t.msgtype in EVENT_TYPES]
        if topic is None:
            if not event_topics:
                return info  # a bag without events: its topics are the whole story
            topic = DEFAULT_TOPIC if DEFAULT_TOPIC in event_topics else event_topics[0]
        elif topic not in bag.topics:
            raise InputError(f"{path}: no topic {topic!r}; topics: "
                             f"{', '.join(bag.topics) or 'none'}")
    data = read_event_file(path, topic=topic, need_geometry=False, time_unit=time_unit, geometry=geometry,
                           strict=strict)
    ev = data.events
    n = int(ev.size)
    duration = int(ev["t"][-1] - ev["t"][0]) if n > 1 else 0
    info["events"] = {
        "topic": data.topic,
        "encoding": data.encoding,
        "count": n,
        "positive": int((ev["p"] > 0).sum()),
        "triggers": int(len(data.triggers)),
        "width": data.width,
        "height": data.height,
        "t_first_ns": int(ev["t"][0]) if n else None,
        "t_last_ns": int(ev["t"][-1]) if n else None,
        "duration_ns": duration,
        "mean_rate_ev_per_s": (n - 1) / (duration * 1e-9) if duration > 0 else None,
        "time_anomalies": {k: v for k, v in data.anomalies.items() if v},
    }
    return info



def format_info(info: dict) -> str:
    lines = [f"{info['path']}  ({info['container']}"
             + (f", {info['storage']})" if "storage" in info else ")")]
    for t in info.get("topics", []):
        lines.append(f"  {t['topic']:<32} {t['type']:<40} {t['messages']:>8} msgs")
    ev = info.get("events")
    if ev:
        head = f"  events{' on ' + ev['topic'] if ev['topic'] else ''}"
        if ev["encoding"]:
            head += f" ({ev['encoding']})"
        lines.append(head + ":")
        lines.append(f"    count       {ev['count']} ({ev['positive']} positive), "
                     f"{ev['triggers']} trigger events")
        lines.append(f"    resolution  {ev['width']}x{ev['height']}" if ev["width"] is not None
                     else "    resolution  unknown (the file gives none: --geometry WxH)")
        if ev["count"]:
            lines.append(f"    time        {format_ns(ev['t_first_ns'])} .. "
                         f"{format_ns(ev['t_last_ns'])} (duration {format_ns(ev['duration_ns'])})")
        if ev["mean_rate_ev_per_s"]:
            lines.append(f"    mean rate   {ev['mean_rate_ev_per_s'] / 1e6:.3f} Mev/s")
        if ev.get("time_anomalies"):
            lines.append("    tolerated   " + ", ".join(f"{n} {k.replace('_', ' ')}"
                                                      for k, n in ev["time_anomalies"].items())
                         + " (time words real sensors write; no event went backwards)")
    return "\n".join(lines)
