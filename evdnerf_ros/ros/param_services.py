"""A node's standard services over Cyclone DDS: the ROS 2 parameter services (rcl_interfaces),
``/parameter_events`` and ``~/get_type_description`` (type_description_interfaces, REP 2011).

Services of node ``/ns/name`` (what ``ros2 param`` calls): ``get_parameters``,
``set_parameters``, ``set_parameters_atomically``, ``list_parameters``,
``describe_parameters``, ``get_parameter_types``; and, as every Jazzy rclcpp / rclpy node,
``get_type_description``: the type description of any message or service type in the node's
typestore whose RIHS01 hash matches the one asked for (no type sources: the node holds no .msg
files). Service ``/ns/name/S`` is the DDS
request topic ``rq/ns/name/SRequest`` (type ``rcl_interfaces::srv::dds_::S_Request_``)
and the reply topic ``rr/ns/name/SReply`` (``..._Response_``), QoS as rclcpp's parameter
services (reliable, volatile, keep-last 1000).

Wire convention: rmw_cyclonedds' — each request and reply payload starts, after the CDR
encapsulation header, with ``uint64 client guid; int64 sequence number``; the reply
echoes the request's pair, which is how the client matches it. (rmw_fastrtps instead
carries the request identity in the RTPS inline QoS ``related_sample_identity``; the
Cyclone binding cannot write that, so ``ros2 param`` reaches these services through
rmw_cyclonedds_cpp, not rmw_fastrtps_cpp: services do not work across the two
middlewares in ROS 2 either.)

Semantics as rclcpp: a set with a value of another type than the parameter's (an
integer for a double included) is refused with the reason, as are undeclared,
read-only and out-of-range values; ``set_parameters`` decides each value on its own,
``set_parameters_atomically`` applies all or none. Only parameters declared ``dynamic``
change while the node runs; each applied change is published on ``/parameter_events``
(reliable, volatile, keep-last 1000), as is the initial set of values (``new_parameters``).
A request that does not decode is logged and ignored; the service keeps running.
"""

from __future__ import annotations

import struct
import threading
import time

import numpy as np

from ..errors import InputError
from . import rostypes
from .qos import PROFILES

EVENTS_TOPIC = "/parameter_events"
EVENT_TYPE = "rcl_interfaces/msg/ParameterEvent"
#: short name -> service type
SERVICES = {
    "get_parameters": "rcl_interfaces/srv/GetParameters",
    "set_parameters": "rcl_interfaces/srv/SetParameters",
    "set_parameters_atomically": "rcl_interfaces/srv/SetParametersAtomically",
    "list_parameters": "rcl_interfaces/srv/ListParameters",
    "describe_parameters": "rcl_interfaces/srv/DescribeParameters",
    "get_parameter_types": "rcl_interfaces/srv/GetParameterTypes",
    "get_type_description": rostypes.TYPE_DESCRIPTION_SERVICE,
}
#: rcl_interfaces/msg/ParameterType
NOT_SET, BOOL, INTEGER, DOUBLE, STRING, BYTE_ARRAY, BOOL_ARRAY, INTEGER_ARRAY, DOUBLE_ARRAY, STRING_ARRAY = range(10)
TYPE_NAMES = ["not set", "bool", "integer", "double", "string", "byte array", "bool array", "integer array",
              "double array", "string array"]
_HEADER = struct.Struct("<Qq")
INT64_MAX = 2**63 - 1


def _msg(_type, **kw):
    return rostypes.message(f"rcl_interfaces/msg/{_type}", **kw)


