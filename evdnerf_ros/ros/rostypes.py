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
    types.update(_service_types(TYPE_DESCRIPTION_SERVICE, *_TYPE_DESCRIPTION_TEXTS))
    ts.register(types)
    return ts


#: The service every Jazzy node offers as ``~/get_type_description`` (REP 2011).
TYPE_DESCRIPTION_SERVICE = "type_description_interfaces/srv/GetTypeDescription"
_TYPE_DESCRIPTION_TEXTS = ("string type_name\nstring type_hash\nbool include_type_sources\n",
                           "bool successful\nstring failure_reason\n"
                           "type_description_interfaces/TypeDescription type_description\n"
                           "type_description_interfaces/TypeSource[] type_sources\n"
                           "type_description_interfaces/KeyValue[] extra_information\n")


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


#: type_description_interfaces/msg/FieldType ids (REP 2011): base types; +48 array, +96 bounded, +144 sequence
_FIELD_TYPE_IDS = {"nested": 1, "int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7,
                   "int64": 8, "uint64": 9, "float32": 10, "float64": 11, "char": 13, "wchar": 14, "bool": 15,
                   "byte": 16, "string": 17, "wstring": 18, "bounded_string": 21}


def type_description(typename: str) -> dict:
    """The REP 2011 type description of ``typename`` as a dict (``type_description`` and the sorted
    ``referenced_type_descriptions``): the JSON whose sha256 is its RIHS01 hash (:func:`type_hash`
    checks that it is)."""
    from rosbags.interfaces import Nodetype as N

    ts = typestore()
    if typename not in ts.fielddefs:
        raise InputError(f"type {typename!r} is not known; use a ROS 2 message type such as 'std_msgs/msg/String'")
    structs: dict[str, dict] = {}

    def field(name, node):
        kind, spec = node
        increment = capacity = string_capacity = 0
        if kind == N.ARRAY:
            increment, capacity, (kind, spec) = 48, spec[1], spec[0]
        elif kind == N.SEQUENCE:
            increment, capacity, (kind, spec) = (96, spec[1], spec[0]) if spec[1] else (144, 0, spec[0])
        nested = ""
        if kind == N.NAME:
            tid, nested = increment + 1, spec
            struct(spec)
        elif spec[0] == "string" and spec[1]:
            tid, string_capacity = increment + _FIELD_TYPE_IDS["bounded_string"], spec[1]
        else:
            tid = increment + _FIELD_TYPE_IDS[spec[0]]
        return {"name": name, "type": {"type_id": tid, "capacity": capacity, "string_capacity": string_capacity,
                                       "nested_type_name": nested}}

    def struct(name):
        if name not in structs:
            structs[name] = {}                  # placed first: the fields keep rosbags' order of discovery
            fields = ts.fielddefs[name][1] or [("structure_needs_at_least_one_member", (N.BASE, ("uint8", 0)))]
            structs[name] = {"type_name": name, "fields": [field(n, d) for n, d in fields]}
        return structs[name]

    main = struct(typename)
    return {"type_description": main,
            "referenced_type_descriptions": [d for n, d in sorted(structs.items()) if n != typename]}


def type_description_response(typename: str | None, failure: str):
    """A GetTypeDescription response: ``typename``'s description, or (None) unsuccessful with ``failure``."""
    ts = typestore()
    m = ts.types
    td = "type_description_interfaces/msg/"

    def individual(d):
        return m[td + "IndividualTypeDescription"](type_name=d["type_name"], fields=[
            m[td + "Field"](name=f["name"], type=m[td + "FieldType"](**f["type"]), default_value="")
            for f in d["fields"]])

    if typename is None:
        desc = m[td + "TypeDescription"](type_description=individual({"type_name": "", "fields": []}),
                                         referenced_type_descriptions=[])
    else:
        d = type_description(typename)
        desc = m[td + "TypeDescription"](type_description=individual(d["type_description"]),
                                         referenced_type_descriptions=[individual(r) for r in
                                                                       d["referenced_type_descriptions"]])
    return m[f"{TYPE_DESCRIPTION_SERVICE}_Response"](successful=typename is not None, failure_reason=failure,
                                                     type_description=desc, type_sources=[], extra_information=[])


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
