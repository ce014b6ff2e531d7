"""Shared node plumbing: named QoS profiles, topic names, parameters, main().

Nodes only translate messages, parameters and timing; all algorithms live in
the ROS-free ``artrack`` package (docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import faulthandler
import gc
import os
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)

from artrack.errors import ArtrackError
from artrack.messages import MsgFactory, bgr_from_image_msg, ns_from_time, rclpy_factory

#: Images in free-running mode: best effort, keep last 5 (REP 2003 sensor data).
IMAGE_QOS_SENSOR = qos_profile_sensor_data
#: Images in lockstep mode (bag replay by bag_player): every frame must arrive, also at a
#: reader whose discovery finished just after the frame was sent (transient local, last 10).
IMAGE_QOS_RELIABLE = QoSProfile(
    history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
#: Results (blobs, priors, edge statistics, bodies): reliable, the last 100 kept for late-matched
#: readers (a process graph on a busy machine matches its endpoints over seconds; volatile
#: readers elsewhere remain compatible) and for readers starved of CPU for a few seconds.
RESULT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: The recorder's readers: as RESULT_QOS, with a deep history (it must not drop what it records).
RECORD_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: Latched per-camera data (camera_info, extrinsics): late joiners get the last one.
LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

BODY_TOPIC = "/artrack/body"
PREDICTION_TOPIC = "/artrack/prediction"
#: the body of a frame that goes round the loop again (skeleton ``refine_passes``): its projection is
#: that frame's priors for the next pass
REFINEMENT_TOPIC = "/artrack/refinement"
GROUND_TRUTH_TOPIC = "/artrack/ground_truth"
DIAGNOSTICS_TOPIC = "/diagnostics"
#: std_msgs/String (RESULT_QOS: kept for late readers, and deep enough that a reader hearing many nodes
#: at once loses none): a node's name, published once the node is constructed, its subscriptions
#: created (:func:`run_node`). The bag player waits for it from every node of the graph
#: (``wait_for_nodes``): a node merely present in the ROS graph may still be loading its models, and a
#: reader created after the first frames were played misses them. Outside /artrack/*, which the
#: bag recorder records.
READY_TOPIC = "/artrack_nodes/ready"
#: /diagnostics: reliable, volatile, last 10 (as diagnostic_updater).
DIAGNOSTICS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)


def camera_topic(camera: str, leaf: str) -> str:
    """/cameras/<camera>/<leaf>: image_raw, camera_info, extrinsics, blobs, blob_priors."""
    return f"/cameras/{camera}/{leaf}"


_factory: MsgFactory | None = None


def msgs() -> MsgFactory:
    """The rclpy message factory (one per process)."""
    global _factory
    if _factory is None:
        _factory = rclpy_factory()
    return _factory


def declare(node: Node, name: str, default: Any, description: str, limits: tuple | None = None,
            runtime: bool = True) -> Any:
    """Declare a parameter with a default, a description and optionally an inclusive range
    ``limits`` (lo, hi) (rclpy refuses values outside it, at start-up and at run time);
    ``runtime=False`` makes it read-only once the node runs. Returns its value."""
    desc = ParameterDescriptor(description=description, read_only=not runtime)
    if limits is not None:
        lo, hi = limits
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f"parameter '{name}': a range needs a numeric default")
        if isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        desc.additional_constraints = f"{lo} <= {name} <= {hi}"
    return node.declare_parameter(name, default, desc).value


def print_help(prog: str, doc: str, params: list[tuple[str, Any, str]]) -> None:
    print(f"usage: {prog} [--ros-args -p NAME:=VALUE ... | --params-file FILE]\n")
    print(doc.strip() + "\n\nparameters (default):")
    for name, default, desc in params:
        print(f"  {name} ({default!r}): {desc}")


#: s a node's teardown (destroy, rclpy shutdown, interpreter exit) may take after its spin has
#: ended before the node dumps its Python stacks to stderr and exits with code 1: a DDS
#: participant that deadlocks on destruction must not keep a stopped node alive.
TEARDOWN_TIMEOUT_S = 30.0

#: s the executor waits at most before it checks again that the context is up. rclpy's SIGTERM /
#: SIGINT handling wakes a waiting executor and shuts the context down from another thread; when
#: the executor has gone back to waiting in between, nothing wakes it again and an unbounded wait
#: (rclpy.spin) never ends: the stop-20 CI failure, a SIGTERMed objects node still in rcl_wait 60 s
#: later. Bounded waits end such a spin within this time.
SPIN_POLL_S = 0.5


def spin(node: Node, poll_s: float = SPIN_POLL_S) -> None:
    """rclpy.spin(node), with every wait bounded by ``poll_s``: returns once the node's context is
    shut down, even by a shutdown that woke nothing (see SPIN_POLL_S)."""
    executor = rclpy.get_global_executor()
    executor.add_node(node)
    try:
        while executor.context.ok():
            executor.spin_once(timeout_sec=poll_s)
    finally:
        executor.remove_node(node)


def announce_ready(node: Node) -> None:
    """Publish the node's name on READY_TOPIC (the publisher is kept on the node)."""
    f = msgs()
    pub = node.create_publisher(f.cls("std_msgs/msg/String"), READY_TOPIC, RESULT_QOS)
    msg = f.cls("std_msgs/msg/String")()
    msg.data = node.get_name()
    pub.publish(msg)
    node._artrack_ready_publisher = pub


