"""Record an event camera into a view's rosbag2 on the session's event topic, in the camera's own encoding.

* Prophesee (``encoding == "evt3"``): every USB transfer's EVT 3.0 bytes go into an EventPacket
  untouched, as metavision_driver records them: ``time_base = 0``, sensor time in the payload,
  ``header.stamp`` the host (wall-clock) time of the transfer's first event.
* iniVation (``encoding == "libcaer"``): the decoded events of each transfer as libcaer_driver
  publishes them (``libcaer`` records, ``time_base`` the host time of the sensor's zero plus the
  31-bit rollover's high bits). libcaer records carry no trigger events, so the camera's
  external-input edges go into a second topic, ``EVENT_TRIGGERS``, as evt3 EventPackets holding
  only EXT_TRIGGER words (never dropped).

Host times: the wall-clock time of the sensor's zero is taken once per stream, from the first
transfer that holds events (``StreamOrigin``): its arrival (wall clock) minus the sensor time of
its last item, so it includes the USB latency of that transfer (the driver's ``Device.clock`` fit
over the whole recording is the finer estimate, for sync). Every stamp is that origin + sensor
time, so the recording's times are one consistent clock, as libcaer_driver's ``time_base`` is:
the view's clock, which the bag's readers decode for either encoding (``ChunkWriter.view_ns``).
Recordings cut from one running stream (``CameraStream``) share its origin: one clock for all.

A recording that starts in a running stream begins with the driver's resume words
(``Device.resume_words``: for EVT 3.0 one packet of TIME_HIGH / TIME_LOW / ADDR_Y / VECT_BASE_X
words, no event), so its readers decode its first transfer as the driver did, at the same
unwrapped sensor times; the camera's own transfers follow untouched.

``CameraStream`` keeps a started camera read in a thread for a whole session and cuts its stream
into spans, one per recording (``open_span`` / ``end_span`` / ``close_span``); what falls outside
every span (the turntable turning, the servo homing) is read and discarded, and counted.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evdnerf_ros.session.recorder import ViewRecorder

from .errors import CameraDisconnected, CameraError


def item_span(chunk) -> tuple[int, int] | None:
    """(first, last) sensor ns of a chunk's events and trigger edges; None when it holds none."""
    ev, tr = chunk.events, chunk.triggers
    if not (ev.size or tr.size):
        return None
    last = max(int(ev["t"][-1]) if ev.size else 0, int(tr["t"].max()) if tr.size else 0)
    first = min(int(ev["t"][0]) if ev.size else last, int(tr["t"].min()) if tr.size else last)
    return first, last


class StreamOrigin:
    """The wall-clock time of a stream's sensor zero (module doc), set by its first transfer
    holding an item; shared by every recording cut from the stream."""

    def __init__(self):
        self.wall_ns: int | None = None

    def see(self, chunk, span: tuple[int, int] | None) -> None:
        if self.wall_ns is None and span is not None:
            self.wall_ns = int(chunk.wall_ns) - span[1]


