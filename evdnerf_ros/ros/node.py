"""The Node base: parameters and ``--ros-args``, names, DDS publishers and subscriptions,
an optional rosbag2 sink, logging, and a clean shutdown on SIGINT / SIGTERM.

A subclass lists its :class:`ParameterSpec` in ``PARAMETERS`` (every node also has rclpy's
``use_sim_time``: true makes :meth:`Node.now_ns` follow ``/clock``) and runs its loop while
:meth:`Node.ok`; the first SIGINT / SIGTERM only asks the loop to stop (a second SIGINT, a
second or more later, interrupts at once), and :meth:`Node.shutdown` then closes the bag (everything published
so far is in it) and the DDS entities. ``dds=False`` runs the same node without any DDS
(bag only), as ``evdnerf publish`` does by default.
"""

from __future__ import annotations

import signal
import threading
import time

from ..errors import InputError
from .args import parse_ros_args
from .bag import BagSink
from .logging import RosLogger
from .names import apply_remaps, resolve_topic, validate_namespace, validate_node_name
from .parameters import ParameterSpec, Parameters, load_params_file
from .qos import profile as qos_profile


class Publisher:
    """A topic's publisher: DDS (when the node has DDS) and the bag sink (when it records the topic)."""

    def __init__(self, node: "Node", topic: str, msgtype: str, dds_pub):
        self.node = node
        self.topic = topic
        self.msgtype = msgtype
        self.dds = dds_pub
        self.messages = 0
        self.bytes = 0

    def publish_raw(self, data, stamp_ns: int) -> None:
        """Send one serialised message (CDR) stamped ``stamp_ns`` (its header time)."""
        if self.dds is not None:
            self.dds.publish_raw(data)
        if self.node.bag is not None:
            self.node.bag.record(self.topic, self.msgtype, data, stamp_ns)
        self.messages += 1
        self.bytes += len(data)

    def publish(self, msg, stamp_ns: int) -> None:
        from ..io.typestore import ros2_typestore

        self.publish_raw(ros2_typestore().serialize_cdr(msg, self.msgtype), stamp_ns)

    def subscribers(self) -> int:
        return self.dds.matched() if self.dds is not None else 0


#: Declared by every node, as rclpy and rclcpp do.
USE_SIM_TIME = ParameterSpec("use_sim_time", False, "the node's clock follows /clock (rosgraph_msgs/msg/Clock) "
                             "instead of the system clock; messages keep the stamps their data carries", dynamic=True)


#: A SIGINT this soon (s) after the first is the same Ctrl-C delivered twice, not a second one: a
#: terminal signals its whole foreground process group, and `ros2 launch` forwards the SIGINT it
#: got to the node as well.
REPEATED_SIGINT_S = 1.0


def is_second_interrupt(first: list[float]) -> bool:
    """Whether a SIGINT after a stop request (its monotonic time in ``first``, if any) is a new
    Ctrl-C that asks to stop at once."""
    return not first or time.monotonic() - first[0] > REPEATED_SIGINT_S


def stop_signal_handler(stop: threading.Event, on_stop=lambda signum: None):
    """A SIGINT / SIGTERM handler that sets ``stop`` (after ``on_stop(signum)``); a second Ctrl-C
    (:func:`is_second_interrupt`) raises KeyboardInterrupt, the same one delivered twice is ignored."""
    first: list[float] = []

    def handler(signum, _frame):
        if stop.is_set() and signum == signal.SIGINT:
            if is_second_interrupt(first):
                raise KeyboardInterrupt
            return
        first.append(time.monotonic())
        on_stop(signum)
        stop.set()

    return handler


