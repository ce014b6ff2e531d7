"""REP 155 body output (artrack/rep155.py) and RViz markers (artrack/markers.py): ROS-free unit tests."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import INSTALL
from scipy.spatial.transform import Rotation

from artrack.body_model import load_body_model
from artrack.markers import DELETEALL, SPHERE, MarkerBuilder, ellipsoid
from artrack.messages import MsgFactory
from artrack.rep155 import BodyFrames, tf_message
from artrack.types import STATUS_INITIALIZING, STATUS_TRACKING, BodyEstimate, LinkEstimate

#: RIHS01 type hash of tf2_msgs/msg/TFMessage in ROS 2 Jazzy (as used in the key expressions of
#: rmw_zenoh clients that publish /tf); the workspace's stand-in must produce the same.
TF_MESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def plain_factory() -> MsgFactory:
    """Messages as namespaces (no ROS needed)."""
    return MsgFactory(lambda name: (lambda **kw: SimpleNamespace(_type=name, **kw)))


def estimate_at(body, theta, stamp_ns=7, status=STATUS_TRACKING) -> BodyEstimate:
    T = body.forward_kinematics(theta)
    links = [LinkEstimate(n, T[k, :3, 3].copy(), T[k, :3, :3].copy()) for k, n in enumerate(body.link_names)]
    return BodyEstimate(stamp_ns, list(body.joint_names), body.joint_positions(theta), links, body.blobs3d(theta),
                        status=status)


def random_pose(body, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    theta = body.rest_pose()
    lo, hi = np.maximum(body.lower, -3.0), np.minimum(body.upper, 3.0)
    theta[6:] = rng.uniform(lo[6:], hi[6:])
    theta[:3] = rng.uniform([-2, -2, 0.8], [2, 2, 1.1])
    theta[3:6] = Rotation.random(random_state=seed).as_rotvec()
    return theta


def world_from_frames(transforms, world: str) -> dict[str, np.ndarray]:
    """Compose a TF tree (parent before child) into world_from_frame 4x4 matrices."""
    out = {world: np.eye(4)}
    for tf in transforms:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = tf.rotation, tf.translation
        out[tf.child] = out[tf.parent] @ M
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tf_tree_gives_back_links_and_joints(seed):
    body = load_body_model()
    est = estimate_at(body, random_pose(body, seed))
    frames = BodyFrames(body, "7")
    tfs = frames.transforms(est, "world")
    assert len({tf.child for tf in tfs}) == len(tfs), "each frame has one parent"
    W = world_from_frames(tfs, "world")
    for lk in est.links:
        M = W[frames.link_frame[lk.name]]
        assert np.allclose(M[:3, 3], lk.position, atol=1e-12) and np.allclose(M[:3, :3], lk.rotation, atol=1e-12)
    for n, j in zip(est.joint_names, est.joints, strict=True):
        assert np.abs(W[frames.joint_frame[n]][:3, 3] - j).max() < 1e-12, n
    root = W["body_7"]
    hips = est.joints[[body.joint_names.index("l_hip"), body.joint_names.index("r_hip")]]
    assert np.allclose(root[:3, 3], hips.mean(axis=0))
    assert np.allclose(root[:3, :3], est.links[0].rotation), "root axes: the pelvis (x forward, z up)"


def test_frame_names_follow_rep155_and_human_description():
    frames = BodyFrames(load_body_model(), "b1")
    assert frames.root == "body_b1"
    assert frames.link_frame["l_forearm"] == "l_forearm_b1"
    assert frames.joint_frame["l_elbow"] == "l_elbow_b1" and frames.joint_frame["head"] == "head_b1"
    assert frames.link_frame["head"] == "head_link_b1", "the head link (origin at the neck) yields its name"
    assert frames.joint_frame["pelvis"] == frames.link_frame["pelvis"] == "pelvis_b1"


def _urdf_fk(urdf: str, names, positions, root_pose: np.ndarray) -> dict[str, np.ndarray]:
    """What robot_state_publisher computes: world_from_link from the URDF and joint angles."""
    q = dict(zip(names, positions, strict=True))
    robot = ET.fromstring(urdf)
    joints = {j.find("child").get("link"): j for j in robot.findall("joint")}
    out: dict[str, np.ndarray] = {}

    def pose(link: str) -> np.ndarray:
        if link in out:
            return out[link]
        if link not in joints:
            out[link] = root_pose
            return root_pose
        j = joints[link]
        M = np.eye(4)
        M[:3, 3] = [float(v) for v in j.find("origin").get("xyz").split()]
        if j.get("type") != "fixed":
            axis = np.array([float(v) for v in j.find("axis").get("xyz").split()])
            M[:3, :3] = Rotation.from_rotvec(axis * q[j.get("name")]).as_matrix()
        out[link] = pose(j.find("parent").get("link")) @ M
        return out[link]

    for child in joints:
        pose(child)
    return out


def test_urdf_and_joint_states_reproduce_the_tf_tree():
    """robot_state_publisher's view (URDF + JointState) equals the published TF."""
    body = load_body_model()
    est = estimate_at(body, random_pose(body, 4))
    frames = BodyFrames(body, "0")
    tfs = frames.transforms(est, "world")
    W = world_from_frames(tfs, "world")
    names, values = frames.joint_state(est)
    urdf = frames.urdf(est)
    fk = _urdf_fk(urdf, names, values, W["body_0"])
    assert set(fk) >= set(W) - {"world"}
    worst = max(np.abs(fk[k] - W[k]).max() for k in W if k != "world")
    assert worst < 1e-8, worst
    assert len(names) == len(set(names)) == 8 * 3 + 6  # 8 ball joints, 6 hinges


