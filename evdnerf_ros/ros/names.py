"""ROS 2 names: validation, namespaces, private ``~/`` names, remapping, DDS names.

Rules follow ROS 2's name design (http://design.ros2.org/articles/topic_and_service_names.html):
tokens of ``[A-Za-z0-9_]`` that do not start with a digit, separated by single ``/``; no
``__`` and no trailing ``/``. A relative name is resolved in the node's namespace, a
private name ``~`` / ``~/x`` in ``<namespace>/<node>``. The DDS topic of ROS topic
``/a/b`` is ``rt/a/b``; the DDS type of ``pkg/msg/T`` is ``pkg::msg::dds_::T_``.
"""

from __future__ import annotations

import re

from ..errors import InputError

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_NODE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _check_tokens(name: str, body: str, what: str) -> None:
    if body == "":
        return
    for tok in body.split("/"):
        if not _TOKEN.fullmatch(tok):
            raise InputError(f"{what} {name!r}: token {tok!r} is not valid (letters, digits and '_', "
                             "not starting with a digit, separated by single '/')")
    if "__" in body:
        raise InputError(f"{what} {name!r}: '__' is reserved in ROS names")


def validate_node_name(name: str) -> str:
    if not isinstance(name, str) or not _NODE.fullmatch(name) or "__" in name:
        raise InputError(f"node name {name!r}: use letters, digits and '_' (not starting with a digit, "
                         "no '__'), e.g. 'event_publisher'")
    return name


def validate_namespace(ns: str) -> str:
    """Absolute namespace without trailing '/' ('' or '/' -> '/')."""
    if not isinstance(ns, str):
        raise InputError(f"namespace {ns!r}: expected a string")
    if ns in ("", "/"):
        return "/"
    if not ns.startswith("/"):
        ns = "/" + ns
    if ns.endswith("/"):
        raise InputError(f"namespace {ns!r}: must not end with '/'")
    _check_tokens(ns, ns[1:], "namespace")
    return ns


def resolve_topic(name: str, namespace: str = "/", node: str | None = None) -> str:
    """Fully qualified topic name of `name` for a node `node` in `namespace`."""
    if not isinstance(name, str) or not name:
        raise InputError(f"topic name {name!r}: expected a non-empty string such as '/event_camera/events'")
    ns = validate_namespace(namespace)
    if name.startswith("~"):
        if node is None:
            raise InputError(f"topic name {name!r}: a private '~' name needs a node name")
        rest = name[1:]
        if rest and not rest.startswith("/"):
            raise InputError(f"topic name {name!r}: write private names as '~/name'")
        base = (ns.rstrip("/") + "/" + validate_node_name(node))
        full = base + rest
    elif name.startswith("/"):
        full = name
    else:
        full = ns.rstrip("/") + "/" + name
    if full.endswith("/") and full != "/":
        raise InputError(f"topic name {name!r}: must not end with '/'")
    if full == "/":
        raise InputError(f"topic name {name!r}: resolves to '/', which is not a topic")
    _check_tokens(name, full[1:], "topic name")
    return full


def apply_remaps(full: str, remaps: dict[str, str], namespace: str = "/", node: str | None = None) -> str:
    """Apply ``from:=to`` topic remaps (both sides resolved like topic names) to a resolved name."""
    for src, dst in remaps.items():
        if src.startswith("__"):
            continue
        if resolve_topic(src, namespace, node) == full:
            return resolve_topic(dst, namespace, node)
    return full


def dds_topic(full: str) -> str:
    """ROS topic ``/a/b`` -> DDS topic ``rt/a/b``."""
    if not full.startswith("/"):
        raise InputError(f"topic {full!r}: resolve it first (absolute name expected)")
    return "rt" + full


def dds_type(msgtype: str) -> str:
    """``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_``."""
    parts = msgtype.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise InputError(f"message type {msgtype!r}: expected 'pkg/msg/Type'")
    return f"{parts[0]}::msg::dds_::{parts[2]}_"
