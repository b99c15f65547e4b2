"""ROS 2 QoS profiles as Cyclone DDS QoS, and the ROS environment's DDS settings.

Profiles (rmw's presets): ``default`` = reliable, volatile, keep-last 10;
``sensor_data`` = best effort, volatile, keep-last 5; ``services_default`` = reliable,
keep-last 10; ``parameters`` = reliable, keep-last 1000; ``transient_local`` (latched,
as ``/tf_static``) = reliable, transient local, keep-last 1. A reliable publisher
matches both kinds of subscribers; a best-effort publisher matches only best-effort ones
(DDS request/offer rules) — the transport logs a warning when DDS reports a mismatch.

Environment: ``ROS_DOMAIN_ID`` (0..232, default 0) is the DDS domain; the Python binding
ignores it, so it is mapped here. ``ROS_LOCALHOST_ONLY=1`` (Humble) or
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` / ``OFF`` (Iron and later) restrict traffic
to the loopback interface with unicast discovery (:data:`LOOPBACK_XML`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

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


def localhost_only(env=None) -> bool:
    """True when ROS's environment restricts discovery to this host."""
    env = os.environ if env is None else env
    rng = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip().upper()
    if rng in ("LOCALHOST", "OFF"):
        return True
    if rng in ("SUBNET", "SYSTEM_DEFAULT"):
        return False
    if rng:
        raise InputError(f"ROS_AUTOMATIC_DISCOVERY_RANGE={rng!r}: use LOCALHOST, SUBNET, OFF or SYSTEM_DEFAULT")
    return env.get("ROS_LOCALHOST_ONLY", "0").strip() == "1"


def domain_config(env=None) -> str | None:
    """Cyclone DDS configuration XML for the environment (None: the library's default / CYCLONEDDS_URI)."""
    return LOOPBACK_XML if localhost_only(env) else None
