"""bag_recorder: records topics of the graph into a rosbag2 .mcap.

Subscribes (serialized, no decoding) to every topic matching the `topics`
patterns as soon as it appears, and writes the CDR bytes with their types
(artrack_msgs included) into a bag that is moved into place only when the
recorder shuts down cleanly (SIGINT/SIGTERM), so no half-written bag is left.
"""

from __future__ import annotations

import fnmatch
import importlib
import sys

from rclpy.node import Node

from artrack.bags import BagWriter

from .common import RECORD_QOS, declare_all, run_node

PARAMS = [
    ("out", "out/recording", "output bag (rosbag2 folder; storage mcap)"),
    ("topics", ["/artrack/*", "/cameras/*/blobs", "/cameras/*/blob_priors", "/cameras/*/edge_statistics"],
     "topic patterns (fnmatch) to record"),
]


def _msg_class(type_name: str):
    pkg, sub, cls = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.{sub}"), cls)


class BagRecorderNode(Node):
    """The bag_recorder node (module docstring): matching topics written, serialized, to a .mcap."""

    def __init__(self):
        super().__init__("bag_recorder")
        p = declare_all(self, PARAMS, runtime={})  # all read-only once running
        self.patterns = list(p["topics"])
        self.writer = BagWriter(p["out"])
        self.writer.__enter__()
        self.subscribed: set[str] = set()
        self.count = 0
        self.create_timer(0.2, self.discover)
        self.discover()
        self.get_logger().info(f"recording {self.patterns} to {p['out']}")

    def discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subscribed or not any(fnmatch.fnmatch(topic, pat) for pat in self.patterns):
                continue
            try:
                cls = _msg_class(types[0])
            except (ImportError, AttributeError, ValueError):
                self.get_logger().error(f"cannot record {topic}: unknown type {types[0]}")
                self.subscribed.add(topic)
                continue
            self.writer.add_topic(topic, types[0])
            self.create_subscription(cls, topic, lambda data, t=topic: self.on_message(t, data), RECORD_QOS, raw=True)
            self.subscribed.add(topic)

    def on_message(self, topic: str, data: bytes) -> None:
        self.writer.write_raw(topic, self.get_clock().now().nanoseconds, data)
        self.count += 1

    def close(self) -> None:
        self.writer.__exit__(None, None, None)
        self.get_logger().info(f"wrote {self.count} messages")


def main(args=None) -> None:
    sys.exit(run_node(BagRecorderNode, __doc__, PARAMS, args))


if __name__ == "__main__":
    main()
