"""What a ROS 2 user sees of the running graph (issue: REP-155 output, faults, parameters, diagnostics).

One `artrack launch` of config/graph.yaml on the small scene, real node processes over DDS.
The test process is a plain ROS 2 participant that knows only REP 155 names and standard
message types (hri_msgs/IdsList, tf2_msgs/TFMessage, std_msgs/String, sensor_msgs/JointState,
visualization_msgs/MarkerArray, diagnostic_msgs/DiagnosticArray, rcl_interfaces services):

- it reconstructs the 15 joints from /tf and compares them with the artrack joints that the
  recorder wrote (acceptance: 1e-6);
- when the body is first tracked it kills one feature node (blob_features_cam02) with
  SIGKILL: the launcher must restart it, the graph must go on and keep tracking;
- at the same moment it changes body_publisher's `marker_sigmas` at run time through the
  parameter service (and checks that out-of-range and start-up-only values are refused);
- it checks the per-node /diagnostics.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import rclpy
from conftest import NODE_BIN, REPO
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation

from artrack.bags import open_bag
from artrack.messages import body_from_msg
from artrack.types import STATUS_TRACKING

pytestmark = pytest.mark.graph
KILLED = "blob_features_cam02"
#: The 15 joints under their REP 155 / human_description-style frame names (<name>_<id>).
JOINTS = ["pelvis", "thorax", "head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
          "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle"]


class Rep155Listener(Node):
    """A subscriber written against REP 155 names and standard types only (body id 'b0')."""

    def __init__(self, context):
        super().__init__("rep155_listener", context=context)
        from diagnostic_msgs.msg import DiagnosticArray
        from hri_msgs.msg import IdsList
        from sensor_msgs.msg import JointState
        from std_msgs.msg import String
        from tf2_msgs.msg import TFMessage
        from visualization_msgs.msg import MarkerArray

        reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.tracked: list[tuple[int, list[str]]] = []
        self.tf: dict[int, dict[str, tuple[str, np.ndarray]]] = {}  # stamp -> child -> (parent, 4x4)
        self.urdf: str | None = None
        self.joint_states: list = []
        self.markers: list = []
        self.diagnostics: dict[str, dict[str, str]] = {}
        self.create_subscription(IdsList, "/humans/bodies/tracked", self.on_tracked, reliable)
        self.create_subscription(TFMessage, "/tf", self.on_tf, reliable)
        self.create_subscription(String, "/humans/bodies/b0/urdf", lambda m: setattr(self, "urdf", m.data), latched)
        self.create_subscription(JointState, "/humans/bodies/b0/joint_states", self.joint_states.append, reliable)
        self.create_subscription(MarkerArray, "/artrack/markers", self.markers.append, reliable)
        self.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, reliable)

    @staticmethod
    def _ns(stamp) -> int:
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def on_tracked(self, msg) -> None:
        self.tracked.append((self._ns(msg.header.stamp), list(msg.ids)))

    def on_tf(self, msg) -> None:
        for t in msg.transforms:
            M = np.eye(4)
            q, p = t.transform.rotation, t.transform.translation
            M[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
            M[:3, 3] = [p.x, p.y, p.z]
            self.tf.setdefault(self._ns(t.header.stamp), {})[t.child_frame_id] = (t.header.frame_id, M)

    def on_diagnostics(self, msg) -> None:
        for status in msg.status:
            self.diagnostics[status.hardware_id] = {kv.key: kv.value for kv in status.values} | {
                "_level": int.from_bytes(status.level, "little"), "_message": status.message}

    def world_position(self, stamp: int, frame: str) -> np.ndarray:
        """Compose /tf up to the fixed frame 'world'."""
        tree = self.tf[stamp]
        M = np.eye(4)
        while frame != "world":
            parent, T = tree[frame]
            M = T @ M
            frame = parent
        return M[:3, 3]


def _child_pid(parent_pid: int, node_name: str) -> int | None:
    """The launcher's child process running ``node_name`` (never anything else on the machine)."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == parent_pid and f"__node:={node_name}".encode() in cmd:
            return int(entry.name)
    return None


