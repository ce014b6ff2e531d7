"""bag_player: replays a recording's cameras into the graph.

Reads rosbag2 (mcap or sqlite3) and ROS 1 bags (images raw or compressed) and
publishes /cameras/<cam>/image_raw, camera_info and extrinsics. Lockstep mode
publishes frame t+1 only after /artrack/body for frame t has come back (the
loop has closed), so a replay is reproducible; real-time mode paces frames by
their stamps times 1/rate. Exits when the recording ends.
"""

from __future__ import annotations

import sys
import time

from rclpy.node import Node

from artrack.bags import read_scene
from artrack.errors import ArtrackError
from artrack.messages import ns_from_time

from .common import (
    BODY_TOPIC,
    PREDICTION_TOPIC,
    READY_TOPIC,
    RESULT_QOS,
    CameraPublishers,
    Pacer,
    camera_topic,
    declare_all,
    msgs,
    run_node,
)

PARAMS = [
    ("bag", "", "recording to play: rosbag2 folder or .mcap/.db3 file, or ROS 1 .bag"),
    ("lockstep", True, "publish frame t+1 only after the body for frame t arrived"),
    ("rate", 1.0, "real-time mode: playback speed factor"),
    ("cameras", [""], "cameras to play (empty: all in the bag)"),
    ("start_timeout_s", 30.0, "wait this long for the graph's subscribers before starting, s"),
    ("frame_timeout_s", 30.0, "lockstep: wait this long for a frame's body before going on, s"),
    ("max_frames", 0, "stop after this many frames (0: all)"),
    ("linger_s", 1.0, "after the last frame, keep running this long, s"),
    ("allow_truncated", False, "a truncated MCAP bag (e.g. a recorder that died): play the frames before the "
                               "damage (default: refuse, exit 1)"),
    ("wait_for_recorder", False, "also wait until a recorder subscribes to the body, prediction, blob and prior "
                                 "topics before starting"),
    ("extra_topics", [""], "further per-frame topics to replay with each frame's images, matched by stamp "
                           "(e.g. /cameras/rgbd/points, /artrack/stick); playing starts once each has a "
                           "subscriber (at most start_timeout_s); empty: none"),
    ("wait_for_nodes", [""], "node names (without namespace) that must have said they are ready (on "
                             "/artrack_nodes/ready, as every artrack node does once constructed) before playing, e.g. "
                             "every node of the launched graph (config/graph.yaml passes ${graph_nodes}): a node "
                             "that starts late would miss the first frames (at most start_timeout_s); in lockstep "
                             "the images' readers the ROS graph lists must be matched too; empty: none"),
    ("linger_for", [""], "TrackedBody topics of slower estimators (e.g. /artrack/particles/body): after the last "
                         "frame, end as soon as each has published a body for it (at most linger_s); empty: none"),
]
LIMITS = {"rate": (0.01, 100.0), "start_timeout_s": (0.0, 3600.0), "frame_timeout_s": (0.0, 3600.0),
          "max_frames": (0, 2**31 - 1), "linger_s": (0.0, 3600.0)}
RUNTIME = ("rate", "frame_timeout_s", "linger_s")  # read from self.p on every tick
#: period of the housekeeping timer (graph discovery, timeouts, lingering), s
HOUSEKEEPING_S = 0.1


