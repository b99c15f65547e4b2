"""The one writer of the capture-session layout (DESIGN.md; read by :mod:`.layout`).

```
<session>/session.yaml    write_session_yaml(): built by session_document() (+ camera_record,
                          servo_record, view_record), checked by the reader's own schema
                          (layout.check_session) before it is written, so a document the
                          reader would refuse never lands
<session>/<view>/         ViewRecorder: one rosbag2 per view, the standard topics
                          (evdnerf_ros.topics):
    /event_camera/events        event_camera_msgs/msg/EventPacket: events() encodes events
                                (evt3 by default, with EXT_TRIGGER edges); event_packet()
                                takes an already serialised EventPacket (a camera's raw
                                bytes passed through untouched)
    /event_camera/triggers      EventPacket (evt3 EXT_TRIGGER words only): trigger_edges(), for a
                                camera whose encoding has no trigger events (libcaer)
    /event_camera/camera_info   sensor_msgs/msg/CameraInfo
    /rig/camera_pose            geometry_msgs/msg/PoseStamped: one (a static camera) or a
                                trajectory (a moving one)
    /rig/servo/joint_states     sensor_msgs/msg/JointState
    /rig/servo/trigger          sensor_msgs/msg/TimeReference: the firmware's START / DONE,
                                header.stamp = host time in the view's clock, time_ref = the
                                servo board's clock, source "rig_servo START" / "... DONE"
```

`evdnerf simulate` writes through this module; the capture node will. Every output is
atomic: a bag appears under its name only when its recorder closes without an error
(BagWriter), session.yaml through :func:`evdnerf_ros.atomic.atomic_output`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from .. import __version__
from ..atomic import atomic_output
from ..errors import InputError
from ..topics import CAMERA_INFO, CAMERA_POSE, EVENT_TRIGGERS, EVENTS, SERVO_JOINT_STATES, SERVO_TRIGGER
from .layout import SESSION_FORMAT, SESSION_FORMAT_VERSION, check_session, session_yaml_path

#: Message type of each standard topic.
MSGTYPES = {
    EVENTS: "event_camera_msgs/msg/EventPacket",
    EVENT_TRIGGERS: "event_camera_msgs/msg/EventPacket",
    CAMERA_INFO: "sensor_msgs/msg/CameraInfo",
    CAMERA_POSE: "geometry_msgs/msg/PoseStamped",
    SERVO_JOINT_STATES: "sensor_msgs/msg/JointState",
    SERVO_TRIGGER: "sensor_msgs/msg/TimeReference",
}
#: The camera's frame (CameraInfo, EventPacket) and the frame poses are given in.
CAMERA_FRAME = "event_camera"
WORLD_FRAME = "world"
#: TimeReference.source of the servo firmware's START / DONE lines: "rig_servo START".
SERVO_SOURCE = "rig_servo"
SERVO_EVENTS = ("START", "DONE")


class ViewRecorder:
    """One view's rosbag2 in the session layout; a context manager (the bag appears under
    its name on a clean exit, nothing on an error).

    ``width`` x ``height`` is the sensor size the event topic declares; ``encoding`` its
    EventPacket encoding (evt3 for Prophesee sensors and the simulator). Times are int64 ns
    in the view's own clock.
    """

    def __init__(self, path, *, width: int, height: int, encoding: str = "evt3",
                 storage: str = "mcap"):
        from ..io.rosbag2 import BagWriter

        self.path = Path(path)
        self.width, self.height, self.encoding = int(width), int(height), encoding
        self._bag = BagWriter(self.path, storage=storage)
        self._raw_checked = False
        self._events_written = False

    def __enter__(self) -> "ViewRecorder":
        self._bag.__enter__()
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None and not self._events_written:     # the event topic is there even when nothing came
            self._bag.add_topic(EVENTS, MSGTYPES[EVENTS])
        return self._bag.__exit__(exc_type, exc, tb)

    # ----- camera
    def camera_info(self, K, D=(0.0, 0.0, 0.0, 0.0, 0.0), *, stamp_ns: int,
                    distortion_model: str = "plumb_bob") -> None:
        """The sensor's intrinsics (3x3 K, distortion D) on the camera-info topic."""
        from ..io.messages import camera_info

        msg = camera_info(self.width, self.height, np.asarray(K, np.float64), D, frame_id=CAMERA_FRAME,
                          stamp_ns=stamp_ns, distortion_model=distortion_model)
        self._bag.write(CAMERA_INFO, MSGTYPES[CAMERA_INFO], msg, stamp_ns)

    def pose(self, T_world_cam, stamp_ns: int) -> None:
        """One camera pose (4x4, OpenCV axes, metres) at `stamp_ns`: a static camera writes
        one; a moving one writes its trajectory (:meth:`poses`)."""
        from ..io.messages import pose_stamped

        self._bag.write(CAMERA_POSE, MSGTYPES[CAMERA_POSE], pose_stamped(T_world_cam, stamp_ns, WORLD_FRAME),
                        stamp_ns)

    def poses(self, t_ns, T_world_cam) -> None:
        """A camera trajectory: poses (M, 4, 4) at increasing times (M,) int64 ns."""
        t = np.asarray(t_ns)
        Ts = np.asarray(T_world_cam, np.float64)
        if t.ndim != 1 or Ts.shape != (t.size, 4, 4):
            raise InputError(f"{self.path}: topic {CAMERA_POSE}: expected M times and M 4x4 poses, got "
                             f"shapes {t.shape} and {Ts.shape}")
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise InputError(f"{self.path}: topic {CAMERA_POSE}: pose times must increase")
        for stamp, T in zip(t.tolist(), Ts):
            self.pose(T, int(stamp))

    # ----- servo
    def servo_joint_state(self, names, positions, stamp_ns: int) -> None:
        """The servo's joint angle(s) in radians at `stamp_ns`."""
        from ..io.messages import joint_state

        self._bag.write(SERVO_JOINT_STATES, MSGTYPES[SERVO_JOINT_STATES],
                        joint_state(list(names), list(positions), stamp_ns=stamp_ns), stamp_ns)

    def servo_trigger(self, what: str, stamp_ns: int, device_ns: int) -> None:
        """The firmware's START or DONE line: received at host time `stamp_ns` (the view's
        clock), stamped `device_ns` by the servo board's own clock."""
        from ..io.messages import time_reference

        if what not in SERVO_EVENTS:
            raise InputError(f"{self.path}: topic {SERVO_TRIGGER}: {what!r} is not one of {SERVO_EVENTS}")
        self._bag.write(SERVO_TRIGGER, MSGTYPES[SERVO_TRIGGER],
                        time_reference(stamp_ns, device_ns, f"{SERVO_SOURCE} {what}"), stamp_ns)

    # ----- events
    def events(self, events, triggers=None) -> int:
        """Encode events (and EXT_TRIGGER edges, evt3/evt2 only) onto the event topic;
        successive calls continue in time. Returns the number of packets written."""
        self._events_written = True
        return self._bag.write_events(EVENTS, events, width=self.width, height=self.height,
                                      encoding=self.encoding,
                                      triggers=triggers if triggers is not None and len(triggers) else None)

    def raw_packet(self, payload, *, stamp_ns: int, time_base: int = 0) -> int:
        """A sensor's bytes in this view's encoding as one EventPacket, untouched (a camera
        driver's transfer: evt3 as metavision_driver records it, libcaer records as
        libcaer_driver publishes them)."""
        return self._bag.write_raw_packet(EVENTS, payload, encoding=self.encoding, width=self.width,
                                          height=self.height, stamp_ns=stamp_ns, time_base=time_base)

    def trigger_edges(self, triggers) -> int:
        """Trigger edges (TRIGGER_DTYPE, the view's clock, whole µs) on their own topic as evt3
        EXT_TRIGGER words: for an encoding without trigger events (libcaer)."""
        from ..events.types import empty_events

        return self._bag.write_events(EVENT_TRIGGERS, empty_events(), triggers=triggers, width=self.width,
                                      height=self.height, encoding="evt3")

    def event_packet(self, data, t_ns: int) -> None:
        """An already serialised (CDR) EventPacket, written untouched at bag time `t_ns`:
        a camera's raw bytes passed through. The first packet is decoded once to check that
        it is an EventPacket of this sensor's size and encoding."""
        data = bytes(data)
        if not self._raw_checked:
            what = f"{self.path}: topic {EVENTS}"
            try:
                msg = self._bag.typestore.deserialize_cdr(data, MSGTYPES[EVENTS])
            except Exception as exc:  # noqa: BLE001 - rosbags raises assorted errors on bad bytes
                raise InputError(f"{what}: the packet is not a serialised {MSGTYPES[EVENTS]} ({exc!r}); "
                                 "pass the CDR bytes of the camera driver's message") from None
            got = (int(msg.width), int(msg.height), str(msg.encoding))
            if got != (self.width, self.height, self.encoding):
                raise InputError(f"{what}: the packet is {got[0]}x{got[1]} {got[2]!r}, but this view "
                                 f"records {self.width}x{self.height} {self.encoding!r}; open the recorder "
                                 "with the camera's size and encoding")
            self._raw_checked = True
        self._events_written = True
        self._bag.write_raw(EVENTS, MSGTYPES[EVENTS], data, t_ns)


