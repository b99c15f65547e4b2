"""Record an event camera into a rosbag2 on the session's event topic, in the camera's own encoding.

* Prophesee (``encoding == "evt3"``): every USB transfer's EVT 3.0 bytes go into an EventPacket
  untouched, as metavision_driver records them: ``time_base = 0``, sensor time in the payload,
  ``header.stamp`` the host (wall-clock) time of the transfer's first event.
* iniVation (``encoding == "libcaer"``): the decoded events of each transfer as libcaer_driver
  publishes them (``libcaer`` records, ``time_base`` the host time of the sensor's zero plus the
  31-bit rollover's high bits). libcaer records carry no trigger events, so the camera's
  external-input edges go into a second topic, ``TRIGGERS``, as evt3 EventPackets holding only
  EXT_TRIGGER words (never dropped).

Host times: the wall-clock time of the sensor's zero is taken once, from the first transfer that
holds events: its arrival (wall clock) minus the sensor time of its last item, so it includes the
USB latency of that transfer (the driver's ``Device.clock`` fit over the whole recording is the
finer estimate, for sync). Every stamp is that origin + sensor time, so the recording's times
are one consistent clock, as libcaer_driver's ``time_base`` is.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evdnerf_ros.events.types import empty_events
from evdnerf_ros.io.rosbag2 import BagWriter
from evdnerf_ros.topics import EVENTS

from .errors import CameraDisconnected

#: Where a libcaer camera's trigger edges are recorded (evt3 EventPackets of EXT_TRIGGER words).
TRIGGERS = "/event_camera/triggers"


def record(device, path, *, duration_s: float, storage: str = "mcap", log=print) -> dict:
    """Start the (opened) ``device``, write ``duration_s`` wall seconds of its stream into the new
    rosbag2 ``path``, stop it. Returns counts; an unplug mid-recording ends the bag validly with
    everything received before it, then re-raises."""
    path = Path(path)
    counts = {"messages": 0, "events": 0, "triggers": 0, "bytes": 0, "sensor_zero_wall_ns": None}
    disconnected = None
    with BagWriter(path, storage=storage) as bag:
        device.start()
        try:
            end = time.monotonic() + float(duration_s)
            while time.monotonic() < end:
                try:
                    chunk = device.read(timeout_s=min(0.5, max(0.01, end - time.monotonic())))
                except CameraDisconnected as exc:
                    disconnected = exc
                    break
                if chunk is None:
                    continue
                _write_chunk(bag, device, chunk, counts)
        finally:
            try:
                device.stop()
            except CameraDisconnected:
                pass
    counts["stats"] = device.stats.as_dict()
    log(f"{path}: {counts['events']} events, {counts['triggers']} trigger events in {counts['messages']} "
        f"messages ({device.model} {device.serial}, {device.encoding}); dropped "
        f"{device.stats.dropped_chunks} transfers")
    if disconnected is not None:
        raise CameraDisconnected(f"{disconnected}; the {counts['messages']} messages received before it are in "
                                 f"{path}")
    return counts


def _write_chunk(bag, device, chunk, counts) -> None:
    ev, tr = chunk.events, chunk.triggers
    if counts["sensor_zero_wall_ns"] is None and (ev.size or tr.size):
        last = max(int(ev["t"][-1]) if ev.size else 0, int(tr["t"].max()) if tr.size else 0)
        counts["sensor_zero_wall_ns"] = chunk.wall_ns - last
    zero = counts["sensor_zero_wall_ns"]
    counts["events"] += int(ev.size)
    counts["triggers"] += int(tr.size)
    counts["bytes"] += len(chunk.raw)
    if device.encoding == "evt3":
        if not chunk.raw:
            return
        first = ev["t"][0] if ev.size else (tr["t"][0] if tr.size else None)
        stamp = chunk.wall_ns if first is None else zero + int(first)   # no item: the stamp defines nothing
        counts["messages"] += bag.write_raw_packet(EVENTS, chunk.raw, encoding="evt3", width=device.width,
                                                   height=device.height, stamp_ns=stamp)
        return
    if ev.size:
        stamp, time_base, payload = device.libcaer_packet(chunk, sensor_zero_host_ns=zero)
        counts["messages"] += bag.write_raw_packet(EVENTS, payload, encoding="libcaer", width=device.width,
                                                   height=device.height, stamp_ns=stamp, time_base=time_base)
    if tr.size:
        shifted = tr.copy()
        shifted["t"] += np.int64(zero - zero % 1000)     # EVT 3.0 carries whole microseconds
        counts["messages"] += bag.write_events(TRIGGERS, empty_events(), triggers=np.sort(shifted, order="t"),
                                               width=device.width, height=device.height)
