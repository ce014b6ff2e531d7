"""skeleton: the 3-D body estimator (ALGORITHMS.md §1: 3-D blobs, Kalman filters,
virtual-work constraint solver; or the triangulate-and-fit baseline).

Subscribes every camera's /cameras/<cam>/blobs (plus camera_info and
extrinsics) and, with ``edges`` on, /cameras/<cam>/edge_statistics (edge_features
nodes; fused as soft constraints on the links, ALGORITHMS.md §2 "Fusion"). Once all
cameras have reported a frame (or, free-running, after sync_timeout_s; there a frame
older than a complete one is dropped, so the node estimates the newest) it publishes
/artrack/body (the estimate at that frame) and /artrack/prediction (the body predicted
for the next frame, which feedback_projection turns into 2-D priors and edge_features
measures about). With ``reseed_topic`` set (e.g. /artrack/loose_limbed/body, the loose_limbed
node's TRACKING bodies, ALGORITHMS.md §4) a lost or not yet started estimator is re-initialised
from the 15 joints of the bodies arriving there; in lockstep, while it is lost or not started and
that topic has a publisher, each frame also waits (up to lockstep_timeout_s) for that topic's body
of the same frame (the loose_limbed node in lockstep answers every frame), so the re-seed comes
before the frame is estimated and the replay stays reproducible.
With ``refine_passes`` k > 0 (lockstep; the feature nodes answer with ``answer_refinements``, their
default), a tracked frame at least ``refine_min_interval_s`` after the previous one goes round
the loop up to k more times, as in ``ClosedLoopPipeline.step``: the node goes back to its state
before the frame, publishes the frame's body on /artrack/refinement (feedback_projection projects
it with the frame's stamp; edge_features nodes measure the frame again about it), and waits for
every camera's blobs (and edge statistics) of the same frame again; the last pass's body and
prediction are published. The same (lockstep) for the
``startup_refine_frames`` frames after the one a track started on, ``startup_refine_passes`` more
times each, as offline. A pass whose blobs have not all come after
``refine_timeout_s`` (a feature node restarted since the frame, or one run without
``answer_refinements``) is abandoned: the previous pass's body and prediction are published, and if no
camera's node of a kind (blob_features, or with edges edge_features) answered at all, refinement is
switched off for the rest of the run (one warning line).
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from artrack.body_model import load_body_model
from artrack.edge_fusion import combine
from artrack.errors import ArtrackError, InputError
from artrack.messages import blobs_from_msg, body_from_msg, body_msg, edge_stats_from_msg
from artrack.pipeline import SkeletonStage, load_pipeline_config, refinable, refine_passes, state_copy
from artrack.types import STATUS_LOST, STATUS_TRACKING

from .common import (
    BODY_TOPIC,
    PREDICTION_TOPIC,
    REFINEMENT_TOPIC,
    RESULT_QOS,
    CameraRigListener,
    NodeDiagnostics,
    Pacer,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)
from .health import CameraWatch

PARAMS = [
    ("camera_names", ["cam01", "cam02", "cam03", "cam04"], "cameras whose blobs are fused"),
    ("estimator", "baseline", "baseline (raw triangulate-and-fit) | kinematic | dynamic"),
    ("fps", 30.0, "nominal frame rate, Hz (first prediction interval)"),
    ("lockstep", False, "wait for every camera's blobs of a frame (up to lockstep_timeout_s)"),
    ("sync_timeout_s", 0.1, "free-running: process a frame with the cameras that reported after this long, s "
                                 "(one older than a complete frame is dropped at once)"),
    ("lockstep_timeout_s", 30.0, "lockstep: process a frame with the cameras that reported after this long (a dead "
                                 "camera node must not stall the graph), s; 0 = wait for ever"),
    ("body_id", 0, "id published in TrackedBody.body_id"),
    ("world_frame", "world", "frame_id of the published bodies"),
    ("body_model", "", "body model YAML (empty: config/body_model.yaml)"),
    ("skeleton_config", "", "estimator tunables YAML (empty: config/skeleton.yaml)"),
    ("edges", False, "also wait for and fuse every camera's edge statistics (edge_features nodes)"),
    ("reseed_topic", "", "TrackedBody topic whose TRACKING bodies re-initialise a lost (or not yet started) "
                         "estimator, e.g. /artrack/loose_limbed/body (empty: off)"),
    ("refine_passes", 0, "lockstep: a tracked frame at least refine_min_interval_s after the previous one goes "
                         "round the loop up to this many more times (the feature nodes answer with their "
                         "answer_refinements)"),
    ("refine_min_interval_s", 0.05, "frame interval from which refine_passes applies, s"),
    ("startup_refine_frames", 10, "lockstep: the frames after the one a track started on that go round "
                                  "the loop startup_refine_passes more times (the start-up pose is crude); 0 = off; "
                                  "free-running nodes cannot go back: off there"),
    ("startup_refine_passes", 2, "extra passes of those frames"),
    ("refine_timeout_s", 10.0, "a refinement pass whose blobs (or edge statistics) have not all come after this "
                               "long is abandoned (the previous pass is published; no camera answering switches "
                               "refinement off), s"),
]
#: re-seed bodies: reliable, volatile (a restarted skeleton must not re-seed from stale bodies)
RESEED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
LIMITS = {"fps": (1.0, 1000.0), "sync_timeout_s": (0.0, 60.0), "lockstep_timeout_s": (0.0, 3600.0),
          "body_id": (0, 2**31 - 1), "refine_passes": (0, 10), "refine_min_interval_s": (0.0, 3600.0),
          "refine_timeout_s": (0.001, 3600.0), "startup_refine_frames": (0, 1000), "startup_refine_passes": (0, 10)}
RUNTIME = ("sync_timeout_s", "lockstep_timeout_s", "refine_timeout_s")  # read by flush() on every call


class SkeletonNode(Node):
    """The skeleton node (module docstring): every camera's blobs (and edge statistics) in, the body
    and its prediction out."""

    def __init__(self):
        super().__init__("skeleton")
        p = declare_all(self, PARAMS, LIMITS, {k: (lambda v: None) for k in RUNTIME})
        self.p = p
        self.names = list(p["camera_names"])
        self.lockstep = bool(p["lockstep"])
        self.body = load_body_model(p["body_model"] or None)
        self.config = load_pipeline_config(estimator=p["estimator"], fps=float(p["fps"]),
                                           skeleton_config=p["skeleton_config"])
        self.config.refine_passes = int(p["refine_passes"])
        self.config.refine_min_interval_s = float(p["refine_min_interval_s"])
        self.config.edges = bool(p["edges"])
        self.config.startup_refine_frames = int(p["startup_refine_frames"]) if self.lockstep else 0
        self.config.startup_refine_passes = int(p["startup_refine_passes"])
        if self.config.refine_passes and not self.lockstep:
            raise InputError("parameter 'refine_passes' needs 'lockstep' (the feature nodes label a refined frame "
                             "again from their state before it)")
        self.previous_stamp: int | None = None  # the last frame estimated (refine_passes)
        self.track_frames = 0  # frames in a row whose body was refinable (startup_refine_frames)
        self.refining: tuple[int, int] | None = None  # (frame, passes left after the one awaited) while refining
        # while refining: (monotonic s the pass was asked for, the stage after the previous pass, its estimate,
        # its prediction, its cameras): what is published if the pass's blobs do not come (refine_timeout_s)
        self.refine_fallback: tuple | None = None
        self.stage: SkeletonStage | None = None
        self.edges = bool(p["edges"])
        self.pending: dict[int, dict] = {}
        self.pending_edges: dict[int, dict] = {}
        self.first_seen: dict[int, float] = {}
        self.last_done = -1
        self.skipped = 0  # free-running: frames dropped for a newer complete one (diagnostics)
        self.reseed_seen = -1  # newest frame stamp heard on reseed_topic
        f = msgs()
        body_cls = f.cls("artrack_msgs/msg/TrackedBody")
        self.body_pub = self.create_publisher(body_cls, BODY_TOPIC, RESULT_QOS)
        self.pred_pub = self.create_publisher(body_cls, PREDICTION_TOPIC, RESULT_QOS)
        self.refine_pub = self.create_publisher(body_cls, REFINEMENT_TOPIC, RESULT_QOS)
        self.rig = CameraRigListener(self, self.names, self.on_cameras)
        for n in self.names:
            self.create_subscription(f.cls("artrack_msgs/msg/Blob2DArray"), camera_topic(n, "blobs"),
                                     self.on_blobs, RESULT_QOS)
            if self.edges:
                self.create_subscription(f.cls("artrack_msgs/msg/LinkEdgeStatistics"),
                                         camera_topic(n, "edge_statistics"), self.on_edges, RESULT_QOS)
        if p["reseed_topic"]:
            self.create_subscription(body_cls, p["reseed_topic"], self.on_reseed, RESEED_QOS)
        # A frame's timeout (sync_timeout_s / lockstep_timeout_s) wakes the node when it is due (the
        # pacer, armed by flush); the slow timer is only a safety net. A 20 ms poll here cost 8 % of a
        # core with nothing to do (stop 60).
        self.pacer = Pacer(self, self.flush)
        self.create_timer(1.0, self.flush)
        self.watch = CameraWatch(self.names, float(p["fps"]))
        watch_report = self.watch.report(self)

        def report(diag) -> None:
            watch_report(diag)
            diag.set("frames_skipped", self.skipped)

        self.diag = NodeDiagnostics(self, update=report)
        self.get_logger().info(f"skeleton ({p['estimator']}{', edges' if self.edges else ''}) over {self.names}, "
                               f"lockstep={self.lockstep}")

    def on_cameras(self, cameras) -> None:
        self.cameras = list(cameras)
        self.stage = SkeletonStage(self.body, cameras, self.config)
        self.get_logger().info("camera rig complete")
        self.flush()

    def on_reseed(self, msg) -> None:
        """A body from another estimator: re-initialises ours if it is lost or has not started."""
        if self.stage is None:
            return
        try:
            other = body_from_msg(msg)
            self.reseed_seen = max(self.reseed_seen, other.stamp_ns)
            if other.status != STATUS_TRACKING:
                self.flush()  # a frame may be waiting for this answer
                return
            taken = self.stage.estimator.reseed(other.stamp_ns, other.joints)
        except (ValueError, AttributeError, ArtrackError) as exc:
            self.get_logger().error(f"dropped re-seed body on {self.p['reseed_topic']}: {exc}")
            self.diag.drop()
            return
        if taken:
            # a body from another estimator, not the crude start-up: no start-up refinement (as
            # ClosedLoopPipeline.restart; with it, the recovery test's body after a re-seed from the
            # loose-limbed body was worse, 229 mm mean against a 200-mm bound, stop 62)
            self.track_frames = self.config.startup_refine_frames + 1
            self.get_logger().info(f"estimator re-initialised from {self.p['reseed_topic']} (frame {other.stamp_ns})")
        self.flush()

    def _waits_for_reseed(self, stamp: int) -> bool:
        """Lockstep with a live reseed_topic: a lost or not yet started estimator waits for that topic's
        body of frame ``stamp`` before estimating it."""
        if not (self.lockstep and self.p["reseed_topic"]) or self.reseed_seen >= stamp:
            return False
        est = self.stage.estimator
        if est.theta is not None and est.status != STATUS_LOST:
            return False
        return self.count_publishers(self.p["reseed_topic"]) > 0

    def on_blobs(self, msg) -> None:
        self._receive(msg, blobs_from_msg, "Blob2DArray", "blobs", self.pending)

    def on_edges(self, msg) -> None:
        self._receive(msg, lambda m: edge_stats_from_msg(m, self.body.link_names), "LinkEdgeStatistics",
                      "edge statistics", self.pending_edges)

    def _receive(self, msg, parse, msg_type: str, what: str, store: dict) -> None:
        """One camera's per-frame input: parsed, checked (camera known, frame not done) and filed
        under its frame; a bad or late one is logged and dropped."""
        self.diag.input()
        try:
            stamp, cam, value = parse(msg)
        except (ValueError, AttributeError) as exc:
            self.get_logger().error(f"dropped bad {msg_type}: {exc}")
            self.diag.drop()
            return
        if cam not in self.names:
            self.get_logger().error(f"dropped {what} of unknown camera '{cam}' (field camera_name)")
            self.diag.drop()
            return
        self.watch.seen(cam)
        if stamp <= self.last_done:
            self.get_logger().warning(f"dropped late {what} of {cam} for frame {stamp}")
            self.diag.drop()
            return
        store.setdefault(stamp, {})[cam] = value
        self.pending.setdefault(stamp, {})  # a frame is pending once any of its inputs is in
        self.first_seen.setdefault(stamp, time.monotonic())
        self.flush()

    def flush(self) -> None:
        """Estimate the frames that are ready (complete, or waited for long enough), then arm the
        pacer for the timeout of the oldest frame still pending (or of the refinement pass awaited)."""
        self._flush()
        if self.stage is None:
            return
        dues = []
        if self.refine_fallback is not None:
            dues.append(self.refine_fallback[0] + float(self.p["refine_timeout_s"]))
        limit = float(self.p["lockstep_timeout_s"] if self.lockstep else self.p["sync_timeout_s"])
        if self.pending and not (self.lockstep and limit <= 0):  # (lockstep_timeout_s 0: wait for ever)
            dues.append(min(self.first_seen.values()) + limit)
        if dues:
            self.pacer.arm(max(0.0, min(dues) - time.monotonic()) + 1e-3)  # (a timeout is "waited > limit")

    def _flush(self) -> None:
        if self.stage is None:
            return
        now = time.monotonic()
        if self.refine_fallback is not None and now - self.refine_fallback[0] > float(self.p["refine_timeout_s"]):
            self._abandon_refinement(now)
        if not self.lockstep:
            # Free-running: the newest complete frame is the one to estimate; older frames still
            # pending (a camera's blobs missing, or the node behind) are dropped, not estimated late.
            complete = [s for s in self.pending if self._complete(s)]
            for stamp in [s for s in self.pending if complete and s < max(complete)]:
                del self.pending[stamp]
                del self.first_seen[stamp]
                self.pending_edges.pop(stamp, None)
                self.skipped += 1
        for stamp in sorted(self.pending):
            got = self.pending[stamp]
            complete = self._complete(stamp)
            waited = now - self.first_seen[stamp]
            timed_out = waited > float(self.p["sync_timeout_s"])
            lock_limit = float(self.p["lockstep_timeout_s"])
            # (free-running, no frame here has a newer complete one: those were dropped above)
            if not complete and (not (lock_limit > 0 and waited > lock_limit) if self.lockstep else not timed_out):
                return
            if complete and self._waits_for_reseed(stamp) and not (lock_limit > 0 and waited > lock_limit):
                return
            if not complete and self.lockstep:
                missing = sorted(set(self.names) - set(got))
                what = f"no blobs from {', '.join(missing)}" if missing else "edge statistics missing"
                self.get_logger().warning(f"frame {stamp}: {what} after {waited:.1f} s (lockstep_timeout_s); "
                                          "going on without")
            del self.pending[stamp]
            del self.first_seen[stamp]
            edges = self.pending_edges.pop(stamp, {})
            if not got:  # edge statistics alone (their blobs were lost): nothing to estimate from
                continue
            self.process(stamp, got, combine([edges[c] for c in sorted(edges)]) if self.edges else None)

    def _complete(self, stamp: int) -> bool:
        """Every camera's blobs (and, with edges, edge statistics) of this frame are in."""
        blobs_in = len(self.pending.get(stamp, {})) == len(self.names)
        return blobs_in and (not self.edges or len(self.pending_edges.get(stamp, {})) == len(self.names))

    def _abandon_refinement(self, now: float) -> None:
        """The refinement pass awaited has not got every camera's blobs (and, with edges, edge
        statistics) within refine_timeout_s: the previous pass stands (its body and prediction are
        published). Refinement is switched off if no node of a kind (blob_features, or with edges
        edge_features) answered at all: they do not label or measure a frame again, and every later
        refinement would wait as long. Some cameras answering: a node restarted since the frame,
        and only this frame's refinement is given up."""
        asked, stamp = self.refine_fallback[0], self.refining[0]
        blobs = set(self.pending.pop(stamp, {}))
        edges = set(self.pending_edges.pop(stamp, {}))
        self.first_seen.pop(stamp, None)
        awaited = [("blobs", blobs)] + ([("edge statistics", edges)] if self.edges else [])
        missing = [f"{what} from {', '.join(sorted(set(self.names) - got))}"
                   for what, got in awaited if set(self.names) - got]
        silent = [what for what, got in awaited if not got]
        what = "refinement off" if silent else "this frame's refinement given up"
        self.get_logger().warning(
            f"frame {stamp}: no refinement {'; no '.join(missing)} after {now - asked:.1f} s "
            f"(refine_timeout_s): the previous pass is published, {what}"
            + ("; do the feature nodes run in lockstep with answer_refinements?" if silent else ""))
        if silent:
            self.config.refine_passes = self.config.startup_refine_frames = 0
        self._previous_pass_stands(stamp)

    def _previous_pass_stands(self, stamp: int) -> None:
        """A refinement pass that failed or never came: the frame keeps the pass before it (that
        pass's stage, body and prediction, ``refine_fallback``), which is published."""
        _, self.stage, estimate, prediction, cameras = self.refine_fallback
        self._publish(stamp, estimate, prediction, cameras)

    def process(self, stamp: int, blobs_by_camera: dict, edges=None) -> None:
        self.last_done = stamp
        if self.refining is not None and self.refining[0] != stamp:
            self.refining = None  # (the refinement's blobs never came: that frame was given up)
            self.refine_fallback = None
        left = (self.refining[1] if self.refining is not None
                else refine_passes(self.config, self.previous_stamp, stamp, self.track_frames))
        # the state before the frame, to go round again from (ClosedLoopPipeline.step)
        before = state_copy(self.stage, [self.body, self.config, *self.cameras]) if left else None
        t0 = time.monotonic()
        try:
            estimate, prediction = self.stage.step(stamp, blobs_by_camera, edges)
        except ArtrackError as exc:
            self.get_logger().error(f"frame {stamp}: {exc}")
            if self.refine_fallback is not None:  # a refinement pass
                self._previous_pass_stands(stamp)
            self.refining = None
            return
        self.diag.processed(time.monotonic() - t0)
        if before is not None and refinable(estimate):
            self.refine_fallback = (time.monotonic(), self.stage, estimate, prediction, sorted(blobs_by_camera))
            self.stage = before
            self.refining = (stamp, left - 1)
            self.last_done = stamp - 1  # this frame's blobs come again
            self.refine_pub.publish(body_msg(msgs(), estimate, self.p["world_frame"], int(self.p["body_id"])))
            return
        self._publish(stamp, estimate, prediction, sorted(blobs_by_camera))

    def _publish(self, stamp: int, estimate, prediction, cameras: list[str]) -> None:
        """The frame's last pass: its prediction and body go out; the frame is done."""
        self.refining = self.refine_fallback = None
        self.previous_stamp = self.last_done = stamp
        self.track_frames = self.track_frames + 1 if refinable(estimate) else 0
        self.watch.estimated(estimate, cameras)
        f = msgs()
        frame, body_id = self.p["world_frame"], int(self.p["body_id"])
        # Prediction first: the priors for t+1 should be on their way before the player hears "t is done".
        self.pred_pub.publish(body_msg(f, prediction, frame, body_id))
        self.body_pub.publish(body_msg(f, estimate, frame, body_id))


def main(args=None) -> None:
    sys.exit(run_node(SkeletonNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