def to_parameter_value(value, ros_type: int | None = None):
    """Python value -> rcl_interfaces/msg/ParameterValue (arrays as numpy where ROS has numbers)."""
    if ros_type is None:
        ros_type = ({bool: BOOL, int: INTEGER, float: DOUBLE, str: STRING}.get(type(value))
                    or (STRING_ARRAY if any(isinstance(v, str) for v in value) else DOUBLE_ARRAY))
    kw = dict(type=ros_type, bool_value=False, integer_value=0, double_value=0.0, string_value="",
              byte_array_value=np.zeros(0, np.uint8), bool_array_value=np.zeros(0, bool),
              integer_array_value=np.zeros(0, np.int64), double_array_value=np.zeros(0, np.float64),
              string_array_value=[])
    field = {BOOL: "bool_value", INTEGER: "integer_value", DOUBLE: "double_value", STRING: "string_value",
             BOOL_ARRAY: "bool_array_value", INTEGER_ARRAY: "integer_array_value",
             DOUBLE_ARRAY: "double_array_value", STRING_ARRAY: "string_array_value"}.get(ros_type)
    if field is not None:
        if ros_type == INTEGER_ARRAY:
            value = np.asarray(value, np.int64)
        elif ros_type == DOUBLE_ARRAY:
            value = np.asarray(value, np.float64)
        elif ros_type == BOOL_ARRAY:
            value = np.asarray(value, bool)
        elif ros_type == STRING_ARRAY:
            value = [str(v) for v in value]
        kw[field] = value
    return _msg("ParameterValue", **kw)


def from_parameter_value(pv):
    """rcl_interfaces/msg/ParameterValue -> (ros type, Python value)."""
    t = int(pv.type)
    if t == BOOL:
        return t, bool(pv.bool_value)
    if t == INTEGER:
        return t, int(pv.integer_value)
    if t == DOUBLE:
        return t, float(pv.double_value)
    if t == STRING:
        return t, str(pv.string_value)
    if t == BYTE_ARRAY:
        return t, [int(v) for v in pv.byte_array_value]
    if t == BOOL_ARRAY:
        return t, [bool(v) for v in pv.bool_array_value]
    if t == INTEGER_ARRAY:
        return t, [int(v) for v in pv.integer_array_value]
    if t == DOUBLE_ARRAY:
        return t, [float(v) for v in pv.double_array_value]
    if t == STRING_ARRAY:
        return t, [str(v) for v in pv.string_array_value]
    if t == NOT_SET:
        return t, None
    raise InputError(f"parameter value type {t} is not a rcl_interfaces/msg/ParameterType")


def _result(reason):
    return _msg("SetParametersResult", successful=reason is None, reason=reason or "")


def split_request(data: bytes) -> tuple[int, int, bytes]:
    """rmw_cyclonedds request/reply payload -> (client guid, sequence number, plain CDR of the body)."""
    data = bytes(data)
    if len(data) < 20 or data[0] != 0 or data[1] not in (0, 1):
        raise InputError(f"{len(data)} bytes do not start with an XCDR1 header and the 16-byte request header")
    fmt = "<Qq" if data[1] == 1 else ">Qq"
    guid, seq = struct.unpack_from(fmt, data, 4)
    return guid, seq, data[:4] + data[20:]


def join_reply(guid: int, seq: int, cdr: bytes) -> bytes:
    """Plain little-endian CDR of a reply -> rmw_cyclonedds payload with the request's header."""
    cdr = bytes(cdr)
    return cdr[:4] + _HEADER.pack(guid, seq) + cdr[4:]


