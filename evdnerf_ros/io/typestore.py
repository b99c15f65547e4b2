"""rosbags typestores with the event-camera message types registered.

The .msg definitions ship with this package under ``evdnerf_ros/io/msg/``:

- ``<pkg>/msg/<Type>.msg``       ROS 2 flavour (``event_camera_msgs/msg/EventPacket``,
  ``dvs_msgs/msg/Event``, ``dvs_msgs/msg/EventArray``; Header without seq,
  ``builtin_interfaces/Time``);
- ``ros1/<pkg>/msg/<Type>.msg``  ROS 1 flavour (``dvs_msgs`` with ``time ts`` and a Header that
  carries ``seq``; ``event_camera_msgs/EventPacket``).

Both typestores are built once per process and cached; treat them as read-only.
"""

from __future__ import annotations

import functools
from importlib.resources import files

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

#: The shipped .msg files (a Traversable: works from a wheel, a zip or a source tree).
MSG_DIR = files(__package__) / "msg"

EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
#: EventPacket's name before event_camera_msgs (2023): the same fields in the same order, what every
#: metavision_driver / libcaer_driver bag recorded before the rename holds; read as EventPacket.
LEGACY_EVENT_PACKET = "event_array_msgs/msg/EventArray"
DVS_EVENT = "dvs_msgs/msg/Event"
DVS_EVENT_ARRAY = "dvs_msgs/msg/EventArray"

#: The message types this toolkit defines itself (the rest come with the rosbags stores).
OWN_TYPES = (EVENT_PACKET, DVS_EVENT, DVS_EVENT_ARRAY)


def _msg_files(root) -> dict[str, str]:
    """Map ``pkg/msg/Type`` -> .msg text for every ``<pkg>/msg/<Type>.msg`` directly under root."""
    found = {}
    for pkg in sorted(root.iterdir(), key=lambda p: p.name):
        sub = pkg / "msg"
        if not pkg.is_dir() or not sub.is_dir():
            continue
        for f in sorted(sub.iterdir(), key=lambda p: p.name):
            if f.name.endswith(".msg"):
                found[f"{pkg.name}/msg/{f.name[:-4]}"] = f.read_text(encoding="utf-8")
    return found


def _build(store: Stores, root) -> Typestore:
    ts = get_typestore(store)
    types = {}
    for name, text in _msg_files(root).items():
        types.update(get_types_from_msg(text, name))
    missing = [name for name in OWN_TYPES if name not in types]
    if missing:  # a broken installation, not a user error
        raise RuntimeError(f"{root}: message definitions {missing} are missing from the package data")
    ts.register(types)
    return ts


@functools.lru_cache(maxsize=None)
def ros2_typestore() -> Typestore:
    """ROS 2 Humble typestore plus EventPacket and dvs_msgs (ROS 2 flavour)."""
    return _build(Stores.ROS2_HUMBLE, MSG_DIR)


@functools.lru_cache(maxsize=None)
def ros1_typestore() -> Typestore:
    """ROS 1 Noetic typestore plus EventPacket and dvs_msgs (ROS 1 flavour)."""
    return _build(Stores.ROS1_NOETIC, MSG_DIR / "ros1")
