"""``/rosout``: every line a node logs, as rcl_interfaces/msg/Log.

QoS as rcl in Jazzy: reliable, transient local, keep-last 1000 (a late ``ros2 topic echo
/rosout`` or rqt_console still gets the recent lines; rcl's 10 s lifespan is not set:
the toolkit's QoS profiles have no lifespan). Levels map debug/info/warn/error/fatal to
10/20/30/40/50; ``name`` is the logger name rcl uses (namespace and node joined with '.').
A failed publish is reported on stderr once, never raised into the caller's log call.
"""

from __future__ import annotations

import sys
import threading

from .qos import QosProfile, RELIABLE, TRANSIENT_LOCAL

ROSOUT_TOPIC = "/rosout"
LOG_TYPE = "rcl_interfaces/msg/Log"
ROSOUT_QOS = QosProfile(RELIABLE, TRANSIENT_LOCAL, 1000)
LEVELS = {"debug": 10, "info": 20, "warn": 30, "error": 40, "fatal": 50}


def logger_name(namespace: str, name: str) -> str:
    """rcl's logger name of node `name` in `namespace` (``/a/b`` + ``n`` -> ``a.b.n``)."""
    return ".".join([t for t in namespace.split("/") if t] + [name])


class RosoutPublisher:
    def __init__(self, node):
        from .transport import DdsPublisher

        self.node = node
        self.name = logger_name(node.namespace, node.name)
        self.writer = DdsPublisher(node.dds, ROSOUT_TOPIC, LOG_TYPE, ROSOUT_QOS)
        self._busy = threading.local()
        self._failed = False
        self.lines = 0
        node.logger.sinks.append(self.write)

    def write(self, level: str, msg: str, stamp_ns: int) -> None:
        if getattr(self._busy, "on", False) or self.writer is None:
            return
        from . import rostypes

        self._busy.on = True
        try:
            sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
            log = rostypes.message(LOG_TYPE, stamp=rostypes.message("builtin_interfaces/msg/Time", sec=sec,
                                                                     nanosec=nsec),
                                   level=LEVELS.get(level, 20), name=self.name, msg=msg, file="", function="",
                                   line=0)
            self.writer.publish_raw(rostypes.serialize(log, LOG_TYPE))
            self.lines += 1
        except Exception as exc:  # noqa: BLE001 - logging must never raise
            if not self._failed:
                self._failed = True
                print(f"[WARN] [{self.name}]: /rosout: could not publish ({exc}); logging to the console only",
                      file=sys.stderr)
        finally:
            self._busy.on = False

    def close(self) -> None:
        try:
            self.node.logger.sinks.remove(self.write)
        except ValueError:
            pass
        self.writer = None