class ChunkWriter:
    """Writes a camera's EventChunks onto a :class:`ViewRecorder` in the camera's encoding and
    knows the view's clock (:meth:`view_ns`). ``origin``: the stream's (shared by the recordings
    cut from it); by default the writer's own."""

    def __init__(self, recorder: ViewRecorder, device, *, also=(), origin: StreamOrigin | None = None):
        self.rec, self.device = recorder, device
        self.also = list(also)              # more sinks with raw_packet / trigger_edges (live topics)
        self.origin = origin if origin is not None else StreamOrigin()
        self.counts = {"messages": 0, "events": 0, "triggers": 0, "bytes": 0, "sensor_zero_wall_ns": None,
                       "first_sensor_ns": None, "last_sensor_ns": None}
        self.rising_ns: list[int] = []      # sensor times of the trigger input's rising edges
        self._resumed = False               # the resume words went first (a cut from a running stream)

    def view_ns(self, sensor_ns):
        """The view's clock (what the bag's readers decode) of a sensor time: the wall-clock time
        of the sensor's zero plus the sensor time, for both encodings (evt3: the readers put the
        stream at its first packet's stamp, which is written as that sum)."""
        zero = self.counts["sensor_zero_wall_ns"]
        if zero is None:
            raise ValueError("the view's clock is set by the first transfer holding events")
        return np.asarray(sensor_ns, np.int64) + np.int64(zero) if np.ndim(sensor_ns) else int(sensor_ns) + zero

    def write(self, chunk, items: tuple[int, int] | None | bool = False) -> None:
        """Write one chunk (``items``: its :func:`item_span` when the caller has it)."""
        counts, device = self.counts, self.device
        ev, tr = chunk.events, chunk.triggers
        span = item_span(chunk) if items is False else items
        self.origin.see(chunk, span)
        if span is not None:
            if counts["first_sensor_ns"] is None:
                counts["first_sensor_ns"] = span[0]
            counts["last_sensor_ns"] = span[1]
        zero = counts["sensor_zero_wall_ns"] = self.origin.wall_ns
        counts["events"] += int(ev.size)
        counts["triggers"] += int(tr.size)
        if tr.size:
            self.rising_ns += [int(t) for t in tr["t"][tr["value"] == 1]]
        counts["bytes"] += len(chunk.raw)
        if device.encoding == "evt3":
            if not chunk.raw:
                return
            stamp = chunk.wall_ns if span is None else zero + span[0]   # no item: the stamp defines nothing
            if not self._resumed:
                self._resumed = True
                self._resume(chunk, stamp)
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

    def _resume(self, chunk, stamp: int) -> None:
        """The driver's resume words as the recording's first packet, stamped as the chunk they
        precede (module doc); nothing before a stream's very first transfer."""
        words = self.device.resume_words(chunk)
        if words:
            self.counts["messages"] += self.rec.raw_packet(words, stamp_ns=stamp)


class ArrivalClock:
    """The sensor time of a host time, from a stream's arrivals: ``host - sensor`` at the least
    latency seen over the last ``window_s``, the sensor clock taken to run at the host's rate
    (a real camera drifts by ppm: microseconds over a view).  Unlike a fit through every
    sample it stays right when the stream lags real time for a while and catches up later
    (a camera twin rendering slower than real time; a busy USB link): the least latency is the
    on-time one. ``host_ns_to_sensor_ns`` raises CameraError before the first sample."""

    def __init__(self, name: str, window_s: float = 60.0):
        self.name = name
        self.window_ns = int(window_s * 1e9)
        self._mins: collections.deque = collections.deque()    # (host_ns, latency_ns), latency increasing

    def add(self, sensor_ns: int, host_ns: int) -> None:
        lat = int(host_ns) - int(sensor_ns)
        mins = self._mins
        while mins and mins[-1][1] >= lat:
            mins.pop()
        mins.append((int(host_ns), lat))
        while mins[0][0] < host_ns - self.window_ns:
            mins.popleft()

    @property
    def latency_ns(self) -> int:
        """host - sensor at the least latency in the window."""
        if not self._mins:
            raise CameraError(f"{self.name}: no clock yet (no timed transfer has arrived)")
        return self._mins[0][1]

    def host_ns_to_sensor_ns(self, host_ns):
        return np.asarray(host_ns, np.int64) - np.int64(self.latency_ns) if np.ndim(host_ns) \
            else int(host_ns) - self.latency_ns