# =========================================================================== session.yaml


def camera_record(width: int, height: int, K, D=(0.0, 0.0, 0.0, 0.0, 0.0), *,
                  distortion_model: str = "plumb_bob") -> dict:
    """session.yaml's `camera` section: size, intrinsics and the standard topic names."""
    return {"width": int(width), "height": int(height), "K": np.asarray(K, np.float64).tolist(),
            "distortion_model": distortion_model, "D": [float(d) for d in D],
            "topics": {"events": EVENTS, "camera_info": CAMERA_INFO, "pose": CAMERA_POSE}}


def servo_record(joint: str, **extra) -> dict:
    """session.yaml's `servo` section: the joint's name, the servo topics, then `extra`
    (e.g. ``start_ns_scene``)."""
    return {"joint": joint, "joint_states": SERVO_JOINT_STATES, "trigger": SERVO_TRIGGER, **extra}


def view_record(name: str, split: str, T_world_cam, *, azimuth_deg: float | None = None,
                moving_arc_deg: float | None = None, bag: str | None = None, **extra) -> dict:
    """One entry of session.yaml's `views`: name, bag folder (default: the name), split,
    azimuth on the rig's ring, the arc a moving camera sweeps (None: static), pose, then
    `extra` (event counts, frames, ground truth, ...)."""
    return {"name": name, "bag": name if bag is None else bag, "split": split,
            "azimuth_deg": None if azimuth_deg is None else float(azimuth_deg),
            "moving_arc_deg": None if moving_arc_deg is None else float(moving_arc_deg),
            "T_world_cam": np.asarray(T_world_cam, np.float64).tolist(), **extra}


