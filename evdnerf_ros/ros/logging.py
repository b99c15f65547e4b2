"""ROS-like console logging: ``[INFO] [1700000000.123456789] [event_publisher]: message``.

Levels debug < info < warn < error < fatal; the threshold comes from ``--log-level``.
Lines go to stderr, as rcutils' console output does by default, and to every callable
in ``sinks`` (a node on DDS adds its ``/rosout`` publisher there).
"""

from __future__ import annotations

import sys
import threading
import time

from .args import LOG_LEVELS


class RosLogger:
    def __init__(self, name: str, level: str = "info", stream=None):
        self.name = name
        self.level = level
        self.stream = stream
        self._lock = threading.Lock()
        #: callables (level, msg, stamp_ns) also given every line logged (e.g. /rosout)
        self.sinks: list = []

    @property
    def level(self) -> str:
        return LOG_LEVELS[self._threshold]

    @level.setter
    def level(self, value: str) -> None:
        self._threshold = LOG_LEVELS.index(value.lower())

    def enabled(self, level: str) -> bool:
        return LOG_LEVELS.index(level) >= self._threshold

    def log(self, level: str, msg: str) -> None:
        if not self.enabled(level):
            return
        stamp = time.time_ns()
        sec, nsec = divmod(stamp, 1_000_000_000)
        line = f"[{level.upper()}] [{sec}.{nsec:09d}] [{self.name}]: {msg}\n"
        stream = self.stream or sys.stderr
        with self._lock:
            stream.write(line)
            stream.flush()
        for sink in list(self.sinks):
            sink(level, msg, stamp)

    def debug(self, msg: str) -> None:
        self.log("debug", msg)

    def info(self, msg: str) -> None:
        self.log("info", msg)

    def warn(self, msg: str) -> None:
        self.log("warn", msg)

    def error(self, msg: str) -> None:
        self.log("error", msg)
