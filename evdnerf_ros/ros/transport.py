"""Publishers and subscriptions over Cyclone DDS with ROS 2's naming, QoS and CDR.

Fast path (default): the message is serialised by rosbags (XCDR1, byte-identical to what
a ROS 2 node sends), padded to 4 bytes and handed to the binding's low-level writer call
``cyclonedds._clayer.ddspy_write``; a subscription takes raw samples with ``ddspy_take``
and rosbags deserialises them. Those two calls are private API of cyclonedds 11.0.1
(pinned in setup.py; ``tests/test_ros_transport.py`` checks them). The slow path
(``fast=False``) goes through the binding's IdlStruct (de)serialisation (Python lists,
kept as the benchmark's peer).

A QoS mismatch (e.g. a best-effort publisher and a reliable subscriber) makes DDS deliver
nothing; :meth:`DdsPublisher.check_qos` / :meth:`DdsSubscription.check_qos` turn the
"incompatible QoS" status into a warning naming the topic, the policy and the fix.
"""

from __future__ import annotations

import time

from ..errors import EvdnerfError, InputError
from ..io.typestore import ros2_typestore
from . import qos as _qos
from .idl import idl_type, to_idl
from .names import dds_topic

#: DDS QoS policy ids (DDS 1.4 spec) of the policies ROS QoS profiles set.
POLICY_NAMES = {2: "DURABILITY", 4: "DEADLINE", 8: "LIVELINESS", 11: "RELIABILITY", 12: "DESTINATION_ORDER",
                13: "HISTORY", 23: "DATA_REPRESENTATION"}


class TransportError(EvdnerfError):
    """The DDS layer failed (library missing, domain could not start, write failed)."""


#: Participant USER_DATA of ROS 2 Iron and later (rmw_cyclonedds / rmw_fastrtps): the security enclave.
ENCLAVE_USER_DATA = b"enclave=/;"


def endpoint_qos(profile, type_hash: str | None):
    """Cyclone QoS of a ROS profile plus the endpoint USER_DATA ``typehash=RIHS01_...;`` (Iron and later)."""
    from cyclonedds.qos import Policy, Qos

    q = profile.to_cyclone()
    if not type_hash:
        return q
    return Qos(*q, Policy.Userdata(f"typehash={type_hash};".encode()))


def _clayer():
    try:
        from cyclonedds._clayer import ddspy_take, ddspy_write
    except ImportError as exc:  # noqa: BLE001
        raise TransportError(f"cyclonedds' low-level calls are unavailable ({exc}); install the pinned "
                             "version: pip install cyclonedds==11.0.1") from None
    return ddspy_write, ddspy_take


#: Domains configured in this process (Cyclone allows one configuration per domain id per process).
_DOMAINS: dict[int, tuple[str, object]] = {}


def _domain(Domain, domain_id: int, config: str):
    have = _DOMAINS.get(domain_id)
    if have is not None:
        if have[0] != config:
            raise TransportError(f"DDS domain {domain_id} is already configured differently in this process; use "
                                 "one configuration per domain id")
        return have[1]
    dom = Domain(domain_id, config)
    _DOMAINS[domain_id] = (config, dom)
    return dom


class DdsContext:
    """One DDS domain participant. ``domain_id`` / ``config`` default to the ROS environment."""

    def __init__(self, domain_id: int | None = None, *, config: str | None = None, env=None):
        try:
            from cyclonedds.domain import Domain, DomainParticipant
        except ImportError as exc:
            raise TransportError(f"cyclonedds is not installed ({exc}); pip install cyclonedds==11.0.1, or run "
                                 "without DDS (evdnerf publish --no-dds)") from None
        self.domain_id = _qos.domain_id(env) if domain_id is None else int(domain_id)
        if config is None:
            _qos.log_discovery_warnings(env)
            config = _qos.domain_config(env)
        self.config = config
        try:
            from cyclonedds.qos import Policy, Qos

            self._domain = _domain(Domain, self.domain_id, self.config) if self.config else None
            # participant USER_DATA "enclave=/;": how Iron and later tell ROS participants apart
            self.participant = DomainParticipant(self.domain_id, qos=Qos(Policy.Userdata(ENCLAVE_USER_DATA)))
        except Exception as exc:  # noqa: BLE001 - DDSException and friends
            raise TransportError(f"DDS domain {self.domain_id} did not start: {exc}") from None
        self._gid = self.participant.guid.bytes
        self._topics: dict[str, object] = {}
        #: called with (kind "reader"/"writer", 16-byte GID) for every endpoint created (graph bookkeeping)
        self.on_endpoint = None

    @property
    def gid(self) -> bytes:
        """The participant's 16-byte GID (its DDS GUID), as rmw_dds_common/msg/Gid carries it."""
        return self._gid

    def topic(self, full: str, msgtype: str, *, dds_name: str | None = None, idl=None):
        """The DDS topic of ROS topic `full` (``dds_name``: a DDS name used as is, e.g.
        ``ros_discovery_info`` or ``rq/...Request``; ``idl``: the IdlStruct, default from msgtype)."""
        from cyclonedds.topic import Topic

        key = dds_name or full
        have = self._topics.get(key)
        if have is not None:
            if have[1] != msgtype:
                raise InputError(f"topic {full} already carries {have[1]} in this process; cannot also use {msgtype}")
            return have[0]
        top = Topic(self.participant, dds_name or dds_topic(full), idl if idl is not None else idl_type(msgtype))
        self._topics[key] = (top, msgtype)
        return top

    def _endpoint_created(self, kind: str, gid: bytes) -> None:
        if self.on_endpoint is not None:
            self.on_endpoint(kind, gid)

    def close(self):
        self._topics.clear()
        self.participant = None
        self._domain = None


