"""ROS 2 QoS profiles as Cyclone DDS QoS, and the ROS environment's DDS settings.

Profiles (rmw's presets): ``default`` = reliable, volatile, keep-last 10;
``sensor_data`` = best effort, volatile, keep-last 5; ``services_default`` = reliable,
keep-last 10; ``parameters`` = reliable, keep-last 1000; ``transient_local`` (latched,
as ``/tf_static``) = reliable, transient local, keep-last 1. A reliable publisher
matches both kinds of subscribers; a best-effort publisher matches only best-effort ones
(DDS request/offer rules) — the transport logs a warning when DDS reports a mismatch.

Environment: ``ROS_DOMAIN_ID`` (0..232, default 0) is the DDS domain; the Python binding
ignores it, so it is mapped here. ``ROS_LOCALHOST_ONLY``, ``ROS_AUTOMATIC_DISCOVERY_RANGE`` and
``ROS_STATIC_PEERS`` are read with rcl's precedence (:func:`discovery`) and turned into the Cyclone
configuration rmw_cyclonedds_cpp would use (:func:`domain_config`).
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from xml.sax.saxutils import escape

from ..errors import InputError

RELIABLE, BEST_EFFORT = "reliable", "best_effort"
VOLATILE, TRANSIENT_LOCAL = "volatile", "transient_local"

#: Longest a reliable write blocks when the reader's history is full (integer ns, as the binding needs).
MAX_BLOCKING_NS = 100_000_000

#: Loopback only, unicast discovery. The large UDP messages / fragments (loopback carries 64 KiB
#: datagrams) and 8 MB socket buffers matter for event streams: with Cyclone's defaults (1344-byte
#: fragments, small buffers) 1 MiB messages went at ~30 MB/s with losses, with these at ~400 MB/s
#: on one shared core (bench/bench_publish.py). They only change how this process sends and
#: receives; peers reassemble any fragment size.
LOOPBACK_XML = ("<CycloneDDS><Domain><General><Interfaces><NetworkInterface name=\"lo\"/></Interfaces>"
                "<AllowMulticast>false</AllowMulticast><MaxMessageSize>65500B</MaxMessageSize>"
                "<FragmentSize>65000B</FragmentSize></General>"
                "<Internal><SocketReceiveBufferSize min=\"8MB\"/><SocketSendBufferSize min=\"8MB\"/></Internal>"
                "<Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>120</MaxAutoParticipantIndex>"
                "<Peers><Peer address=\"localhost\"/></Peers></Discovery></Domain></CycloneDDS>")


@dataclass(frozen=True)
class QosProfile:
    reliability: str = RELIABLE
    durability: str = VOLATILE
    depth: int = 10

    def __post_init__(self):
        if self.reliability not in (RELIABLE, BEST_EFFORT):
            raise InputError(f"QoS reliability {self.reliability!r}: use 'reliable' or 'best_effort'")
        if self.durability not in (VOLATILE, TRANSIENT_LOCAL):
            raise InputError(f"QoS durability {self.durability!r}: use 'volatile' or 'transient_local'")
        if not isinstance(self.depth, int) or isinstance(self.depth, bool) or self.depth < 1:
            raise InputError(f"QoS depth {self.depth!r}: must be an integer >= 1")

    def to_cyclone(self):
        from cyclonedds.qos import Policy, Qos

        rel = (Policy.Reliability.Reliable(max_blocking_time=MAX_BLOCKING_NS) if self.reliability == RELIABLE
               else Policy.Reliability.BestEffort)
        dur = Policy.Durability.TransientLocal if self.durability == TRANSIENT_LOCAL else Policy.Durability.Volatile
        return Qos(rel, dur, Policy.History.KeepLast(self.depth))

    def describe(self) -> str:
        return f"{self.reliability}, {self.durability}, keep-last {self.depth}"


PROFILES = {
    "default": QosProfile(RELIABLE, VOLATILE, 10),
    "sensor_data": QosProfile(BEST_EFFORT, VOLATILE, 5),
    "services_default": QosProfile(RELIABLE, VOLATILE, 10),
    "parameters": QosProfile(RELIABLE, VOLATILE, 1000),
    "transient_local": QosProfile(RELIABLE, TRANSIENT_LOCAL, 1),
}


def profile(name_or_profile, depth: int | None = None) -> QosProfile:
    """A profile by name (see :data:`PROFILES`), optionally with another history depth."""
    if isinstance(name_or_profile, QosProfile):
        p = name_or_profile
    else:
        try:
            p = PROFILES[name_or_profile]
        except (KeyError, TypeError):
            raise InputError(f"QoS profile {name_or_profile!r}: use one of {list(PROFILES)}") from None
    return p if depth is None else QosProfile(p.reliability, p.durability, depth)


def domain_id(env=None) -> int:
    """``ROS_DOMAIN_ID`` (default 0)."""
    env = os.environ if env is None else env
    text = env.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= 232:
        raise InputError(f"ROS_DOMAIN_ID={text!r}: must be an integer in 0..232 (ROS 2's valid range); "
                         "unset it for domain 0")
    return value


#: Participants per host that unicast discovery probes for (rmw_cyclonedds_cpp's MaxAutoParticipantIndex).
MAX_AUTO_PARTICIPANTS = 32
#: ROS_AUTOMATIC_DISCOVERY_RANGE values rcl accepts (exact, case-sensitive, as rcl compares them).
DISCOVERY_RANGES = ("OFF", "LOCALHOST", "SUBNET", "SYSTEM_DEFAULT")
#: rcl's longest static peer (RMW_DISCOVERY_OPTIONS_STATIC_PEERS_MAX_LENGTH - 1 characters).
MAX_PEER_LENGTH = 255


@dataclass(frozen=True)
class Discovery:
    """Discovery settings as rcl derives them from the environment."""
    range: str                      # one of DISCOVERY_RANGES
    static_peers: tuple = ()        # host names / addresses discovered by unicast as well
    warnings: tuple = ()            # what rcl would log about the environment, in its words


def discovery(env=None) -> Discovery:
    """The discovery range and static peers of rcl 9.2 (Jazzy) for ``env``: ``ROS_LOCALHOST_ONLY``
    starting with ``1`` wins (range LOCALHOST, no static peers); else ``ROS_AUTOMATIC_DISCOVERY_RANGE``
    (unset or empty: SUBNET; an unknown value: LOCALHOST, with a warning) and, unless the range is
    OFF, ``ROS_STATIC_PEERS`` (``;``-separated)."""
    env = os.environ if env is None else env
    warnings = []
    localhost = env.get("ROS_LOCALHOST_ONLY", "")
    if localhost:
        warnings.append("ROS_LOCALHOST_ONLY is deprecated but still honored if it is enabled. "
                        "Use ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_STATIC_PEERS instead.")
    if localhost.startswith("1"):
        warnings.append("'localhost_only' is enabled, 'automatic_discovery_range' and 'static_peers' will be ignored.")
        return Discovery("LOCALHOST", (), tuple(warnings))
    if localhost:
        warnings.append("'localhost_only' is disabled, 'automatic_discovery_range' and 'static_peers' will be used.")
    rng = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "")
    if rng == "":
        rng = "SUBNET"
    elif rng not in DISCOVERY_RANGES:
        warnings.append(f"Invalid value '{rng}' specified for 'ROS_AUTOMATIC_DISCOVERY_RANGE', assuming localhost only")
        rng = "LOCALHOST"
    peers = []
    if rng != "OFF":
        for peer in env.get("ROS_STATIC_PEERS", "").split(";"):
            if not peer:
                continue
            if len(peer) > MAX_PEER_LENGTH:
                warnings.append(f"Static peer {peer} specified to 'ROS_STATIC_PEERS' is too long (maximum of "
                                f"{MAX_PEER_LENGTH}); skipping")
                continue
            peers.append(peer)
    elif env.get("ROS_STATIC_PEERS", ""):
        warnings.append("Note: ROS_AUTOMATIC_DISCOVERY_RANGE is set to OFF, but found static peers in "
                        "ROS_STATIC_PEERS. ROS_STATIC_PEERS will be ignored.")
    if rng == "SYSTEM_DEFAULT" and peers:
        warnings.append(f"{len(peers)} static peers were specified, but discovery is set to use the RMW "
                        "implementation default, so these static peers will be ignored.")
        peers = []
    return Discovery(rng, tuple(peers), tuple(warnings))


def domain_config(env=None) -> str | None:
    """Cyclone DDS configuration for the environment, as rmw_cyclonedds_cpp 2.2 (Jazzy) builds it from
    :func:`discovery`, followed by ``CYCLONEDDS_URI`` (None: the library's default, which reads it).

    LOCALHOST: no multicast, unicast discovery of ``localhost`` and the static peers; with no static
    peers also the loopback interface and the large-message settings of :data:`LOOPBACK_XML`. SUBNET:
    multicast, plus the static peers. OFF: no discovery at all (a tag only this process carries).
    SYSTEM_DEFAULT: the library's own settings."""
    env = os.environ if env is None else env
    d = discovery(env)
    if d.range == "SYSTEM_DEFAULT":
        return None
    if d.range == "LOCALHOST" and not d.static_peers:
        config = LOOPBACK_XML
    else:
        general = "<General><AllowMulticast>false</AllowMulticast></General>" if d.range in ("LOCALHOST", "OFF") else ""
        if d.range == "OFF":
            disc = f"<ParticipantIndex>none</ParticipantIndex><Tag>ros_discovery_off_{os.getpid()}</Tag>"
        else:
            peers = (["localhost"] if d.range == "LOCALHOST" else []) + list(d.static_peers)
            disc = (f"<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>{MAX_AUTO_PARTICIPANTS}"
                    "</MaxAutoParticipantIndex>")
            if peers:
                disc += "<Peers>" + "".join(f'<Peer address="{escape(p, {chr(34): "&quot;"})}"/>' for p in peers) \
                        + "</Peers>"
        config = f"<CycloneDDS><Domain>{general}<Discovery>{disc}</Discovery></Domain></CycloneDDS>"
    uri = env.get("CYCLONEDDS_URI", "")
    return f"{config},{uri}" if uri else config


_warned: set = set()


def log_discovery_warnings(env=None, stream=None) -> None:
    """Print rcl's warnings about the environment (once per process), in rcutils' console format."""
    for text in discovery(env).warnings:
        if text in _warned:
            continue
        _warned.add(text)
        sec, nsec = divmod(time.time_ns(), 1_000_000_000)
        (stream or sys.stderr).write(f"[WARN] [{sec}.{nsec:09d}] [rcl]: {text}\n")
