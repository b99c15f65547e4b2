"""Event byte-stream codecs: Prophesee EVT 3.0 and EVT 2.0, and the ROS `mono` encoding.

    decode(data, "evt3", time_base_ns=..., source=...) -> Decoded(events, triggers)
    encode(events, "evt3", triggers=..., time_base_ns=...) -> bytes
    make_decoder("evt3", ...).feed(chunk) / .close()     streaming, any chunk boundaries
    make_encoder("evt3", ...).encode(events, triggers)    chunks concatenate into one stream

Times: event t (ns) = time_base_ns + 1000 * sensor microseconds for evt3/evt2, and
time_base_ns + dt (ns) for mono. The EVT formats carry whole microseconds only: encoding a
time that is not a whole microsecond after time_base_ns raises InputError; round explicitly
with quantize_to_us() if that is what you want.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ...errors import InputError
from ..types import as_events, sort_events
from ._common import Decoded, DroppedEventsWarning, check_time_base
from .evt2 import Evt2Decoder, Evt2Encoder
from .evt3 import Evt3Decoder, Evt3Encoder
from .libcaer import LibcaerCmpDecoder, LibcaerCmpEncoder, LibcaerDecoder, LibcaerEncoder
from .mono import MonoDecoder, MonoEncoder

__all__ = [
    "ENCODINGS", "Decoded", "DroppedEventsWarning", "StreamDecoder", "StreamEncoder", "decode",
    "encode", "make_decoder", "make_encoder", "quantize_to_us",
]


class StreamDecoder(Protocol):
    """What make_decoder() returns."""

    def feed(self, chunk) -> Decoded: ...

    def close(self) -> Decoded: ...


class StreamEncoder(Protocol):
    """What make_encoder() returns."""

    def encode(self, events, triggers=None) -> bytes: ...


ENCODINGS = ("evt3", "evt2", "mono", "libcaer", "libcaer_cmp")

_DECODERS = {"evt3": Evt3Decoder, "evt2": Evt2Decoder, "mono": MonoDecoder, "libcaer": LibcaerDecoder,
             "libcaer_cmp": LibcaerCmpDecoder}
_ENCODERS = {"evt3": Evt3Encoder, "evt2": Evt2Encoder, "mono": MonoEncoder, "libcaer": LibcaerEncoder,
             "libcaer_cmp": LibcaerCmpEncoder}


def _check_encoding(encoding) -> str:
    if not isinstance(encoding, str) or encoding not in _DECODERS:
        raise InputError(f"unknown event encoding {encoding!r}; valid encodings are "
                         f"{', '.join(ENCODINGS)}")
    return encoding


def make_decoder(encoding: str, *, time_base_ns: int = 0, source: str = "<stream>",
                 offset: int = 0, time_low_carry: bool = False) -> StreamDecoder:
    """A streaming decoder: .feed(chunk) -> Decoded for the whole words so far, .close() -> Decoded.

    `offset` is the absolute byte offset of the first byte fed (e.g. a file's header size); it
    only affects the offsets named in error messages. `time_low_carry` (evt3 only) accepts
    streams that let TIME_LOW wrap without TIME_HIGH words, as expelliarmus writes them.
    """
    cls = _DECODERS[_check_encoding(encoding)]
    if time_low_carry:
        if encoding != "evt3":
            raise InputError(f"time_low_carry only applies to evt3, not {encoding}")
        return cls(time_base_ns=time_base_ns, source=source, offset=offset, time_low_carry=True)
    return cls(time_base_ns=time_base_ns, source=source, offset=offset)


def make_encoder(encoding: str, *, time_base_ns: int = 0) -> StreamEncoder:
    """A streaming encoder: .encode(events, triggers=None) -> bytes; outputs concatenate."""
    return _ENCODERS[_check_encoding(encoding)](time_base_ns=time_base_ns)


def decode(data, encoding: str, *, time_base_ns: int = 0, source: str = "<bytes>",
           time_low_carry: bool = False) -> Decoded:
    """Decode a complete byte stream (a partial trailing word raises FormatError)."""
    dec = make_decoder(encoding, time_base_ns=time_base_ns, source=source,
                       time_low_carry=time_low_carry)
    out = dec.feed(data)
    dec.close()
    return out


def encode(events, encoding: str, *, triggers=None, time_base_ns: int = 0) -> bytes:
    """Encode sorted events (and triggers) as one self-contained byte stream."""
    return make_encoder(encoding, time_base_ns=time_base_ns).encode(events, triggers)


def quantize_to_us(events, *, time_base_ns: int = 0) -> np.ndarray:
    """Floor every event time to a whole microsecond after `time_base_ns` (a new array).

    The result is stably re-sorted by time, so it is ready for encode(). This is the explicit,
    lossy step the EVT encoders refuse to take on their own.
    """
    base = check_time_base(time_base_ns)
    out = np.array(as_events(events), copy=True)
    rel = out["t"] - np.int64(base)
    out["t"] = np.int64(base) + np.floor_divide(rel, 1000) * 1000
    return sort_events(out)
