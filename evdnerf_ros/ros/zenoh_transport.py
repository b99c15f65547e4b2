"""Publishers and subscriptions over Zenoh, following rmw_zenoh's conventions (optional transport).

Selected like ROS 2 selects its middleware: ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` in the
environment, or ``rmw="rmw_zenoh_cpp"`` given to :class:`~evdnerf_ros.ros.node.Node`; anything
else (unset, ``rmw_cyclonedds_cpp``, ``rmw_fastrtps_cpp``, ...) keeps the DDS transport
(:mod:`.transport`). Needs PyPI ``eclipse-zenoh`` 1.x (in the checkout: ``.venv/bin/pip install -e '.[zenoh]'``; the distribution is ``rig``).

What goes on the wire is what rmw_zenoh_cpp (docs/design.md, Jazzy and later) sends and expects:

- data key expression ``<domain_id>/<topic without leading '/'>/<DDS type name>/<RIHS01 type hash>``,
  e.g. ``0/event_publisher/events/event_camera_msgs::msg::dds_::EventPacket_/RIHS01_d6fa...``;
  the domain is ``ROS_DOMAIN_ID`` (so domains never cross-talk on one Zenoh network);
- payload: the CDR serialisation with its XCDR1 encapsulation header (rosbags' ``serialize_cdr``),
  unpadded;
- attachment (zenoh-ext serialisation): int64 sequence number (little-endian, from 1), int64
  source timestamp (ns since the UNIX epoch, little-endian), then the 16-byte publisher GID
  as a sequence (1 length byte ``0x10`` + 16 bytes): 33 bytes;
- graph presence by liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|MS>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]`` with ``/`` mangled to ``%`` and the QoS in
  rmw_zenoh's compact form (``::,10:,:,:,,`` = reliable, volatile, keep-last 10).

Differences, on purpose: the GID is the first 16 bytes of BLAKE2b of the entity's liveliness
key expression (rmw_zenoh takes XXH3-128 of the same string; peers only read the GID, they never
recompute it); a reliable publisher blocks when Zenoh's queues are full (congestion control
BLOCK, like a reliable DDS writer) where rmw_zenoh blocks only for keep-all history.

Sessions run in peer mode on loopback without a router: unless configured otherwise, the first
process listens on ``tcp/127.0.0.1:7447`` (rmw_zenohd's port, so a running ``rmw_zenohd`` is used
as rmw_zenoh would use it) and later ones connect there; multicast scouting is off, gossip
scouting (Zenoh's default) introduces the peers to each other. ``ZENOH_SESSION_CONFIG_URI``
(a Zenoh JSON5 file) and ``ZENOH_CONFIG_OVERRIDE`` (``key=value;key=value``, values in JSON5)
work as in rmw_zenoh; a node's ``dds_config`` may be Zenoh JSON5 text or a path to such a file.

Received samples without a valid attachment, with a payload that is not CDR, or that do not
deserialise as the topic's type are dropped and logged (never raised).
"""

from __future__ import annotations

import hashlib
import json
import os
import struct
import threading
import time
from collections import deque

from ..errors import InputError
from ..io.typestore import ros2_typestore
from . import qos as _qos
from .names import dds_type
from .transport import TransportError

#: ``RMW_IMPLEMENTATION`` value that selects this transport (as in ROS 2).
RMW_ZENOH = "rmw_zenoh_cpp"
#: values that keep the DDS transport (Cyclone DDS here; it interoperates with the others over RTPS)
RMW_DDS = ("rmw_cyclonedds_cpp", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp", "rmw_connextdds",
           "rmw_gurumdds_cpp")
#: where the first peer listens and the others connect when nothing else is configured
RENDEZVOUS = "tcp/127.0.0.1:7447"
ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
#: attachment: int64 seq, int64 ns timestamp, sequence length byte (16), 16 GID bytes
ATTACHMENT_HEAD = struct.Struct("<qqB")
ATTACHMENT_SIZE = ATTACHMENT_HEAD.size + GID_SIZE
#: rmw_zenoh's default QoS (qos.cpp), against which the liveliness QoS field is written
_DEFAULT_DEPTH = 42
INSTALL_HINT = ("pip install 'rig[zenoh]' (in the checkout: .venv/bin/pip install -e '.[zenoh]', which installs "
                "eclipse-zenoh>=1.0,<2)")