def run_node(make: Callable[[], Node], doc: str, params: list[tuple[str, Any, str]], args=None,
             limits: dict[str, tuple] | None = None, runtime: Iterable[str] | None = None) -> int:
    """main() for every node: --help, init, spin, clean shutdown. Returns the exit code.
    ``limits`` / ``runtime`` (the node's declared ranges and run-time parameters, as given to
    :func:`declare_all`): when either is given, --help lists them after ``doc``."""
    argv = list(sys.argv if args is None else args)
    if any(a in ("-h", "--help") for a in argv[1:]):
        if limits is not None or runtime is not None:
            doc = doc + "\n" + param_limits_help(limits or {}, runtime or ())
        print_help(os.path.basename(argv[0]), doc, params)
        return 0
    # `kill -USR1 <pid>` dumps every thread's Python stack to stderr (the node keeps running).
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=argv)
    node = None
    code = 0
    try:
        node = make()
        announce_ready(node)
        spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except SystemExit as exc:  # a node asking to stop (e.g. the player at the end of the bag)
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
            code = 1
        else:
            code = int(exc.code or 0)
    except (ArtrackError, ParameterException) as exc:  # bad input / parameter at start-up: one line, exit 1
        print(f"{os.path.basename(argv[0])}: {exc}", file=sys.stderr)
        code = 1
    except Exception:
        if rclpy.ok():
            raise
        # SIGTERM / SIGINT shut the context down while the executor was waiting or a callback
        # ran (rcl then fails on the invalid context, e.g. in rcl_wait): a clean stop.
    finally:
        try:
            if node is not None:
                close = getattr(node, "close", None)
                if close is not None:
                    close()  # outputs first (the recorder's bag), unbounded
                # From here on nothing is left to write: bound the rest (see TEARDOWN_TIMEOUT_S).
                faulthandler.dump_traceback_later(TEARDOWN_TIMEOUT_S, exit=True)
                node.destroy_node()
        except Exception:
            if rclpy.ok():
                raise
        if rclpy.ok():
            rclpy.shutdown()
        # Finalise what the teardown left (rclpy's executor tasks and futures, often in reference
        # cycles) now, while the interpreter is whole: collected only at interpreter exit, a
        # future's __del__ ran with its module globals already torn down and printed a traceback
        # into the node's log (one CI run in stop 36). A future whose exception nobody fetched
        # still says so here, in one line (rclpy's "The following exception was never retrieved").
        gc.collect()
    return code


Params = list[tuple[str, Any, str]]


def declare_all(node: Node, params: Params, limits: dict[str, tuple] | None = None,
                runtime: dict[str, Callable[[Any], None]] | None = None) -> dict[str, Any]:
    """Declare every (name, default, description) of a node; return the values.

    ``limits``: name -> (lo, hi) declared ranges. ``runtime``: name -> handler for the parameters
    that may change while the node runs (``ros2 param set``, or a parameter client): the handler
    gets the new (range-checked) value; every other parameter of a node that passes ``runtime`` is
    read-only after start-up. Without ``runtime`` the parameters stay as before (writable, no effect).
    """
    limits = limits or {}
    values = {name: declare(node, name, default, desc, limits.get(name),
                            runtime=runtime is None or name in runtime)
              for name, default, desc in params}
    if runtime:
        def on_set(changes):
            for change in changes:
                if change.name in runtime:
                    runtime[change.name](change.value)
                    values[change.name] = change.value
                    node.get_logger().info(f"parameter {change.name} set to {change.value!r}")
            return SetParametersResult(successful=True)

        node.add_on_set_parameters_callback(on_set)
    return values


