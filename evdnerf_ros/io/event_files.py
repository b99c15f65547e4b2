"""One entry point to read and write events in every supported container, chosen by path.

| path                     | container                                              |
|--------------------------|--------------------------------------------------------|
| `*.raw`                  | OpenEB RAW (EVT 3.0 or EVT 2.0, told by its header)     |
| `*.npz`                  | numpy arrays t, x, y, p + width, height                 |
| `*.h5`, `*.hdf5`         | HDF5 events/{t,x,y,p} (see h5events.py)                |
| `*.txt`                  | text `t x y p` per line, read only (see text.py)       |
| `*.bin`                  | N-MNIST / N-Caltech101 ATIS, read only (atis_bin.py)   |
| `*.aedat4`               | AEDAT 4.0 (iniVation DV), read only (aedat4.py)        |
| `*.dat`                  | Prophesee DAT (CD events), read only (dat.py)          |
| `*.bag`                  | ROS 1 bag, dvs_msgs/EventArray                          |
| directory, `*.mcap`, `*.db3` | rosbag2 (MCAP or sqlite3), EventPacket or EventArray |

Times are int64 ns in every container and come back exactly; a RAW file carries sensor
microseconds after the origin in its `% t0` header line, so events at epoch times make files
as small as events at sensor times (see raw.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..topics import EVENTS
from ..events.types import empty_triggers

DEFAULT_TOPIC = EVENTS
BAG_ENCODINGS = ("evt3", "mono", "array")
RAW_ENCODINGS = ("evt3", "evt2")
#: containers read but never written, and what they are called in messages
READ_ONLY = {"text": "text event file", "atis": "N-MNIST-style .bin file", "aedat4": "AEDAT 4.0 file",
             "dat": "Prophesee DAT file"}


@dataclass
class EventFile:
    """Events read from any container, with the sensor geometry."""

    events: np.ndarray
    triggers: np.ndarray
    width: int
    height: int
    kind: str  # container kind: raw, npz, h5, rosbag1, rosbag2
    encoding: str | None = None
    topic: str | None = None
    anomalies: dict = field(default_factory=dict)   # tolerated time-word anomalies (RAW EVT 3.0)


def container_kind(path) -> str:
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".raw":
        return "raw"
    if suffix == ".npz":
        return "npz"
    if suffix in (".h5", ".hdf5"):
        return "h5"
    if suffix == ".txt":
        return "text"
    if suffix == ".bin":
        return "atis"
    if suffix == ".aedat4":
        return "aedat4"
    if suffix == ".dat":
        return "dat"
    if suffix == ".bag":
        return "rosbag1"
    if suffix in (".mcap", ".db3") or suffix == "" or path.is_dir():
        return "rosbag2"
    raise InputError(f"{path}: unknown event file type {suffix!r}; use .raw, .npz, .h5, .txt, .bin, .aedat4, .dat, .bag, "
                     ".mcap, .db3 or a rosbag2 directory")


def read_event_file(path, *, topic: str | None = None, need_geometry: bool = True,
                    geometry: tuple[int, int] | None = None, time_unit: str | None = None,
                    strict: bool = False) -> EventFile:
    """Read any container (see the module doc). A RAW file whose header gives no geometry (and
    no plugin_name it follows from), or an HDF5 file without width / height attributes, takes
    `geometry` (W, H, the CLI's --geometry WxH); without it, such a RAW file is refused unless
    `need_geometry` is False (width / height are then None). An HDF5 file whose times do not
    say their unit takes `time_unit` (the CLI's --time-unit; see h5events.py). A RAW file cut
    inside its last word reads its complete words with a warning; `strict` (--strict) refuses it."""
    path = Path(path)
    kind = container_kind(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if kind != "rosbag2" and kind != "rosbag1" and topic is not None:
        raise InputError(f"{path}: --topic applies only to bags, not to {kind} files")
    if time_unit is not None and kind not in ("h5", "text"):
        raise InputError(f"{path}: --time-unit applies only to HDF5 and text files (a {kind} file carries its "
                         "own unit)")
    if kind in ("raw", "npz", "h5") and path.is_dir():
        raise InputError(f"{path}: is a folder, not a {kind} file")
    if kind == "raw":
        from .raw import read_raw, read_raw_header

        header = read_raw_header(path)          # refuse a header without geometry before decoding
        if (header.width is None or header.height is None) and geometry is None and need_geometry:
            raise FormatError("the RAW header gives no sensor geometry; give it with --geometry WxH "
                              "(or add a header line '% geometry WIDTHxHEIGHT' before '% end')",
                              source=str(path))
        decoded, header = read_raw(path, strict=strict)
        if geometry is not None and (header.width is None or header.height is None):
            header = replace(header, width=int(geometry[0]), height=int(geometry[1]))
        ev = decoded.events
        known = header.width is not None and header.height is not None
        if known and ev.size and (int(ev["x"].max()) >= header.width or int(ev["y"].max()) >= header.height):
            i = int(np.flatnonzero((ev["x"] >= header.width) | (ev["y"] >= header.height))[0])
            raise FormatError(f"event {i} at x={int(ev['x'][i])}, y={int(ev['y'][i])} lies outside the "
                              f"header's {header.width}x{header.height} geometry; the file is damaged or its "
                              "header is wrong", source=str(path))
        return EventFile(ev, decoded.triggers, header.width, header.height, kind, header.encoding,
                         anomalies=decoded.anomalies)
    if kind == "npz":
        from .npz import read_npz

        return EventFile(*read_npz(path), kind)
    if kind == "h5":
        from .h5events import read_h5

        return EventFile(*read_h5(path, time_unit=time_unit, geometry=geometry), kind)
    if kind in READ_ONLY:
        triggers = empty_triggers()
        if kind == "aedat4":
            from .aedat4 import read_aedat4

            events, triggers, width, height, _ = read_aedat4(path)
        elif kind == "dat":
            from .dat import read_dat

            events, width, height = read_dat(path, geometry=geometry, strict=strict)
        elif kind == "text":
            from .text import read_text

            events, width, height = read_text(path, time_unit=time_unit, geometry=geometry)
        else:
            from .atis_bin import read_atis_bin

            events, width, height = read_atis_bin(path, geometry=geometry)
        if width is None and need_geometry:
            raise InputError(f"{path}: a {READ_ONLY[kind]} gives no sensor size; give it with --geometry WxH")
        return EventFile(events, triggers, width, height, kind)
    from .bag_reader import pick_event_topic, read_events

    stream = read_events(path, topic=pick_event_topic(path, topic))
    triggers = stream.triggers if stream.triggers is not None else empty_triggers()
    return EventFile(stream.events, triggers, stream.width, stream.height, kind,
                     stream.encoding, stream.topic)


def write_event_file(path, data: EventFile, *, encoding: str | None = None,
                     topic: str | None = None, storage: str | None = None) -> str:
    """Write `data` to `path` (container from the path); returns the encoding used."""
    path = Path(path)
    kind = container_kind(path)
    if kind in READ_ONLY:
        raise InputError(f"{path}: {READ_ONLY[kind]}s are read only; write .npz, .h5, .raw or a bag")
    if kind in ("raw", "rosbag1", "rosbag2") and encoding is None:
        encoding = {"raw": "evt3", "rosbag1": "array", "rosbag2": "evt3"}[kind]
    allowed = {"raw": RAW_ENCODINGS, "rosbag1": ("array",), "rosbag2": BAG_ENCODINGS}.get(kind)
    if encoding is not None and allowed is None:
        raise InputError(f"{path}: --encoding does not apply to {kind} files")
    if allowed is not None and encoding not in allowed:
        raise InputError(f"{path}: encoding {encoding!r} is not available for {kind} output; "
                         f"choose one of {', '.join(allowed)}")
    if topic is not None and kind not in ("rosbag1", "rosbag2"):
        raise InputError(f"{path}: --topic applies only to bag outputs")
    topic = topic or DEFAULT_TOPIC
    triggers = data.triggers if len(data.triggers) else None
    if kind == "raw":
        from .raw import write_raw

        write_raw(path, data.events, width=data.width, height=data.height, encoding=encoding,
                  triggers=triggers)
    elif kind == "npz":
        from .npz import write_npz

        write_npz(path, data.events, data.width, data.height, data.triggers)
    elif kind == "h5":
        from .h5events import write_h5

        write_h5(path, data.events, data.width, data.height, data.triggers)
    elif kind == "rosbag1":
        from .rosbag1 import write_events_rosbag1

        _refuse_dropped_triggers(path, triggers, encoding)
        write_events_rosbag1(path, data.events, width=data.width, height=data.height, topic=topic)
    else:
        from .rosbag2 import BagWriter

        _refuse_dropped_triggers(path, triggers, encoding)
        if storage is None:
            storage = "sqlite3" if path.suffix.lower() == ".db3" else "mcap"
        with BagWriter(path, storage=storage) as bag:
            bag.write_events(topic, data.events, width=data.width, height=data.height,
                             encoding=encoding, triggers=triggers)
    return encoding


def _refuse_dropped_triggers(path, triggers, encoding) -> None:
    if triggers is not None and encoding != "evt3":
        raise InputError(f"{path}: the input has {len(triggers)} trigger events, which only the "
                         "evt3 encoding carries; use --encoding evt3 (rosbag2) so none are lost")
