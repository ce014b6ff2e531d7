"""blob_features: one camera's 2-D blob tracker (ALGORITHMS.md §1, "2-D blobs").

Subscribes /cameras/<cam>/image_raw and /cameras/<cam>/blob_priors, publishes
/cameras/<cam>/blobs. In lockstep mode every image after the first waits for
the prior that predicts it (so results are reproducible); in free-running mode
the newest prior is used and its staleness reported in the message.
"""

from __future__ import annotations

import sys
import time
from collections import deque

from rclpy.node import Node

from artrack.body_model import load_body_model
from artrack.errors import ArtrackError
from artrack.messages import bgr_from_image_msg, blob_array_msg, ns_from_time, priors_from_msg
from artrack.pipeline import BlobStage, load_pipeline_config

from .common import (
    IMAGE_QOS_RELIABLE,
    IMAGE_QOS_SENSOR,
    RESULT_QOS,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)

PARAMS = [
    ("camera_name", "cam01", "camera this node serves (topic /cameras/<camera_name>/...)"),
    ("lockstep", False, "wait for the prior predicting each frame (reproducible replay); reliable image QoS"),
    ("feedback", True, "use the projected 3-D priors; false = 2-D temporal smoothness once tracking "
                 "(priors only label the start-up blobs)"),
    ("fps", 30.0, "nominal frame rate, Hz (prior-to-frame matching tolerance is half a frame)"),
    ("prior_timeout_s", 10.0, "lockstep: give up waiting for a prior after this long, s"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("blob_config", "", "blob tracker tunables YAML (empty: config/blob_features.yaml)"),
]


class BlobFeaturesNode(Node):
    def __init__(self):
        super().__init__("blob_features")
        p = declare_all(self, PARAMS)
        self.camera = p["camera_name"]
        self.lockstep = bool(p["lockstep"])
        self.tol_ns = int(0.5e9 / float(p["fps"]))
        self.prior_timeout_s = float(p["prior_timeout_s"])
        config = load_pipeline_config(feedback=bool(p["feedback"]), fps=float(p["fps"]), blob_config=p["blob_config"])
        self.stage = BlobStage(self.camera, load_body_model(p["body_model"] or None), config)
        f = msgs()
        self.pub = self.create_publisher(f.cls("artrack_msgs/msg/Blob2DArray"), camera_topic(self.camera, "blobs"),
                                         RESULT_QOS)
        self.create_subscription(f.cls("sensor_msgs/msg/Image"), camera_topic(self.camera, "image_raw"),
                                 self.on_image, IMAGE_QOS_RELIABLE if self.lockstep else IMAGE_QOS_SENSOR)
        self.create_subscription(f.cls("artrack_msgs/msg/BlobPrior2DArray"), camera_topic(self.camera, "blob_priors"),
                                 self.on_priors, RESULT_QOS)
        self.priors: dict[int, list] = {}
        self.queue: deque = deque()
        self.frames = 0
        self.create_timer(0.1, self.process_queue)
        self.get_logger().info(f"blob_features for {self.camera} (lockstep={self.lockstep})")

    def on_image(self, msg) -> None:
        try:
            image = bgr_from_image_msg(msg, camera_topic(self.camera, "image_raw"))
        except ValueError as exc:
            self.get_logger().error(f"dropped bad image: {exc}")
            return
        self.queue.append((ns_from_time(msg.header.stamp), image, time.monotonic()))
        self.process_queue()

    def on_priors(self, msg) -> None:
        try:
            stamp, _, priors = priors_from_msg(msg)
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad prior message on {camera_topic(self.camera, 'blob_priors')}: {exc}")
            return
        self.priors[stamp] = priors
        for old in sorted(self.priors)[:-8]:
            del self.priors[old]
        self.process_queue()

    def _prior_for(self, stamp: int) -> tuple[int, list] | None:
        """Lockstep: the prior predicting this frame; free-running: the newest not after it."""
        if self.lockstep:
            for s, pri in self.priors.items():
                if abs(s - stamp) <= self.tol_ns:
                    return s, pri
            return None
        older = [s for s in self.priors if s <= stamp + self.tol_ns]
        return (max(older), self.priors[max(older)]) if older else None

    def process_queue(self) -> None:
        while self.queue:
            stamp, image, arrived = self.queue[0]
            found = self._prior_for(stamp)
            if self.lockstep and self.frames > 0 and found is None:
                if time.monotonic() - arrived < self.prior_timeout_s:
                    return
                self.get_logger().warning(f"no prior for frame {stamp} after {self.prior_timeout_s}s; going on")
            self.queue.popleft()
            if not self.lockstep:  # free-running: only the newest image matters
                while self.queue:
                    stamp, image, arrived = self.queue.popleft()
                found = self._prior_for(stamp)
            prior_stamp, priors = found if found is not None else (None, None)
            if self.frames == 0:
                prior_stamp, priors = None, None
            try:
                blobs = self.stage.step(image, priors)
            except ArtrackError as exc:
                self.get_logger().error(f"frame {stamp}: {exc}")
                continue
            self.frames += 1
            used = prior_stamp if (priors is not None and self.stage.used_priors) else None
            self.pub.publish(blob_array_msg(msgs(), stamp, self.camera, f"{self.camera}_optical_frame", blobs, used))


def main(args=None) -> None:
    sys.exit(run_node(BlobFeaturesNode, __doc__, PARAMS, args))


if __name__ == "__main__":
    main()