def param_limits_help(limits: dict[str, tuple], runtime: Iterable[str]) -> str:
    """A --help paragraph on ranges and run-time changeable parameters."""
    ranges = ", ".join(f"{k} in [{lo}, {hi}]" for k, (lo, hi) in limits.items())
    return (f"ranges: {ranges or '-'}\nchangeable at run time (ros2 param set): "
            f"{', '.join(sorted(runtime)) or '-'}; the others are read-only once the node runs")


class NodeDiagnostics:
    """Per-node diagnostic_msgs/DiagnosticArray on /diagnostics (REP 107 style), once per ``period_s``.

    Counts the node's inputs (rate over the last ``window_s``), processing times, dropped
    frames/messages; nodes add their own values (prior staleness, track quality, tracking
    status, silent cameras) with :meth:`set` and raise the level with :meth:`warn` / :meth:`error`
    (reset after each publication).
    """

    OK, WARN, ERROR, STALE = 0, 1, 2, 3

    def __init__(self, node: Node, period_s: float = 1.0, window_s: float = 5.0,
                 update: Callable[[NodeDiagnostics], None] | None = None):
        f = msgs()
        self.node = node
        self.update = update  # called before each publication (node-specific values and checks)
        self.window_s = window_s
        self.pub = node.create_publisher(f.cls("diagnostic_msgs/msg/DiagnosticArray"), DIAGNOSTICS_TOPIC,
                                         DIAGNOSTICS_QOS)
        self.inputs: deque = deque()
        self.times: deque = deque()
        self.dropped = 0
        self.processed_total = 0
        self.values: dict[str, Any] = {}
        self.level, self.messages = self.OK, []
        self.t_start = time.monotonic()
        node.create_timer(period_s, self.publish)

    def input(self) -> None:
        self.inputs.append(time.monotonic())

    def processed(self, seconds: float) -> None:
        self.times.append((time.monotonic(), float(seconds)))
        self.processed_total += 1

    def drop(self, n: int = 1) -> None:
        self.dropped += n

    def set(self, key: str, value: Any) -> None:
        self.values[key] = value

    def warn(self, message: str) -> None:
        self.level = max(self.level, self.WARN)
        self.messages.append(message)

    def error(self, message: str) -> None:
        self.level = max(self.level, self.ERROR)
        self.messages.append(message)

    def rate_hz(self) -> float:
        now = time.monotonic()
        while self.inputs and now - self.inputs[0] > self.window_s:
            self.inputs.popleft()
        span = min(self.window_s, now - self.t_start)
        return len(self.inputs) / span if span > 0 else 0.0

    def publish(self) -> None:
        f = msgs()
        if self.update is not None:
            self.update(self)
        now = time.monotonic()
        while self.times and now - self.times[0][0] > self.window_s:
            self.times.popleft()
        durations = [d for _, d in self.times]
        values = {"input_rate_hz": f"{self.rate_hz():.3f}",
                  "processing_time_ms_mean": f"{1e3 * sum(durations) / len(durations):.3f}" if durations else "nan",
                  "processing_time_ms_max": f"{1e3 * max(durations):.3f}" if durations else "nan",
                  "processed_total": str(self.processed_total), "dropped_total": str(self.dropped)}
        values.update({k: (f"{v:.6g}" if isinstance(v, float) else str(v)) for k, v in self.values.items()})
        name = self.node.get_fully_qualified_name()
        status = f("diagnostic_msgs/msg/DiagnosticStatus", level=bytes([self.level]),
                   name=f"{name.lstrip('/')}: artrack", message="; ".join(self.messages) or "ok", hardware_id=name,
                   values=[f("diagnostic_msgs/msg/KeyValue", key=k, value=v) for k, v in values.items()])
        stamp = self.node.get_clock().now().to_msg()
        self.pub.publish(f("diagnostic_msgs/msg/DiagnosticArray",
                           header=f("std_msgs/msg/Header", stamp=stamp, frame_id=""), status=[status]))
        self.level, self.messages = self.OK, []


