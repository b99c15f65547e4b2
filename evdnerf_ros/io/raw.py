"""OpenEB / Metavision RAW files: `% ` text header lines followed by EVT 3.0 or EVT 2.0 words.

    read_raw_header(path) -> RawHeader
    read_raw(path) -> (Decoded, RawHeader)         whole file, exact-size output
    iter_raw(path) -> Iterator[Decoded]             bounded memory, chunk by chunk
    write_raw(path, events, width=, height=, encoding="evt3", triggers=None, t0_ns=None)

Header: lines starting with "% " (or a bare "%") before the binary data; it ends after a
"% end" line or at the first line that does not start that way. The encoding comes from
`% format EVT3;height=720;width=1280` or from the older `% evt 3.0` / `% evt 2.0` lines; the
geometry from the format line's width/height or from `% geometry 1280x720`, else (files
before 2021) from `% plugin_name` as OpenEB infers it (gen3 / gen31: 640x480, gen41 / imx636:
1280x720, imx8: 320x320).

Times and the `% t0` line. The words of a RAW file carry sensor-clock microseconds, counted
from when the camera started streaming, not from the recording's start nor from any date
(Prophesee's "Timestamp Shifting" page); OpenEB writes no header line about the time origin.
Its readers shift times by default so that they count from the file's first TIME_HIGH (less
one 4096 us unit; RawFileConfig do_time_shifting_), which loses the sensor time; this module
never shifts: a file's event times are t_ns = t0 + 1000 * sensor_us, where t0 is 0 unless
the header has a line `% t0 <integer>`: the time origin in **microseconds**, as faery
(aestream's I/O library) writes it (`% t0 <first event's us>`) and reads it back
(RawHeader.t0_ns holds it in ns). This module writes `% t0 <us>` with a `% t0_unit us` line
beside it. A file whose header names its unit (`% t0_unit us` or `ns`) is read in that unit;
files written by this toolkit before it wrote `% t0_unit` said `% camera_integrator_name
evdnerf_ros` and gave t0 in nanoseconds, and are read so; any other `% t0` is microseconds
(RawHeader.t0_unit says which rule applied). OpenEB keeps header keys it does not know and
ignores them, so its tools read such a file at its sensor times.

write_raw keeps sensor times that lie in a sensor clock's first 2**24 us period (t0 = 0, no
`% t0` line: what a camera writes reads back unchanged); any other first time (an epoch time,
or a negative one) becomes t0 = that time rounded down to a multiple of 4096 us (one EVT 3.0
TIME_HIGH unit), written in the `% t0` line, and the sensor times start below 4096 us. Without
that, EVT 3.0 must count every 2**24 us wrap since the sensor's zero: 0.6 s of events at a
2023 epoch took 810 MB of TIME_HIGH words; now the size follows the events, not the date.
EVT 2.0 / 3.0 carry whole microseconds: reading a file back gives the written int64 ns times
exactly, and times that are not whole microseconds are refused (round them explicitly with
evdnerf_ros.events.codecs.quantize_to_us).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from ..atomic import atomic_output
from ..errors import FormatError, InputError, OutputExistsError
from ..events.codecs import Decoded, make_decoder, make_encoder
from ..events.codecs._common import (
    TIME_BASE_LIMIT, check_events_for_us, check_time_base, concat_triggers, sensor_origin_ns,
    triggers_to_us,
)
from ..events.types import EVENT_DTYPE, MAX_SENSOR_SIZE, as_events
from ..limits import check_memory
from .guard import writing

_MAX_LINE = 1 << 16
_MAX_HEADER = 1 << 24
_ENCODING_NAMES = {"EVT3": "evt3", "EVT3.0": "evt3", "EVT2": "evt2", "EVT2.0": "evt2"}
_EVT_VERSIONS = {"3.0": "evt3", "3": "evt3", "2.0": "evt2", "2": "evt2"}
_UNSUPPORTED = {"EVT21", "EVT2.1", "2.1"}
_WRITE_CHUNK_EVENTS = 1 << 20


@dataclass
class RawHeader:
    """What a RAW file's text header says. width / height are None when it gives no geometry;
    t0_ns is the time origin of its `% t0` line (0 without one): event t_ns = t0_ns + 1000 * us;
    t0_unit how that line was read (module doc): "us", "ns" or "" (no line)."""

    encoding: str
    width: int | None
    height: int | None
    fields: dict[str, str] = field(default_factory=dict)
    header_bytes: int = 0
    t0_ns: int = 0
    t0_unit: str = ""


def _parse_header_bytes(read, source: str) -> tuple[dict[str, str], int]:
    """Parse header lines from the byte source `read(offset, n) -> bytes`.

    Returns (fields, header_bytes). Field keys keep their spelling; the first word after
    "% " is the key and the rest of the line (stripped) is the value.
    """
    fields: dict[str, str] = {}
    pos = 0
    buf = read(0, 1 << 16)
    base = 0
    while True:
        rel = pos - base
        if rel >= len(buf):
            more = read(pos, 1 << 16)
            if not more:
                break                        # end of file: header only
            buf, base, rel = more, pos, 0
        if buf[rel:rel + 1] != b"%":
            break
        if rel + 1 >= len(buf):
            buf = buf[rel:] + read(base + len(buf), 1 << 16)
            base, rel = pos, 0
        if buf[rel + 1:rel + 2] not in (b" ", b"\n", b"\r", b""):
            break                            # '%' followed by something else: binary data
        nl = buf.find(b"\n", rel)
        while nl < 0:
            if len(buf) - rel > _MAX_LINE:
                raise FormatError(f"header line longer than {_MAX_LINE} bytes; this is not an "
                                  "OpenEB RAW header (or the file is corrupt)", source=source,
                                  offset=pos)
            more = read(base + len(buf), 1 << 16)
            if not more:
                raise FormatError("header line has no end of line: the file is truncated inside its "
                                  "header", source=source, offset=pos)
            buf = buf[rel:] + more
            base, rel = pos, 0
            nl = buf.find(b"\n", rel)
        raw_line = buf[rel:nl]
        if raw_line.endswith(b"\r"):
            raw_line = raw_line[:-1]
        if raw_line != b"%" and not raw_line.startswith(b"% "):
            break                            # e.g. '%' + CR + binary: not a header line
        try:
            text = raw_line.decode("utf-8")
        except UnicodeDecodeError:
            raise FormatError("header line is not UTF-8 text; the file is corrupt or the header is "
                              "not terminated with '% end'", source=source, offset=pos) from None
        if any(ord(c) < 32 and c != "\t" for c in text):
            raise FormatError("header line contains control characters; the file is corrupt or the "
                              "header is not terminated with '% end'", source=source, offset=pos)
        pos = base + nl + 1
        if pos > _MAX_HEADER:
            raise FormatError(f"header longer than {_MAX_HEADER} bytes; not an OpenEB RAW file",
                              source=source, offset=pos)
        body = text[2:].strip() if len(text) > 1 else ""
        if body == "end":
            break
        if not body:
            continue
        key, _, value = body.partition(" ")
        fields[key] = value.strip()
    return fields, pos


def _lookup(fields: dict[str, str], key: str) -> str | None:
    for k, v in fields.items():
        if k.lower() == key:
            return v
    return None


def _positive_int(text: str, what: str, source: str) -> int:
    try:
        v = int(text.strip())
    except ValueError:
        raise FormatError(f"header {what} {text!r} is not an integer", source=source) from None
    if not 0 < v <= 1 << 16:
        raise FormatError(f"header {what} {v} is out of range", source=source)
    return v


def _interpret(fields: dict[str, str], header_bytes: int, source: str) -> RawHeader:
    enc_fmt = enc_evt = None
    width = height = None
    fmt = _lookup(fields, "format")
    if fmt is not None:
        parts = [p.strip() for p in fmt.split(";")]
        name = parts[0].upper()
        if name in _UNSUPPORTED:
            raise FormatError(f"format {parts[0]} (EVT 2.1) is not supported; only EVT 3.0 and "
                              "EVT 2.0 RAW files can be read (convert it with metavision tools)",
                              source=source)
        enc_fmt = _ENCODING_NAMES.get(name)
        if enc_fmt is None:
            raise FormatError(f"unknown format {parts[0]!r} in '% format {fmt}'; supported: EVT3, EVT2",
                              source=source)
        for opt in parts[1:]:
            k, _, v = opt.partition("=")
            if k.strip().lower() == "width":
                width = _positive_int(v, "format width", source)
            elif k.strip().lower() == "height":
                height = _positive_int(v, "format height", source)
    evt = _lookup(fields, "evt")
    if evt is not None:
        ver = evt.split()[0] if evt.split() else ""
        if ver in _UNSUPPORTED:
            raise FormatError("'% evt 2.1' (EVT 2.1) is not supported; only EVT 3.0 and EVT 2.0",
                              source=source)
        enc_evt = _EVT_VERSIONS.get(ver)
        if enc_evt is None and enc_fmt is None:
            raise FormatError(f"unknown event format version '% evt {evt}'; supported: 3.0, 2.0",
                              source=source)
    if enc_fmt and enc_evt and enc_fmt != enc_evt:
        raise FormatError(f"header contradicts itself: '% format {fmt}' but '% evt {evt}'",
                          source=source)
    encoding = enc_fmt or enc_evt
    if encoding is None:
        raise FormatError("the header names no event encoding; add a line such as "
                          "'% format EVT3;height=720;width=1280' (or '% evt 3.0') before the data",
                          source=source)
    geom = _lookup(fields, "geometry")
    if geom is None and (width is None or height is None):
        geom = _plugin_geometry(_lookup(fields, "plugin_name"))
    if geom is not None and (width is None or height is None):
        w, sep, h = geom.lower().partition("x")
        if not sep:
            raise FormatError(f"'% geometry {geom}' is not WIDTHxHEIGHT", source=source)
        width = _positive_int(w, "geometry width", source) if width is None else width
        height = _positive_int(h, "geometry height", source) if height is None else height
    t0_ns, t0_unit = _t0(fields, source)
    return RawHeader(encoding, width, height, dict(fields), header_bytes, t0_ns, t0_unit)


#: What this toolkit writes in `% camera_integrator_name`; with no `% t0_unit` line, such a file's
#: `% t0` is in nanoseconds (written before the unit line existed).
INTEGRATOR = "evdnerf_ros"
_NS_PER = {"us": 1000, "ns": 1}


def _t0(fields: dict[str, str], source: str) -> tuple[int, str]:
    """(t0 in ns, the unit its `% t0` line was read in) from the header (module doc)."""
    text = _lookup(fields, "t0")
    if text is None:
        return 0, ""
    unit = _lookup(fields, "t0_unit")
    if unit is not None:
        unit = unit.strip().lower()
        if unit not in _NS_PER:
            raise FormatError(f"'% t0_unit {unit}' is not us or ns: fix or remove the line (without it "
                              "'% t0' is in microseconds, as faery writes it)", source=source)
    else:
        integrator = (_lookup(fields, "camera_integrator_name") or "").strip()
        unit = "ns" if integrator == INTEGRATOR else "us"
    try:
        v = int(text.strip())
    except ValueError:
        raise FormatError(f"'% t0 {text}' is not an integer; the line gives the time origin in "
                          f"{'microseconds' if unit == 'us' else 'nanoseconds'} (e.g. '% t0 1700000000000000'): "
                          "fix or remove it", source=source) from None
    t0_ns = v * _NS_PER[unit]
    if abs(t0_ns) >= TIME_BASE_LIMIT:
        raise FormatError(f"'% t0 {text}' ({unit}) is out of range (|t0| < 2**62 ns, about 146 years): fix "
                          "or remove the line", source=source)
    return t0_ns, unit


# Pre-2021 RAW files have no geometry line; OpenEB infers the sensor size from the HAL
# plugin's name. Checked in this order: the more specific names first.
_PLUGIN_GEOMETRY = (("gen41", "1280x720"), ("imx636", "1280x720"), ("gen31", "640x480"),
                    ("gen3", "640x480"), ("imx8", "320x320"))


def _plugin_geometry(plugin_name) -> str | None:
    name = str(plugin_name or "").lower()
    return next((geom for key, geom in _PLUGIN_GEOMETRY if key in name), None)


def read_raw_header(path) -> RawHeader:
    """Parse the text header of a RAW file (FormatError if it is malformed or names no encoding)."""
    source = str(path)
    try:
        with open(path, "rb") as f:
            def read(offset, n):
                f.seek(offset)
                return f.read(n)
            fields, header_bytes = _parse_header_bytes(read, source)
    except FileNotFoundError:
        raise InputError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{source}: is a directory, not a RAW file") from None
    return _interpret(fields, header_bytes, source)


def parse_raw_header(data: bytes, source: str = "<bytes>") -> RawHeader:
    """Parse a RAW header held in memory (the start of a file)."""
    mv = bytes(data)
    fields, header_bytes = _parse_header_bytes(lambda o, n: mv[o:o + n], source)
    return _interpret(fields, header_bytes, source)


def _chunk_size(chunk_bytes) -> int:
    if isinstance(chunk_bytes, bool) or not isinstance(chunk_bytes, (int, np.integer)):
        raise InputError(f"chunk_bytes must be an integer, got {chunk_bytes!r}")
    c = int(chunk_bytes) // 8 * 8
    if c <= 0:
        raise InputError(f"chunk_bytes must be at least 8, got {chunk_bytes}")
    return c


def _read_body(path, header_bytes: int, piece: int, source: str, on_piece=None) -> np.ndarray:
    """The bytes after the header, in one aligned array, read `piece` bytes at a time;
    `on_piece(start, view)` sees each piece while it is still in cache."""
    with open(path, "rb", buffering=0) as f:
        size = os.fstat(f.fileno()).st_size
        check_memory(max(size - header_bytes, 0), f"{source}: {size - header_bytes} body bytes",
                     "read it chunk by chunk with iter_raw(), or on a machine with more memory")
        body = np.empty(max(size - header_bytes, 0), np.uint8)
        f.seek(header_bytes)
        got = 0
        view = memoryview(body)
        while got < body.shape[0]:
            n = f.readinto(view[got:got + piece])
            if not n:
                break
            if on_piece is not None:
                on_piece(got, body[got:got + n])
            got += n
        del view
    if got < body.shape[0]:
        raise InputError(f"{source}: the file shrank while being read ({got} of "
                         f"{body.shape[0]} body bytes); read it again when it is complete")
    return body


def read_raw(path, *, chunk_bytes: int = 64 << 20, time_low_carry: bool = False, strict: bool = False
             ) -> tuple[Decoded, RawHeader]:
    """Decode a whole RAW file; returns (Decoded, RawHeader). Times: t_ns = t0 + 1000 * sensor
    us, t0 from the header's `% t0` line (0 without one; see the module doc).

    The body is read into memory (counting an upper bound of its events piece by piece while
    in cache), then streamed through the decoder in `chunk_bytes` pieces straight into one
    event array of that size, so no partial results are concatenated. For bounded memory use
    iter_raw(). `time_low_carry` (EVT 3.0) reads files whose writer omitted TIME_HIGH words
    (expelliarmus). Errors name the file and the absolute byte offset. A file cut inside its last
    word (a killed recording) gives every complete word with a TruncatedStreamWarning naming the
    offset; ``strict`` refuses it instead.
    """
    header = read_raw_header(path)
    chunk = _chunk_size(chunk_bytes)
    source = str(path)
    dec = make_decoder(header.encoding, time_base_ns=header.t0_ns, source=source,
                       offset=header.header_bytes, time_low_carry=time_low_carry)
    # count the events piece by piece while the bytes are in cache; pieces must start on
    # word boundaries (a short read would break that: then count again afterwards)
    counts = []
    state = {"next": 0, "aligned": True}

    def count_piece(start, view):
        if state["aligned"] and start == state["next"]:
            counts.append(dec.count_events(view))
            state["next"] = start + view.shape[0]
            state["aligned"] = view.shape[0] % 8 == 0
        else:
            state["next"] = -1

    body = _read_body(path, header.header_bytes, min(chunk, 1 << 20), source, count_piece)
    if state["next"] == body.shape[0]:
        total = sum(counts)
    else:
        total = sum(dec.count_events(body[a:a + chunk]) for a in range(0, body.shape[0], chunk))
    # a few vector words can declare many events: size the output against the budget first
    check_memory(total * EVENT_DTYPE.itemsize + body.nbytes, f"{source}: {total} events",
                 "read it chunk by chunk with iter_raw(), or on a machine with more memory")
    out = np.empty(total, EVENT_DTYPE)
    pos = 0
    trigs = []
    for a in range(0, body.shape[0], chunk):
        k, tr = dec._feed_into(body[a:a + chunk], out[pos:])
        pos += k
        if tr.size:
            trigs.append(tr)
    del body
    dec.close(strict=strict)
    if pos < total:
        out = out[:pos].copy() if pos < total // 2 else out[:pos]
    return Decoded(out, concat_triggers(trigs), getattr(dec, "time_anomalies", {})), header


def iter_raw(path, *, chunk_bytes: int = 16 << 20, time_low_carry: bool = False, strict: bool = False
             ) -> Iterator[Decoded]:
    """Yield the events of a RAW file chunk by chunk (memory bounded by `chunk_bytes`).

    Chunks that decode to nothing are skipped; a truncated last word is dropped with a warning at
    the end (``strict``: raises FormatError), as read_raw.
    """
    header = read_raw_header(path)
    chunk = _chunk_size(chunk_bytes)
    dec = make_decoder(header.encoding, time_base_ns=header.t0_ns, source=str(path),
                       offset=header.header_bytes, time_low_carry=time_low_carry)
    buf = np.empty(chunk, np.uint8)
    with open(path, "rb") as f:
        f.seek(header.header_bytes)
        while True:
            n = f.readinto(memoryview(buf))
            if not n:
                break
            part = dec.feed(buf[:n])
            if part.events.size or part.triggers.size:
                yield part
    dec.close(strict=strict)


def _header_text(encoding: str, width: int, height: int, t0_ns: int) -> bytes:
    evt = "3.0" if encoding == "evt3" else "2.0"
    fmt = "EVT3" if encoding == "evt3" else "EVT2"
    lines = [
        f"% camera_integrator_name {INTEGRATOR}",
        f"% evt {evt}",
        f"% format {fmt};height={height};width={width}",
        f"% geometry {width}x{height}",
    ]
    if t0_ns:
        lines += [f"% t0 {t0_ns // 1000}", "% t0_unit us"]
    lines.append("% end")
    return ("\n".join(lines) + "\n").encode("ascii")


def write_raw(path, events, *, width: int, height: int, encoding: str = "evt3",
              triggers=None, t0_ns: int | None = None) -> None:
    """Write events (and triggers; int64 ns, whole microseconds) as an OpenEB RAW file.

    The sensor times written are t - t0 in microseconds; t0 goes in a `% t0` header line, in
    microseconds with a `% t0_unit us` line, when it is not 0 (whole microseconds). By default (t0_ns=None) t0 is 0 when the first time lies in a sensor
    clock's first 2**24 us, else that time rounded down to 4096 us, so the file's size follows
    the events, not the date (module doc). An explicit t0_ns must not be after the first time.

    Refuses an existing path (OutputExistsError); the file appears atomically (see
    evdnerf_ros.atomic: nothing is left behind on error, an existing file is never replaced).
    """
    if encoding not in ("evt3", "evt2"):
        raise InputError(f"RAW files hold evt3 or evt2, not {encoding!r}")
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 < v <= MAX_SENSOR_SIZE:
            raise InputError(f"{name} must be an integer in 1..{MAX_SENSOR_SIZE}, got {v!r}")
    path = Path(path)
    if path.exists():
        raise OutputExistsError(path)
    # validate everything up front so that a bad input never leaves a file behind
    name = "EVT 3.0" if encoding == "evt3" else "EVT 2.0"
    events = as_events(events, source="events")
    first = _first_time(events, triggers)
    if t0_ns is None:
        t0 = sensor_origin_ns(first) if first is not None else 0
    else:
        try:
            t0 = check_time_base(t0_ns)
        except InputError:
            raise InputError(f"t0_ns must be an integer number of nanoseconds with |t0_ns| < 2**62, "
                             f"got {t0_ns!r}") from None
        if first is not None and first < t0:
            raise InputError(f"{path}: t0_ns={t0} is after the first event or trigger (t={first} ns); "
                             "the time origin must be at or before it (or leave t0_ns=None)")
        if t0 % 1000:
            raise InputError(f"{path}: t0_ns={t0} is not whole microseconds (the `% t0` line is in "
                             "microseconds); round it, or leave t0_ns=None")
    events = check_events_for_us(events, t0, name)
    for axis, limit in (("x", int(width)), ("y", int(height))):
        col = events[axis]
        if col.size and int(col.max()) >= limit:
            i = int(np.flatnonzero(col >= limit)[0])
            raise InputError(f"events: event {i} has {axis}={int(col[i])} outside the declared "
                             f"{width}x{height} geometry; give the sensor's real width and height")
    triggers, _ = triggers_to_us(triggers, t0, name, max_id=16 if encoding == "evt3" else 32)
    enc = make_encoder(encoding, time_base_ns=t0)
    with atomic_output(path) as tmp, writing(path), open(tmp, "wb") as f:
        f.write(_header_text(encoding, int(width), int(height), t0))
        n = events.shape[0]
        if triggers.size:
            # triggers go with the chunk that covers their time
            tt = triggers["t"]
            bounds = [events["t"][min(a + _WRITE_CHUNK_EVENTS, n) - 1] if n else None
                      for a in range(0, max(n, 1), _WRITE_CHUNK_EVENTS)]
        for ci, a in enumerate(range(0, max(n, 1), _WRITE_CHUNK_EVENTS)):
            ev = events[a:a + _WRITE_CHUNK_EVENTS]
            tr = None
            if triggers.size:
                last = ci == len(bounds) - 1
                lo = 0 if ci == 0 else np.searchsorted(tt, bounds[ci - 1], side="right")
                hi = tt.shape[0] if last else np.searchsorted(tt, bounds[ci], side="right")
                tr = triggers[lo:hi]
            f.write(enc.encode(ev, tr))


def _first_time(events: np.ndarray, triggers) -> int | None:
    """The earliest of the first event's and the first trigger's time (None if neither); a
    malformed trigger array is left to triggers_to_us to refuse."""
    firsts = [int(events["t"][0])] if events.ndim == 1 and events.size else []
    if triggers is not None:
        tr = np.asarray(triggers)
        if tr.ndim == 1 and tr.size and "t" in (tr.dtype.names or ()):
            firsts.append(int(tr["t"][0]))
    return min(firsts) if firsts else None