@dataclass
class Span:
    """One recording's share of a :class:`CameraStream`: the chunks from ``start_sensor_ns``
    (the sensor time of ``start_host_ns`` on the stream's :class:`ArrivalClock`; when nothing
    timed had arrived yet, the first chunk arriving after ``start_host_ns``) to
    ``end_sensor_ns`` (None: open).
    Whole transfers are written: one holding an item at or after the start and none after the
    end (EVT 3.0 words carry state from word to word, so a transfer is never cut)."""
    writer: ChunkWriter
    start_host_ns: int
    start_sensor_ns: int | None
    end_sensor_ns: int | None = None
    started: bool = False           # a chunk has been written
    closed: bool = False
    last_host_ns: int | None = None     # arrival of the last chunk written
    dropped_at_open: int = 0        # the stream's dropped transfers when the span opened
    dropped: int = 0                # ... while it was open
    #: what the stream carried, and was discarded, between the previous span's content (or the
    #: camera's start) and this one's: the turntable turning, the servo homing, a lagging stream
    discarded_before: dict = field(default_factory=dict)

    def takes(self, chunk, items: tuple[int, int] | None, reached: int | None) -> bool:
        """Whether ``chunk`` (its :func:`item_span`; ``reached``: the stream's sensor time after
        it, for a chunk of time words only) is this span's."""
        if self.end_sensor_ns is not None:
            after = items[0] if items is not None else reached
            if after is not None and after > self.end_sensor_ns:
                return False
        if self.started:
            return True
        if self.start_sensor_ns is None:
            return chunk.host_ns >= self.start_host_ns
        at = items[1] if items is not None else reached
        return at is not None and at >= self.start_sensor_ns


@dataclass
class Discarded:
    """What the stream carried outside every span (read, counted, not recorded)."""
    transfers: int = 0
    events: int = 0
    triggers: int = 0

    def add(self, chunk) -> None:
        self.transfers += 1
        self.events += int(chunk.events.size)
        self.triggers += int(chunk.triggers.size)

    def take(self) -> dict:
        """The counts so far, as a dict; the counter starts again from zero."""
        out = dict(vars(self))
        self.transfers = self.events = self.triggers = 0
        return out


