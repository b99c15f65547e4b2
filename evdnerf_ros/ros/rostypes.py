"""ROS 2 (Jazzy) interface types for the graph, parameter, log, tf and clock topics:
serialisation, RIHS01 type hashes and Cyclone IDL types.

The toolkit's main typestore is Humble's (bags); the graph needs Iron-and-later layouts
(``rmw_dds_common/msg/Gid`` is 16 bytes since Iron, 24 before), so this module keeps a
Jazzy typestore with the toolkit's own event types and the ``rcl_interfaces`` services
registered as ``pkg/srv/S_Request`` / ``_Response`` (plus ``_Event`` and the service
struct itself, which is what the service's RIHS01 hash covers, REP 2011).

RIHS01 (REP 2011): sha256 over the JSON type description, computed by rosbags'
``hash_rihs01``. Checked against published values: ``std_msgs/msg/String`` ->
``RIHS01_df668c74...``, ``example_interfaces/srv/AddTwoInts`` -> ``RIHS01_e118de6b...``
(the latter needs ``service_msgs/msg/ServiceEventInfo.client_gid`` as ``uint8[16]``; rosbags'
store has ``char[16]``, corrected here).
"""

from __future__ import annotations

import functools

from ..errors import InputError

#: rcl_interfaces services: name -> (request .msg text, response .msg text)
RCL_SERVICES = {
    "GetParameters": ("string[] names\n", "rcl_interfaces/ParameterValue[] values\n"),
    "SetParameters": ("rcl_interfaces/Parameter[] parameters\n", "rcl_interfaces/SetParametersResult[] results\n"),
    "SetParametersAtomically": ("rcl_interfaces/Parameter[] parameters\n",
                                "rcl_interfaces/SetParametersResult result\n"),
    "ListParameters": ("uint64 DEPTH_RECURSIVE=0\nstring[] prefixes\nuint64 depth\n",
                       "rcl_interfaces/ListParametersResult result\n"),
    "DescribeParameters": ("string[] names\n", "rcl_interfaces/ParameterDescriptor[] descriptors\n"),
    "GetParameterTypes": ("string[] names\n", "uint8[] types\n"),
}


def _service_types(srv: str, req: str, rep: str) -> dict:
    from rosbags.interfaces import Nodetype as N
    from rosbags.typesys import get_types_from_msg

    pkg = srv.split("/")[0]
    out = {}
    for suffix, text in (("Request", req), ("Response", rep)):
        tmp = f"{pkg}/msg/Srv_{suffix}_tmp"
        out[f"{srv}_{suffix}"] = get_types_from_msg(text, tmp)[tmp]
    out[f"{srv}_Event"] = ([], [("info", (N.NAME, "service_msgs/msg/ServiceEventInfo")),
                                ("request", (N.SEQUENCE, ((N.NAME, f"{srv}_Request"), 1))),
                                ("response", (N.SEQUENCE, ((N.NAME, f"{srv}_Response"), 1)))])
    out[srv] = ([], [("request_message", (N.NAME, f"{srv}_Request")),
                     ("response_message", (N.NAME, f"{srv}_Response")),
                     ("event_message", (N.NAME, f"{srv}_Event"))])
    return out


@functools.lru_cache(maxsize=None)
def typestore():
    """Jazzy typestore + the toolkit's event messages + rcl_interfaces services."""
    from rosbags.interfaces import Nodetype as N
    from rosbags.typesys import Stores

    from ..io.typestore import MSG_DIR, _build

    ts = _build(Stores.ROS2_JAZZY, MSG_DIR)
    consts, fields = ts.fielddefs["service_msgs/msg/ServiceEventInfo"]
    ts.fielddefs["service_msgs/msg/ServiceEventInfo"] = (consts, [
        (n, (N.ARRAY, ((N.BASE, ("uint8", 0)), 16))) if n == "client_gid" else (n, d) for n, d in fields])
    types = {}
    for name, (req, rep) in RCL_SERVICES.items():
        types.update(_service_types(f"rcl_interfaces/srv/{name}", req, rep))
    ts.register(types)
    return ts


def register_service(srv: str, request: str, response: str) -> None:
    """Register another service ``pkg/srv/Name`` from its request / response .msg texts."""
    typestore().register(_service_types(srv, request, response))


@functools.lru_cache(maxsize=None)
def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex>`` of a message (``pkg/msg/T``) or service (``pkg/srv/S``) type."""
    ts = typestore()
    if typename not in ts.fielddefs:
        raise InputError(f"type {typename!r} is not known; use a ROS 2 message type such as 'std_msgs/msg/String'")
    return ts.hash_rihs01(typename)


def dds_type_name(typename: str) -> str:
    """``pkg/msg/T`` -> ``pkg::msg::dds_::T_``; ``pkg/srv/S_Request`` -> ``pkg::srv::dds_::S_Request_``."""
    parts = typename.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv") or not all(parts):
        raise InputError(f"type {typename!r}: expected 'pkg/msg/Type' or 'pkg/srv/Service_Request'")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def serialize(msg, typename: str) -> bytes:
    return bytes(typestore().serialize_cdr(msg, typename))


def deserialize(data, typename: str):
    return typestore().deserialize_cdr(data, typename)


def message(typename: str, **fields):
    """A message object of `typename` (every field must be given, as rosbags requires)."""
    return typestore().types[typename](**fields)


_BASE = {"bool": "bool", "byte": "uint8", "char": "uint8", "int8": "int8", "uint8": "uint8", "int16": "int16",
         "uint16": "uint16", "int32": "int32", "uint32": "uint32", "int64": "int64", "uint64": "uint64",
         "float32": "float32", "float64": "float64", "string": "str"}


def _idl_field(node):
    import cyclonedds.idl.types as t
    from rosbags.interfaces import Nodetype as N

    kind, spec = node
    if kind == N.BASE:
        name, bound = spec
        if name == "string":
            return t.bounded_str[bound] if bound else str
        if name == "bool":
            return bool
        return getattr(t, _BASE[name])
    if kind == N.NAME:
        return idl_struct(spec)
    if kind == N.ARRAY:
        return t.array[_idl_field(spec[0]), spec[1]]
    elem, bound = spec
    return t.sequence[_idl_field(elem), bound] if bound else t.sequence[_idl_field(elem)]


@functools.lru_cache(maxsize=None)
def idl_struct(typename: str, request_header: bool = False):
    """Cyclone IdlStruct with ROS 2's type name and layout. ``request_header`` prepends
    rmw_cyclonedds' service header (``uint64 guid; int64 seq``) as the first members, which
    is how that middleware lays out requests and replies on the wire."""
    import cyclonedds.idl.types as t
    from cyclonedds.idl import make_idl_struct

    ts = typestore()
    if typename not in ts.fielddefs:
        raise InputError(f"type {typename!r} is not in the typestore")
    members = {}
    if request_header:
        members["cdds_request_header_guid"] = t.uint64
        members["cdds_request_header_seq"] = t.int64
    for name, node in ts.fielddefs[typename][1]:
        members[name] = _idl_field(node)
    if not members:
        members["structure_needs_at_least_one_member"] = t.uint8
    return make_idl_struct(typename.split("/")[-1] + "_", dds_type_name(typename), members)
