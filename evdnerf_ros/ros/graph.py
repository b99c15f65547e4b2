"""ROS 2 graph presence over DDS: ``ros_discovery_info`` and the node's standard interfaces.

``ros2 node list`` / ``ros2 node info`` build the node graph from each participant's
``ros_discovery_info`` sample (rmw_dds_common/msg/ParticipantEntitiesInfo: the
participant's GID and, per node, its namespace, name and the GIDs of its readers and
writers). rmw_cyclonedds and rmw_fastrtps publish it on the DDS topic
``ros_discovery_info`` (no ``rt/`` prefix) as reliable, transient local, keep-last 1,
and republish it whenever the node's endpoints change. A GID is the entity's 16-byte
DDS GUID (Iron and later; 24 bytes before). Endpoints also carry ``typehash=RIHS01_...;``
and the participant ``enclave=/;`` in their USER_DATA (see :mod:`.transport`), so
``ros2 topic info -v`` shows the type hash.

:func:`attach` gives a node, when it runs on DDS: the graph entry, ``/rosout``
(:mod:`.rosout`), ``/parameter_events`` and the parameter services
(:mod:`.param_services`). A malformed ``ros_discovery_info`` sample from the network is
logged and skipped (:func:`parse_discovery_info`), never fatal.
"""

from __future__ import annotations

import threading

from ..errors import EvdnerfError
from .qos import QosProfile, RELIABLE, TRANSIENT_LOCAL

DISCOVERY_TOPIC = "ros_discovery_info"
PARTICIPANT_INFO = "rmw_dds_common/msg/ParticipantEntitiesInfo"
DISCOVERY_QOS = QosProfile(RELIABLE, TRANSIENT_LOCAL, 1)


def gid_hex(gid: bytes) -> str:
    return bytes(gid).hex()


class ParticipantGraph:
    """The participant's ``ros_discovery_info``: one entry per node on this DDS context."""

    def __init__(self, ctx, log=None):
        import numpy as np

        from . import rostypes
        from .transport import DdsPublisher

        self.ctx = ctx
        self._np = np
        self._log = log or (lambda level, msg: None)
        self._lock = threading.Lock()
        self.nodes: dict[tuple[str, str], dict[str, list[bytes]]] = {}
        self._current: tuple[str, str] | None = None
        self.writer = DdsPublisher(ctx, "/" + DISCOVERY_TOPIC, PARTICIPANT_INFO, DISCOVERY_QOS,
                                   dds_name=DISCOVERY_TOPIC, idl=rostypes.idl_struct(PARTICIPANT_INFO), log=log)
        self.published = 0
        ctx.on_endpoint = self._endpoint

    def add_node(self, namespace: str, name: str) -> None:
        """Endpoints created from now on belong to this node (until the next add_node)."""
        with self._lock:
            self.nodes.setdefault((namespace, name), {"reader": [], "writer": []})
            self._current = (namespace, name)
        self.publish()

    def _endpoint(self, kind: str, gid: bytes) -> None:
        with self._lock:
            if self._current is None:
                return
            self.nodes[self._current][kind].append(bytes(gid))
        self.publish()

    def message(self):
        from . import rostypes

        np = self._np

        def gid(b):
            return rostypes.message("rmw_dds_common/msg/Gid", data=np.frombuffer(bytes(b).ljust(16, b"\0"), np.uint8))

        with self._lock:
            nodes = [rostypes.message("rmw_dds_common/msg/NodeEntitiesInfo", node_namespace=ns, node_name=name,
                                      reader_gid_seq=[gid(g) for g in ep["reader"]],
                                      writer_gid_seq=[gid(g) for g in ep["writer"]])
                     for (ns, name), ep in self.nodes.items()]
        return rostypes.message(PARTICIPANT_INFO, gid=gid(self.ctx.gid), node_entities_info_seq=nodes)

    def publish(self) -> None:
        from . import rostypes

        try:
            self.writer.publish_raw(rostypes.serialize(self.message(), PARTICIPANT_INFO))
            self.published += 1
        except EvdnerfError as exc:
            self._log("warn", f"{DISCOVERY_TOPIC}: could not publish the graph ({exc})")


def parse_discovery_info(data, log=None):
    """A received ``ros_discovery_info`` sample -> {"gid": hex, "nodes": [{namespace, name,
    readers: [hex], writers: [hex]}]}; None (and a warning) when it does not decode."""
    from . import rostypes

    try:
        msg = rostypes.deserialize(bytes(data), PARTICIPANT_INFO)
        return {"gid": gid_hex(bytes(msg.gid.data)),
                "nodes": [{"namespace": n.node_namespace, "name": n.node_name,
                           "readers": [gid_hex(bytes(g.data)) for g in n.reader_gid_seq],
                           "writers": [gid_hex(bytes(g.data)) for g in n.writer_gid_seq]}
                          for n in msg.node_entities_info_seq]}
    except Exception as exc:  # noqa: BLE001 - bytes from the network
        if log is not None:
            log("warn", f"{DISCOVERY_TOPIC}: ignored a malformed sample ({len(bytes(data))} bytes: "
                        f"{exc.__class__.__name__}: {exc})")
        return None


class RosInterfaces:
    """What :func:`attach` adds to a node: graph entry, /rosout, parameters over DDS."""

    def __init__(self, node):
        from .param_services import ParameterServer
        from .rosout import RosoutPublisher

        ctx = node.dds
        graph = getattr(ctx, "ros_graph", None)
        if graph is None:
            graph = ctx.ros_graph = ParticipantGraph(ctx, log=node.logger.log)
        self.graph = graph
        graph.add_node(node.namespace, node.name)
        self.rosout = RosoutPublisher(node)
        self.params = ParameterServer(node)

    def close(self) -> None:
        self.params.close()
        self.rosout.close()


def attach(node):
    """Graph presence, /rosout and parameter services for `node` when it runs on DDS
    (Cyclone); None for other transports or without DDS."""
    from .transport import DdsContext

    if not isinstance(node.dds, DdsContext):
        return None
    return RosInterfaces(node)
