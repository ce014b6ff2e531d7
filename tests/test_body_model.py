"""Tests of artrack.body_model: YAML loading, forward kinematics, errors."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from artrack.body_model import BodyModel, body_model_from_dict, load_body_model
from artrack.body_quadrics import visible_surface_gaussian
from artrack.errors import ArtrackError, BodyModelError

CONFIG = Path(__file__).resolve().parents[1] / "config" / "body_model.yaml"

JOINTS = ["pelvis", "thorax", "head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow",
          "r_wrist", "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle"]
LINKS = ["pelvis", "torso", "head", "l_upper_arm", "l_forearm", "l_hand", "r_upper_arm", "r_forearm",
         "r_hand", "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot"]


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return load_body_model()


@pytest.fixture(scope="module")
def raw() -> dict:
    return yaml.safe_load(CONFIG.read_text())


def test_structure(body):
    assert body.link_names == LINKS
    assert body.joint_names == JOINTS
    assert body.parent_index[0] == -1
    assert all(body.parent_index[i] < i for i in range(1, len(LINKS)))
    # 6 root + 8 ball * 3 + 6 hinges (elbows, knees, ankles)
    assert body.n_dof == 6 + 8 * 3 + 6
    assert body.lower.shape == body.upper.shape == (body.n_dof,)
    assert np.all(body.lower <= body.upper)
    assert set(body.blob_labels) == {"pelvis", "head", "torso", "l_hand", "r_hand", "l_thigh", "r_thigh",
                                     "l_shin", "r_shin"}
    assert body.within_limits(body.rest_pose())


def test_default_path_via_env(monkeypatch, tmp_path):
    (tmp_path / "body_model.yaml").write_text(CONFIG.read_text().replace("adult_1p75", "from_env"))
    monkeypatch.setenv("ARTRACK_CONFIG_DIR", str(tmp_path))
    assert load_body_model().name == "from_env"


def test_rest_pose_joint_heights(body):
    theta = body.rest_pose()
    J = dict(zip(body.joint_names, body.joint_positions(theta), strict=True))
    assert J["pelvis"] == pytest.approx([0.0, 0.0, 0.95])
    assert J["thorax"][2] == pytest.approx(1.47)
    assert J["head"][2] == pytest.approx(1.62)
    for side, sy in (("l", 1.0), ("r", -1.0)):
        assert J[f"{side}_shoulder"] == pytest.approx([0.0, sy * 0.19, 1.42])
        assert J[f"{side}_elbow"] == pytest.approx([0.0, sy * 0.19, 1.13])
        assert J[f"{side}_wrist"] == pytest.approx([0.0, sy * 0.19, 0.88])
        assert J[f"{side}_hip"] == pytest.approx([0.0, sy * 0.09, 0.95])
        assert J[f"{side}_knee"] == pytest.approx([0.0, sy * 0.09, 0.51])
        assert J[f"{side}_ankle"] == pytest.approx([0.0, sy * 0.09, 0.08])
    # all link frames aligned with the world at rest
    T = body.forward_kinematics(theta)
    assert np.allclose(T[:, :3, :3], np.eye(3))
    # feet rest on the floor, head top near 1.75 m
    p0, p1, r, _, _ = body.capsules(theta)
    lows = np.minimum(p0[:, 2], p1[:, 2]) - r
    highs = np.maximum(p0[:, 2], p1[:, 2]) + r
    assert lows.min() == pytest.approx(0.0, abs=0.01)
    assert 1.70 < highs.max() < 1.80


def test_elbow_flexion_by_hand(body):
    theta = body.rest_pose()
    theta[body.dof_slice("l_forearm")] = np.pi / 2
    J = dict(zip(body.joint_names, body.joint_positions(theta), strict=True))
    # forearm (0.25 m) points forward (+x) from the elbow
    assert J["l_elbow"] == pytest.approx([0.0, 0.19, 1.13])
    assert J["l_wrist"] == pytest.approx([0.25, 0.19, 1.13])
    # 60 degrees: wrist at elbow + 0.25 (sin 60, 0, -cos 60)
    theta[body.dof_slice("l_forearm")] = np.pi / 3
    wrist = body.joint_positions(theta)[body.joint_names.index("l_wrist")]
    assert wrist == pytest.approx([0.25 * np.sin(np.pi / 3), 0.19, 1.13 - 0.25 * 0.5])


def test_shoulder_abduction_and_root_rotation(body):
    theta = body.rest_pose()
    theta[body.dof_slice("l_upper_arm")] = [np.pi / 2, 0.0, 0.0]  # arm straight out to the left
    J = dict(zip(body.joint_names, body.joint_positions(theta), strict=True))
    assert J["l_wrist"] == pytest.approx([0.0, 0.19 + 0.54, 1.42])
    # turn the whole body 90 degrees to the left about z: +y (left) becomes -x
    theta[3:6] = [0.0, 0.0, np.pi / 2]
    theta[0:3] = [1.0, 2.0, 0.95]
    J = dict(zip(body.joint_names, body.joint_positions(theta), strict=True))
    assert J["l_wrist"] == pytest.approx([1.0 - 0.73, 2.0, 1.42])


def test_batch_equals_single(body):
    rng = np.random.default_rng(0)
    n = 500
    theta = rng.uniform(np.maximum(body.lower, -3), np.minimum(body.upper, 3), size=(n, body.n_dof))
    Tb = body.forward_kinematics(theta)
    assert Tb.shape == (n, 15, 4, 4)
    for k in (0, 17, 499):
        assert np.allclose(Tb[k], body.forward_kinematics(theta[k]))
    jb = body.joint_positions(theta.reshape(20, 25, -1))
    assert jb.shape == (20, 25, 15, 3)
    assert np.allclose(jb.reshape(n, 15, 3)[123], body.joint_positions(theta[123]))
    # rigid: bone lengths preserved
    L = np.linalg.norm(jb[..., 4, :] - jb[..., 5, :], axis=-1)
    assert np.allclose(L, 0.25)
    means, covs = body.blob_gaussians(theta[:3])
    assert means.shape == (3, 9, 3) and covs.shape == (3, 9, 3, 3)
    assert np.allclose(covs, np.swapaxes(covs, -1, -2))


def test_forward_kinematics_equals_link_by_link_composition(body):
    """The level-by-level batched tree walk equals composing each link on its parent, one at a
    time, with scipy's rotations (hinges as rotation vectors angle * axis)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    theta = rng.uniform(np.maximum(body.lower, -3), np.minimum(body.upper, 3), size=(4, body.n_dof))
    got = body.forward_kinematics(theta)
    for k in range(len(theta)):
        world = []
        for i, lk in enumerate(body.links):
            q = theta[k, lk.dof_slice]
            if lk.joint == "free":
                local = np.eye(4)
                local[:3, :3] = Rotation.from_rotvec(q[3:]).as_matrix()
                local[:3, 3] = q[:3]
            else:
                local = np.eye(4)
                rv = q if lk.joint == "ball" else q[0] * np.asarray(lk.axis, float)
                local[:3, :3] = Rotation.from_rotvec(rv).as_matrix()
                local[:3, 3] = lk.offset
            p = body.parent_index[i]
            world.append(local if p < 0 else world[p] @ local)
        assert np.allclose(got[k], np.array(world), atol=1e-12)