def _type_hash(msgtype: str) -> str | None:
    from .rostypes import type_hash

    try:
        return type_hash(msgtype)
    except EvdnerfError:
        return None


class _Endpoint:
    def __init__(self, full, msgtype, profile, log):
        self.topic = full
        self.msgtype = msgtype
        self.qos = _qos.profile(profile)
        self.gid = b""
        self._log = log or (lambda level, msg: None)
        self._warned = 0
        #: how the user changes this endpoint's QoS (a command's own flag); None: the generic hint
        self.qos_fix: str | None = None

    def _incompatible(self, status, side: str):
        if status.total_count > self._warned:
            self._warned = status.total_count
            policy = POLICY_NAMES.get(status.last_policy_id, f"policy id {status.last_policy_id}")
            other = "subscriber" if side == "offered" else "publisher"
            fix = self.qos_fix or "use qos 'default' on the publisher, or 'sensor_data' on the subscriber"
            self._log("warn", f"topic {self.topic}: a {other} has incompatible QoS ({policy}); ours is "
                              f"{self.qos.describe()}. It receives nothing until both agree: a reliable "
                              f"subscriber needs a reliable publisher ({fix})")
            return True
        return False


class DdsPublisher(_Endpoint):
    def __init__(self, ctx: DdsContext, full: str, msgtype: str, profile="default", *, fast: bool = True, log=None,
                 dds_name: str | None = None, idl=None, type_hash: str | None = None):
        from cyclonedds.pub import DataWriter

        super().__init__(full, msgtype, profile, log)
        self.fast = fast
        self._write, _ = _clayer()
        self.writer = DataWriter(ctx.participant, ctx.topic(full, msgtype, dds_name=dds_name, idl=idl),
                                 endpoint_qos(self.qos, type_hash or _type_hash(msgtype)))
        self.gid = self.writer.guid.bytes
        ctx._endpoint_created("writer", self.gid)
        self._ts = ros2_typestore()
        self.bytes_sent = 0
        self.messages_sent = 0

    def publish_raw(self, data) -> None:
        """Send one serialised XCDR1 message (rosbags' ``serialize_cdr`` output)."""
        data = bytes(data)
        if len(data) % 4:
            data += b"\x00" * (-len(data) % 4)
        ret = self._write(self.writer._ref, data)
        if ret < 0:
            raise TransportError(f"topic {self.topic}: DDS write failed (return code {ret})")
        self.bytes_sent += len(data)
        self.messages_sent += 1

    def publish(self, msg) -> None:
        if self.fast:
            self.publish_raw(self._ts.serialize_cdr(msg, self.msgtype))
        else:
            self.writer.write(to_idl(msg, self.msgtype))
            self.messages_sent += 1

    def matched(self) -> int:
        return int(self.writer.get_publication_matched_status().current_count)

    def wait_for_subscribers(self, n: int = 1, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.matched() < n:
            self.check_qos()
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def wait_for_acks(self, timeout_s: float = 1.0) -> bool:
        from cyclonedds.util import duration

        try:
            return bool(self.writer.wait_for_acks(duration(seconds=timeout_s)))
        except Exception:  # noqa: BLE001 - best effort on shutdown
            return False

    def check_qos(self) -> bool:
        return self._incompatible(self.writer.get_offered_incompatible_qos_status(), "offered")


class DdsSubscription(_Endpoint):
    def __init__(self, ctx: DdsContext, full: str, msgtype: str, profile="default", *, fast: bool = True, log=None,
                 dds_name: str | None = None, idl=None, type_hash: str | None = None):
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.sub import DataReader

        super().__init__(full, msgtype, profile, log)
        self.fast = fast
        _, self._take = _clayer()
        self.reader = DataReader(ctx.participant, ctx.topic(full, msgtype, dds_name=dds_name, idl=idl),
                                 endpoint_qos(self.qos, type_hash or _type_hash(msgtype)))
        self.gid = self.reader.guid.bytes
        ctx._endpoint_created("reader", self.gid)
        self._mask = SampleState.Any | ViewState.Any | InstanceState.Any
        self._waitset = WaitSet(ctx.participant)
        self._cond = ReadCondition(self.reader, self._mask)
        self._waitset.attach(self._cond)
        self._ts = ros2_typestore()

    def take_raw(self, n: int = 256) -> list[tuple[bytes, int]]:
        """Up to n received messages as (XCDR1 bytes, source timestamp ns)."""
        ret = self._take(self.reader._ref, self._mask, n)
        if isinstance(ret, int):
            raise TransportError(f"topic {self.topic}: DDS take failed (return code {ret})")
        return [(data, info.source_timestamp) for data, info in ret if info.valid_data]

    def take(self, n: int = 256) -> list:
        """Up to n received messages, decoded (rosbags objects; IdlStruct samples when fast=False)."""
        if not self.fast:
            return list(self.reader.take(N=n))
        return [self._ts.deserialize_cdr(data, self.msgtype) for data, _ in self.take_raw(n)]

    def wait(self, timeout_s: float) -> bool:
        """Block until data is available (True) or the timeout passes (False)."""
        from cyclonedds.util import duration

        return self._waitset.wait(duration(seconds=max(timeout_s, 0.0))) > 0

    def matched(self) -> int:
        return int(self.reader.get_subscription_matched_status().current_count)

    def check_qos(self) -> bool:
        return self._incompatible(self.reader.get_requested_incompatible_qos_status(), "requested")
