"""One camera (ALGORITHMS.md §1: "a part seen by one camera only still constrains the ray"): the
start-up from a single view (depth from the floor), the ray-shaped measurements, the upright trunk
and the ``few_cameras`` section of config/skeleton.yaml that switches them on for one or two."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from test_skeleton import blobs_2d, stamp, startup_blobs

from artrack.body_fit import BodyTerms, GroundContact, PointTarget, UprightSegment, fit_pose
from artrack.body_model import load_body_model
from artrack.cameras import Camera
from artrack.config import config_dir
from artrack.errors import InputError
from artrack.skeleton import BodyKinematics, make_estimator
from artrack.skeleton_config import SkeletonConfig, load_skeleton_config
from artrack.startup import one_view_start_points, ray_information
from artrack.types import STATUS_INITIALIZING, STATUS_TRACKING, Blob2D, Blob3D


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def camera():
    """The synthetic rig's kind of camera: 1.9 m up, 4 m from the person, looking at 1 m height."""
    f, w, h = 600.0, 640, 480
    K = np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1.0]])
    return Camera.look_at("cam0", w, h, K, np.array([4.0, 0.5, 1.9]), np.array([0.0, 0.0, 1.0]))


def _pose(body, yaw=2.9):
    """Standing at (0.3, -0.2), facing the camera roughly (yaw about the camera's azimuth + π)."""
    theta = body.rest_pose()
    theta[0:6] = [0.3, -0.2, theta[2], 0.0, 0.0, yaw]
    return theta


def _config():
    return yaml.safe_load((config_dir() / "skeleton.yaml").read_text())


def test_one_view_start_points_take_their_depth_from_the_floor(body, camera):
    """The foreground centroid's ray is cut at the rest pose's centroid height: the body centre lands
    within 0.25 m of the true one (0.18 here, along the ray: the ray falls 1 m in 4, so depth errs
    about 4 times the height, and the image centroid of the body is not its centroid's image), and
    every skin point lies on its own ray (it reprojects onto its blob)."""
    theta = _pose(body)
    blobs = startup_blobs(body, [camera], theta)["cam0"]
    fg = next(b for b in blobs if b.label == "foreground")
    skin = [b for b in blobs if b.label == "skin"]
    kin = BodyKinematics(body)
    p, R = kin.poses(theta)
    centre_true = p[0] + R[0] @ kin.body_centroid_local()  # the body's mass centroid
    out = one_view_start_points(camera, fg, skin, centre_height_m=float(centre_true[2]))
    assert out is not None
    centre, points = out
    assert np.linalg.norm(centre - centre_true) < 0.25, centre - centre_true
    assert len(points) == 3
    for X, count, cams in points:
        assert cams == ("cam0",) and count == 300
        uv, _ = camera.project(X[None])
        assert min(np.linalg.norm(uv[0] - b.mean) for b in skin) < 1e-6
        # (X - centre) is the blob's viewing ray, as the start-up's ray-shaped targets assume
        rays = camera.rays(np.array([b.mean for b in skin]))[1]
        assert min(np.linalg.norm((X - camera.center) / np.linalg.norm(X - camera.center) - r) for r in rays) < 1e-12
    # A camera at the centroid's height, looking level, has no floor cue: no start.
    level = Camera.look_at("cam1", 640, 480, camera.K, np.array([4.0, 0.5, 0.9]), np.array([0.0, 0.0, 0.9]))
    fg_level = Blob2D("foreground", np.array([319.5, 239.5]), np.eye(2) * 400.0, pixel_count=5000)
    assert one_view_start_points(level, fg_level, [], centre_height_m=0.9) is None