def test_capsules_and_blobs(body):
    theta = body.rest_pose()
    p0, p1, radius, link, colour = body.capsules(theta)
    S = len(radius)
    assert p0.shape == p1.shape == (S, 3) and link.shape == (S,) and len(colour) == S
    assert {"skin", "shirt", "trousers", "shoes", "hair"} <= set(colour)
    blobs = body.blobs3d(theta)
    assert [b.label for b in blobs] == body.blob_labels
    head = blobs[body.blob_labels.index("head")]
    # the head's skin surface ('auto'): below the face ellipsoid's centre (0.15 m up the link; the
    # hair covers its top) and in front of the head's axis (the face), as its pixels show it
    link = body.link_names.index("head")
    auto_centre, _ = visible_surface_gaussian(body, link, "skin")
    assert 0.05 < auto_centre[2] < 0.14 and auto_centre[0] > 0.02
    # the default body places the head's blob where the tracker triangulates it (measured by
    # bench/blob_centres.py, config/body_model.yaml): lower still, at the neck
    T = body.forward_kinematics(theta)[link]
    assert np.allclose(T[:3, :3].T @ (head.mean - T[:3, 3]), body.links[link].blob.centre)
    assert 1.50 < head.mean[2] < 1.61
    assert np.all(np.linalg.eigvalsh(head.cov) > 0)
    pb = body.capsules(np.stack([theta, theta]))[0]
    assert pb.shape == (2, S, 3)


