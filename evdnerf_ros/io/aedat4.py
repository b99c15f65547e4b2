"""AEDAT 4.0 files (what iniVation's DV software writes for every current camera: DVXplorer,
DAVIS346, ...): read only, through the `aedat` package (neuromorphicsystems' Rust decoder of the
format's FlatBuffers packets, LZ4 / zstd compressed; a run-time dependency, why in the README).

The events of the file's event stream (its size from the stream's own description) come back as
int64 ns (the format's µs x 1000) with +1/-1 polarity; trigger packets as triggers (id = the
packet's source). IMU samples and frames are counted (``AedatContents``) and not kept: training
reads events. Several event streams: the first (``stream`` picks another).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..events.types import empty_triggers, make_events, make_triggers, validate_events


@dataclass
class AedatContents:
    """What the file holds besides the events read: per stream id its type, and the IMU samples
    and frames seen."""

    streams: dict = field(default_factory=dict)
    imu_samples: int = 0
    frames: int = 0


def read_aedat4(path, *, stream: int | None = None):
    """(events, triggers, width, height, AedatContents) of an AEDAT 4.0 file (module doc)."""
    import aedat

    path = Path(path)
    try:
        decoder = aedat.Decoder(str(path))
        streams = decoder.id_to_stream()
    except Exception as exc:  # noqa: BLE001 - the Rust decoder raises plain exceptions
        raise FormatError(f"not a readable AEDAT 4.0 file ({exc})", source=str(path)) from None
    event_streams = sorted(k for k, v in streams.items() if v.get("type") == "events")
    if not event_streams:
        raise InputError(f"{path}: the file has no event stream (streams: "
                         f"{ {k: v.get('type') for k, v in streams.items()} })")
    chosen = event_streams[0] if stream is None else int(stream)
    if chosen not in event_streams:
        raise InputError(f"{path}: stream {chosen} is not an event stream (event streams: {event_streams})")
    width, height = int(streams[chosen]["width"]), int(streams[chosen]["height"])
    contents = AedatContents(streams={k: v.get("type") for k, v in streams.items()})
    parts, trigs = [], []
    try:
        for packet in decoder:
            if "events" in packet and packet["stream_id"] == chosen:
                parts.append(packet["events"])
            elif "triggers" in packet:
                tr = packet["triggers"]
                if tr.size:
                    source = tr["source"].astype(np.int64) if "source" in tr.dtype.names else np.zeros(tr.size, np.int64)
                    trigs.append(make_triggers(tr["t"].astype(np.int64) * 1000, source, np.ones(tr.size, np.int8)))
            elif "imus" in packet:
                contents.imu_samples += int(packet["imus"].size)
            elif "frame" in packet:
                contents.frames += 1
    except Exception as exc:  # noqa: BLE001
        raise FormatError(f"reading its packets failed ({exc}); the file is damaged or truncated",
                          source=str(path)) from None
    raw = np.concatenate(parts) if parts else np.zeros(0, [("t", "<u8"), ("x", "<u2"), ("y", "<u2"), ("on", "?")])
    if raw.size and int(raw["t"].max()) >= 2**62 // 1000:
        raise FormatError("event times beyond the int64 nanosecond range", source=str(path))
    events = make_events(raw["t"].astype(np.int64) * 1000, raw["x"], raw["y"],
                         np.where(raw["on"], 1, -1).astype(np.int8))
    validate_events(events, width=width, height=height, source=str(path))
    triggers = np.concatenate(trigs) if trigs else empty_triggers()
    return events, triggers, width, height, contents


__all__ = ["read_aedat4", "AedatContents"]