def _zenoh():
    try:
        import zenoh
    except ImportError as exc:
        raise TransportError(f"RMW_IMPLEMENTATION={RMW_ZENOH} needs the Zenoh Python package ({exc}); "
                             f"{INSTALL_HINT}, or unset RMW_IMPLEMENTATION to use DDS") from None
    return zenoh


# ----------------------------------------------------------------------------- selection
def selected_rmw(rmw: str | None = None, env=None) -> str:
    """``"zenoh"`` or ``"dds"``: `rmw` when given, else ``RMW_IMPLEMENTATION``."""
    env = os.environ if env is None else env
    value = (rmw if rmw is not None else env.get("RMW_IMPLEMENTATION", "")).strip()
    source = "rmw" if rmw is not None else "RMW_IMPLEMENTATION"
    if value in ("", "dds") or value in RMW_DDS:
        return "dds"
    if value in (RMW_ZENOH, "zenoh"):
        return "zenoh"
    raise InputError(f"{source}={value!r}: not a middleware this toolkit speaks; use {RMW_ZENOH} (Zenoh) or "
                     f"one of {', '.join(RMW_DDS)} / unset (DDS)")


def open_transport(node, domain_id: int | None, config: str | None, rmw: str | None = None):
    """The node's transport context: :class:`ZenohContext` or :class:`.transport.DdsContext`."""
    if selected_rmw(rmw) == "zenoh":
        return ZenohContext(domain_id, config=config, node_name=node.name, namespace=node.namespace,
                            log=node.logger.log)
    from .transport import DdsContext

    return DdsContext(domain_id, config=config)


def endpoint_classes(ctx):
    """(publisher class, subscription class) for a context made by :func:`open_transport`."""
    if isinstance(ctx, ZenohContext):
        return ZenohPublisher, ZenohSubscription
    from .transport import DdsPublisher, DdsSubscription

    return DdsPublisher, DdsSubscription


# ----------------------------------------------------------------------------- names
def mangle(name: str) -> str:
    return name.replace("/", "%")


def topic_keyexpr(domain_id: int, full: str, msgtype: str, type_hash: str) -> str:
    """rmw_zenoh's data key expression of topic `full` (absolute ROS name)."""
    if not full.startswith("/"):
        raise InputError(f"topic {full!r}: resolve it first (absolute name expected)")
    return f"{int(domain_id)}/{full.strip('/')}/{dds_type(msgtype)}/{type_hash}"


def qos_keyexpr(profile) -> str:
    """rmw_zenoh's compact QoS (``qos_to_keyexpr``): fields equal to its defaults are left empty."""
    p = _qos.profile(profile)
    rel = "" if p.reliability == _qos.RELIABLE else "2"          # RMW_QOS_POLICY_RELIABILITY_BEST_EFFORT
    dur = "" if p.durability == _qos.VOLATILE else "1"            # RMW_QOS_POLICY_DURABILITY_TRANSIENT_LOCAL
    depth = "" if p.depth == _DEFAULT_DEPTH else str(p.depth)     # history keep-last is the default
    return f"{rel}:{dur}:,{depth}:,:,:,,"


def gid_of(keyexpr: str) -> bytes:
    """16-byte GID of an entity, derived from its liveliness key expression."""
    return hashlib.blake2b(keyexpr.encode(), digest_size=GID_SIZE).digest()


def make_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    return ATTACHMENT_HEAD.pack(seq, stamp_ns, GID_SIZE) + gid


def parse_attachment(raw: bytes | None):
    """(sequence number, source timestamp ns, 16-byte GID), or None when `raw` is not one."""
    if raw is None or len(raw) != ATTACHMENT_SIZE:
        return None
    seq, stamp, n = ATTACHMENT_HEAD.unpack_from(raw)
    if n != GID_SIZE:
        return None
    return seq, stamp, bytes(raw[ATTACHMENT_HEAD.size:])


def parse_liveliness(keyexpr: str) -> dict | None:
    """The fields of an ``@ros2_lv`` token (None when it is not a well-formed one)."""
    parts = keyexpr.split("/")
    if len(parts) not in (9, 13) or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        return None
    kind = parts[5]
    if kind not in ("NN", "MP", "MS", "SS", "SC") or (kind == "NN") != (len(parts) == 9):
        return None
    out = {"domain": parts[1], "zid": parts[2], "nid": parts[3], "id": parts[4], "kind": kind,
           "enclave": parts[6].replace("%", "/"), "namespace": parts[7].replace("%", "/"), "node": parts[8]}
    if len(parts) == 13:
        out.update(topic=parts[9].replace("%", "/"), type=parts[10], hash=parts[11], qos=parts[12])
    return out