def _mutated(raw, fn):
    data = copy.deepcopy(raw)
    fn(data)
    return data


def _link(data, name):
    return next(lk for lk in data["links"] if lk["name"] == name)


@pytest.mark.parametrize("mutate, expected", [
    (lambda d: _link(d, "l_hand").__setitem__("parent", "l_arm"),
     "link 'l_hand' names unknown parent 'l_arm'"),
    (lambda d: _link(d, "torso").__setitem__("parent", None), "link 'torso' has no parent"),
    (lambda d: _link(d, "l_forearm").__setitem__("joint", "slider"),
     "link 'l_forearm' field 'joint': unknown joint type 'slider'"),
    (lambda d: _link(d, "l_forearm").__setitem__("limits", [[0, 1], [0, 1], [0, 1]]),
     "link 'l_forearm' field 'limits'"),
    (lambda d: _link(d, "head").__setitem__("limits", [[0, 1]]), "link 'head' field 'limits'"),
    (lambda d: _link(d, "l_shin").pop("axis"), "link 'l_shin' field 'axis'"),
    (lambda d: _link(d, "r_foot").__setitem__("colour", "purple"), "link 'r_foot' field 'colour'"),
    (lambda d: d["joints"][0].__setitem__("link", "nope"), "joint 'pelvis' names unknown link 'nope'"),
    (lambda d: _link(d, "l_hand")["blob"].update(colour="shoes", centre="auto"),
     "link 'l_hand' field 'blob': 'auto' needs a visible shape of the blob's colour"),
])
def test_errors_name_link_and_field(raw, mutate, expected):
    with pytest.raises(BodyModelError, match=expected) as info:
        body_model_from_dict(_mutated(raw, mutate), source="body_model.yaml")
    assert str(info.value).startswith("body_model.yaml: ")
    assert isinstance(info.value, ArtrackError)


def test_error_names_file(tmp_path, raw):
    path = tmp_path / "body_model.yaml"
    bad = _mutated(raw, lambda d: _link(d, "l_hand").__setitem__("parent", "l_arm"))
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(BodyModelError, match=r"body_model\.yaml: link 'l_hand' names unknown parent 'l_arm'"):
        load_body_model(path)
    with pytest.raises(BodyModelError, match="missing.yaml"):
        load_body_model(tmp_path / "missing.yaml")