class Node:
    #: default node name (``-r __node:=`` overrides it)
    NAME = "node"
    PARAMETERS: list[ParameterSpec] = []

    def __init__(self, argv=(), *, name: str | None = None, namespace: str = "/", overrides=None,
                 dds: bool = True, domain_id: int | None = None, dds_config: str | None = None, log_stream=None,
                 rmw: str | None = None):
        default_name = validate_node_name(name or self.NAME)
        ros, rest = parse_ros_args(list(argv), default_name)
        if rest:
            raise InputError(f"{default_name}: unexpected arguments {rest}; pass settings as --ros-args -p name:=value")
        self.name = validate_node_name(ros.node_name or default_name)
        self.namespace = validate_namespace(ros.namespace or namespace)
        self.logger = RosLogger(self.name, ros.log_level or "info", log_stream)
        self.remaps = ros.remaps
        self.params = Parameters(self.PARAMETERS + [USE_SIM_TIME])
        unknown = []
        for f in ros.params_files:
            unknown += self.params.apply(load_params_file(f, self.name, self.namespace), f"--params-file {f}")
        if overrides:
            unknown += self.params.apply(dict(overrides), "overrides")
        unknown += self.params.apply(ros.params, "--ros-args -p")
        if unknown:
            self.logger.warn(f"ignoring parameters this node does not declare: {sorted(set(unknown))}")
        self._dds = None
        if dds:  # DDS, or Zenoh when RMW_IMPLEMENTATION=rmw_zenoh_cpp / rmw="rmw_zenoh_cpp" (zenoh_transport)
            from .zenoh_transport import open_transport

            self._dds = open_transport(self, domain_id, dds_config, rmw)
        self.bag: BagSink | None = None
        self.publishers: dict[str, Publisher] = {}
        self._subs = []
        self._stop = threading.Event()
        self._old_handlers = {}
        self._closed = False
        #: graph entry, /rosout and parameter services when on DDS (graph.attach); None otherwise
        self.ros = None
        self._clock_sub = None
        self._sim_ns = None                     # the latest /clock while use_sim_time is true
        if self._dds is not None:
            from .graph import attach

            self.ros = attach(self)
        self.params.listeners.append(self._on_params)
        self._follow_clock(bool(self.params["use_sim_time"]))

    # ----- names, endpoints
    def resolve(self, name: str) -> str:
        full = resolve_topic(name, self.namespace, self.name)
        return apply_remaps(full, self.remaps, self.namespace, self.name)

    @property
    def fully_qualified_name(self) -> str:
        return self.namespace.rstrip("/") + "/" + self.name

    @property
    def dds(self):
        return self._dds

    def create_publisher(self, topic: str, msgtype: str, qos="default", *, fast: bool = True) -> Publisher:
        full = self.resolve(topic)
        if full in self.publishers:
            raise InputError(f"{self.name}: topic {full} already has a publisher in this node")
        dds_pub = None
        if self._dds is not None:
            from .zenoh_transport import endpoint_classes

            pub_cls = endpoint_classes(self._dds)[0]
            dds_pub = pub_cls(self._dds, full, msgtype, qos_profile(qos), fast=fast, log=self.logger.log)
        pub = self.publishers[full] = Publisher(self, full, msgtype, dds_pub)
        if self.bag is not None:
            self.bag.add_topic(full, msgtype)
        return pub

    def create_subscription(self, topic: str, msgtype: str, qos="default", *, depth: int | None = None,
                            fast: bool = True):
        if self._dds is None:
            raise InputError(f"{self.name}: subscriptions need DDS (this node runs without it)")
        from .zenoh_transport import endpoint_classes

        sub_cls = endpoint_classes(self._dds)[1]
        sub = sub_cls(self._dds, self.resolve(topic), msgtype, qos_profile(qos, depth), fast=fast,
                      log=self.logger.log)
        self._subs.append(sub)
        return sub

    def record_to(self, path, topics=None, *, storage: str = "mcap") -> BagSink:
        """Record `topics` (names as given to create_publisher; None: all) into a new rosbag2."""
        resolved = None if topics is None else [self.resolve(t) for t in topics]
        self.bag = BagSink(path, resolved, storage=storage)
        for pub in self.publishers.values():
            self.bag.add_topic(pub.topic, pub.msgtype)
        return self.bag

    def check_qos(self) -> None:
        for ep in [p.dds for p in self.publishers.values() if p.dds is not None] + self._subs:
            ep.check_qos()

    # ----- time
    def now_ns(self) -> int:
        """The node's clock: /clock's latest time with use_sim_time (0 before the first, as rclpy), else
        time.time_ns()."""
        if self.params["use_sim_time"]:
            if self._clock_sub is not None:
                from .tf import clock_stamp_ns

                samples = self._clock_sub.take_raw(256)
                if samples:
                    self._sim_ns = clock_stamp_ns(samples[-1][0])
            return 0 if self._sim_ns is None else self._sim_ns
        import time

        return time.time_ns()

    def _on_params(self, changes: dict) -> None:
        if "use_sim_time" in changes:
            self._follow_clock(bool(changes["use_sim_time"]))

    def _follow_clock(self, on: bool) -> None:
        if not on or self._clock_sub is not None or self._dds is None:
            return
        from .tf import CLOCK_QOS, CLOCK_TOPIC, CLOCK_TYPE

        self._clock_sub = self.create_subscription(CLOCK_TOPIC, CLOCK_TYPE, CLOCK_QOS)

    # ----- lifecycle
    def ok(self) -> bool:
        return not self._stop.is_set()

    def request_stop(self) -> None:
        self._stop.set()

    def sleep(self, seconds: float) -> bool:
        """Sleep, waking early on a stop request; returns ok()."""
        if seconds > 0:
            self._stop.wait(seconds)
        return self.ok()

    def install_signal_handlers(self) -> None:
        """SIGINT / SIGTERM ask the loop to stop (a later second SIGINT raises KeyboardInterrupt)."""
        if threading.current_thread() is not threading.main_thread():
            return
        handler = stop_signal_handler(
            self._stop, lambda signum: self.logger.info(f"{signal.Signals(signum).name}: stopping"))

        for sig in (signal.SIGINT, signal.SIGTERM):
            self._old_handlers[sig] = signal.signal(sig, handler)

    def shutdown(self, *, failed: bool = False) -> None:
        """Close the bag (published when not `failed`, discarded otherwise) and DDS."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.bag is not None:
                if failed:
                    self.bag.abort()
                else:
                    self.bag.close()
                    self.logger.info(f"bag {self.bag.path}: {self.bag.messages} messages")
            for p in self.publishers.values():
                if p.dds is not None and p.dds.qos.reliability == "reliable" and p.subscribers():
                    p.dds.wait_for_acks(1.0)
        finally:
            if self.ros is not None:
                self.ros.close()
            if self._dds is not None:
                self._dds.close()
            for sig, old in self._old_handlers.items():
                signal.signal(sig, old)
            self._old_handlers.clear()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.shutdown(failed=exc_type is not None and not issubclass(exc_type, KeyboardInterrupt))
        return False