class BagPlayerNode(Node):
    """The bag_player node (module docstring): a recording's camera topics published frame by frame."""

    def __init__(self):
        super().__init__("bag_player")
        p = declare_all(self, PARAMS, LIMITS, {k: (lambda v: None) for k in RUNTIME})
        self.p = p
        if not p["bag"]:
            raise SystemExit("bag_player: parameter 'bag' is empty")
        wanted = [c for c in p["cameras"] if c]
        self.scene = read_scene(p["bag"], allow_truncated=bool(p["allow_truncated"]))
        if self.scene.truncated:
            self.get_logger().warning(f"{p['bag']}: {self.scene.problem}; playing the frames before the damage")
        cameras = [c for c in self.scene.cameras if not wanted or c.name in wanted]
        unknown = sorted(set(wanted) - {c.name for c in self.scene.cameras})
        if unknown:
            raise ArtrackError(f"{p['bag']}: no camera named '{unknown[0]}'")
        self.names = [c.name for c in cameras]
        self.frames = self.scene.frames()
        self.pubs = CameraPublishers(self, cameras, reliable_images=bool(p["lockstep"]))
        self.extra = self._load_extra([t for t in p["extra_topics"] if t])
        self.create_subscription(msgs().cls("artrack_msgs/msg/TrackedBody"), BODY_TOPIC, self.on_body, RESULT_QOS)
        self.ready_nodes: set[str] = set()  # names heard on READY_TOPIC
        self.create_subscription(msgs().cls("std_msgs/msg/String"), READY_TOPIC,
                                 lambda m: self.ready_nodes.add(str(m.data)), RESULT_QOS)
        self.linger_for: dict[str, set[int]] = {t: set() for t in p["linger_for"] if t}
        for t in self.linger_for:
            self.create_subscription(msgs().cls("artrack_msgs/msg/TrackedBody"), t,
                                     lambda m, t=t: self.linger_for[t].add(ns_from_time(m.header.stamp)), RESULT_QOS)
        self.last_stamp: int | None = None
        self.lockstep = bool(p["lockstep"])
        self.state = "wait_graph"
        self.t_state = time.monotonic()
        self.sent = 0
        self.waiting_for: int | None = None
        self.bodies_seen: set[int] = set()
        self.t_first_sent: float | None = None  # wall clock of the first frame published
        self.t_last_body: float | None = None  # wall clock of the newest body received
        self.sent_at: dict[int, float] = {}  # frame stamp -> wall clock it was sent
        self.latency_s: list[float] = []  # from sending a frame to receiving its body
        self.next_frame = None
        # Event-driven: a frame goes out when its body has come back (lockstep, on_body) or
        # when it is due (free-running, the pacer); the timer only waits for the graph and
        # watches the timeouts.
        self.pacer = Pacer(self, self._play)
        self.timer = self.create_timer(HOUSEKEEPING_S, self.tick)
        self.get_logger().info(f"playing {p['bag']} ({len(self.names)} cameras, lockstep={self.lockstep})")

    def _load_extra(self, topics: list[str]) -> dict:
        """{log stamp: [(publisher, serialised message)]} of the extra topics (read up front).
        Point clouds get the image QoS, other topics the result QoS."""
        self.extra_pubs: list = []
        if not topics:
            return {}
        from artrack.bags import open_bag

        from .common import IMAGE_QOS_RELIABLE, IMAGE_QOS_SENSOR

        out: dict = {}
        with open_bag(self.p["bag"]) as bag:
            types = bag.topics()
            pubs = {}
            for t in topics:
                if t not in types:
                    raise ArtrackError(f"{self.p['bag']}: no topic '{t}' (parameter extra_topics)")
                image_qos = IMAGE_QOS_RELIABLE if self.p["lockstep"] else IMAGE_QOS_SENSOR
                qos = image_qos if types[t].endswith("/PointCloud2") else RESULT_QOS
                pubs[t] = self.create_publisher(msgs().cls(types[t]), t, qos)
            self.extra_pubs = list(pubs.values())
            for topic, stamp, data in bag.messages(topics, raw=True):
                out.setdefault(int(stamp), []).append((pubs[topic], bytes(data)))
        return out

    def on_body(self, msg) -> None:
        stamp = ns_from_time(msg.header.stamp)
        self.t_last_body = time.monotonic()
        if stamp in self.sent_at and stamp not in self.bodies_seen:
            self.latency_s.append(self.t_last_body - self.sent_at[stamp])
        self.bodies_seen.add(stamp)
        if self.state == "wait_body" and stamp == self.waiting_for:
            self._next_frame()  # lockstep: the loop has closed, the next frame goes out at once

    def _missing_nodes(self) -> list[str]:
        """The names of ``wait_for_nodes`` that have not (yet) said they are ready, this node's own
        excepted."""
        return sorted(n for n in self.p["wait_for_nodes"] if n and n != self.get_name() and n not in self.ready_nodes)

    def _graph_ready(self) -> bool:
        if self._missing_nodes():
            return False
        if self.pubs.subscriber_count() < 1:
            return False
        if self.lockstep and not self.pubs.all_matched():
            return False  # a reader the graph lists, not matched yet, would miss the first frames
        if any(p.get_subscription_count() < 1 for p in self.extra_pubs):
            return False  # e.g. a particle_tracker still starting: it would miss the first frames
        if self.p["wait_for_recorder"] and not self._recorder_ready():
            return False
        return not self.lockstep or self.count_publishers(BODY_TOPIC) >= 1

    def _recorder_ready(self) -> bool:
        """The recorder has subscribed to the graph's topics next to their regular readers (it
        subscribes as it discovers them: frames played before would be missing from its bag)."""
        needed = {BODY_TOPIC: 2, PREDICTION_TOPIC: 2}  # player / feedback_projection + recorder
        for n in self.names:
            needed[camera_topic(n, "blobs")] = 2  # skeleton + recorder
            needed[camera_topic(n, "blob_priors")] = 2  # blob_features + recorder
        return all(self.count_subscribers(t) >= k for t, k in needed.items())

    def _advance(self) -> bool:
        if self.p["max_frames"] and self.sent >= int(self.p["max_frames"]):
            return False
        self.next_frame = next(self.frames, None)
        return self.next_frame is not None

    def tick(self) -> None:
        """Housekeeping: start once the graph is there, a lockstep frame's timeout, the end."""
        now = time.monotonic()
        if self.state == "wait_graph":
            if self._graph_ready() or now - self.t_state > float(self.p["start_timeout_s"]):
                if not self._graph_ready():
                    missing = self._missing_nodes()
                    self.get_logger().warning("graph not complete after start_timeout_s"
                                              + (f" (not ready: {', '.join(missing)})" if missing else "")
                                              + "; playing anyway")
                time.sleep(0.5)  # let late discovery of the remaining endpoints settle
                self._next_frame()
            return
        if self.state == "wait_body":
            if now - self.t_state > float(self.p["frame_timeout_s"]):
                self.get_logger().warning(f"no body for frame {self.waiting_for}; going on")
                self._next_frame()
            return
        if self.state == "linger":
            caught_up = bool(self.linger_for) and all(self.last_stamp in seen for seen in self.linger_for.values())
            if caught_up or now - self.t_state > float(self.p["linger_s"]):
                late = [t for t, seen in self.linger_for.items() if self.last_stamp not in seen]
                if late:
                    self.get_logger().warning(f"linger_s over before {', '.join(late)} published the last frame")
                self.get_logger().info(f"done: {self.sent} frames; {self._throughput()}")
                raise SystemExit(0)

    def _next_frame(self) -> None:
        """Take the next frame and play it (lockstep: now; free-running: when due), or linger."""
        self.state = "play" if self._advance() else "linger"
        self.t_state = time.monotonic()
        if self.state == "play":
            self._play()

    def _play(self) -> None:
        """Publish the pending frame (free-running: once it is due; then the pacer wakes this
        for the next one)."""
        if self.state != "play":
            return
        now = time.monotonic()
        stamp, images = self.next_frame
        if not self.lockstep:
            wait = self.pacer.due_in(stamp, float(self.p["rate"]))
            if wait > 0:
                self.pacer.arm(wait)
                return
        for pub, data in self.extra.pop(stamp, []):
            pub.publish(data)  # serialised CDR, as recorded
        self.pubs.publish_images(stamp, {n: images[n] for n in self.names if n in images})
        self.sent += 1
        self.last_stamp = stamp
        self.sent_at[stamp] = now
        if self.t_first_sent is None:
            self.t_first_sent = now
        if self.lockstep:
            self.waiting_for, self.state, self.t_state = stamp, "wait_body", now
        elif not self._advance():
            self.state, self.t_state = "linger", now
        else:  # one frame per call: the executor serves the bodies in between
            self.pacer.arm(max(0.0, self.pacer.due_in(self.next_frame[0], float(self.p["rate"]))))

    def _throughput(self) -> str:
        """Closed-loop throughput: bodies received per second of wall clock, from the first
        frame sent to the last body received (lockstep: one frame in flight at a time); with
        the share of frames that got a body and the latency from sending a frame to its body."""
        n = len(self.bodies_seen)
        if self.t_first_sent is None or self.t_last_body is None or n == 0:
            return "no body came back"
        span = max(self.t_last_body - self.t_first_sent, 1e-9)
        lat = sorted(self.latency_s)
        latency = (f"; {len(lat)} of {self.sent} frames got a body, {1e3 * lat[len(lat) // 2]:.0f} ms "
                   f"(median) and {1e3 * lat[-1]:.0f} ms (max) after they were sent") if lat else ""
        return f"{n} bodies in {span:.1f} s: {n / span:.2f} frames per second (closed loop){latency}"


def main(args=None) -> None:
    sys.exit(run_node(BagPlayerNode, __doc__, PARAMS, args, LIMITS, RUNTIME))


if __name__ == "__main__":
    main()
