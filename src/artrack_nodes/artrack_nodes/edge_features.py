"""edge_features: one camera's edge measurements about the predicted body (ALGORITHMS.md §2).

Subscribes /cameras/<cam>/image_raw, the camera's camera_info and extrinsics, and
/artrack/prediction. For each image it tracks the body's contour edges in its view from the
prediction for that frame (contour samples of the quadric body, 1-D search along the image
normals with edge polarity, robust per-link motion statistics, eqs. 7-10, Algorithm 1; a few
cycles), measures them at the pose reached (artrack.edge_fusion.EdgeStage) and publishes
/cameras/<cam>/edge_statistics (artrack_msgs/LinkEdgeStatistics, information form; empty when
there is no prediction with links), which the skeleton node fuses with the blobs ("Fusion").
In lockstep mode every image after the first waits for the prediction of its frame. In lockstep
(with ``answer_refinements``, the default) a body on /artrack/refinement stamped with the frame just
measured sends that frame round again (the skeleton's ``refine_passes`` and
``startup_refine_frames``): the node goes back to its state before the frame, a copy of which it
keeps every frame, and measures the same image about that body, as blob_features labels it again
(``ClosedLoopPipeline.step``). Without it, such a body is logged once and left unanswered (the
skeleton then switches refinement off after its ``refine_timeout_s``).
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node

from artrack.body_model import load_body_model
from artrack.config import config_path
from artrack.edge_fusion import EdgeStage
from artrack.edge_tracker import EdgeTrackerConfig
from artrack.errors import ArtrackError
from artrack.messages import body_from_msg, edge_stats_msg
from artrack.pipeline import link_poses

from .common import (
    IMAGE_QOS_RELIABLE,
    IMAGE_QOS_SENSOR,
    PREDICTION_TOPIC,
    REFINEMENT_TOPIC,
    RESULT_QOS,
    CameraRigListener,
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
    ("lockstep", False, "wait for the prediction of each frame (reproducible replay); reliable image QoS"),
    ("fps", 30.0, "nominal frame rate, Hz (prediction-to-frame matching tolerance is half a frame)"),
    ("prediction_timeout_s", 10.0, "lockstep: give up waiting for a prediction after this long, s"),
    ("loop_wait_s", 0.5, "free-running: after a frame, wait up to this long for the skeleton's prediction from it "
                         "before taking the newest image without one, s (0: every image as it comes)"),
    ("answer_refinements", True, "lockstep: keep a copy of the state before each frame and answer the skeleton's "
                                 "refinement bodies (/artrack/refinement) stamped with the frame just processed by "
                                 "measuring it again"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("edge_config", "", "edge tracker tunables YAML (empty: config/edge_features.yaml)"),
]
LIMITS = {"fps": (1.0, 1000.0), "prediction_timeout_s": (0.0, 3600.0), "loop_wait_s": (0.0, 60.0)}
RUNTIME = ("prediction_timeout_s",)


class EdgeFeaturesNode(Node):
    """The edge_features node (module docstring): one camera's edge statistics about the predicted body."""

    def __init__(self):
        super().__init__("edge_features")
        p = declare_all(self, PARAMS, LIMITS,
                        {"prediction_timeout_s": lambda v: setattr(self.queue, "timeout_s", float(v))})
        self.camera = p["camera_name"]
        self.lockstep = bool(p["lockstep"])
        self.timeout_s = float(p["prediction_timeout_s"])
        self.body = load_body_model(p["body_model"] or None)
        self.edge_config = EdgeTrackerConfig.from_yaml(config_path(p["edge_config"], "edge_features.yaml"))
        self.stage: EdgeStage | None = None
        f = msgs()
        self.pub = self.create_publisher(f.cls("artrack_msgs/msg/LinkEdgeStatistics"),
                                         camera_topic(self.camera, "edge_statistics"), RESULT_QOS)
        self.rig = CameraRigListener(self, [self.camera], self.on_camera)
        self.create_subscription(f.cls("sensor_msgs/msg/Image"), camera_topic(self.camera, "image_raw"),
                                 self.on_image, IMAGE_QOS_RELIABLE if self.lockstep else IMAGE_QOS_SENSOR)
        self.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), PREDICTION_TOPIC, self.on_prediction,
                                 RESULT_QOS)
        # (a free-running node has moved past the frame a refinement asks for: it never answers)
        self.refine = bool(p["answer_refinements"]) and self.lockstep
        self.before = FrameBefore() if self.refine else None  # the frame last processed, its state before
        self.refined = 0  # passes measured again (diagnostics)
        self.told_no_refine = False  # a refinement came without answer_refinements (logged once)
        self.last_stamp: int | None = None  # the frame last measured
        if self.lockstep:
            self.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), REFINEMENT_TOPIC, self.on_refinement,
                                     RESULT_QOS)
        self.queue = FrameQueue(self, self.lockstep, float(p["fps"]), self.timeout_s, "prediction",
                                loop_wait_s=float(p["loop_wait_s"]))
        self.frames = 0
        self.diag = NodeDiagnostics(self, update=self._report)
        self.diag.set("prediction_staleness_s", float("nan"))
        self.create_timer(0.1, self.process_queue)
        self.get_logger().info(f"edge_features for {self.camera} (lockstep={self.lockstep})")

    def _report(self, diag) -> None:
        diag.set("images_skipped", self.queue.skipped)
        if self.refine:
            diag.set("passes_refined", self.refined)

    def on_camera(self, cameras) -> None:
        self.stage = EdgeStage(cameras[0], self.body, self.edge_config)
        self.process_queue()

    def on_image(self, msg, info) -> None:
        self.diag.input()
        if self.queue.add_image_msg(msg, camera_topic(self.camera, "image_raw"), received_ns(info)):
            self.process_queue()
        else:
            self.diag.drop()

    def _reference(self, msg, topic: str):
        """(stamp, link poses or None, status) of a TrackedBody; None (logged) if it is bad."""
        try:
            body = body_from_msg(msg)
            poses = link_poses(body)
            if poses is not None and len(poses) != len(self.body.links):
                raise ValueError(f"field 'links' has {len(poses)} links, the body model {len(self.body.links)}")
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad TrackedBody on {topic}: {exc}")
            return None
        return body.stamp_ns, poses, body.status

    def on_prediction(self, msg, info) -> None:
        ref = self._reference(msg, PREDICTION_TOPIC)
        if ref is None:
            return
        self.queue.add_input(ref[0], ref[1:], received_ns(info))
        self.process_queue()

    def on_refinement(self, msg) -> None:
        """The skeleton's body of a frame's previous pass: the frame last measured, measured again
        from the state before it about that body; the statistics go out with the frame's stamp."""
        ref = self._reference(msg, REFINEMENT_TOPIC)
        if ref is not None and not self.refine and ref[0] == self.last_stamp and not self.told_no_refine:
            self.get_logger().warning(f"refinement of frame {ref[0]}, the frame just measured: not measured again, "
                                      "this node runs without answer_refinements in lockstep")
            self.told_no_refine = True
        if ref is None or self.before is None or ref[0] != self.before.stamp or self.stage is None:
            return
        self.stage = self.before.again()
        if self._measure(ref[0], self.before.image, ref[1], ref[2], ref[0], ", refinement"):
            self.refined += 1

    def process_queue(self) -> None:
        if self.stage is None:  # the camera's calibration has not arrived yet
            return
        for stamp, image, found in self.queue.ready(lambda: self.frames == 0):
            ref_stamp, (reference, status) = found if found is not None else (0, (None, None))
            if self.before is not None:  # (what a step never changes: the body model, the camera, the tunables)
                self.before.keep(stamp, image, self.stage, [self.body, self.stage.camera, self.edge_config])
            self.last_stamp = stamp
            if self._measure(stamp, image, reference, status, ref_stamp):
                self.frames += 1

    def _measure(self, stamp: int, image, reference, status, ref_stamp: int, context: str = "") -> bool:
        """The edge statistics of one image about ``reference`` (link poses, None: no body),
        published with the frame's stamp; False (logged, counted as a drop) on a bad image."""
        t0 = time.monotonic()
        try:
            stats = self.stage.step(image, reference, status) if reference is not None else None
        except (ArtrackError, ValueError) as exc:
            self.get_logger().error(f"frame {stamp}{context}: {exc}")
            self.diag.drop()
            return False
        self.diag.processed(time.monotonic() - t0)
        self.diag.set("prediction_staleness_s", (stamp - ref_stamp) * 1e-9 if reference is not None
                      else float("nan"))
        self.pub.publish(edge_stats_msg(msgs(), stamp, self.camera, f"{self.camera}_optical_frame",
                                        self.body.link_names, stats, ref_stamp))
        return True


def main(args=None) -> None:
    sys.exit(run_node(EdgeFeaturesNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