class ParameterServer:
    """Serves the node's parameters over DDS in a background thread."""

    def __init__(self, node, *, poll_s: float = 0.05):
        from cyclonedds.core import WaitSet

        from .transport import DdsPublisher, DdsSubscription

        self.node = node
        self.params = node.params
        self.fqn = node.fully_qualified_name
        self._log = node.logger.log
        ctx = node.dds
        qos = PROFILES["parameters"]
        self.events = DdsPublisher(ctx, EVENTS_TOPIC, EVENT_TYPE, qos)
        self._services = []
        self._waitset = WaitSet(ctx.participant)
        base = self.fqn
        for short, stype in SERVICES.items():
            thash = rostypes.type_hash(stype)
            full = f"{base}/{short}"
            req = DdsSubscription(ctx, full, stype + "_Request", qos, dds_name=f"rq{full}Request",
                                  idl=rostypes.idl_struct(stype + "_Request", True), type_hash=thash,
                                  log=self._log)
            rep = DdsPublisher(ctx, full, stype + "_Response", qos, dds_name=f"rr{full}Reply",
                               idl=rostypes.idl_struct(stype + "_Response", True), type_hash=thash, log=self._log)
            self._waitset.attach(req._cond)
            self._services.append((short, stype, req, rep))
        self.requests = 0
        self.malformed = 0
        self._stop = threading.Event()
        self.publish_event(new=self.params.as_dict())
        self._thread = threading.Thread(target=self._loop, args=(poll_s,), name=f"{node.name}-parameters",
                                        daemon=True)
        self._thread.start()

    # ----- events
    def publish_event(self, *, new=None, changed=None) -> None:
        specs = {s.name: s for s in self.params.specs()}

        def plist(d):
            return [_msg("Parameter", name=k, value=to_parameter_value(v, specs[k].ros_type)) for k, v in (d or {}).items()]

        sec, nsec = divmod(self.node.now_ns(), 1_000_000_000)
        ev = _msg("ParameterEvent", stamp=rostypes.message("builtin_interfaces/msg/Time", sec=sec, nanosec=nsec),
                  node=self.fqn, new_parameters=plist(new), changed_parameters=plist(changed), deleted_parameters=[])
        self.events.publish_raw(rostypes.serialize(ev, EVENT_TYPE))

    # ----- serving
    def _loop(self, poll_s: float) -> None:
        from cyclonedds.util import duration

        while not self._stop.is_set():
            try:
                self._waitset.wait(duration(seconds=poll_s))
            except Exception:  # noqa: BLE001 - closed under us on shutdown
                return
            if self._stop.is_set():
                return
            self.spin_once()

    def spin_once(self) -> int:
        """Answer every pending request; returns how many were answered."""
        done = 0
        for short, stype, req, rep in self._services:
            try:
                samples = req.take_raw(64)
            except Exception as exc:  # noqa: BLE001
                self._log("warn", f"{req.topic}: take failed ({exc})")
                continue
            for data, _ in samples:
                self.requests += 1
                try:
                    guid, seq, body = split_request(data)
                    request = rostypes.deserialize(body, f"{stype}_Request")
                    response = getattr(self, "_" + short)(request)
                    out = rostypes.serialize(response, f"{stype}_Response")
                except Exception as exc:  # noqa: BLE001 - bytes from the network: log, ignore, keep serving
                    self.malformed += 1
                    self._log("warn", f"service {req.topic}: ignored a malformed request ({len(bytes(data))} bytes: "
                                      f"{exc.__class__.__name__}: {exc})")
                    continue
                rep.publish_raw(join_reply(guid, seq, out))
                done += 1
        return done

    def _values(self):
        return self.params.as_dict()

    def _get_parameters(self, req):
        values, specs = self._values(), {s.name: s for s in self.params.specs()}
        return rostypes.message("rcl_interfaces/srv/GetParameters_Response", values=[
            to_parameter_value(values[n], specs[n].ros_type) if n in specs else to_parameter_value(None, NOT_SET)
            for n in req.names])

    def _get_parameter_types(self, req):
        specs = {s.name: s for s in self.params.specs()}
        return rostypes.message("rcl_interfaces/srv/GetParameterTypes_Response", types=np.asarray(
            [specs[n].ros_type if n in specs else NOT_SET for n in req.names], np.uint8))

    def _describe_parameters(self, req):
        specs = {s.name: s for s in self.params.specs()}
        out = []
        for n in req.names:
            s = specs.get(n)
            if s is None:
                out.append(_msg("ParameterDescriptor", name=n, type=NOT_SET, description="", additional_constraints="",
                                read_only=False, dynamic_typing=False, floating_point_range=[], integer_range=[]))
                continue
            fr, ir = [], []
            if s.min is not None or s.max is not None:
                if s.kind is float:
                    fr = [_msg("FloatingPointRange", from_value=float("-inf") if s.min is None else float(s.min),
                               to_value=float("inf") if s.max is None else float(s.max), step=0.0)]
                elif s.kind is int:
                    ir = [_msg("IntegerRange", from_value=-INT64_MAX - 1 if s.min is None else int(s.min),
                               to_value=INT64_MAX if s.max is None else int(s.max), step=0)]
            constraints = f"one of {list(s.choices)}" if s.choices else ""
            if not s.dynamic and not s.read_only:
                constraints = (constraints + "; " if constraints else "") + "set at start-up only"
            out.append(_msg("ParameterDescriptor", name=n, type=s.ros_type, description=s.description,
                            additional_constraints=constraints, read_only=bool(s.read_only or not s.dynamic),
                            dynamic_typing=False, floating_point_range=fr, integer_range=ir))
        return rostypes.message("rcl_interfaces/srv/DescribeParameters_Response", descriptors=out)

    def _list_parameters(self, req):
        depth = int(req.depth)
        prefixes = list(req.prefixes)
        names = []
        for n in self.params.as_dict():
            if prefixes:
                ok = any(n == p or (n.startswith(p + ".") and (depth == 0 or n.count(".") - p.count(".") <= depth))
                         for p in prefixes)
            else:
                ok = depth == 0 or n.count(".") < depth
            if ok:
                names.append(n)
        pre = sorted({n.rsplit(".", 1)[0] for n in names if "." in n})
        return rostypes.message("rcl_interfaces/srv/ListParameters_Response",
                                result=_msg("ListParametersResult", names=names, prefixes=pre))

    def _checked_values(self, parameters):
        """[(name, python value or None, reason or None)] with ROS 2's strict type check."""
        specs = {s.name: s for s in self.params.specs()}
        out = []
        for p in parameters:
            name = str(p.name)
            t, value = from_parameter_value(p.value)
            spec = specs.get(name)
            if spec is None:
                out.append((name, None, f"parameter {name!r} cannot be set because it was not declared"))
            elif t == NOT_SET:
                out.append((name, None, f"parameter {name!r}: cannot undeclare a statically typed parameter"))
            elif t != spec.ros_type and not (spec.kind is list and t in (INTEGER_ARRAY, DOUBLE_ARRAY, STRING_ARRAY,
                                                                        BOOL_ARRAY)):
                out.append((name, None, f"Wrong parameter type, parameter {{{name}}} is of type "
                                        f"{{{TYPE_NAMES[spec.ros_type]}}}, setting it to {{{TYPE_NAMES[t]}}} is not "
                                        "allowed."))
            else:
                out.append((name, value, None))
        return out

    def _apply(self, parameters, atomically: bool):
        checked = self._checked_values(parameters)
        pending = [(n, v) for n, v, r in checked if r is None]
        source = "parameter service"
        if atomically:
            bad = next((r for _, _, r in checked if r), None)
            if bad is not None:
                self._log("warn", f"set_parameters_atomically refused: {bad}")
                return [bad]
            reasons = self.params.set_runtime(pending, source, atomically=True)
            reason = next((r for r in reasons if r), None)
            if reason is None and pending:
                self.publish_event(changed={n: self.params[n] for n, _ in pending})
            return [reason]
        reasons = iter(self.params.set_runtime(pending, source) if pending else [])
        results, changed = [], {}
        for n, _, r in checked:
            if r is None:
                r = next(reasons)
                if r is None:
                    changed[n] = self.params[n]
            results.append(r)
        for r in results:
            if r:
                self._log("warn", f"set_parameters refused: {r}")
        if changed:
            self._log("info", f"parameters set: {changed}")
            self.publish_event(changed=changed)
        return results

    def _set_parameters(self, req):
        return rostypes.message("rcl_interfaces/srv/SetParameters_Response",
                                results=[_result(r) for r in self._apply(req.parameters, False)])

    def _set_parameters_atomically(self, req):
        return rostypes.message("rcl_interfaces/srv/SetParametersAtomically_Response",
                                result=_result(self._apply(req.parameters, True)[0]))

    def _get_type_description(self, req):
        name, want = str(req.type_name), str(req.type_hash)
        try:
            have = rostypes.type_hash(name)
        except InputError:
            return rostypes.type_description_response(None, f"type {name!r} is not known to this node")
        if want and want != have:
            return rostypes.type_description_response(None, f"type {name!r}: hash {want} asked for, this node "
                                                            f"has {have}")
        return rostypes.type_description_response(name, "")

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(2.0)