class Pacer:
    """A one-shot wake-up at a chosen delay (free-running playback paced by frame stamps).

    ``arm(delay_s)`` calls ``callback`` once, ``delay_s`` from now (a later ``arm`` replaces
    the pending call); ``due_in`` tells how long until a frame's stamp is due (bag_player,
    camera_ingest). It replaces a 2 ms polling timer, which woke the node 500 times a second
    (measured at stop 60: ~0.5 s of CPU over a 30 s lockstep replay, small beside the image
    messages' cost then, but paid for nothing).
    """

    def __init__(self, node: Node, callback: Callable[[], None]):
        self.node = node
        self.callback = callback
        self.timer = None
        self.anchor: tuple[float, int] | None = None  # (monotonic s, stamp ns) of the first frame paced

    def due_in(self, stamp_ns: int, rate: float) -> float:
        """Seconds until the frame stamped ``stamp_ns`` is due (<= 0: now): frames keep the spacing
        of their stamps divided by ``rate``, from the first frame asked about, which is due at once."""
        now = time.monotonic()
        if self.anchor is None:
            self.anchor = (now, stamp_ns)
        return self.anchor[0] + (stamp_ns - self.anchor[1]) * 1e-9 / rate - now

    def arm(self, delay_s: float) -> None:
        period_ns = max(int(delay_s * 1e9), 1)
        if self.timer is None:
            self.timer = self.node.create_timer(period_ns * 1e-9, self._fire)
        else:
            self.timer.timer_period_ns = period_ns
            self.timer.reset()  # from now (and re-enabled after _fire's cancel)

    def _fire(self) -> None:
        self.timer.cancel()
        self.callback()


class CameraPublishers:
    """Publishes images, camera_info and extrinsics of a camera rig (player and ingest)."""

    def __init__(self, node: Node, cameras: list, reliable_images: bool):
        f = msgs()
        self.node = node
        self.cameras = {c.name: c for c in cameras}
        qos = IMAGE_QOS_RELIABLE if reliable_images else IMAGE_QOS_SENSOR
        self.image_pub = {n: node.create_publisher(f.cls("sensor_msgs/msg/Image"), camera_topic(n, "image_raw"), qos)
                          for n in self.cameras}
        self.info_pub = {n: node.create_publisher(f.cls("sensor_msgs/msg/CameraInfo"),
                                                  camera_topic(n, "camera_info"), LATCHED_QOS) for n in self.cameras}
        self.extr_pub = {n: node.create_publisher(f.cls("geometry_msgs/msg/TransformStamped"),
                                                  camera_topic(n, "extrinsics"), LATCHED_QOS) for n in self.cameras}
        self.publish_calibration(0)

    def publish_calibration(self, stamp_ns: int) -> None:
        from artrack.messages import camera_info_msg, extrinsics_msg

        f = msgs()
        for name, cam in self.cameras.items():
            self.info_pub[name].publish(camera_info_msg(f, cam, stamp_ns))
            self.extr_pub[name].publish(extrinsics_msg(f, cam, stamp_ns))

    def publish_images(self, stamp_ns: int, images: dict) -> None:
        from artrack.messages import image_msg

        f = msgs()
        for name in sorted(images):
            if name in self.image_pub:
                self.image_pub[name].publish(image_msg(f, images[name], stamp_ns, self.cameras[name].frame_id))

    def subscriber_count(self) -> int:
        """Smallest number of subscribers over the image topics."""
        return min((p.get_subscription_count() for p in self.image_pub.values()), default=0)

    def all_matched(self) -> bool:
        """Whether every image topic's publisher has matched as many readers as the ROS graph lists
        for it (discovery lists a reader before its publisher has matched it)."""
        return all(p.get_subscription_count() >= self.node.count_subscribers(p.topic_name)
                   for p in self.image_pub.values())


