"""Record an event camera into a view's rosbag2 on the session's event topic, in the camera's own encoding.

* Prophesee (``encoding == "evt3"``): every USB transfer's EVT 3.0 bytes go into an EventPacket
  untouched, as metavision_driver records them: ``time_base = 0``, sensor time in the payload,
  ``header.stamp`` the host (wall-clock) time of the transfer's first event.
* iniVation (``encoding == "libcaer"``): the decoded events of each transfer as libcaer_driver
  publishes them (``libcaer`` records, ``time_base`` the host time of the sensor's zero plus the
  31-bit rollover's high bits). libcaer records carry no trigger events, so the camera's
  external-input edges go into a second topic, ``EVENT_TRIGGERS``, as evt3 EventPackets holding
  only EXT_TRIGGER words (never dropped).

Host times: the wall-clock time of the sensor's zero is taken once, from the first transfer that
holds events: its arrival (wall clock) minus the sensor time of its last item, so it includes the
USB latency of that transfer (the driver's ``Device.clock`` fit over the whole recording is the
finer estimate, for sync). Every stamp is that origin + sensor time, so the recording's times
are one consistent clock, as libcaer_driver's ``time_base`` is: the view's clock, which the bag's
readers decode for either encoding (``ChunkWriter.view_ns``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from evdnerf_ros.session.recorder import ViewRecorder

from .errors import CameraDisconnected


class ChunkWriter:
    """Writes a camera's EventChunks onto a :class:`ViewRecorder` in the camera's encoding and
    knows the view's clock (:meth:`view_ns`)."""

    def __init__(self, recorder: ViewRecorder, device, *, also=()):
        self.rec, self.device = recorder, device
        self.also = list(also)              # more sinks with raw_packet / trigger_edges (live topics)
        self.counts = {"messages": 0, "events": 0, "triggers": 0, "bytes": 0, "sensor_zero_wall_ns": None,
                       "first_sensor_ns": None, "last_sensor_ns": None}
        self.rising_ns: list[int] = []      # sensor times of the trigger input's rising edges

    def view_ns(self, sensor_ns):
        """The view's clock (what the bag's readers decode) of a sensor time: the wall-clock time
        of the sensor's zero plus the sensor time, for both encodings (evt3: the readers put the
        stream at its first packet's stamp, which is written as that sum)."""
        zero = self.counts["sensor_zero_wall_ns"]
        if zero is None:
            raise ValueError("the view's clock is set by the first transfer holding events")
        return np.asarray(sensor_ns, np.int64) + np.int64(zero) if np.ndim(sensor_ns) else int(sensor_ns) + zero

    def write(self, chunk) -> None:
        counts, device = self.counts, self.device
        ev, tr = chunk.events, chunk.triggers
        if ev.size or tr.size:
            last = max(int(ev["t"][-1]) if ev.size else 0, int(tr["t"].max()) if tr.size else 0)
            first = min(int(ev["t"][0]) if ev.size else last, int(tr["t"].min()) if tr.size else last)
            if counts["sensor_zero_wall_ns"] is None:
                counts["sensor_zero_wall_ns"] = chunk.wall_ns - last
                counts["first_sensor_ns"] = first
            counts["last_sensor_ns"] = last
        zero = counts["sensor_zero_wall_ns"]
        counts["events"] += int(ev.size)
        counts["triggers"] += int(tr.size)
        if tr.size:
            self.rising_ns += [int(t) for t in tr["t"][tr["value"] == 1]]
        counts["bytes"] += len(chunk.raw)
        if device.encoding == "evt3":
            if not chunk.raw:
                return
            first = ev["t"][0] if ev.size else (tr["t"][0] if tr.size else None)
            stamp = chunk.wall_ns if first is None else zero + int(first)   # no item: the stamp defines nothing
            counts["messages"] += self.rec.raw_packet(chunk.raw, stamp_ns=stamp)
            for sink in self.also:
                sink.raw_packet(chunk.raw, stamp_ns=stamp)
            return
        if ev.size:
            stamp, time_base, payload = device.libcaer_packet(chunk, sensor_zero_host_ns=zero)
            counts["messages"] += self.rec.raw_packet(payload, stamp_ns=stamp, time_base=time_base)
            for sink in self.also:
                sink.raw_packet(payload, stamp_ns=stamp, time_base=time_base)
        if tr.size:
            shifted = tr.copy()
            shifted["t"] += np.int64(zero - zero % 1000)     # EVT 3.0 carries whole microseconds
            shifted = np.sort(shifted, order="t")
            counts["messages"] += self.rec.trigger_edges(shifted)
            for sink in self.also:
                sink.trigger_edges(shifted)


def record(device, path, *, duration_s: float, storage: str = "mcap", log=print) -> dict:
    """Start the (opened) ``device``, write ``duration_s`` wall seconds of its stream into the new
    rosbag2 ``path``, stop it. Returns counts; an unplug mid-recording ends the bag validly with
    everything received before it, then re-raises."""
    path = Path(path)
    disconnected = None
    with ViewRecorder(path, width=device.width, height=device.height, encoding=device.encoding,
                      storage=storage) as rec:
        writer = ChunkWriter(rec, device)
        device.start()
        try:
            end = time.monotonic() + float(duration_s)
            while time.monotonic() < end:
                try:
                    chunk = device.read(timeout_s=min(0.5, max(0.01, end - time.monotonic())))
                except CameraDisconnected as exc:
                    disconnected = exc
                    break
                if chunk is not None:
                    writer.write(chunk)
        finally:
            try:
                device.stop()
            except CameraDisconnected:
                pass
    counts = dict(writer.counts, stats=device.stats.as_dict())
    log(f"{path}: {counts['events']} events, {counts['triggers']} trigger events in {counts['messages']} "
        f"messages ({device.model} {device.serial}, {device.encoding}); dropped "
        f"{device.stats.dropped_chunks} transfers")
    if disconnected is not None:
        raise CameraDisconnected(f"{disconnected}; the {counts['messages']} messages received before it are in "
                                 f"{path}")
    return counts
