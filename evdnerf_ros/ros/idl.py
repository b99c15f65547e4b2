"""Cyclone DDS IDL types built from the rosbags typestore's message definitions.

``idl_type("pkg/msg/T")`` is an ``IdlStruct`` named ``pkg::msg::dds_::T_`` with ROS 2's
field layout, so the DDS topic carries the type name and structure ROS 2 nodes use. The
transport's fast path only needs it for the topic's type; the (slow) IdlStruct path also
(de)serialises samples with it, which is what the benchmark compares against.
"""

from __future__ import annotations

import functools

import numpy as np

from ..errors import InputError
from ..io.typestore import ros2_typestore
from .names import dds_type

_BASE = {"bool": bool, "byte": "uint8", "char": "uint8", "int8": "int8", "uint8": "uint8",
         "int16": "int16", "uint16": "uint16", "int32": "int32", "uint32": "uint32", "int64": "int64",
         "uint64": "uint64", "float32": "float32", "float64": "float64", "string": str}


def _field_type(node):
    import cyclonedds.idl.types as t
    from rosbags.interfaces import Nodetype

    kind, spec = node
    if kind == Nodetype.BASE:
        name, bound = spec
        if name not in _BASE:
            raise InputError(f"ROS base type {name!r} has no IDL mapping here")
        if name == "string" and bound:
            return t.bounded_str[bound]
        mapped = _BASE[name]
        return getattr(t, mapped) if isinstance(mapped, str) else mapped
    if kind == Nodetype.NAME:
        return idl_type(spec)
    if kind == Nodetype.ARRAY:
        elem, n = spec
        return t.array[_field_type(elem), n]
    if kind == Nodetype.SEQUENCE:
        elem, bound = spec
        return t.sequence[_field_type(elem), bound] if bound else t.sequence[_field_type(elem)]
    raise InputError(f"ROS field kind {kind} has no IDL mapping here")


@functools.lru_cache(maxsize=None)
def idl_type(msgtype: str):
    """The IdlStruct of a ROS 2 message type known to the toolkit's typestore."""
    from cyclonedds.idl import make_idl_struct

    ts = ros2_typestore()
    if msgtype not in ts.fielddefs:
        raise InputError(f"message type {msgtype!r} is not in the typestore; use e.g. "
                         "'event_camera_msgs/msg/EventPacket' or 'sensor_msgs/msg/CameraInfo'")
    _, fields = ts.fielddefs[msgtype]
    members = {name: _field_type(node) for name, node in fields}
    if not members:      # ROS 2 gives empty messages one dummy member
        import cyclonedds.idl.types as t
        members = {"structure_needs_at_least_one_member": t.uint8}
    return make_idl_struct(msgtype.split("/")[-1] + "_", dds_type(msgtype), members)


def to_idl(msg, msgtype: str):
    """rosbags message object -> IdlStruct sample (numpy arrays become lists)."""
    cls = idl_type(msgtype)
    ts = ros2_typestore()
    from rosbags.interfaces import Nodetype

    _, fields = ts.fielddefs[msgtype]
    kwargs = {}
    for name, (kind, spec) in fields:
        value = getattr(msg, name)
        if kind == Nodetype.NAME:
            value = to_idl(value, spec)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            ekind, espec = spec[0]
            if ekind == Nodetype.NAME:
                value = [to_idl(v, espec) for v in value]
            elif isinstance(value, np.ndarray):
                value = value.tolist()
            else:
                value = list(value)
        kwargs[name] = value
    return cls(**kwargs)
