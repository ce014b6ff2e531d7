"""loose_limbed: the loose-limbed body by non-parametric BP (ALGORITHMS.md §4) as a node.

Subscribes every camera's /cameras/<cam>/image_raw (plus camera_info and extrinsics) and
/artrack/body (the skeleton's estimate, for its status). Once all cameras have sent a frame it
feeds the frame to the ROS-free LooseLimbedStage (per-camera background seeded from the first
frames, shouters + NBP) and publishes /artrack/loose_limbed/body (artrack_msgs/TrackedBody: the
15 joints and one link per part; status INITIALIZING on a frame found from no prior pose).

With ``lockstep`` (graph: lockstep replay) it answers every complete frame: the estimate, or a body
with status LOST and NaN joints when it did not infer or found nobody, so that a skeleton waiting
for its re-seed (skeleton ``reseed_topic`` in lockstep) never waits in vain. It also takes a frame
only once it has heard the skeleton's body of the frame before (up to ``lockstep_timeout_s``): that
body's status decides whether to infer, and its message races the next frame's images, so without
the wait a replay's inferences would depend on the order the messages happen to arrive in.

mode=initialiser: infers at start until its first body and whenever the skeleton's last body has
status LOST (artrack.loose_limbed_stage.InitialiserPolicy): the first frame after the skeleton
became LOST is found from no prior pose (INITIALIZING), the following ones are tracked (TRACKING,
what the skeleton re-seeds from); with ``start_skeleton`` also while the skeleton has not started,
so that its first TRACKING body starts the skeleton; a body scoring below ``min_score`` is not published
and the next frame starts afresh. mode=estimator: tracks every frame, an estimator of its own.
The skeleton reads /artrack/loose_limbed/body when its ``reseed_topic`` names it (graph:
``--set loose_limbed=true --set reseed_topic=/artrack/loose_limbed/body``) and starts from it when
it has not started, or restarts from it when lost.
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node

from artrack.body_model import load_body_model
from artrack.errors import ArtrackError, InputError
from artrack.loose_limbed_stage import InitialiserPolicy, LooseLimbedStage, StageConfig
from artrack.messages import bgr_from_image_msg, body_msg, ns_from_time
from artrack.part_potentials import load_model
from artrack.types import STATUS_LOST, BodyEstimate

from .common import (
    BODY_TOPIC,
    IMAGE_QOS_RELIABLE,
    IMAGE_QOS_SENSOR,
    RESULT_QOS,
    CameraRigListener,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)

OUTPUT_TOPIC = "/artrack/loose_limbed/body"

PARAMS = [
    ("camera_names", ["cam01", "cam02", "cam03", "cam04"], "cameras whose images are used"),
    ("mode", "initialiser", "initialiser (at start and when the skeleton is LOST) | estimator (every frame)"),
    ("start_skeleton", False, "mode=initialiser: also infer while the skeleton has not started, so that this "
     "node's body starts it (default: the skeleton starts from its own blobs, which measured better)"),
    ("reliable_images", False, "reliable image QoS (lockstep bag replay) instead of sensor data"),
    ("lockstep", False, "answer every frame (LOST with NaN joints when there is no estimate): a lockstep "
                        "skeleton with reseed_topic waits for it"),
    ("lockstep_timeout_s", 30.0, "lockstep: take a frame after this long without the skeleton's body of the "
                                 "frame before (a dead skeleton must not stall this node), s; 0 = wait for ever"),
    ("init_iterations", 10, "BP iterations when finding the body from no prior pose"),
    ("track_iterations", 2, "BP iterations per tracked frame (mode=estimator)"),
    ("particles", 100, "belief samples per part and iteration"),
    ("seed", 0, "random seed of the inference"),
    ("min_score", -14.5, "no body when its mean part log-likelihood is below this (a person scores about -10 to "
                         "-14, a body found in background ghosts about -14.3 to -17.5); the next frame starts afresh"),
    ("background_frames", 11, "frames in each camera's background median (seeded before any inference)"),
    ("background_stride", 4, "one background seed frame every this many frames"),
    ("model", "", "potentials YAML (empty: config/loose_limbed_model.yaml)"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("body_id", 0, "id published in TrackedBody.body_id"),
    ("world_frame", "world", "frame_id of the published bodies"),
]
LIMITS = {"lockstep_timeout_s": (0.0, 3600.0), "min_score": (-1000.0, 0.0), "init_iterations": (1, 100),
          "track_iterations": (1, 50), "particles": (10, 10000), "background_frames": (1, 1000),
          "background_stride": (1, 1000)}
RUNTIME: tuple[str, ...] = ()  # all read-only once running


class LooseLimbedNode(Node):
    """The loose_limbed node (module docstring): the loose-limbed body from every camera's images."""

    def __init__(self):
        super().__init__("loose_limbed")
        p = declare_all(self, PARAMS, LIMITS, runtime={})
        self.p = p
        self.names = list(p["camera_names"])
        if p["mode"] not in ("initialiser", "estimator"):
            raise InputError(f"loose_limbed: parameter 'mode' must be initialiser or estimator, got {p['mode']!r}")
        self.policy = InitialiserPolicy(estimator=p["mode"] == "estimator", start=p["start_skeleton"])
        self.body = load_body_model(p["body_model"] or None)
        self.model = load_model(p["model"] or None)
        self.stage: LooseLimbedStage | None = None
        self.pending: dict[int, dict] = {}  # frames still missing a camera's image
        self.complete: dict[int, tuple[float, dict]] = {}  # lockstep: (arrival, images) of frames held back
        self.last_taken: int | None = None  # stamp of the frame processed last
        self.skeleton_heard = -1  # stamp of the skeleton's newest body
        f = msgs()
        self.pub = self.create_publisher(f.cls("artrack_msgs/msg/TrackedBody"), OUTPUT_TOPIC, RESULT_QOS)
        self.rig = CameraRigListener(self, self.names, self.on_cameras)
        qos = IMAGE_QOS_RELIABLE if p["reliable_images"] else IMAGE_QOS_SENSOR
        for n in self.names:
            self.create_subscription(f.cls("sensor_msgs/msg/Image"), camera_topic(n, "image_raw"),
                                     lambda m, n=n: self.on_image(n, m), qos)
        self.create_subscription(f.cls("artrack_msgs/msg/TrackedBody"), BODY_TOPIC, self.on_skeleton, RESULT_QOS)
        if p["lockstep"]:
            self.create_timer(0.05, self.take_complete)  # lockstep_timeout_s
        self.get_logger().info(f"loose_limbed ({p['mode']}) over {self.names}")

    def on_cameras(self, cameras) -> None:
        p = self.p
        self.stage = LooseLimbedStage(self.body, cameras, self.model, StageConfig(
            init_iterations=int(p["init_iterations"]), track_iterations=int(p["track_iterations"]),
            n_particles=int(p["particles"]), seed=int(p["seed"]),
            background_seed_frames=int(p["background_frames"]), background_seed_stride=int(p["background_stride"]),
            min_score=float(p["min_score"])))

    def on_skeleton(self, msg) -> None:
        self.skeleton_heard = max(self.skeleton_heard, ns_from_time(msg.header.stamp))
        if self.policy.skeleton(int(msg.status)):
            self.get_logger().info("skeleton reports LOST: re-initialising")
        self.take_complete()

    def on_image(self, name: str, msg) -> None:
        topic = camera_topic(name, "image_raw")
        try:
            image = bgr_from_image_msg(msg, topic)
        except ValueError as exc:
            self.get_logger().error(f"dropped bad image: {exc}")
            return
        stamp = ns_from_time(msg.header.stamp)
        self.pending.setdefault(stamp, {})[name] = image
        for old in sorted(self.pending)[:-4]:  # keep the newest few incomplete frames
            del self.pending[old]
        if self.stage is not None and len(self.pending.get(stamp, {})) == len(self.names):
            self.complete[stamp] = (time.monotonic(), self.pending.pop(stamp))
            self.take_complete()

    def take_complete(self) -> None:
        """Process the complete frames in order; in lockstep each waits for the skeleton's body of the
        frame processed before it (while the skeleton publishes, at most lockstep_timeout_s)."""
        while self.complete:
            stamp = min(self.complete)
            arrived, images = self.complete[stamp]
            if (self.p["lockstep"] and self.last_taken is not None and self.skeleton_heard < self.last_taken
                    and self.count_publishers(BODY_TOPIC) > 0):
                waited, limit = time.monotonic() - arrived, float(self.p["lockstep_timeout_s"])
                if limit == 0 or waited <= limit:
                    return
                self.get_logger().warning(f"frame {stamp}: no skeleton body for frame {self.last_taken} after "
                                          f"{waited:.1f} s; going on with its last status")
            del self.complete[stamp]
            self.last_taken = stamp
            self.process(stamp, images)

    def process(self, stamp: int, images: dict) -> None:
        assert self.stage is not None
        try:
            est = self.policy.step(self.stage, stamp, images)
        except (ArtrackError, ValueError) as exc:
            self.get_logger().error(f"dropped frame {stamp}: {exc}")
            return
        if est is None:
            if not self.p["lockstep"]:
                return
            est = BodyEstimate.empty(self.body.joint_names, stamp, STATUS_LOST)
        self.pub.publish(body_msg(msgs(), est, self.p["world_frame"], int(self.p["body_id"])))


def main(args=None) -> None:
    sys.exit(run_node(LooseLimbedNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
