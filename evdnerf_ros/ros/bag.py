"""Record chosen topics of a node to rosbag2 (MCAP by default) with the toolkit's BagWriter.

Messages are recorded as the exact bytes the transport sends (CDR), stamped with their
header time. The bag is written atomically: it appears under its name only when the sink
closes cleanly (normal end, SIGINT, SIGTERM); an error discards it. What was recorded is
put on disk every `flush_period_s` seconds, so a recording killed outright (SIGKILL) keeps
all but its last second in its `.partial` folder: `evdnerf salvage-bag` writes it out.
"""

from __future__ import annotations

import time

from ..io.rosbag2 import BagWriter


class BagSink:
    def __init__(self, path, topics=None, *, storage: str = "mcap", flush_period_s: float = 1.0):
        """`topics`: resolved topic names to record (None: every topic the node publishes)."""
        self.topics = None if topics is None else set(topics)
        self.writer = BagWriter(path, storage=storage).open()
        self.path = self.writer.path
        self.messages = 0
        self.flush_period_s = flush_period_s
        self._next_flush = time.monotonic() + flush_period_s

    def wants(self, topic: str) -> bool:
        return self.topics is None or topic in self.topics

    def add_topic(self, topic: str, msgtype: str) -> None:
        """List a recorded topic in the bag from the start (also when nothing is published on it)."""
        if self.wants(topic):
            self.writer.add_topic(topic, msgtype)

    def record(self, topic: str, msgtype: str, data, t_ns: int) -> None:
        if self.wants(topic):
            self.writer.write_raw(topic, msgtype, data, t_ns)
            self.messages += 1
            if time.monotonic() >= self._next_flush:
                self.writer.flush()
                self._next_flush = time.monotonic() + self.flush_period_s

    def close(self) -> None:
        self.writer.close()

    def abort(self) -> None:
        self.writer.abort()