class CameraRigListener:
    """Collects camera_info + extrinsics of named cameras; `.cameras()` once complete."""

    def __init__(self, node: Node, camera_names: list[str], on_complete: Callable[[list], None] | None = None):
        f = msgs()
        self.node = node
        self.names = list(camera_names)
        self.info: dict[str, Any] = {}
        self.extr: dict[str, Any] = {}
        self.on_complete = on_complete
        self.done = False
        for n in self.names:
            node.create_subscription(f.cls("sensor_msgs/msg/CameraInfo"), camera_topic(n, "camera_info"),
                                     lambda m, n=n: self._got(self.info, n, m), LATCHED_QOS)
            node.create_subscription(f.cls("geometry_msgs/msg/TransformStamped"), camera_topic(n, "extrinsics"),
                                     lambda m, n=n: self._got(self.extr, n, m), LATCHED_QOS)

    def _got(self, store: dict, name: str, msg: Any) -> None:
        from artrack.messages import camera_from_msgs

        store[name] = msg
        if name in self.info and name in self.extr:
            # each camera is checked as soon as it is complete, camera_info alone first, so that the
            # faulty message (not the one that happened to complete the pair) is dropped and named;
            # the next good one completes the rig
            for leaf, bad_store, extr in (("camera_info", self.info, None), ("extrinsics", self.extr,
                                                                           self.extr[name])):
                try:
                    camera_from_msgs(name, self.info[name], extr)
                except (ArtrackError, ValueError, AttributeError) as exc:
                    self.node.get_logger().error(f"dropped bad calibration of camera '{name}' on "
                                                 f"{camera_topic(name, leaf)}: {exc}")
                    bad_store.pop(name, None)
                    return
        if not self.done and all(n in self.info and n in self.extr for n in self.names):
            cameras = self.cameras()
            self.done = True
            if self.on_complete is not None:
                self.on_complete(cameras)

    def cameras(self) -> list:
        from artrack.messages import camera_from_msgs

        return [camera_from_msgs(n, self.info[n], self.extr[n]) for n in self.names]


def received_ns(info: Any) -> int:
    """When DDS received a message, ns, from the MessageInfo of a two-argument subscription
    callback (rclpy gives a dict); 0 if unknown."""
    try:
        return int(info["received_timestamp"] or 0)
    except (TypeError, KeyError, ValueError):
        return 0


class FrameBefore:
    """A lockstep feature node's answer to the skeleton's refinement (``ClosedLoopPipeline.step``):
    the frame last processed, its image and a copy of the node's stage from before it, to process
    that frame again from (blob_features labels it again, edge_features measures it again)."""

    def __init__(self):
        self.stamp: int | None = None  # the frame kept (None: none yet)
        self.image = None
        self._state = None
        self._shared: list = []

    def keep(self, stamp: int, image, stage, shared: list) -> None:
        """Before processing frame ``stamp``: its image and a copy of ``stage`` (sharing ``shared``,
        the objects a step never changes)."""
        from artrack.pipeline import state_copy  # (here: the nodes without stages need not import it)

        self.stamp, self.image, self._shared = stamp, image, shared
        self._state = state_copy(stage, shared)

    def again(self) -> Any:
        """A fresh copy of the stage before the kept frame (the kept one stays for a further pass)."""
        from artrack.pipeline import state_copy

        return state_copy(self._state, self._shared)


