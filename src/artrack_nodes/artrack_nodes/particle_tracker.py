"""particle_tracker: the body from dense 3-D points by a particle filter with spatial motion
priors and a held stick (ALGORITHMS.md §3).

Subscribes /cameras/<camera_name>/points (sensor_msgs/PointCloud2, the depth camera's
optical frame), that camera's camera_info and extrinsics, and the stick: with
stick_source=pose3d /artrack/stick (geometry_msgs/PoseStamped, world frame, x axis along
the stick, length = parameter stick_length), with stick_source=detection2d
/cameras/<camera_name>/stick_2d (artrack_msgs/Stick2D from object_features), or none.
Each point cloud waits for its frame's stick until it arrives, a later frame's stick arrives
(the source skipped this frame), or sync_timeout_s passed while the node was idle; then the
stick priors fall back to the projected spatial prior (logged). In lockstep replay the wait
before the first stick is first_stick_timeout_s (once: a replay without sticks then goes on
at sync_timeout_s a frame): the stick's publisher can be discovered after the clouds'.
Publishes artrack_msgs/TrackedBody on body_topic
(default /artrack/particles/body, so it can run beside the skeleton node, which owns
/artrack/body). The points are cropped to a box around the person's initial root position.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from artrack.body_model import load_body_model
from artrack.config import config_path, load_dataclass_yaml
from artrack.errors import ArtrackError, InputError
from artrack.messages import body_msg, ns_from_time, points_from_pointcloud_msg, stick_from_pose_msg
from artrack.particles import ParticleConfig, ParticleFilter, Stick2D, Stick3D, gamma_on_stick
from artrack.pointcloud import crop_box, workspace_box, world_from_camera_points
from artrack.realtime import keep_freed_memory
from artrack.stick_scene import holding_pose

from .common import (
    IMAGE_QOS_SENSOR,
    RESULT_QOS,
    CameraRigListener,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)

STICK_TOPIC = "/artrack/stick"
#: point clouds in lockstep replay: as IMAGE_QOS_RELIABLE, with a history deep enough for a whole bag
POINTS_QOS_REPLAY = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.TRANSIENT_LOCAL)

PARAMS = [
    ("camera_name", "rgbd", "the depth camera: /cameras/<camera_name>/points, camera_info, extrinsics"),
    ("stick_source", "pose3d", "pose3d (/artrack/stick) | detection2d (/cameras/<camera_name>/stick_2d) | none"),
    ("stick_length", 1.4, "length of the stick, m (pose3d)"),
    ("prior", "", "gp | proj | stick3d | stick2d | kkb (empty: the particle_config file's)"),
    ("n_particles", 0, "number of particles (0: the particle_config file's)"),
    ("seed", 0, "random seed of the filter"),
    ("initial_theta", [0.0], "initial full pose (body model dofs); [0.0]: standing, forearms forward"),
    ("body_topic", "/artrack/particles/body", "where the estimates go (TrackedBody, world frame)"),
    ("body_id", 1, "id published in TrackedBody.body_id"),
    ("world_frame", "world", "frame_id of the published bodies"),
    ("fps", 15.0, "nominal frame rate, Hz (stick-to-cloud matching tolerance is half a frame)"),
    ("sync_timeout_s", 0.5, "a point cloud waits this long for its frame's stick (time spent processing "
                            "other clouds not counted), s"),
    ("first_stick_timeout_s", 10.0, "lockstep: before any stick arrived, a point cloud waits this long for one "
                                    "(once), s"),
    ("lockstep", False, "bag replay: reliable point clouds, every one kept until processed"),
    ("particle_config", "", "ParticleConfig YAML (empty: config/particle_tracker.yaml)"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
]
LIMITS = {"stick_length": (0.1, 10.0), "n_particles": (0, 100000), "fps": (1.0, 1000.0),
          "sync_timeout_s": (0.0, 3600.0), "first_stick_timeout_s": (0.0, 3600.0)}
RUNTIME: tuple[str, ...] = ()  # all read-only once running


class ParticleTrackerNode(Node):
    """The particle_tracker node (module docstring): the body from 3-D points and the stick."""

    def __init__(self):
        super().__init__("particle_tracker")
        p = declare_all(self, PARAMS, LIMITS, runtime={})
        self.p = p
        self.camera_name = p["camera_name"]
        self.source = p["stick_source"]
        if self.source not in ("pose3d", "detection2d", "none"):
            raise InputError(f"parameter stick_source: unknown value '{self.source}' "
                             "(expected pose3d, detection2d or none)")
        self.body = load_body_model(p["body_model"] or None)
        path = config_path(p["particle_config"], "particle_tracker.yaml")
        self.config = load_dataclass_yaml(path, ParticleConfig)
        if p["prior"]:
            self.config.prior = p["prior"]
        if int(p["n_particles"]) > 0:
            self.config.n_particles = int(p["n_particles"])
        self.config.seed = int(p["seed"])
        try:
            self.config.check()
        except ValueError as exc:
            raise InputError(f"{path} / parameters: {exc}") from None
        theta0 = np.asarray(p["initial_theta"], float)
        if theta0.size == 1:
            theta0 = holding_pose(self.body)
        if theta0.shape != (self.body.n_dof,) or not np.all(np.isfinite(theta0)):
            raise InputError(f"parameter initial_theta: expected {self.body.n_dof} finite numbers, got {theta0.size}")
        self.theta0 = theta0
        self.box = workspace_box(theta0[:3])
        self.filter: ParticleFilter | None = None
        self.camera = None
        self.tol_ns = int(0.5e9 / float(p["fps"]))
        self.clouds: dict[int, tuple[np.ndarray, float]] = {}
        self.sticks: dict[int, object] = {}  # the stick source keeps a deep history too (RESULT_QOS)
        self.first_stick_waited = False  # a cloud waited first_stick_timeout_s in vain (no stick source?)
        f = msgs()
        self.pub = self.create_publisher(f.cls("artrack_msgs/msg/TrackedBody"), p["body_topic"], RESULT_QOS)
        self.rig = CameraRigListener(self, [self.camera_name], self.on_cameras)
        # lockstep (bag replay): keep every cloud until processed, this tracker may be slower than the loop
        qos = POINTS_QOS_REPLAY if p["lockstep"] else IMAGE_QOS_SENSOR
        self.points_topic = camera_topic(self.camera_name, "points")
        self.create_subscription(f.cls("sensor_msgs/msg/PointCloud2"), self.points_topic, self.on_points, qos)
        if self.source == "pose3d":
            self.create_subscription(f.cls("geometry_msgs/msg/PoseStamped"), STICK_TOPIC, self.on_stick3d, RESULT_QOS)
        elif self.source == "detection2d":
            self.create_subscription(f.cls("artrack_msgs/msg/Stick2D"), camera_topic(self.camera_name, "stick_2d"),
                                     self.on_stick2d, RESULT_QOS)
        self.create_timer(0.02, self.flush)
        self.get_logger().info(f"particle_tracker: {self.config.n_particles} particles, prior {self.config.prior}, "
                               f"stick from {self.source}, camera {self.camera_name}")

    def on_cameras(self, cameras) -> None:
        self.camera = cameras[0]
        self.get_logger().info("camera calibration complete")

    def on_points(self, msg) -> None:
        try:
            pts = points_from_pointcloud_msg(msg, self.points_topic)
            stamp = ns_from_time(msg.header.stamp)
        except (ValueError, AttributeError, TypeError) as exc:
            self.get_logger().error(f"dropped bad PointCloud2: {exc}")
            return
        self.clouds[stamp] = (pts, time.monotonic())
        self.flush()

    def on_stick3d(self, msg) -> None:
        try:
            a, b = stick_from_pose_msg(msg, float(self.p["stick_length"]), STICK_TOPIC)
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad stick pose: {exc}")
            return
        self._add_stick(ns_from_time(msg.header.stamp), Stick3D(a, b))

    def on_stick2d(self, msg) -> None:
        a, b = np.asarray(msg.a, float), np.asarray(msg.b, float)
        if not (msg.found and np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            self._add_stick(ns_from_time(msg.header.stamp), None)
            return
        self._add_stick(ns_from_time(msg.header.stamp), (a, b))

    def _add_stick(self, stamp: int, stick) -> None:
        """Keep the stick; forget the sticks beyond the newest 50 that no waiting cloud can use
        (a tracker slower than the replay may be far behind its sticks)."""
        self.sticks[stamp] = stick
        needed_from = min(self.clouds) - self.tol_ns if self.clouds else stamp
        for old in sorted(self.sticks)[:-50]:
            if old < needed_from:
                del self.sticks[old]
        self.flush()

    def _stick_for(self, stamp: int):
        """(found, stick or None) of the frame."""
        for s, v in self.sticks.items():
            if abs(s - stamp) <= self.tol_ns:
                if isinstance(v, tuple):
                    return True, Stick2D(v[0], v[1], self.camera)
                return True, v
        return False, None

    def flush(self) -> None:
        """Process the oldest point cloud once its frame's stick is known: arrived, or missing (a
        later stick arrived, or the wait timed out). One cloud per call, so that the sticks queued
        while it was processed are taken before the next; that busy time is not counted as the
        remaining clouds' wait (they could not have received their sticks during it)."""
        if self.camera is None or not self.clouds:
            return
        stamp = min(self.clouds)
        pts, arrived = self.clouds[stamp]
        stick = None
        if self.source != "none":
            found, stick = self._stick_for(stamp)
            if not found:
                later = bool(self.sticks) and max(self.sticks) > stamp + self.tol_ns
                timeout = float(self.p["sync_timeout_s"])
                if self.p["lockstep"] and not self.sticks and not self.first_stick_waited:
                    timeout = max(timeout, float(self.p["first_stick_timeout_s"]))
                if not later and time.monotonic() - arrived < timeout:
                    return
                self.first_stick_waited = self.first_stick_waited or not self.sticks  # once, not every frame
                why = "a later frame's stick arrived" if later else f"none within {timeout:g} s"
                self.get_logger().warning(f"frame {stamp}: no stick ({why}); stick priors fall back to "
                                          "the spatial prior")
        del self.clouds[stamp]
        t0 = time.monotonic()
        self.process(stamp, pts, stick)
        busy = time.monotonic() - t0
        self.clouds = {s: (p, a + busy) for s, (p, a) in self.clouds.items()}

    def process(self, stamp: int, points_cam: np.ndarray, stick) -> None:
        cam = self.camera
        pts = crop_box(world_from_camera_points(cam, points_cam), *self.box)
        if self.filter is None:
            gamma0 = None
            if self.theta0 is not None:
                from artrack.pose_manifold import PoseManifold

                M = PoseManifold(self.body, self.theta0, self.config.active_links, self.config.point_links)
                hands = M.hands(M.active(self.theta0)[None])[0]
                if isinstance(stick, Stick3D):
                    gamma0 = gamma_on_stick(stick.a, stick.b, hands)
                elif isinstance(stick, Stick2D):
                    uv, _ = cam.project(hands)
                    gamma0 = gamma_on_stick(stick.a_uv, stick.b_uv, uv)
            self.filter = ParticleFilter(self.body, self.theta0, self.config, gamma0)
        try:
            theta, stats = self.filter.step(pts, cam.center, stick)
        except (ArtrackError, ValueError) as exc:
            self.get_logger().error(f"frame {stamp}: {exc}")
            return
        est = self.filter.body_estimate(theta, stamp)
        self.pub.publish(body_msg(msgs(), est, self.p["world_frame"], int(self.p["body_id"])))
        self.get_logger().debug(f"frame {stamp}: prior {stats.prior}, {stats.n_points} points, ess {stats.ess:.1f}, "
                                f"{stats.prior_s + stats.likelihood_s:.3f} s")


def main(args=None) -> None:
    keep_freed_memory()  # the same cost every frame (artrack/realtime.py)
    sys.exit(run_node(ParticleTrackerNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