def _config(zenoh, text: str | None, rendezvous: str, listen_first: bool):
    """A Zenoh config: explicit JSON5 (text or file), ZENOH_SESSION_CONFIG_URI, or the loopback default."""
    if text is not None and text.lstrip().startswith("<"):
        raise InputError("the Zenoh transport got a Cyclone DDS XML config; give Zenoh JSON5 (text or a .json5 "
                         "file) or unset RMW_IMPLEMENTATION to use DDS")
    uri = os.environ.get("ZENOH_SESSION_CONFIG_URI", "").strip()
    try:
        if text is not None and text.lstrip().startswith("{"):
            cfg = zenoh.Config.from_json5(text)
        elif text is not None:
            cfg = zenoh.Config.from_file(text)
        elif uri:
            cfg = zenoh.Config.from_file(uri)
        else:
            cfg = zenoh.Config()
            cfg.insert_json5("mode", '"peer"')
            cfg.insert_json5("scouting/multicast/enabled", "false")
            cfg.insert_json5("listen/endpoints", json.dumps([rendezvous if listen_first else "tcp/127.0.0.1:0"]))
            cfg.insert_json5("connect/endpoints", json.dumps([] if listen_first else [rendezvous]))
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError and OS errors
        where = "the given Zenoh config" if text is not None else f"ZENOH_SESSION_CONFIG_URI={uri}"
        raise InputError(f"{where}: not a valid Zenoh JSON5 config ({exc})") from None
    override = os.environ.get("ZENOH_CONFIG_OVERRIDE", "").strip()
    for item in filter(None, (s.strip() for s in override.split(";"))):
        key, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError("expected key=value")
            cfg.insert_json5(key.strip(), value.strip())
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"ZENOH_CONFIG_OVERRIDE item {item!r}: {exc}; write key=value pairs separated by "
                             "';', values in JSON5 (e.g. mode=\"peer\";scouting/multicast/enabled=false)") from None
    return cfg