class FrameQueue:
    """Images waiting for the per-frame input that belongs to them (blob_features: the priors
    predicting the frame; edge_features: the predicted body of the frame).

    Lockstep: every image after the first waits for the input stamped within half a frame of
    it (or ``timeout_s``, then goes on without). Free-running: only the newest image is
    processed, with the input nearest to it in time; and, with ``loop_wait_s`` > 0, only once
    the loop has closed since the last processed frame (an input stamped after that frame and
    received after it was taken: the skeleton's prediction from it) or ``loop_wait_s`` has
    passed. The graph then runs at the rate of its own loop on the newest images, every 2-D
    step with the prediction of the step before, instead of spending the CPU on frames whose
    priors are stale and whose blobs the skeleton, behind, would drop (ALGORITHMS.md §1, the
    closed loop, in real time). The image taken when the loop closes is the newest that had
    arrived before the input that closed it (DDS receive times, ``received_ns``), not the newest
    by the time this node gets the CPU: so every camera's node takes the same frame, also when
    they run one after another on fewer cores than cameras. Inputs are kept for the last
    ``keep`` stamps.
    """

    def __init__(self, node: Node, lockstep: bool, fps: float, timeout_s: float, what: str, keep: int = 8,
                 loop_wait_s: float = 0.0, clock_ns: Callable[[], int] = time.time_ns):
        self.node = node
        self.lockstep = lockstep
        self.tol_ns = int(0.5e9 / fps)
        self.timeout_s = timeout_s
        self.loop_wait_s = loop_wait_s
        self.what = what
        self.keep = keep
        self.inputs: dict[int, Any] = {}
        self.input_received: dict[int, int] = {}  # input stamp -> DDS receive time, ns (0: unknown)
        self.images: deque = deque()
        self.skipped = 0  # free-running: images dropped for a newer one (diagnostics)
        self.clock_ns = clock_ns  # the clock of DDS's receive times (system time, ns)
        self.last_stamp: int | None = None  # free-running: the stamp of the last image processed ...
        self.last_time = 0.0  # ... and when (monotonic s) ...
        self.last_pick_ns = 0  # ... (clock_ns)

    def add_input(self, stamp_ns: int, value: Any, received_ns: int = 0) -> None:
        """received_ns: when DDS received it (``received_ns(info)``; 0: unknown)."""
        self.inputs[stamp_ns] = value
        self.input_received[stamp_ns] = received_ns
        for old in sorted(self.inputs)[:-self.keep]:
            del self.inputs[old]
            del self.input_received[old]

    def add_image_msg(self, msg: Any, topic: str, received_ns: int = 0) -> bool:
        """Queue a sensor_msgs/Image as BGR; a bad one is logged (naming ``topic`` and the field)
        and dropped. Returns whether it was queued. received_ns: as for :meth:`add_input`."""
        try:
            image = bgr_from_image_msg(msg, topic)
        except ValueError as exc:
            self.node.get_logger().error(f"dropped bad image: {exc}")
            return False
        self.images.append((ns_from_time(msg.header.stamp), image, time.monotonic(), received_ns))
        return True

    def input_for(self, stamp_ns: int) -> tuple[int, Any] | None:
        """Lockstep: the input of this frame; free-running: the one nearest to it in time (ties:
        the earlier)."""
        if self.lockstep:
            for s, value in self.inputs.items():
                if abs(s - stamp_ns) <= self.tol_ns:
                    return s, value
            return None
        if not self.inputs:
            return None
        best = min(self.inputs, key=lambda s: (abs(s - stamp_ns), s))
        return best, self.inputs[best]

    def _free_running_pick(self) -> int | None:
        """Free-running: the index in ``images`` of the image to process now, or None to wait
        (see the class docstring)."""
        newest = len(self.images) - 1
        if self.loop_wait_s <= 0 or self.last_stamp is None:
            return newest
        # the loop closes with an input stamped after the last frame (its prediction) that came after it
        closing = [r for s, r in self.input_received.items()
                   if s > self.last_stamp and (r == 0 or r > self.last_pick_ns)]
        if not closing:
            return newest if time.monotonic() - self.last_time >= self.loop_wait_s else None
        closed_at = min(closing)
        if not closed_at:
            return newest  # receive times unknown
        before = [i for i, im in enumerate(self.images) if 0 < im[3] <= closed_at]
        return before[-1] if before else 0  # else the first image to arrive after it

    def ready(self, first: Callable[[], bool]) -> Iterator[tuple[int, Any, tuple[int, Any] | None]]:
        """Yield (stamp, image, (input stamp, input) or None) for every image that may be processed
        now, in order; ``first()`` tells whether no frame has been processed yet (it has no input)."""
        while self.images:
            stamp, image, arrived, _ = self.images[0]
            if not self.lockstep:  # free-running: the newest image, once the loop closed
                pick = len(self.images) - 1 if first() else self._free_running_pick()
                if pick is None:
                    return
                for _ in range(pick):
                    self.images.popleft()
                    self.skipped += 1
                stamp, image, arrived, _ = self.images.popleft()
                self.last_stamp, self.last_time, self.last_pick_ns = stamp, time.monotonic(), self.clock_ns()
                yield stamp, image, (None if first() else self.input_for(stamp))
                continue
            found = self.input_for(stamp)
            if not first() and found is None:
                if time.monotonic() - arrived < self.timeout_s:
                    return
                self.node.get_logger().warning(f"no {self.what} for frame {stamp} after {self.timeout_s}s; going on")
            self.images.popleft()
            yield stamp, image, (None if first() else found)
