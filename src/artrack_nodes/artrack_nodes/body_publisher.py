"""body_publisher: the tracked body for standard ROS 2 tools (REP 155, TF, RViz / Foxglove).

Subscribes /artrack/body and /artrack/prediction (artrack_msgs/TrackedBody) and publishes,
with standard message types only (artrack/rep155.py, artrack/markers.py):
- /humans/bodies/tracked (hri_msgs/IdsList): ids of the bodies being tracked (REP 155);
- /tf (tf2_msgs/TFMessage): world -> body_<id> (mid-hip, x forward, z up) -> one frame per
  link <link>_<id> and per output joint <joint>_<id>;
- /humans/bodies/<id>/joint_states (sensor_msgs/JointState) and /humans/bodies/<id>/urdf
  (std_msgs/String, transient local; the tracked body's dimensions), which together drive
  robot_state_publisher to the same frames;
- /artrack/markers (visualization_msgs/MarkerArray: bones, joints, blob ellipsoids, predicted
  priors, status) and /artrack/link_poses (geometry_msgs/PoseArray);
- /diagnostics (diagnostic_msgs/DiagnosticArray): input rate, processing time, tracking status.
A body that is starting up or lost leaves the tracked list and is not put on /tf.
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from artrack.body_model import load_body_model
from artrack.errors import ArtrackError
from artrack.markers import STATUS_NAMES, MarkerBuilder
from artrack.messages import body_from_msg
from artrack.rep155 import TF_TOPIC, TRACKED_TOPIC, BodyFrames, body_topic, ids_list_msg, joint_state_msg, tf_message
from artrack.types import STATUS_LOST, STATUS_TRACKING

from .common import (
    BODY_TOPIC,
    LATCHED_QOS,
    PREDICTION_TOPIC,
    RESULT_QOS,
    NodeDiagnostics,
    declare_all,
    msgs,
    run_node,
)

PARAMS = [
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("id_prefix", "b", "REP 155 id of a body: this prefix + TrackedBody.body_id (an id must start with a letter: "
                       "it is a topic name token, /humans/bodies/<id>/...)"),
    ("publish_tf", True, "put the body on /tf (false: leave it to robot_state_publisher with the URDF and "
                         "joint_states)"),
    ("publish_markers", True, "publish /artrack/markers and /artrack/link_poses"),
    ("marker_sigmas", 2.0, "blob ellipsoids drawn at this many standard deviations"),
    ("marker_lifetime_s", 1.0, "markers vanish after this long without a new body, s (0: never)"),
    ("urdf_tolerance_m", 0.001, "republish the URDF when a measured dimension moved by more than this, m"),
]
LIMITS = {"marker_sigmas": (0.1, 5.0), "marker_lifetime_s": (0.0, 60.0), "urdf_tolerance_m": (1e-6, 0.5)}
RUNTIME = ("publish_tf", "publish_markers", "marker_sigmas", "marker_lifetime_s", "urdf_tolerance_m")

#: /tf as tf2's TransformBroadcaster: reliable, volatile, last 100.
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
#: /humans/bodies/tracked and joint_states: reliable, volatile, last 10.
STATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
#: markers and link poses: reliable, transient local, last 10 (a view opened late shows the newest
#: body; the bag recorder's transient-local readers can record them for Foxglove).
VIEW_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
MARKERS_TOPIC = "/artrack/markers"
POSES_TOPIC = "/artrack/link_poses"


class BodyPublisherNode(Node):
    """The body_publisher node (module docstring): the tracked body as REP 155 TF, joint states and markers."""

    def __init__(self):
        super().__init__("body_publisher")
        self.p = declare_all(self, PARAMS, LIMITS, {k: (lambda v, k=k: self._set(k, v)) for k in RUNTIME})
        self.body = load_body_model(self.p["body_model"] or None)
        prefix = str(self.p["id_prefix"])
        if not (prefix[:1].isalpha() and prefix.replace("_", "").isalnum()):
            raise ArtrackError(f"parameter 'id_prefix' is '{prefix}': it must start with a letter and hold only "
                               "letters, digits and '_'")
        f = msgs()
        self.frames: dict[str, BodyFrames] = {}
        self.urdf_dims: dict[str, object] = {}
        self.predictions: dict[int, object] = {}
        self.markers = MarkerBuilder(f, self.body, sigmas=float(self.p["marker_sigmas"]),
                                     lifetime_s=float(self.p["marker_lifetime_s"]))
        self.tracked_pub = self.create_publisher(f.cls("hri_msgs/msg/IdsList"), TRACKED_TOPIC, STATE_QOS)
        self.tf_pub = self.create_publisher(f.cls("tf2_msgs/msg/TFMessage"), TF_TOPIC, TF_QOS)
        self.marker_pub = self.create_publisher(f.cls("visualization_msgs/msg/MarkerArray"), MARKERS_TOPIC, VIEW_QOS)
        self.pose_pub = self.create_publisher(f.cls("geometry_msgs/msg/PoseArray"), POSES_TOPIC, VIEW_QOS)
        self.joint_pubs: dict[str, object] = {}
        self.urdf_pubs: dict[str, object] = {}
        body_cls = f.cls("artrack_msgs/msg/TrackedBody")
        self.create_subscription(body_cls, BODY_TOPIC, self.on_body, RESULT_QOS)
        self.create_subscription(body_cls, PREDICTION_TOPIC, self.on_prediction, RESULT_QOS)
        self.diag = NodeDiagnostics(self)
        self.get_logger().info("body_publisher: REP 155 /humans/bodies/tracked, /tf, markers")

    def _set(self, key: str, value) -> None:
        self.p[key] = value
        self.markers.sigmas = float(self.p["marker_sigmas"])
        self.markers.lifetime_s = float(self.p["marker_lifetime_s"])

    def on_prediction(self, msg) -> None:
        try:
            pred = body_from_msg(msg)
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad TrackedBody on {PREDICTION_TOPIC}: {exc}")
            return
        self.predictions[pred.stamp_ns] = pred
        for old in sorted(self.predictions)[:-4]:
            del self.predictions[old]

    def _body_frames(self, body_id: str) -> BodyFrames:
        if body_id not in self.frames:
            f = msgs()
            self.frames[body_id] = BodyFrames(self.body, body_id)
            self.joint_pubs[body_id] = self.create_publisher(f.cls("sensor_msgs/msg/JointState"),
                                                             body_topic(body_id, "joint_states"), STATE_QOS)
            self.urdf_pubs[body_id] = self.create_publisher(f.cls("std_msgs/msg/String"), body_topic(body_id, "urdf"),
                                                            LATCHED_QOS)
        return self.frames[body_id]

    def on_body(self, msg) -> None:
        t0 = time.monotonic()
        self.diag.input()
        try:
            est = body_from_msg(msg)
            body_id = f"{self.p['id_prefix']}{int(msg.body_id)}"
            frames = self._body_frames(body_id)
            publishable = frames.publishable(est)
            world = msg.header.frame_id or "world"
            # (raises on a body that does not fit the model)
            rotations = frames.joint_rotations(est) if publishable else None
            transforms = frames.transforms(est, world, rotations) if publishable else []
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad TrackedBody on {BODY_TOPIC}: {exc}")
            self.diag.drop()
            return
        f = msgs()
        self.tracked_pub.publish(ids_list_msg(f, [body_id] if publishable else [], est.stamp_ns, world))
        if publishable:
            if self.p["publish_tf"]:
                self.tf_pub.publish(tf_message(f, transforms, est.stamp_ns))
            names, values = frames.joint_state(est, rotations)
            self.joint_pubs[body_id].publish(joint_state_msg(f, names, values, est.stamp_ns))
            self._maybe_urdf(body_id, frames, est, transforms)
        if self.p["publish_markers"]:
            self.marker_pub.publish(self.markers.marker_array(est, world, body_id, self.predictions.get(est.stamp_ns)))
            self.pose_pub.publish(self.markers.pose_array(est, world))
        self.diag.set("tracking_status", STATUS_NAMES.get(est.status, str(est.status)))
        self.diag.set("track_quality", float(est.quality))
        self.diag.set("tracked_ids", body_id if publishable else "")
        if est.status == STATUS_LOST:
            self.diag.warn(f"body {body_id} lost")
        elif est.status != STATUS_TRACKING:
            self.diag.warn(f"body {body_id} initializing")
        self.diag.processed(time.monotonic() - t0)

    def _maybe_urdf(self, body_id: str, frames: BodyFrames, est, transforms) -> None:
        dims = frames.dimensions(est, transforms)
        last = self.urdf_dims.get(body_id)
        if last is not None and abs(dims - last).max() <= float(self.p["urdf_tolerance_m"]):
            return
        self.urdf_dims[body_id] = dims
        self.urdf_pubs[body_id].publish(msgs()("std_msgs/msg/String", data=frames.urdf(est)))


def main(args=None) -> None:
    sys.exit(run_node(BodyPublisherNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