class CameraStream:
    """A started camera read in a thread for a whole session, its stream cut into spans (module
    doc). ``live``: a sink (raw_packet / trigger_edges) that gets every chunk, in or out of a span.

    The reader thread never blocks on the recorder: a chunk is written (or counted discarded)
    as it arrives, so the transfer queue drains while nothing records. A camera fault ends the
    thread; :meth:`check` raises it (every chunk received before it was routed first)."""

    READ_TIMEOUT_S = 0.1

    def __init__(self, device, *, live=None):
        self.device = device
        self.origin = StreamOrigin()
        self.live = None if live is None else ChunkWriter(live, device, origin=self.origin)
        self.discarded = Discarded()
        self._gap = Discarded()                 # discarded since the last span's content
        self.clock = ArrivalClock(device.name)
        self.error: BaseException | None = None
        self.last_chunk_host_ns: int | None = None
        self.start_s = self.stop_s = 0.0         # wall time camera.start() / stop() took
        self.restarts = 0                        # restart(): a stream that could not catch up
        self._span: Span | None = None
        self._lock = threading.Lock()
        self._progress = threading.Condition(self._lock)
        self._chunks = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ----- life cycle
    def start(self) -> "CameraStream":
        tic = time.monotonic()
        self.device.start()
        self.start_s = time.monotonic() - tic
        self._thread = threading.Thread(target=self._run, name=f"stream {self.device.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """End the reader and stop the camera (faults of a camera already gone are not raised);
        again: nothing."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5 * self.READ_TIMEOUT_S + 5)
        tic = time.monotonic()
        try:
            self.device.stop()
        except CameraError:
            pass
        self.stop_s = time.monotonic() - tic

    def restart(self) -> None:
        """Stop and start the camera again: for a stream too far behind real time to catch up (a
        camera twin rendering slower than real time), whose backlog is dropped as a start / stop
        per view would; the stream gets a new sensor zero and clock. Between spans only."""
        with self._lock:
            if self._span is not None:
                raise RuntimeError("CameraStream: restart while a span is open")
        self.stop()
        self.restarts += 1
        self._stop = threading.Event()
        self.origin = StreamOrigin()
        if self.live is not None:
            self.live.origin = self.origin
        self.clock = ArrivalClock(self.device.name)
        self.last_chunk_host_ns = None
        self.start()

    def __enter__(self) -> "CameraStream":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ----- spans (the recording side)
    def open_span(self, writer: ChunkWriter) -> Span:
        """Start routing the stream into ``writer`` from now on (the camera's clock: ``Span``)."""
        self.check()
        host = time.monotonic_ns()
        with self._lock:
            try:
                start = int(self.clock.host_ns_to_sensor_ns(host))
            except CameraError:                 # nothing timed has arrived yet: nothing to tell apart
                start = None
            if self._span is not None:
                raise RuntimeError("CameraStream: open_span while another span is open")
            span = Span(writer, host, start, dropped_at_open=self.device.stats.dropped_chunks)
            self._span = span
        return span

    def end_span(self, span: Span, end_sensor_ns: int) -> None:
        """The span's last sensor time: later chunks are not its own."""
        with self._lock:
            span.end_sensor_ns = int(end_sensor_ns)

    def close_span(self, span: Span) -> None:
        """Stop routing into the span; once this returns nothing more is written to it."""
        with self._lock:
            if self._span is span:
                self._span = None
            span.closed = True
            span.dropped = self.device.stats.dropped_chunks - span.dropped_at_open
            if not span.started:            # nothing came: the gap so far is the one before it
                span.discarded_before = self._gap.take()

    def discarded_since_span(self) -> dict:
        """What was discarded since the last span's content (or the camera's start)."""
        with self._lock:
            return dict(vars(self._gap))

    def check(self) -> None:
        """Raise the camera fault that ended the reader, if one did."""
        if self.error is not None:
            raise self.error

    def wait(self, timeout_s: float) -> None:
        """Until the next chunk arrives (or ``timeout_s``, or the reader ended)."""
        with self._progress:
            seen = self._chunks
            if self.error is None:
                self._progress.wait_for(lambda: self._chunks != seen or self.error is not None, timeout_s)

    # ----- the reader thread
    def _run(self) -> None:
        device = self.device
        try:
            while not self._stop.is_set():
                chunk = device.read(timeout_s=self.READ_TIMEOUT_S)
                if chunk is None:
                    continue
                items = item_span(chunk)
                self.origin.see(chunk, items)
                reached = device.sensor_time_ns
                with self._lock:
                    if reached is not None:
                        self.clock.add(reached, chunk.host_ns)
                    view = self._span
                    if view is not None and view.takes(chunk, items, reached):
                        if not view.started:    # the gap before it ends here
                            view.started = True
                            view.discarded_before = self._gap.take()
                        view.writer.write(chunk, items)
                        view.last_host_ns = chunk.host_ns
                    else:
                        self.discarded.add(chunk)
                        self._gap.add(chunk)
                    if self.live is not None:
                        self.live.write(chunk, items)
                    self.last_chunk_host_ns = chunk.host_ns
                    self._chunks += 1
                    self._progress.notify_all()
        except BaseException as exc:  # noqa: BLE001 - handed to the recording side by check()
            with self._lock:
                self.error = exc
                self._progress.notify_all()


def record(device, path, *, duration_s: float, storage: str = "mcap", log=print) -> dict:
    """Start the (opened) ``device``, write ``duration_s`` wall seconds of its stream (every transfer
    that arrived in them) into the new rosbag2 ``path``, stop it. Returns counts; an unplug
    mid-recording ends the bag validly with everything received before it, then re-raises."""
    path = Path(path)
    disconnected = None
    with ViewRecorder(path, width=device.width, height=device.height, encoding=device.encoding,
                      storage=storage) as rec:
        writer = ChunkWriter(rec, device)
        device.start()
        try:
            end = time.monotonic() + float(duration_s)
            end_ns = int(end * 1e9)
            while time.monotonic() < end:
                try:
                    chunk = device.read(timeout_s=min(0.5, max(0.01, end - time.monotonic())))
                except CameraDisconnected as exc:
                    disconnected = exc
                    break
                if chunk is not None:
                    writer.write(chunk)
            else:
                # transfers that arrived inside the window but still wait in the queue (the loop
                # fell behind it: a stalled write) are the recording's too; stop() would drop them
                try:
                    while (chunk := device.read(timeout_s=0)) is not None and chunk.host_ns <= end_ns:
                        writer.write(chunk)
                except CameraDisconnected as exc:
                    disconnected = exc
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