def test_extends_with_link_overrides(body, tmp_path):
    """A variant file takes the base body and changes only what it names: the Pose2Sim body
    adds skin blobs on the upper arms and the (bare, so skin-coloured) feet, puts the head's blob on
    the cap (class 'hair', 'auto': the head's hair-coloured shape, stop 44) and keeps the pelvis' and
    thighs' earlier blob centres (stop 42), everything else (links, limits, shapes, joints, the other
    blobs) equal."""
    variant = load_body_model(CONFIG.parent / "pose2sim_body_model.yaml")
    assert variant.link_names == body.link_names and variant.joint_names == body.joint_names
    assert np.array_equal(variant.lower, body.lower) and np.array_equal(variant.upper, body.upper)
    assert variant.blob_labels == ["pelvis", "torso", "head", "l_upper_arm", "l_hand", "r_upper_arm", "r_hand",
                                   "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot"]
    head = variant.link("head").blob
    assert head.colour == "hair" and head.centre[2] > 0.15  # on top of the head, not at the face (0.058)
    for side in "lr":
        foot = variant.link(f"{side}_foot")
        assert foot.colour == "skin" and foot.blob.colour == "skin" and body.link(f"{side}_foot").blob is None
        assert foot.blob.centre[0] > 0.03  # towards the toes
    for side in "lr":
        blob = variant.link(f"{side}_upper_arm").blob
        assert blob.colour == "skin"
        np.testing.assert_allclose(blob.centre, [0.0, 0.0, -0.145])
        assert body.link(f"{side}_upper_arm").blob is None
    for name in ("torso", "l_hand", "r_shin"):
        np.testing.assert_array_equal(variant.link(name).blob.centre, body.link(name).blob.centre)
    np.testing.assert_allclose(variant.link("pelvis").blob.centre, [0.046, 0.0, -0.018])
    assert not np.allclose(variant.link("r_thigh").blob.centre, body.link("r_thigh").blob.centre)
    theta = body.rest_pose() + 0.1
    np.testing.assert_array_equal(variant.forward_kinematics(theta), body.forward_kinematics(theta))

    # a top-level field replaces the base's; the base is found next to the variant
    (tmp_path / "base.yaml").write_text(CONFIG.read_text())
    (tmp_path / "renamed.yaml").write_text("extends: base.yaml\nname: renamed\n")
    assert load_body_model(tmp_path / "renamed.yaml").name == "renamed"


@pytest.mark.parametrize("text, expected", [
    ("extends: base.yaml\nlink_overrides: {l_arm: {colour: skin}}\n", r"v\.yaml: link_overrides: unknown link 'l_arm'"),
    ("extends: base.yaml\nlink_overrides: {l_hand: {parent: torso}}\n", r"v\.yaml: link_overrides\.l_hand: must be"),
    ("extends: nowhere.yaml\n", r"nowhere\.yaml: cannot read"),
    ("extends: v.yaml\n", r"v\.yaml: 'extends' loops back"),
    ("link_overrides: {l_hand: {colour: skin}}\n", r"v\.yaml: field 'link_overrides' needs 'extends'"),
    ("extends: base.yaml\nlink_overrides: {l_hand: {blob: {colour: paint}}}\n", r"v\.yaml: .*l_hand"),
])
def test_extends_errors_name_the_file(tmp_path, text, expected):
    (tmp_path / "base.yaml").write_text(CONFIG.read_text())
    (tmp_path / "v.yaml").write_text(text)
    with pytest.raises(BodyModelError, match=expected):
        load_body_model(tmp_path / "v.yaml")


def test_point_and_link_twist_jacobians_match_finite_differences(body):
    """BodyModel.point_jacobian / link_twist_jacobian (the analytic Jacobian of the body fit) against
    forward differences of the forward kinematics at a random pose within the limits."""
    from artrack.lie import inverse_se3, log_se3

    rng = np.random.default_rng(4)
    theta = body.clip(body.rest_pose() + rng.normal(0.0, 0.6, body.n_dof))
    links = np.arange(len(body.links))
    points = rng.normal(0.0, 0.2, (len(links), 3))
    J = body.point_jacobian(theta, links, points)
    G = body.link_twist_jacobian(theta, links)
    assert J.shape == (len(links), 3, body.n_dof) and G.shape == (len(links), 6, body.n_dof)
    T0 = body.forward_kinematics(theta)
    x0 = body.transform_points(T0, links, points)
    h = 1e-6
    for d in range(body.n_dof):
        t = theta.copy()
        t[d] += h
        T = body.forward_kinematics(t)
        np.testing.assert_allclose(J[:, :, d], (body.transform_points(T, links, points) - x0) / h, atol=2e-5)
        np.testing.assert_allclose(G[:, :, d], log_se3(inverse_se3(T0) @ T) / h, atol=2e-5)
    # a dof moves only its own link and the links below it
    hand = body.link_names.index("l_hand")
    assert not np.any(J[body.link_names.index("r_hand"), :, body.links[hand].dof_slice])