def session_document(*, source: dict, rig: dict, camera: dict, thresholds: dict, views: list,
                     servo: dict | None = None, **sections) -> dict:
    """A whole session.yaml: format header and software version, then the sections in the
    layout's order (`sections`, e.g. time / frames / options, go before `views`)."""
    return {"format": SESSION_FORMAT, "format_version": SESSION_FORMAT_VERSION,
            "software_version": __version__, "source": source, "rig": rig, "camera": camera,
            "servo": servo, "thresholds": thresholds, **sections, "views": views}


def write_session_yaml(root, data: dict, *, overwrite: bool = False) -> Path:
    """Write (or, with overwrite=True, atomically replace) ``<root>/session.yaml``.

    The document is dumped, read back and checked with the reader's schema
    (:func:`evdnerf_ros.session.layout.check_session`) first: a document the reader would
    refuse raises InputError naming the key at fault, and nothing is written."""
    root = Path(root)
    path = session_yaml_path(root)
    try:
        text = yaml.safe_dump(data, sort_keys=False)
        back = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not written: the document holds a value YAML cannot represent "
                         f"({' '.join(str(exc).split())}); convert numpy values with int() / float() / "
                         ".tolist()") from None
    try:
        check_session(root, back, path=path)
    except InputError as exc:
        raise InputError(f"{exc} (session.yaml not written)") from None
    with atomic_output(path, overwrite=overwrite) as tmp:
        tmp.write_text(text)
    return path