def test_joint_rotations_computed_once_give_the_same_tf_and_joint_states():
    """body_publisher computes the links' relative rotations once for TF and JointState: the same
    values as each computing its own."""
    body = load_body_model()
    est = estimate_at(body, random_pose(body, 5))
    frames = BodyFrames(body, "0")
    rotations = frames.joint_rotations(est)
    assert len(rotations.relative) == len(rotations.angles) == len(body.links) - 1
    for a, b in zip(frames.transforms(est, "world"), frames.transforms(est, "world", rotations), strict=True):
        assert (a.parent, a.child) == (b.parent, b.child)
        assert np.array_equal(a.translation, b.translation) and np.array_equal(a.rotation, b.rotation)
    names, values = frames.joint_state(est)
    names2, values2 = frames.joint_state(est, rotations)
    assert names == names2 and np.array_equal(values, values2)


def test_only_tracked_finite_bodies_are_published():
    body = load_body_model()
    est = estimate_at(body, body.rest_pose())
    assert BodyFrames.publishable(est)
    est.status = STATUS_INITIALIZING
    assert not BodyFrames.publishable(est)
    est.status = STATUS_TRACKING
    est.joints = est.joints.copy()
    est.joints[3] = np.nan
    assert not BodyFrames.publishable(est)


def test_tf_message_fields():
    body = load_body_model()
    est = estimate_at(body, body.rest_pose(), stamp_ns=3_000_000_007)
    msg = tf_message(plain_factory(), BodyFrames(body, "0").transforms(est, "world"), est.stamp_ns)
    first = msg.transforms[0]
    assert first.header.frame_id == "world" and first.child_frame_id == "body_0"
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (3, 7)
    assert first.transform.rotation.w == pytest.approx(1.0)


def test_batched_quaternions_equal_one_by_one():
    """tf_message and pose_array convert all rotations in one scipy call: the same values, bit for bit,
    as FrameTransform.quaternion / Rotation.from_matrix per transform and link."""
    body = load_body_model()
    rng = np.random.default_rng(4)
    theta = body.rest_pose() + rng.normal(0.0, 0.3, body.n_dof) * (np.arange(body.n_dof) >= 6)
    est = estimate_at(body, np.clip(theta, body.lower, body.upper))
    tfs = BodyFrames(body, "0").transforms(est, "world")
    msg = tf_message(plain_factory(), tfs, est.stamp_ns)
    for tf, m in zip(tfs, msg.transforms, strict=True):
        r = m.transform.rotation
        assert np.array_equal([r.x, r.y, r.z, r.w], tf.quaternion())
    poses = MarkerBuilder(plain_factory(), body).pose_array(est, "world").poses
    for lk, pose in zip(est.links, poses, strict=True):
        o = pose.orientation
        assert np.array_equal([o.x, o.y, o.z, o.w], Rotation.from_matrix(lk.rotation).as_quat())


def test_ellipsoid_reproduces_the_covariance():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    cov = A @ A.T * 0.01
    d, R = ellipsoid(cov, sigmas=2.0)
    assert np.linalg.det(R) > 0
    assert np.allclose(R @ np.diag((d / 4.0) ** 2) @ R.T, cov)


def test_marker_array_has_bones_joints_blobs_and_predicted_priors():
    body = load_body_model()
    theta = random_pose(body, 5)
    est, pred = estimate_at(body, theta), estimate_at(body, theta + 0.01)
    b = MarkerBuilder(plain_factory(), body)
    arr = b.marker_array(est, "world", "0", prediction=pred)
    assert arr.markers[0].action == DELETEALL
    by_ns: dict[str, list] = {}
    for m in arr.markers[1:]:
        by_ns.setdefault(m.ns, []).append(m)
    assert set(by_ns) == {"artrack/bones", "artrack/joints", "artrack/blobs", "artrack/predicted_blobs",
                          "artrack/status"}
    assert len(by_ns["artrack/bones"][0].points) == 2 * len(body.links)
    assert len(by_ns["artrack/joints"][0].points) == 15
    assert len(by_ns["artrack/blobs"]) == len(est.blobs) == len(by_ns["artrack/predicted_blobs"])
    m = by_ns["artrack/blobs"][0]
    assert m.type == SPHERE and m.header.frame_id == "world"
    q = m.pose.orientation
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    d = np.array([m.scale.x, m.scale.y, m.scale.z])
    assert np.allclose(R @ np.diag((d / 2) ** 2) @ R.T, est.blobs[0].cov)
    poses = b.pose_array(est, "world")
    assert len(poses.poses) == len(body.links)


def test_workspace_tf2_msgs_has_the_official_type_hash():
    """The stand-in tf2_msgs (src/ros_standins) is wire-identical to ROS 2 Jazzy's: same RIHS01."""
    path = INSTALL / "tf2_msgs" / "share" / "tf2_msgs" / "msg" / "TFMessage.json"
    if not path.is_file():
        pytest.fail("workspace not built: run `make setup`")
    hashes = {h["type_name"]: h["hash_string"] for h in json.loads(path.read_text())["type_hashes"]}
    assert hashes["tf2_msgs/msg/TFMessage"] == TF_MESSAGE_HASH