class ParameterClient:
    """A client of another node's parameter services (rmw_cyclonedds conventions): what
    ``ros2 param`` does, for tests, benchmarks and scripts."""

    def __init__(self, ctx, node_fqn: str, *, client_id: int | None = None):
        import os

        from .transport import DdsPublisher, DdsSubscription

        qos = PROFILES["parameters"]
        self.ctx = ctx
        self.guid = client_id if client_id is not None else (os.getpid() << 20) ^ id(self) & 0xFFFFFFFFFFFF
        self._seq = 0
        self._ep = {}
        for short, stype in SERVICES.items():
            full = f"{node_fqn}/{short}"
            thash = rostypes.type_hash(stype)
            req = DdsPublisher(ctx, full, stype + "_Request", qos, dds_name=f"rq{full}Request",
                               idl=rostypes.idl_struct(stype + "_Request", True), type_hash=thash)
            rep = DdsSubscription(ctx, full, stype + "_Response", qos, dds_name=f"rr{full}Reply",
                                  idl=rostypes.idl_struct(stype + "_Response", True), type_hash=thash)
            self._ep[short] = (stype, req, rep)

    def wait_for_service(self, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(req.matched() and rep.matched() for _, req, rep in self._ep.values()):
                return True
            time.sleep(0.01)
        return False

    def call(self, short: str, timeout_s: float = 5.0, **fields):
        stype, req, rep = self._ep[short]
        self._seq += 1
        seq = self._seq
        body = rostypes.serialize(rostypes.message(f"{stype}_Request", **fields), f"{stype}_Request")
        req.publish_raw(join_reply(self.guid, seq, body))
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            rep.wait(0.05)
            for data, _ in rep.take_raw(64):
                guid, s, cdr = split_request(data)
                if guid == self.guid and s == seq:
                    return rostypes.deserialize(cdr, f"{stype}_Response")
        raise InputError(f"service {req.topic}: no reply within {timeout_s} s; is the node running on this domain?")

    # what `ros2 param get/set/list/describe` does
    def get(self, *names):
        return [from_parameter_value(v)[1] for v in self.call("get_parameters", names=list(names)).values]

    def set(self, atomically: bool = False, **values):
        params = [_msg("Parameter", name=k, value=to_parameter_value(v)) for k, v in values.items()]
        if atomically:
            r = self.call("set_parameters_atomically", parameters=params).result
            return [(bool(r.successful), str(r.reason))]
        return [(bool(r.successful), str(r.reason)) for r in self.call("set_parameters", parameters=params).results]

    def set_typed(self, name: str, value, ros_type: int):
        params = [_msg("Parameter", name=name, value=to_parameter_value(value, ros_type))]
        r = self.call("set_parameters", parameters=params).results[0]
        return bool(r.successful), str(r.reason)

    def list(self, prefixes=(), depth: int = 0):
        r = self.call("list_parameters", prefixes=list(prefixes), depth=depth).result
        return list(r.names)

    def describe(self, *names):
        return list(self.call("describe_parameters", names=list(names)).descriptors)

    def types(self, *names):
        return [int(t) for t in self.call("get_parameter_types", names=list(names)).types]