def test_ray_information_is_tight_across_and_loose_along():
    d = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    info = ray_information(d, 0.03, 1.0)
    assert np.isclose(d @ info @ d, 1.0)
    across = np.cross(d, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    assert np.isclose(across @ info @ across, 1.0 / 0.03**2)


def test_one_camera_starts_and_tracks_only_with_the_one_view_settings(body, camera):
    """With the file's settings a single camera starts from the start-up blobs (before stop 46 it never
    did) and then tracks labelled blobs from that view alone; with ``few_cameras`` off (and the
    one-view start-up off) the same frames never start."""
    theta = _pose(body)
    est = make_estimator("baseline", body, [camera], _config())
    assert est.cfg.fit.ground_sigma_m == 0.005 and est.cfg.measurement.one_view_depth_sigma_m == 0.1
    e = est.update(stamp(0), startup_blobs(body, [camera], theta))
    assert e.status == STATUS_TRACKING
    truth = body.joint_positions(theta)
    assert np.linalg.norm(e.joints[0] - truth[0]) < 0.3
    rng = np.random.default_rng(5)
    for k in range(1, 16):
        e = est.update(stamp(k), blobs_2d(body, [camera], theta, rng, sigma_px=0.5))
    assert e.status == STATUS_TRACKING
    err = np.linalg.norm(e.joints - truth, axis=1)
    assert err[0] < 0.2 and err.mean() < 0.2, err
    # Without the one-view settings: never starts.
    cfg = _config()
    cfg["few_cameras"]["max_cameras"] = 0
    cfg["startup"]["one_view_depth_sigma_m"] = 0.0
    off = make_estimator("baseline", body, [camera], cfg)
    assert off.update(stamp(0), startup_blobs(body, [camera], theta)).status == STATUS_INITIALIZING


def test_one_view_blobs_count_across_their_ray_only(body, camera):
    """measurement.one_view_depth_sigma_m: a 3-D blob from one view, triangulated with a tight prior
    (its depth is the prediction's), is a fit target of that sigma along the ray and keeps its
    across-ray information; a blob from two views is unchanged."""
    est = make_estimator("baseline", body, [camera], {"few_cameras": {"measurement": {"one_view_depth_sigma_m": 0.5}}})
    mean = np.array([0.3, -0.2, 1.2])
    cov = np.eye(3) * 0.01**2
    one = est._blob_targets({"head": Blob3D("head", mean, cov, ("cam0",))})[0]
    two = est._blob_targets({"head": Blob3D("head", mean, cov, ("cam0", "cam9"))})[0]
    d = (mean - camera.center) / np.linalg.norm(mean - camera.center)
    assert np.isclose(d @ one.info @ d, 1.0 / 0.5**2)
    np.testing.assert_allclose(two.info, np.linalg.inv(est.measurement_cov(Blob3D("head", mean, cov))))
    across = np.cross(d, [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    assert np.isclose(across @ one.info @ across, across @ two.info @ across)


def test_upright_trunk_holds_the_thorax_over_the_pelvis(body):
    """fit.upright_sigma_m: a thorax target pulled 0.3 m sideways tilts the plain fit's trunk; with the
    upright term it stays within a few cm; its analytic Jacobian, stacked with the floor contact's
    (BodyTerms), equals forward differences."""
    rest = body.rest_pose()
    rest[2] = 0.95
    T = body.forward_kinematics(rest)
    names = list(body.joint_names)
    upright = UprightSegment.from_body(body, 0.02)
    assert np.allclose(upright.residuals(T), 0.0)
    torso = body.link_names.index("torso")
    top = body.joint_positions(rest)[names.index("thorax")]
    local = (np.linalg.inv(T[torso]) @ np.append(top, 1.0))[:3]
    pelvis = body.joint_positions(rest)[names.index("pelvis")]
    targets = [PointTarget(torso, local, top + [0.3, 0.0, 0.0], np.eye(3) / 0.05**2),
               PointTarget(0, np.zeros(3), pelvis, np.eye(3) / 0.01**2)]
    lean = {}
    for name, term in (("plain", None), ("upright", upright)):
        theta, _, _ = fit_pose(body, rest, targets, rest, 1.0, max_nfev=100, ground=term)
        j = body.joint_positions(theta)
        lean[name] = float(np.linalg.norm((j[names.index("thorax")] - j[names.index("pelvis")])[:2]))
    assert lean["plain"] > 0.15 and lean["upright"] < 0.05, lean
    terms = BodyTerms([GroundContact.from_body(body, 0.01), UprightSegment.from_body(body, 0.1)])
    theta = body.clip(rest + np.random.default_rng(2).normal(0.0, 0.2, body.n_dof))
    theta[2] = 0.9  # (the lower ankle below the floor: the floor rows are active)
    J = terms.jacobian(body, theta, body.forward_kinematics(theta))
    h = 1e-6
    J_num = np.stack([(terms.residuals(body.forward_kinematics(theta + h * e)) - terms.residuals(
        body.forward_kinematics(theta))) / h for e in np.eye(body.n_dof)], axis=1)
    assert J.shape == (5, body.n_dof) and np.abs(J[3:]).max() > 1.0
    np.testing.assert_allclose(J, J_num, atol=1e-3)
    with pytest.raises(InputError, match="'chin'"):
        UprightSegment.from_body(body, 0.1, top="chin")


def test_few_cameras_section_applies_to_one_or_two_cameras_only():
    cfg = load_skeleton_config(_config())
    assert cfg.few_cameras_max == 2
    assert cfg.for_cameras(4) is cfg and cfg.for_cameras(3) is cfg
    one = cfg.for_cameras(1)
    assert one.fit.ground_sigma_m == 0.005 and one.fit.upright_sigma_m == 0.15
    assert one.measurement.one_view_depth_sigma_m == 0.1
    assert cfg.for_cameras(2) == one
    assert cfg.fit.ground_sigma_m == 0.0  # the values for more cameras are untouched
    assert SkeletonConfig().for_cameras(1) == one
    assert load_skeleton_config({"few_cameras": {"max_cameras": 3}}).for_cameras(3).fit.upright_sigma_m == 0.15
    assert load_skeleton_config({"few_cameras": {"max_cameras": 0}}).for_cameras(1).fit.upright_sigma_m == 0.0
    merged = load_skeleton_config({"few_cameras": {"fit": {"upright_sigma_m": 0.3}}}).for_cameras(1)
    assert merged.fit.upright_sigma_m == 0.3 and merged.fit.ground_sigma_m == 0.005  # merged into the defaults
    with pytest.raises(InputError, match="fit.bogus"):
        load_skeleton_config({"few_cameras": {"fit": {"bogus": 1}}})
    with pytest.raises(InputError, match="upright_sigma_m"):
        load_skeleton_config({"few_cameras": {"fit": {"upright_sigma_m": -1.0}}})
    with pytest.raises(InputError, match="few_cameras.max_cameras"):
        load_skeleton_config({"few_cameras": {"max_cameras": "two"}})
    with pytest.raises(InputError, match="unknown section 'few_cameras_max'"):
        load_skeleton_config({"few_cameras_max": 3})


@pytest.mark.parametrize("kind", ["baseline", "kinematic"])
def test_one_camera_follows_a_walk_along_its_rays(body, camera, kind):
    """A person walking 1.6 m straight towards the one camera (along its rays, where one view sees
    no motion but growth): both estimators keep the body within 0.25 m (mean joint error) through
    70 frames, the kinematic one past its warm-up on the raw tracker (its filters' depth comes from
    the frame's body fit: floor, upright trunk). With each view's depth left at the prediction's
    (``one_view_depth_sigma_m`` 0) both fall behind the walk by several times that."""
    def pose(k):
        theta = _pose(body)
        theta[0] += 1.6 * k / 70
        return theta

    errors = {}
    for depth_sigma in (0.1, 0.0):
        cfg = _config()
        cfg["few_cameras"]["measurement"]["one_view_depth_sigma_m"] = depth_sigma
        est = make_estimator(kind, body, [camera], cfg)
        est.update(stamp(0), startup_blobs(body, [camera], pose(0)))
        rng = np.random.default_rng(7)
        err = []
        for k in range(1, 71):
            e = est.update(stamp(k), blobs_2d(body, [camera], pose(k), rng, sigma_px=0.5))
            assert e.status == STATUS_TRACKING
            err.append(float(np.linalg.norm(e.joints - body.joint_positions(pose(k)), axis=1).mean()))
        errors[depth_sigma] = max(err[-20:])
    assert errors[0.1] < 0.25, errors  # (0.16 m for both)
    assert errors[0.0] > 2 * errors[0.1], errors  # (0.96 / 0.83 m)