def _set_params(node, executor, target: str, params: list) -> list:
    """rcl_interfaces/SetParameters on ``target`` over DDS; the per-parameter results."""
    from conftest import call_service
    from rcl_interfaces.srv import SetParameters

    client = node.create_client(SetParameters, f"/{target}/set_parameters")
    deadline = time.monotonic() + 30
    while not client.service_is_ready() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.1)
    assert client.service_is_ready(), f"no parameter service on /{target}"
    response = call_service(executor, client, SetParameters.Request(parameters=[p.to_parameter_msg() for p in params]))
    assert response is not None, "parameter service did not answer"
    return list(response.results)


@pytest.fixture(scope="module")
def ros_user_run(tmp_path_factory, env, small_scene):
    from rclpy.parameter import Parameter

    out = tmp_path_factory.mktemp("ros_user")
    context = Context()
    rclpy.init(context=context, domain_id=int(env["ROS_DOMAIN_ID"]))
    listener = Rep155Listener(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener)
    events: dict = {}
    proc = subprocess.Popen(
        [str(NODE_BIN / "artrack"), "launch", "config/graph.yaml", "--set", f"bag={small_scene}",
         "--set", f"out={out / 'graph'}", "--log-dir", str(out / "logs"), "--timeout", "300"],
        env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 360
        while proc.poll() is None and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if "killed" not in events and any(ids for _, ids in listener.tracked):
                pid = _child_pid(proc.pid, KILLED)
                assert pid is not None, f"no process {KILLED} under the launcher"
                os.kill(pid, signal.SIGKILL)
                events["killed"] = max(s for s, ids in listener.tracked if ids)
                events["params"] = _set_params(listener, executor, "body_publisher", [
                    Parameter("marker_sigmas", value=3.0), Parameter("marker_sigmas", value=50.0),
                    Parameter("body_model", value="other.yaml")])
                events["params_at"] = len(listener.markers)
        for _ in range(40):  # what is still in flight
            executor.spin_once(timeout_sec=0.05)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        executor.shutdown()
        listener.destroy_node()
        rclpy.shutdown(context=context)
    logs = "\n".join(p.read_text(errors="replace")[-2000:] for p in sorted((out / "logs").glob("*.log")))
    assert proc.returncode == 0, f"launch failed ({proc.returncode}):\n{stderr}\n{logs}"
    with open_bag(out / "graph") as reader:
        bodies = {b.stamp_ns: b for b in (body_from_msg(m) for _, _, m in reader.messages(["/artrack/body"]))}
        recorded_markers = sum(1 for _ in reader.messages(["/artrack/markers"]))
    return {"listener": listener, "events": events, "stderr": stderr, "bodies": bodies, "logs": logs,
            "recorded_markers": recorded_markers}


def test_rep155_subscriber_reconstructs_the_15_joints_from_tf(ros_user_run):
    listener, bodies = ros_user_run["listener"], ros_user_run["bodies"]
    tracked = sorted(s for s, b in bodies.items() if b.status == STATUS_TRACKING)
    assert len(tracked) >= 10, f"only {len(tracked)} tracked bodies"
    assert sorted(listener.tf) == tracked, "one /tf message per tracked body, none for others"
    worst = 0.0
    for stamp in tracked:
        body = bodies[stamp]
        for name in JOINTS:
            got = listener.world_position(stamp, f"{name}_b0")
            worst = max(worst, float(np.abs(got - body.joints[body.joint_names.index(name)]).max()))
        root = listener.tf[stamp]["body_b0"]
        assert root[0] == "world"
    print(f"REP 155 reconstruction: {len(tracked)} tracked frames, worst joint error {worst:.3g} m")
    assert worst <= 1e-6, f"joints from TF differ from the artrack joints by {worst:.3g} m"
    ids = dict(listener.tracked)
    assert all(ids[s] == ["b0"] for s in tracked)
    assert all(ids[s] == [] for s in ids if s not in tracked), "untracked bodies leave /humans/bodies/tracked"


def test_urdf_and_joint_states_describe_the_same_frames(ros_user_run):
    listener = ros_user_run["listener"]
    assert listener.urdf is not None, "no URDF on /humans/bodies/b0/urdf"
    robot = ET.fromstring(listener.urdf)
    links = {link.get("name") for link in robot.findall("link")}
    stamp = max(listener.tf)
    assert set(listener.tf[stamp]) == links, "the URDF's links are the frames on /tf"
    movable = {j.get("name") for j in robot.findall("joint") if j.get("type") != "fixed"}
    js = listener.joint_states[-1]
    assert set(js.name) == movable and len(js.position) == len(js.name) == 30
    assert np.all(np.isfinite(js.position))


def test_killed_feature_node_is_restarted_and_tracking_resumes(ros_user_run):
    bodies, events = ros_user_run["bodies"], ros_user_run["events"]
    assert "killed" in events, "the body was never tracked, nothing was killed"
    assert f"{KILLED} exited (-9); restarting" in ros_user_run["stderr"]
    after = sorted(s for s in bodies if s > events["killed"])
    assert len(after) >= 5, f"the graph stopped after the kill ({len(after)} bodies after it)"
    tracked_after = [s for s in after if bodies[s].status == STATUS_TRACKING]
    assert len(tracked_after) >= 0.8 * len(after) and bodies[after[-1]].status == STATUS_TRACKING, \
        "tracking goes on after the feature node is killed"


def test_parameter_changed_at_run_time_over_dds(ros_user_run):
    listener, events, bodies = ros_user_run["listener"], ros_user_run["events"], ros_user_run["bodies"]
    ok, out_of_range, read_only = events["params"]
    assert ok.successful, ok.reason
    assert not out_of_range.successful and not read_only.successful

    def sigmas(marker_array) -> float | None:
        stamp = Rep155Listener._ns(marker_array.markers[0].header.stamp)
        blobs = [m for m in marker_array.markers if m.ns == "artrack/blobs"]
        if not blobs or stamp not in bodies:
            return None
        m = blobs[0]
        cov = next(b.cov for b in bodies[stamp].blobs if b.label == m.text)
        return float(m.scale.x + m.scale.y + m.scale.z) / (2 * np.sqrt(np.linalg.eigvalsh(cov)).clip(0).sum())

    before = [s for s in map(sigmas, listener.markers[:events["params_at"]]) if s is not None]
    after = [s for s in map(sigmas, listener.markers[events["params_at"] + 2:]) if s is not None]
    assert before and after
    assert before[0] == pytest.approx(2.0, rel=1e-6) and after[-1] == pytest.approx(3.0, rel=1e-6)


def test_markers_are_recorded_for_foxglove(ros_user_run):
    """The recorder keeps /artrack/markers next to the bodies (a bag Foxglove can replay)."""
    assert ros_user_run["recorded_markers"] >= 0.9 * len(ros_user_run["bodies"]) > 0


def test_every_node_publishes_diagnostics(ros_user_run):
    diag = ros_user_run["listener"].diagnostics
    for node in ("/skeleton", "/body_publisher", "/blob_features_cam01", "/feedback_projection"):
        assert node in diag, f"no diagnostics from {node}: {sorted(diag)}"
        for key in ("input_rate_hz", "processing_time_ms_mean", "dropped_total"):
            assert key in diag[node], (node, key)
    assert "track_quality" in diag["/skeleton"] and "tracking_status" in diag["/skeleton"]
    assert "prior_staleness_s" in diag["/blob_features_cam01"]
