"""feedback_projection: predicted 3-D blobs -> 2-D priors in every camera
(ALGORITHMS.md §1, "Inverse observation model").

Subscribes /artrack/prediction and the cameras' camera_info/extrinsics;
publishes /cameras/<cam>/blob_priors stamped with the frame they predict. Also
projects /artrack/refinement, the body of a frame the skeleton sends round the loop
again (its ``refine_passes``): those priors carry that frame's own stamp.
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node

from artrack.body_model import load_body_model
from artrack.errors import ArtrackError
from artrack.messages import body_from_msg, prior_array_msg
from artrack.pipeline import ProjectionStage
from artrack.projection import DEFAULT_CENTRE_OCCLUSION_LABELS, DEFAULT_OCCLUSION_SURFACE_SIGMA

from .common import (
    PREDICTION_TOPIC,
    REFINEMENT_TOPIC,
    RESULT_QOS,
    CameraRigListener,
    NodeDiagnostics,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)

PARAMS = [
    ("camera_names", ["cam01", "cam02", "cam03", "cam04"], "cameras to project into"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("occlusion_surface_sigma", DEFAULT_OCCLUSION_SURFACE_SIGMA,
     "a prior is occluded when its line of sight, stopped this many of the blob's standard deviations "
     "short of its mean, passes through another link (0: stopped 5 cm short)"),
    ("centre_occlusion_labels", list(DEFAULT_CENTRE_OCCLUSION_LABELS),
     "blobs whose line of sight runs to their mean (less 5 cm) whatever their extent"),
]
LIMITS = {"occlusion_surface_sigma": (0.0, 10.0)}


class FeedbackProjectionNode(Node):
    """The feedback_projection node (module docstring): the predicted body's blobs as 2-D priors per camera."""

    def __init__(self):
        super().__init__("feedback_projection")
        p = declare_all(self, PARAMS, LIMITS, runtime={})  # all read-only once running
        self.names = list(p["camera_names"])
        self.body = load_body_model(p["body_model"] or None)
        self.occlusion_surface_sigma = float(p["occlusion_surface_sigma"])
        self.centre_occlusion_labels = [str(x) for x in p["centre_occlusion_labels"]]
        self.stage: ProjectionStage | None = None
        self.waiting: list = []
        f = msgs()
        self.pubs = {n: self.create_publisher(f.cls("artrack_msgs/msg/BlobPrior2DArray"),
                                              camera_topic(n, "blob_priors"), RESULT_QOS) for n in self.names}
        self.rig = CameraRigListener(self, self.names, self.on_cameras)
        self.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), PREDICTION_TOPIC, self.on_prediction,
                                 RESULT_QOS)
        self.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), REFINEMENT_TOPIC, self.on_prediction,
                                 RESULT_QOS)
        self.diag = NodeDiagnostics(self, update=lambda d: d.set("waiting_for_cameras", self.stage is None))

    def on_cameras(self, cameras) -> None:
        self.stage = ProjectionStage(self.body, cameras, self.occlusion_surface_sigma, self.centre_occlusion_labels)
        for msg in self.waiting:
            self.on_prediction(msg)
        self.waiting.clear()

    def on_prediction(self, msg) -> None:
        if self.stage is None:
            self.waiting.append(msg)
            return
        self.diag.input()
        t0 = time.monotonic()
        try:
            prediction = body_from_msg(msg)
            priors = self.stage.step(prediction)
        except (ArtrackError, ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad prediction on {PREDICTION_TOPIC} or {REFINEMENT_TOPIC}: {exc}")
            self.diag.drop()
            return
        self.diag.processed(time.monotonic() - t0)
        f = msgs()
        for name in self.names:
            self.pubs[name].publish(prior_array_msg(f, prediction.stamp_ns, name, f"{name}_optical_frame",
                                                    priors.get(name, [])))


def main(args=None) -> None:
    sys.exit(run_node(FeedbackProjectionNode, __doc__, PARAMS, args, LIMITS))


if __name__ == "__main__":
    main()
