"""blob_features: one camera's 2-D blob tracker (ALGORITHMS.md §1, "2-D blobs").

Subscribes /cameras/<cam>/image_raw and /cameras/<cam>/blob_priors, publishes
/cameras/<cam>/blobs. In lockstep mode every image after the first waits for
the prior that predicts it (so results are reproducible); in free-running mode
the newest prior is used and its staleness reported in the message. In lockstep (with
``answer_refinements``, the default) priors stamped with the frame just processed send that frame
round again (the skeleton's ``refine_passes`` and ``startup_refine_frames``): the node goes back
to its state before the frame, a copy of which it keeps every frame (~1-2 ms), and labels the same
image with them (``ClosedLoopPipeline.step``). Without it, such priors are logged once and left
unanswered (the skeleton gives the refinement up after its ``refine_timeout_s``).
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node

from artrack.body_model import load_body_model
from artrack.errors import ArtrackError
from artrack.messages import blob_array_msg, priors_from_msg
from artrack.pipeline import BlobStage, load_pipeline_config

from .common import (
    IMAGE_QOS_RELIABLE,
    IMAGE_QOS_SENSOR,
    RESULT_QOS,
    FrameBefore,
    FrameQueue,
    NodeDiagnostics,
    camera_topic,
    declare_all,
    msgs,
    received_ns,
    run_node,
)

PARAMS = [
    ("camera_name", "cam01", "camera this node serves (topic /cameras/<camera_name>/...)"),
    ("lockstep", False, "wait for the prior predicting each frame (reproducible replay); reliable image QoS"),
    ("feedback", True, "use the projected 3-D priors; false = 2-D temporal smoothness once tracking "
                 "(priors only label the start-up blobs)"),
    ("fps", 30.0, "nominal frame rate, Hz (prior-to-frame matching tolerance is half a frame)"),
    ("prior_timeout_s", 10.0, "lockstep: give up waiting for a prior after this long, s"),
    ("loop_wait_s", 0.5, "free-running: after a frame, wait up to this long for the skeleton's prior from it "
                         "before taking the newest image without one, s (0: every image as it comes)"),
    ("answer_refinements", True, "lockstep: keep a copy of the state before each frame and answer priors stamped "
                                 "with the frame just processed (the skeleton's refinement) by labelling it again"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("blob_config", "", "blob tracker tunables YAML (empty: config/blob_features.yaml)"),
]
LIMITS = {"fps": (1.0, 1000.0), "prior_timeout_s": (0.0, 3600.0), "loop_wait_s": (0.0, 60.0)}
#: run-time changeable (ros2 param set): feedback on/off, the lockstep prior timeout
RUNTIME = ("feedback", "prior_timeout_s")


class BlobFeaturesNode(Node):
    """The blob_features node (module docstring): one camera's images and priors in, its 2-D blobs out."""

    def __init__(self):
        super().__init__("blob_features")
        p = declare_all(self, PARAMS, LIMITS, {"feedback": lambda v: setattr(self.stage, "feedback", bool(v)),
                                               "prior_timeout_s": lambda v: setattr(self.queue, "timeout_s", float(v))})
        self.camera = p["camera_name"]
        self.lockstep = bool(p["lockstep"])
        self.prior_timeout_s = float(p["prior_timeout_s"])
        config = load_pipeline_config(feedback=bool(p["feedback"]), fps=float(p["fps"]), blob_config=p["blob_config"])
        body = load_body_model(p["body_model"] or None)
        self.stage = BlobStage(self.camera, body, config)
        self._shared = [body, config]  # never changed by a step (state_copy)
        f = msgs()
        self.pub = self.create_publisher(f.cls("artrack_msgs/msg/Blob2DArray"), camera_topic(self.camera, "blobs"),
                                         RESULT_QOS)
        self.create_subscription(f.cls("sensor_msgs/msg/Image"), camera_topic(self.camera, "image_raw"),
                                 self.on_image, IMAGE_QOS_RELIABLE if self.lockstep else IMAGE_QOS_SENSOR)
        self.create_subscription(f.cls("artrack_msgs/msg/BlobPrior2DArray"), camera_topic(self.camera, "blob_priors"),
                                 self.on_priors, RESULT_QOS)
        self.queue = FrameQueue(self, self.lockstep, float(p["fps"]), self.prior_timeout_s, "prior",
                                loop_wait_s=float(p["loop_wait_s"]))
        self.frames = 0
        # (a free-running node has moved past the frame a refinement asks for: it never answers)
        self.refine = bool(p["answer_refinements"]) and self.lockstep
        self.before = FrameBefore() if self.refine else None  # the frame last processed, its state before
        self.last_stamp: int | None = None  # the frame last processed
        self.told_no_refine = False  # a refinement's priors came without answer_refinements (logged once)
        self.refined = 0  # passes run again (diagnostics)
        self.diag = NodeDiagnostics(self, update=self._report)
        self.diag.set("prior_staleness_s", float("nan"))
        self.create_timer(0.1, self.process_queue)
        self.get_logger().info(f"blob_features for {self.camera} (lockstep={self.lockstep})")

    def _report(self, diag) -> None:
        diag.set("images_skipped", self.queue.skipped)
        if self.refine:
            diag.set("passes_refined", self.refined)

    def on_image(self, msg, info) -> None:
        self.diag.input()
        if self.queue.add_image_msg(msg, camera_topic(self.camera, "image_raw"), received_ns(info)):
            self.process_queue()
        else:
            self.diag.drop()

    def on_priors(self, msg, info) -> None:
        try:
            stamp, _, priors = priors_from_msg(msg)
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad prior message on {camera_topic(self.camera, 'blob_priors')}: {exc}")
            return
        if self.before is not None and stamp == self.before.stamp:
            self.refine_frame(priors)
            return
        if not self.refine and stamp == self.last_stamp:
            if not self.told_no_refine:
                self.get_logger().warning(f"priors for frame {stamp}, the frame just labelled (the skeleton refines "
                                          "it): not labelled again, this node runs without answer_refinements "
                                          "in lockstep")
                self.told_no_refine = True
            return
        self.queue.add_input(stamp, priors, received_ns(info))
        self.process_queue()

    def process_queue(self) -> None:
        for stamp, image, found in self.queue.ready(lambda: self.frames == 0):
            prior_stamp, priors = found if found is not None else (None, None)
            self.last_stamp = stamp
            if self.before is not None:
                self.before.keep(stamp, image, self.stage, self._shared)
            if self._label(stamp, image, priors, prior_stamp):
                self.frames += 1

    def refine_frame(self, priors) -> None:
        """The frame last processed, labelled again from the state before it with these priors
        (the body of its previous pass, projected); the blobs go out with the frame's stamp."""
        stamp = self.before.stamp
        feedback = self.stage.feedback  # (as set now: a run-time parameter)
        self.stage = self.before.again()
        self.stage.feedback = feedback
        if self._label(stamp, self.before.image, priors, stamp, ", refinement"):
            self.refined += 1

    def _label(self, stamp: int, image, priors, prior_stamp: int | None, context: str = "") -> bool:
        """The blobs of one image with the priors stamped ``prior_stamp`` (None: none), published
        with the frame's stamp; False (logged, counted as a drop) if the tracker refused the image."""
        t0 = time.monotonic()
        try:
            blobs = self.stage.step(image, priors)
        except ArtrackError as exc:
            self.get_logger().error(f"frame {stamp}{context}: {exc}")
            self.diag.drop()
            return False
        self.diag.processed(time.monotonic() - t0)
        used = prior_stamp if (priors is not None and self.stage.used_priors) else None
        self.diag.set("prior_staleness_s", (stamp - used) * 1e-9 if used is not None else float("nan"))
        self.pub.publish(blob_array_msg(msgs(), stamp, self.camera, f"{self.camera}_optical_frame", blobs, used))
        return True

def main(args=None) -> None:
    sys.exit(run_node(BlobFeaturesNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
