"""Salvage the messages of an MCAP file that was never closed (a recording killed outright).

A killed writer leaves the MCAP header and every chunk it had flushed, but no summary,
footer or rosbag2 metadata.yaml, so no reader opens it. The records themselves are intact
up to where the writing stopped: this module walks them in file order (MCAP: opcode u8,
length u64, body), takes the schemas, channels and messages out of every complete chunk
(uncompressed or zstd), and stops at the first record cut short. `salvage_bag` writes what
it found into a new rosbag2 through the toolkit's BagWriter.

Recording nodes flush a chunk about once a second (`BagSink.flush_period_s`), so a killed
recording loses at most about the last second.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from ..errors import FormatError, InputError

MAGIC = b"\x89MCAP0\r\n"
OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x03, 0x04, 0x05, 0x06


@dataclass(frozen=True)
class SalvagedMessage:
    topic: str
    msgtype: str
    t_ns: int
    data: bytes


def _string(buf: bytes, pos: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", buf, pos)
    end = pos + 4 + n
    if end > len(buf):
        raise ValueError("string runs past its record")
    return buf[pos + 4:end].decode("utf-8"), end


def _records(buf: bytes, pos: int = 0) -> Iterator[tuple[int, bytes]]:
    """(opcode, body) of every complete record from `pos`; stops at a truncated one."""
    while pos + 9 <= len(buf):
        op = buf[pos]
        (n,) = struct.unpack_from("<Q", buf, pos + 1)
        if pos + 9 + n > len(buf):
            return
        yield op, buf[pos + 9:pos + 9 + n]
        pos += 9 + n


def _chunk_records(body: bytes) -> bytes:
    _start, _end, size, _crc = struct.unpack_from("<QQQI", body, 0)
    compression, pos = _string(body, 28)
    (n,) = struct.unpack_from("<Q", body, pos)
    data = body[pos + 8:pos + 8 + n]
    if compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    elif compression:
        raise ValueError(f"chunk compression {compression!r} is not supported")
    return data


def salvage_messages(path) -> Iterator[SalvagedMessage]:
    """The messages of every complete chunk of an unclosed (or closed) MCAP file, in file order."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not buf.startswith(MAGIC):
        raise FormatError("not an MCAP file (no MCAP magic at the start); nothing to salvage", source=str(path))
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    for op, body in _records(buf, len(MAGIC)):
        if op != OP_CHUNK:
            continue
        try:
            inner = _chunk_records(body)
        except (ValueError, struct.error, ImportError) as exc:
            raise FormatError(f"a chunk cannot be read ({exc}); the messages before it were salvaged",
                              source=str(path)) from None
        for iop, rec in _records(inner):
            if iop == OP_SCHEMA:
                (sid,) = struct.unpack_from("<H", rec, 0)
                schemas[sid], _ = _string(rec, 2)
            elif iop == OP_CHANNEL:
                cid, sid = struct.unpack_from("<HH", rec, 0)
                topic, _ = _string(rec, 4)
                channels[cid] = (topic, schemas.get(sid, ""))
            elif iop == OP_MESSAGE:
                cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", rec, 0)
                if cid in channels:
                    topic, msgtype = channels[cid]
                    yield SalvagedMessage(topic, msgtype, int(log_time), bytes(rec[22:]))


def find_unclosed_mcap(path) -> Path:
    """The .mcap of a partial output folder, a bag folder, or the file itself."""
    path = Path(path)
    if path.is_file():
        return path
    found = sorted(path.rglob("*.mcap")) if path.is_dir() else []
    if len(found) != 1:
        raise InputError(f"{path}: expected one .mcap file (a killed recording's partial folder, e.g. "
                         f".BAG.<pid>.<id>.partial), found {len(found)}")
    return found[0]


def salvage_bag(src, out, *, storage: str = "mcap") -> dict:
    """Write the salvageable messages of `src` (an unclosed .mcap, or a folder holding one)
    into the new rosbag2 `out`; returns {topic: messages}."""
    from .rosbag2 import BagWriter

    mcap = find_unclosed_mcap(src)
    counts: dict[str, int] = {}
    with BagWriter(out, storage=storage) as writer:
        for m in salvage_messages(mcap):
            if m.topic not in counts:
                writer.add_topic(m.topic, m.msgtype)
                counts[m.topic] = 0
            writer.write_raw(m.topic, m.msgtype, m.data, m.t_ns)
            counts[m.topic] += 1
    return counts