# ----------------------------------------------------------------------------- context
class ZenohContext:
    """One Zenoh session for one node: its ``NN`` liveliness token and a graph cache of peers' tokens."""

    def __init__(self, domain_id: int | None = None, *, config: str | None = None, node_name: str = "node",
                 namespace: str = "/", enclave: str = "/", env=None, rendezvous: str = RENDEZVOUS, log=None):
        zenoh = self.zenoh = _zenoh()
        self.domain_id = _qos.domain_id(env) if domain_id is None else int(domain_id)
        self.node_name, self.namespace, self.enclave = node_name, namespace, enclave
        self._log = log or (lambda level, msg: None)
        self.session = None
        try:
            self.session = zenoh.open(_config(zenoh, config, rendezvous, listen_first=True))
        except InputError:
            raise
        except Exception as first:  # noqa: BLE001 - the rendezvous port is taken: join whoever holds it
            if config is not None or os.environ.get("ZENOH_SESSION_CONFIG_URI", "").strip():
                raise TransportError(f"Zenoh session did not open: {first}") from None
            try:
                self.session = zenoh.open(_config(zenoh, None, rendezvous, listen_first=False))
            except Exception as exc:  # noqa: BLE001
                raise TransportError(f"Zenoh session did not open ({exc}); check ZENOH_SESSION_CONFIG_URI / "
                                     "ZENOH_CONFIG_OVERRIDE") from None
        self.zid = str(self.session.info.zid())
        self._lock = threading.Lock()
        self._next_id = 0
        self.node_id = self._new_id()
        self.node_keyexpr = self._token_key("NN", self.node_id)
        self._tokens = [self.session.liveliness().declare_token(self.node_keyexpr)]
        self.graph: dict[str, dict] = {}
        self._graph_sub = self.session.liveliness().declare_subscriber(
            f"{ADMIN_SPACE}/{self.domain_id}/**", self._on_token, history=True)
        self._ts = ros2_typestore()
        self._hashes: dict[str, str] = {}

    def _new_id(self) -> int:
        with self._lock:
            n = self._next_id
            self._next_id += 1
            return n

    def _token_key(self, kind: str, entity_id: int, topic_part: str = "") -> str:
        base = (f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{mangle(self.enclave)}/{mangle(self.namespace)}/{self.node_name}")
        return base + ("/" + topic_part if topic_part else "")

    def _on_token(self, sample) -> None:
        key = str(sample.key_expr)
        if sample.kind == self.zenoh.SampleKind.DELETE:
            self.graph.pop(key, None)
            return
        info = parse_liveliness(key)
        if info is not None:
            self.graph[key] = info

    def type_hash(self, msgtype: str) -> str:
        h = self._hashes.get(msgtype)
        if h is None:
            h = self._hashes[msgtype] = self._ts.hash_rihs01(msgtype)
        return h

    def entity(self, kind: str, full: str, msgtype: str, profile):
        """(data key expression, liveliness key expression, GID) of a new publisher / subscription."""
        key = topic_keyexpr(self.domain_id, full, msgtype, self.type_hash(msgtype))
        token = self._token_key(kind, self._new_id(), "/".join(
            (mangle(full), dds_type(msgtype), self.type_hash(msgtype), qos_keyexpr(profile))))
        return key, token, gid_of(token)

    def declare_token(self, keyexpr: str):
        tok = self.session.liveliness().declare_token(keyexpr)
        self._tokens.append(tok)
        return tok

    def count(self, kind: str, full: str, msgtype: str) -> int:
        """Entities of `kind` (MP / MS) on `full` with `msgtype` in the graph (this session's included)."""
        want = (str(self.domain_id), kind, full, dds_type(msgtype), self.type_hash(msgtype))
        return sum(1 for g in list(self.graph.values())
                   if (g["domain"], g["kind"], g.get("topic"), g.get("type"), g.get("hash")) == want)

    def close(self) -> None:
        if self.session is None:
            return
        for tok in self._tokens:
            try:
                tok.undeclare()
            except Exception:  # noqa: BLE001 - best effort on shutdown
                pass
        self._tokens.clear()
        try:
            self._graph_sub.undeclare()
            self.session.close()
        except Exception:  # noqa: BLE001
            pass
        self.session = None


class _ZEndpoint:
    kind = ""

    def __init__(self, ctx: ZenohContext, full: str, msgtype: str, profile, log):
        if not isinstance(ctx, ZenohContext):
            raise TransportError(f"topic {full}: a Zenoh endpoint needs a ZenohContext")
        self.ctx = ctx
        self.topic = full
        self.msgtype = msgtype
        self.qos = _qos.profile(profile)
        self._log = log or (lambda level, msg: None)
        self.qos_fix: str | None = None
        self.keyexpr, self.token_keyexpr, self.gid = ctx.entity(self.kind, full, msgtype, self.qos)
        self._ts = ros2_typestore()

    def check_qos(self) -> bool:
        """Zenoh has no incompatible QoS (rmw_zenoh matches every publisher with every subscription)."""
        return False


class ZenohPublisher(_ZEndpoint):
    kind = "MP"

    def __init__(self, ctx: ZenohContext, full: str, msgtype: str, profile="default", *, fast: bool = True,
                 log=None):
        super().__init__(ctx, full, msgtype, profile, log)
        z = ctx.zenoh
        self.fast = fast
        reliable = self.qos.reliability == _qos.RELIABLE
        self.pub = ctx.session.declare_publisher(
            self.keyexpr, reliability=z.Reliability.RELIABLE if reliable else z.Reliability.BEST_EFFORT,
            congestion_control=z.CongestionControl.BLOCK if reliable else z.CongestionControl.DROP)
        ctx.declare_token(self.token_keyexpr)
        self.sequence = 1
        self.bytes_sent = 0
        self.messages_sent = 0

    def publish_raw(self, data, stamp_ns: int | None = None) -> None:
        """Send one serialised CDR message; `stamp_ns` is the attachment's source time (default: now)."""
        data = bytes(data)
        att = make_attachment(self.sequence, time.time_ns() if stamp_ns is None else int(stamp_ns), self.gid)
        try:
            self.pub.put(data, attachment=att)
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError
            raise TransportError(f"topic {self.topic}: Zenoh put failed ({exc})") from None
        self.sequence += 1
        self.bytes_sent += len(data)
        self.messages_sent += 1

    def publish(self, msg) -> None:
        self.publish_raw(self._ts.serialize_cdr(msg, self.msgtype))

    def matched(self) -> int:
        """Subscriptions in the graph (liveliness ``MS`` tokens); at least 1 while a plain Zenoh
        subscriber (no token) matches the key expression."""
        n = self.ctx.count("MS", self.topic, self.msgtype)
        if n == 0:
            try:
                n = int(bool(self.pub.matching_status.matching))
            except Exception:  # noqa: BLE001
                n = 0
        return n

    def wait_for_subscribers(self, n: int = 1, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.matched() < n:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def wait_for_acks(self, timeout_s: float = 1.0) -> bool:
        """Zenoh has no acknowledgements; a reliable publisher's samples already sit in the session's
        transmit queue (congestion control BLOCK), which closing the session flushes."""
        return True

    def close(self) -> None:
        try:
            self.pub.undeclare()
        except Exception:  # noqa: BLE001
            pass


class ZenohSubscription(_ZEndpoint):
    kind = "MS"

    def __init__(self, ctx: ZenohContext, full: str, msgtype: str, profile="default", *, fast: bool = True,
                 log=None, validate: bool = True):
        """`validate`: deserialise each sample with rosbags before keeping it (drops malformed CDR)."""
        super().__init__(ctx, full, msgtype, profile, log)
        self.fast = fast
        self.validate = validate
        self._queue: deque = deque(maxlen=self.qos.depth)   # keep-last history
        self._cond = threading.Condition()
        self.dropped = 0
        self.received = 0
        self._warned = 0
        self.sub = ctx.session.declare_subscriber(self.keyexpr, self._on_sample)
        ctx.declare_token(self.token_keyexpr)

    def _bad(self, why: str) -> None:
        self.dropped += 1
        if self.dropped in (1, 10, 100, 1000) or self.dropped % 10000 == 0:
            self._log("warn", f"topic {self.topic}: ignored a malformed Zenoh sample ({why}); {self.dropped} so "
                              "far. The sender does not follow rmw_zenoh's format (CDR payload + 33-byte "
                              "attachment with sequence number, timestamp and GID)")

    def _on_sample(self, sample) -> None:
        try:
            if sample.kind != self.ctx.zenoh.SampleKind.PUT:
                return
            att = parse_attachment(None if sample.attachment is None else sample.attachment.to_bytes())
            if att is None:
                self._bad("missing or malformed attachment")
                return
            data = sample.payload.to_bytes()
            if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
                self._bad("payload is not CDR (no encapsulation header 00 00 / 00 01)")
                return
            with self._cond:
                self._queue.append((data, att))
                self.received += 1
                self._cond.notify_all()
        except Exception as exc:  # noqa: BLE001 - never let a bad sample kill Zenoh's callback thread
            self._bad(f"{type(exc).__name__}: {exc}")

    def _pop(self, n: int) -> list:
        with self._cond:
            out = []
            while self._queue and len(out) < n:
                out.append(self._queue.popleft())
            return out

    def take_with_info(self, n: int = 256) -> list[tuple[bytes, int, int, bytes]]:
        """Up to n received messages as (CDR bytes, source timestamp ns, sequence number, publisher GID)."""
        out = []
        for data, (seq, stamp, gid) in self._pop(n):
            if self.validate:
                try:
                    self._ts.deserialize_cdr(data, self.msgtype)
                except Exception as exc:  # noqa: BLE001 - rosbags raises several kinds on bad bytes
                    self._bad(f"does not deserialise as {self.msgtype}: {type(exc).__name__}: {exc}")
                    continue
            out.append((data, stamp, seq, gid))
        return out

    def take_raw(self, n: int = 256) -> list[tuple[bytes, int]]:
        """Up to n received messages as (CDR bytes, source timestamp ns)."""
        return [(d, s) for d, s, _, _ in self.take_with_info(n)]

    def take(self, n: int = 256) -> list:
        return [self._ts.deserialize_cdr(d, self.msgtype) for d, _ in self.take_raw(n)]

    def wait(self, timeout_s: float) -> bool:
        with self._cond:
            if not self._queue:
                self._cond.wait(max(timeout_s, 0.0))
            return bool(self._queue)

    def matched(self) -> int:
        """Publishers in the graph (liveliness ``MP`` tokens)."""
        return self.ctx.count("MP", self.topic, self.msgtype)

    def close(self) -> None:
        try:
            self.sub.undeclare()
        except Exception:  # noqa: BLE001
            pass
