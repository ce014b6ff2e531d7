"""3-D estimators (ALGORITHMS.md §1): baseline fit, Kalman + constraints, start-up.

Synthetic data only: blob Gaussians of the body model projected into a ring of
four pinhole cameras (no renderer).
"""

import dataclasses
import math

import numpy as np
import pytest
import yaml

from artrack.body_fit import (
    GroundContact,
    LinkGoals,
    PointTarget,
    UprightSegment,
    exchange_sides,
    fit_pose,
    mirror_label,
)
from artrack.body_model import body_model_from_dict, default_config_path, load_body_model
from artrack.cameras import Camera
from artrack.config import config_dir
from artrack.constraints import assemble, soft_energy_terms
from artrack.errors import InputError
from artrack.lie import exp_se3, inverse_se3
from artrack.motion import pose_at
from artrack.projection import visible_points
from artrack.skeleton import BodyKinematics, make_estimator
from artrack.skeleton_config import SkeletonConfig, load_skeleton_config
from artrack.startup import blob_size_m, facing_agreement, facing_direction, match_skin_blobs
from artrack.triangulation import associate_views, triangulate_blobs
from artrack.types import STATUS_INITIALIZING, STATUS_LOST, STATUS_TRACKING, Blob2D, Blob3D

FPS = 30.0


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def body_shape_hands():
    """The default body with the hands' blob centres at their shapes' visible surface ('auto', the
    default until stop 72; now they are measured, 15 mm nearer the hand's midline). The hand-built
    scenes below were laid out around those centres: a hand at the side seen by the views the
    test names, a leg screen's cost just under ``fit.mirror_screen_ratio``, a start-up just within
    its bound. What they test is the mechanism, not the centres."""
    raw = yaml.safe_load(default_config_path().read_text())
    for link in raw["links"]:
        if link["name"] in ("l_hand", "r_hand"):
            link["blob"]["centre"] = "auto"
    return body_model_from_dict(raw, source="body_model.yaml (hands 'auto')")


@pytest.fixture(scope="module")
def cameras():
    f, w, h = 600.0, 640, 480
    K = np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1.0]])
    cams = []
    for k in range(4):
        a = 2 * np.pi * k / 4 + 0.3
        eye = np.array([4.0 * np.cos(a), 4.0 * np.sin(a), 1.6])
        cams.append(Camera.look_at(f"cam{k}", w, h, K, eye, np.array([0.0, 0.0, 1.0])))
    return cams


def blobs_2d(body, cameras, theta, rng=None, sigma_px=0.0, hide=()):
    """Labelled 2-D blobs: projected blob-feature Gaussians (+ pixel noise on the means), each with
    the pixel count of its 2-sigma ellipse (4 pi sqrt(det C))."""
    means, covs = body.blob_gaussians(theta)
    out = {}
    for cam in cameras:
        uv, J = cam.project_jacobian(means)
        blobs = []
        for k, label in enumerate(body.blob_labels):
            if label in hide:
                continue
            m = uv[k] + (rng.normal(scale=sigma_px, size=2) if rng is not None else 0.0)
            C = J[k] @ covs[k] @ J[k].T
            blobs.append(Blob2D(label, m, C, pixel_count=max(1, int(4.0 * np.pi * np.sqrt(np.linalg.det(C))))))
        out[cam.name] = blobs
    return out


def startup_blobs(body, cameras, theta, face_forward=0.07):
    """Start-up classes: one 'foreground' blob (projected scatter of the body volume) and
    three unlabelled 'skin' blobs (face in front of the head, both hands), shuffled per camera."""
    T = body.forward_kinematics(theta)
    p0, p1, rad, _, _ = body.capsules(theta, T)
    vol = np.pi * rad**2 * np.linalg.norm(p1 - p0, axis=1) + 4 / 3 * np.pi * rad**3
    rng = np.random.default_rng(123)
    k = rng.choice(len(rad), size=400, p=vol / vol.sum())
    pts = p0[k] + rng.random(400)[:, None] * (p1[k] - p0[k]) + rng.normal(size=(400, 3)) * rad[k, None] * 0.5
    means, _ = body.blob_gaussians(theta)
    head = body.link_index("head")
    labels = body.blob_labels
    face = means[labels.index("head")] + face_forward * T[head, :3, 0]
    skin = [face, means[labels.index("l_hand")], means[labels.index("r_hand")]]
    out = {}
    for ci, cam in enumerate(cameras):
        uv, _ = cam.project(pts)
        blobs = [Blob2D("foreground", uv.mean(0), np.cov(uv.T), pixel_count=5000)]
        for j in [(ci + i) % 3 for i in range(3)]:
            m, J = cam.project_jacobian(skin[j][None])
            blobs.append(Blob2D("skin", m[0], J[0] @ (np.eye(3) * 0.03**2) @ J[0].T, pixel_count=300))
        out[cam.name] = blobs
    return out


def stamp(k: int) -> int:
    return int(round(k * 1e9 / FPS))


def test_body_kinematics_roundtrip(body):
    kin = BodyKinematics(body)
    rng = np.random.default_rng(0)
    theta = body.clip(body.rest_pose() + rng.normal(scale=0.3, size=body.n_dof))
    p, R = kin.poses(theta)
    np.testing.assert_allclose(kin.theta_from_poses(p, R), theta, atol=1e-9)
    assert np.linalg.norm(kin.solver().residual(p, R)) < 1e-12
    assert np.all(kin.masses > 0) and 50 < kin.masses.sum() < 100  # an adult, kg


def _test_pose(body):
    theta = body.rest_pose()
    theta[0:6] = [0.2, -0.1, 0.95, 0.0, 0.0, 0.5]
    for name, value in {
        "torso": [0.05, 0.2, 0.1],
        "l_upper_arm": [0.8, 0.0, 0.0],
        "l_forearm": [0.9],
        "r_upper_arm": [0.0, -0.7, 0.0],
        "r_forearm": [0.5],
        "l_thigh": [0.0, -0.4, 0.0],
        "l_shin": [0.6],
        "r_thigh": [0.0, 0.2, 0.0],
        "r_shin": [0.3],
    }.items():
        theta[body.dof_slice(name)] = value
    return theta


def test_baseline_recovers_known_pose_from_exact_blobs(body, cameras):
    theta = _test_pose(body)
    # every blob in every view: the body model's Gaussians (1.5x the tracker's blobs) of the legs
    # overlap in some views here, which fit.overlap_parts would leave out
    est = make_estimator("baseline", body, cameras, {"fit": {"overlap_parts": []}})
    for k in range(3):
        e = est.update(stamp(k), blobs_2d(body, cameras, theta))
    assert e.status == STATUS_TRACKING
    err = np.linalg.norm(e.joints - body.joint_positions(theta), axis=1)
    assert err.mean() < 0.020, dict(zip(body.joint_names, err.round(3), strict=True))
    # Observed blobs are fitted closely; every output is consistent with the body model.
    np.testing.assert_allclose([b.mean for b in e.blobs], body.blob_centres(theta), atol=0.01)
    assert [b.label for b in e.blobs] == body.blob_labels
    assert [lk.name for lk in e.links] == body.link_names
    assert all(np.all(np.linalg.eigvalsh(b.cov) > 0) for b in e.blobs)


@pytest.fixture(scope="module")
def line_runs(body, cameras):
    """The paper's line-following test: the right hand moves on a straight line; 1 px
    noise on the 2-D blob means; baseline vs kinematic tracker (estimates and predictions).
    'baseline' is the paper's raw feature tracker, blob means only (the torso-shape heading
    cue off, as the kinematic estimator has none; no mirror tests, the labels are right);
    'baseline+axis' has the cue (default)."""
    n = 40
    thetas = [pose_at("line", k / FPS, body) for k in range(n + 1)]
    runs = {}
    configs = {"baseline": {"fit": {"axis_sigma_rad": 0.0, "mirror_groups": [], "predict_velocity_gain": 0.0}},
               "baseline+axis": {"fit": {"mirror_groups": []}},
               "kinematic": {"kinematic": {"warmup_frames": 0}}}  # the filters from the first frame
    for name, config in configs.items():
        kind = name.split("+")[0]
        rng = np.random.default_rng(42)
        est = make_estimator(kind, body, cameras, config)
        estimates, predictions = [], []
        for k in range(n):
            estimates.append(est.update(stamp(k), blobs_2d(body, cameras, thetas[k], rng, 1.0)))
            predictions.append(est.predict(stamp(k + 1)))
        runs[name] = (estimates, predictions)
    return thetas, runs


def _hand(estimate, label="r_hand"):
    return next(b.mean for b in estimate.blobs if b.label == label)


def test_kinematic_follows_line_better_than_baseline(body, line_runs):
    thetas, runs = line_runs
    k_hand = body.blob_labels.index("r_hand")
    truth = np.array([body.blob_centres(t)[k_hand] for t in thetas[:-1]])
    c = truth.mean(0)
    u = np.linalg.svd(truth - c)[2][0]  # the line's direction (best fit to the true path)

    def perpendicular_rms(d):
        return float(np.sqrt(np.mean(np.sum((d - np.outer(d @ u, u)) ** 2, axis=1))))

    skip = 10  # filter convergence
    line, lateral, mpjpe = {}, {}, {}
    for kind, (estimates, _) in runs.items():
        hand = np.array([_hand(e) for e in estimates[skip:]])
        line[kind] = perpendicular_rms(hand - c)  # distance to the best-fit line of the true path
        lateral[kind] = perpendicular_rms(hand - truth[skip:])  # error across the line
        mpjpe[kind] = np.mean(
            [
                np.linalg.norm(e.joints - body.joint_positions(t), axis=1).mean()
                for e, t in zip(estimates[skip:], thetas[skip:], strict=False)
            ]
        )
        assert all(e.status == STATUS_TRACKING for e in estimates)
    assert line["kinematic"] < line["baseline"], line
    assert lateral["kinematic"] < 0.85 * lateral["baseline"], lateral
    assert mpjpe["kinematic"] < 0.85 * mpjpe["baseline"], mpjpe
    assert mpjpe["kinematic"] < 0.02
    # the torso's shape holds the heading better than the blob means alone (checked: 10.6 vs 13.6 mm,
    # below the kinematic estimator's 11.5 mm, which has no such cue)
    assert mpjpe["baseline+axis"] < 0.9 * mpjpe["baseline"], mpjpe


def test_predict_is_ahead_for_moving_hand(body, line_runs):
    thetas, runs = line_runs
    k_hand = body.blob_labels.index("r_hand")
    estimates, predictions = runs["kinematic"]
    lead, gain = [], []
    for k in range(10, len(estimates)):
        est, pred = _hand(estimates[k]), _hand(predictions[k])
        true_now = body.blob_centres(thetas[k])[k_hand]
        true_next = body.blob_centres(thetas[k + 1])[k_hand]
        v = true_next - true_now
        if np.linalg.norm(v) * FPS < 0.15:  # only while the hand moves (> 0.15 m/s)
            continue
        lead.append((pred - est) @ v / (v @ v))  # 1 = exactly one frame ahead
        gain.append(np.linalg.norm(est - true_next) - np.linalg.norm(pred - true_next))
    assert len(lead) > 10
    assert 0.5 < np.median(lead) < 1.5
    assert np.mean(gain) > 0  # the prediction is nearer the next position than the last estimate
    # The prediction's blobs carry the (growing) prediction covariance, and the baseline's
    # zero-velocity prediction (fit.predict_velocity_gain 0) stays where it was.
    assert predictions[-1].stamp_ns == stamp(len(estimates))
    b_est, b_pred = runs["baseline"][0][-1], runs["baseline"][1][-1]
    np.testing.assert_allclose(_hand(b_pred), _hand(b_est))
    cov_e = next(b.cov for b in b_est.blobs if b.label == "r_hand")
    cov_p = next(b.cov for b in b_pred.blobs if b.label == "r_hand")
    assert np.trace(cov_p) > np.trace(cov_e)


def test_outputs_are_consistent_skeletons(body, line_runs):
    _, runs = line_runs
    kin = BodyKinematics(body)
    for estimates, predictions in runs.values():
        for e in (estimates[-1], predictions[-1]):
            p = np.array([lk.position for lk in e.links])
            R = np.array([lk.rotation for lk in e.links])
            assert np.linalg.norm(kin.solver().residual(p, R)) < 1e-9  # joints exact, bones rigid
            theta = kin.theta_from_poses(p, R)
            np.testing.assert_allclose(body.joint_positions(theta), e.joints, atol=1e-9)
            assert body.within_limits(theta, tol=1e-6)
            assert all(lk.cov.shape == (6, 6) and np.all(np.isfinite(lk.cov)) for lk in e.links)


@pytest.mark.parametrize("yaw", [0.0, 1.2, 2.6, -2.0])
def test_startup_from_foreground_and_skin_gives_right_facing(body, cameras, yaw):
    theta = body.rest_pose()
    theta[0:6] = [0.3, -0.2, 0.95, 0.0, 0.0, yaw]
    theta[body.dof_slice("r_upper_arm")] = [0.0, -0.8, 0.0]  # right hand forward
    theta[body.dof_slice("r_forearm")] = [0.9]
    est = make_estimator("kinematic", body, cameras, None)
    e = est.update(stamp(0), startup_blobs(body, cameras, theta))
    assert e.status == STATUS_TRACKING
    R_root = e.links[0].rotation
    heading = math.atan2(R_root[1, 0], R_root[0, 0])
    assert abs((heading - yaw + np.pi) % (2 * np.pi) - np.pi) < np.radians(20)
    centres = body.blob_centres(theta)
    for label in ("l_hand", "r_hand", "head"):
        assert np.linalg.norm(_hand(e, label) - centres[body.blob_labels.index(label)]) < 0.08, label
    # The next frame's labelled blobs are tracked from there.
    e = est.update(stamp(1), blobs_2d(body, cameras, theta))
    assert e.status == STATUS_TRACKING
    assert np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean() < 0.06


@pytest.mark.parametrize("yaw", [0.0, 1.2, 2.6, -2.0])
def test_startup_reads_the_heading_from_the_face_sizes(body, cameras, yaw):
    """The rotation scene's start: the right hand raised forward, the left at the side, so the line
    between the hands runs diagonally, and the face skin blob no farther forward than the head's
    centre (no offset from the body axis to read). The face's blob is ~4x larger (at 1 m) in the
    views it looks at than from behind (the face check's cue, :func:`facing_direction`): with
    ``startup.facing_from_sizes`` the start heading is within 10 deg, without it ~48 deg off (the
    diagonal hand line's), the hands fitted either way."""
    theta = body.rest_pose()
    theta[0:6] = [0.3, -0.2, 0.95, 0.0, 0.0, yaw]
    theta[body.dof_slice("r_upper_arm")] = [0.0, -1.2, 0.0]  # raised forward
    blobs = startup_blobs(body, cameras, theta, face_forward=0.0)
    means, _ = body.blob_gaussians(theta)
    face = means[body.blob_labels.index("head")]
    forward = np.array([math.cos(yaw), math.sin(yaw)])
    for cam in cameras:
        uv, _ = cam.project(face[None])
        face_blob = min((b for b in blobs[cam.name] if b.label == "skin"), key=lambda b: np.linalg.norm(b.mean - uv[0]))
        to_cam = np.asarray(cam.center) - face
        size = 400 * (1 + 0.6 * forward @ (to_cam[:2] / np.linalg.norm(to_cam[:2]))) / (to_cam @ to_cam)
        blobs[cam.name] = [dataclasses.replace(b, pixel_count=int(round(size))) if b is face_blob else b
                           for b in blobs[cam.name]]
    centres = body.blob_centres(theta)
    errors = {}
    for sizes in (True, False):
        e = make_estimator("baseline", body, cameras, {"startup": {"facing_from_sizes": sizes}}).update(stamp(0), blobs)
        assert e.status == STATUS_TRACKING
        R = e.links[0].rotation
        errors[sizes] = math.degrees(abs((math.atan2(R[1, 0], R[0, 0]) - yaw + np.pi) % (2 * np.pi) - np.pi))
        for label in ("l_hand", "r_hand"):
            assert np.linalg.norm(_hand(e, label) - centres[body.blob_labels.index(label)]) < 0.05, (sizes, label)
    assert errors[True] < 10 and errors[False] > 35, errors


def test_startup_picks_the_person_at_start_xy(body, cameras):
    """Two people in view: the other one stands 0.25 m higher (on a step), so their face is the
    highest skin point and the plain start-up (no start radius, no person grouping) takes it.
    With startup.start_xy on the first person, the start is on them, whether by start_radius_m or
    by grouping the skin points into people (person_gap_m, the default) and taking the nearest."""
    theta = body.rest_pose()
    theta[0:6] = [0.3, -0.2, 0.95, 0.0, 0.0, 0.5]
    other = body.rest_pose()
    other[0:6] = [-0.9, 0.9, 1.20, 0.0, 0.0, -2.0]
    blobs = startup_blobs(body, cameras, theta)
    for name, extra in startup_blobs(body, cameras, other).items():
        blobs[name] += [b for b in extra if b.label == "skin"]
    head = body.blob_centres(theta)[body.blob_labels.index("head")]
    dist = {}
    for radius, gap in ((0.0, 0.0), (0.7, 0.0), (0.0, 1.0)):
        cfg = {"startup": {"max_skin_blobs_per_camera": 6, "start_xy": [0.3, -0.2], "start_radius_m": radius,
                           "person_gap_m": gap}}
        e = make_estimator("baseline", body, cameras, cfg).update(stamp(0), blobs)
        assert e.status == STATUS_TRACKING
        dist[radius, gap] = float(np.linalg.norm(_hand(e, "head") - head))
    assert dist[0.0, 0.0] > 0.5, dist
    assert dist[0.7, 0.0] < 0.08, dist
    assert dist[0.0, 1.0] < 0.08, dist


def test_nearest_person_groups_skin_points_by_horizontal_gaps():
    """Single linkage at person_gap_m: a face and two hands 0.4 m apart are one person, a face and
    a hand 4 m away another; the fuller group wins over a lone point nearer start_xy, and of equal
    groups the one whose highest point is nearer start_xy."""
    from artrack.startup import nearest_person

    def pt(x, y, z):
        return (np.array([x, y, z], float), 0.0, ("cam01", "cam02"), None)

    me = [pt(2.0, 0.0, 1.6), pt(2.3, 0.3, 1.0), pt(1.7, -0.3, 1.0)]
    other = [pt(-2.0, 0.0, 1.7), pt(-2.3, 0.2, 1.1)]
    lone = [pt(0.0, 0.1, 1.5)]
    xy = np.zeros(2)

    def picks(points, at=xy):
        return [id(p) for p in nearest_person(points, at, 1.0)]

    assert picks(me + other) == [id(p) for p in me]
    assert picks(other + me + lone) == [id(p) for p in me]
    two = [pt(0.0, 3.0, 1.7), pt(0.1, 3.3, 1.1), pt(-0.1, 2.7, 1.1)]
    assert picks(two + me) == [id(p) for p in me]
    assert picks(two + me, np.array([0.0, 3.0])) == [id(p) for p in two]
    assert picks(me) == [id(p) for p in me]


@pytest.mark.parametrize("yaw", [0.0, 1.2, 2.6, -2.0])
def test_startup_holds_its_heading_and_skips_a_two_view_ghost_hand(body_shape_hands, cameras, yaw):
    """The left hand is hidden in every view; a skin-coloured ghost within arm's reach is seen by
    two of the four cameras. By default (startup.min_hand_views 3) the ghost is no hand and the
    heading is right; taken as the left hand (min_hand_views 0), the fit still keeps the heading
    within 20 deg because each candidate is held near its heading (startup.heading_sigma_rad); with
    that off too, the fit turns the body towards the ghost by 28-40 deg. (Held: 15-17 deg since the
    head's blob centre sits where the tracker triangulates it, at the neck, config/body_model.yaml;
    1-13 deg with the 'auto' centre 31 mm further forward, which told the fit more of the facing.
    In the closed loop the start-up headings of seeds 1-10 moved by 3 deg at most.) Shown without
    startup.share_taken_views, then with it (the default), where a hand's blob can make the ghost's
    third view."""
    body = body_shape_hands  # the scene's geometry: see the fixture
    theta = body.rest_pose()
    theta[0:6] = [0.3, -0.2, 0.95, 0.0, 0.0, yaw]
    theta[body.dof_slice("l_upper_arm")] = [0.0, 0.5, 0.0]  # left arm swung back
    theta[body.dof_slice("r_upper_arm")] = [0.0, -0.6, 0.0]  # right arm forward
    theta[body.dof_slice("r_forearm")] = [0.6]
    blobs = startup_blobs(body, cameras, theta)
    centres = body.blob_centres(theta)
    left = centres[body.blob_labels.index("l_hand")]
    ghost = np.array([0.3 + 0.6 * math.cos(yaw + 1.9), -0.2 + 0.6 * math.sin(yaw + 1.9), 1.2])
    for ci, cam in enumerate(cameras):
        uv, _ = cam.project(left[None])
        hidden = min((b for b in blobs[cam.name] if b.label == "skin"), key=lambda b: np.linalg.norm(b.mean - uv[0]))
        blobs[cam.name] = [b for b in blobs[cam.name] if b is not hidden]
        if ci in (0, 2):
            m, J = cam.project_jacobian(ghost[None])
            blobs[cam.name].append(Blob2D("skin", m[0], J[0] @ (np.eye(3) * 0.03**2) @ J[0].T, pixel_count=300))

    def start(**startup):
        e = make_estimator("baseline", body, cameras, {"startup": startup}).update(stamp(0), blobs)
        assert e.status == STATUS_TRACKING
        R = e.links[0].rotation
        err = abs((math.atan2(R[1, 0], R[0, 0]) - yaw + np.pi) % (2 * np.pi) - np.pi)
        return math.degrees(err), float(np.linalg.norm(_hand(e, "l_hand") - ghost)), e

    err, to_ghost, e = start(share_taken_views=False)
    assert err < 10 and to_ghost > 0.3, (err, to_ghost)
    assert np.linalg.norm(_hand(e, "r_hand") - centres[body.blob_labels.index("r_hand")]) < 0.05
    err, to_ghost, _ = start(min_hand_views=0, share_taken_views=False)
    assert to_ghost < 0.05 and err < 20, (err, to_ghost)
    err, to_ghost, _ = start(min_hand_views=0, heading_sigma_rad=0.0, share_taken_views=False)
    assert to_ghost < 0.05 and err > 25, (err, to_ghost)
    # The cost of startup.share_taken_views (on by default): at yaw 0 and 2.6 the ghost's line of
    # sight in a third view passes through the right hand's blob (at yaw 0: cam1), which then counts
    # among the ghost's views, and the ghost is taken as the left hand; the heading is still held
    # within 20 deg.
    err, to_ghost, _ = start()
    if yaw in (0.0, 2.6):
        assert to_ghost < 0.05 and err < 20, (err, to_ghost)
    else:
        assert err < 10 and to_ghost > 0.3, (err, to_ghost)


def test_an_oversized_skin_blob_sees_a_start_up_point_but_does_not_locate_it(cameras):
    """startup.max_skin_size_m (:func:`match_skin_blobs`): a hand whose blob is merged in two of four
    views with a large skin-coloured region is seen by all four but located by the two hand-sized
    blobs; and two large regions (the start position's ghost) that happen to line up with a small
    blob in a third view no longer make a three-view point: without the gate they did."""
    cams = {c.name: c for c in cameras}
    hand, ghost = np.array([0.2, 0.1, 0.85]), np.array([-0.3, 0.5, 0.7])

    def blob(cam, X, sigma_m, shift_m=(0.0, 0.0, 0.0)):
        m, J = cam.project_jacobian((X + np.asarray(shift_m))[None])
        return Blob2D("skin", m[0], J[0] @ (np.eye(3) * sigma_m**2) @ J[0].T, pixel_count=300)

    skin = {}
    for k, cam in enumerate(cameras):
        big = k in (0, 2)
        skin[cam.name] = [blob(cam, hand, 0.25 if big else 0.03, (0.1, 0.0, -0.1) if big else (0.0, 0.0, 0.0)),
                          blob(cam, ghost, 0.03 if k == 1 else 0.25)]
    def depth(cam, X):
        return float(cam.project(X[None])[1][0])

    assert blob_size_m(cams["cam1"], skin["cam1"][0], depth(cams["cam1"], hand)) == pytest.approx(
        math.sqrt(4 * math.pi) * 0.03, rel=0.05)
    assert blob_size_m(cams["cam0"], skin["cam0"][1], depth(cams["cam0"], ghost)) > 0.8

    def points(max_size_m):
        found = match_skin_blobs(skin, cams, 6, max_size_m=max_size_m)
        return [(X, set(views), set(b.cameras)) for X, _, views, b in found]

    plain = points(0.0)
    assert any(len(v) >= 3 and np.linalg.norm(X - ghost) < 0.1 for X, v, _ in plain), plain
    gated = points(0.32)
    assert not any(np.linalg.norm(X - ghost) < 0.2 for X, _, _ in gated), gated
    X, views, located = min(gated, key=lambda p: np.linalg.norm(p[0] - hand))
    assert np.linalg.norm(X - hand) < 0.01
    assert views == {"cam0", "cam1", "cam2", "cam3"} and located == {"cam1", "cam3"}


def test_a_view_where_the_hands_merge_sees_both_start_up_points(cameras):
    """startup.share_taken_views (:func:`match_skin_blobs`): the two hands merge into one blob in cam0
    and are apart in the other three views. The better hand takes the merged blob; the other hand's
    candidates all extend to that blob too, and without sharing they were all dropped, so the start-up
    saw one hand. With sharing the second hand is kept, triangulated from its own three blobs, and
    cam0 counts among its views without locating it; not when the hands are nearer each other
    horizontally than share_min_separation_m. The face's blobs are not shared."""
    cams = {c.name: c for c in cameras}
    face, left, right = np.array([0.0, 0.0, 1.6]), np.array([0.05, 0.2, 1.0]), np.array([0.05, 0.0, 0.95])

    def blob(cam, X, sigma_m, pixels=300):
        m, J = cam.project_jacobian(X[None])
        return Blob2D("skin", m[0], J[0] @ (np.eye(3) * sigma_m**2) @ J[0].T, pixel_count=pixels)

    skin = {name: [blob(cam, face, 0.06, 900)] for name, cam in cams.items()}
    for name, cam in cams.items():
        if name == "cam0":
            skin[name].append(blob(cam, 0.5 * (left + right), 0.12, 600))
        else:
            skin[name] += [blob(cam, left, 0.03), blob(cam, right, 0.03)]

    def near(found, X):
        return [(views, set(b.cameras)) for P, _, views, b in found if np.linalg.norm(P - X) < 0.01]

    dropped = match_skin_blobs(skin, cams, 6)
    assert len(near(dropped, face)) == 1
    assert len(near(dropped, left)) + len(near(dropped, right)) == 1, dropped
    shared = match_skin_blobs(skin, cams, 6, share_taken_views=True)
    assert len(near(shared, left)) == 1 and len(near(shared, right)) == 1, shared
    views = [set(v) for v, _ in near(shared, left) + near(shared, right)]
    assert views == [set(cams)] * 2
    located = sorted(len(cams_) for _, cams_ in near(shared, left) + near(shared, right))
    assert located == [3, 4]
    # The hands are 0.2 m apart horizontally: a point that close to the blob's owner is not the other hand.
    apart = match_skin_blobs(skin, cams, 6, share_taken_views=True, share_min_separation_m=0.25)
    assert len(near(apart, left)) + len(near(apart, right)) == 1, apart

    # A skin-coloured ghost 0.15 m beside the face, apart from it in cam1 and cam3 and inside the
    # face's wide blob in cam0 and cam2: the face's blobs are not shared, so it stays a two-view point.
    ghost = face + np.array([0.0, 0.15, -0.05])
    for name, cam in cams.items():
        if name in ("cam0", "cam2"):
            skin[name][0] = blob(cam, face, 0.1, 1500)
        else:
            skin[name].append(blob(cam, ghost, 0.03, 200))
    found = match_skin_blobs(skin, cams, 6, share_taken_views=True)
    assert len(near(found, face)) == 1
    assert [len(v) for v, _ in near(found, ghost)] in ([], [2]), found


def test_a_skin_speck_above_the_face_is_neither_face_nor_hand(cameras):
    """startup.min_skin_size_m (:func:`match_skin_blobs` ``min_size_m``): a few skin-coloured pixels
    0.2 m above the face that three views agree on (line scene seed 1: through the hair on the crown)
    made the highest start-up point, which the start-up takes for the face; the body then started
    facing backwards. Blobs of 0.04 m at the point are a speck: with the gate it is not a point, while
    the face (0.21 m) and two hands (0.11 m) still are."""
    cams = {c.name: c for c in cameras}
    face, speck = np.array([0.08, 0.0, 1.55]), np.array([-0.12, 0.0, 1.75])
    hands = [np.array([0.1, 0.25, 0.85]), np.array([0.1, -0.25, 0.85])]

    def blob(cam, X, sigma_m, pixels):
        m, J = cam.project_jacobian(X[None])
        return Blob2D("skin", m[0], J[0] @ (np.eye(3) * sigma_m**2) @ J[0].T, pixel_count=pixels)

    skin = {name: [blob(cam, face, 0.06, 800), *(blob(cam, h, 0.03, 150) for h in hands)]
            for name, cam in cams.items()}
    for name in ("cam0", "cam1", "cam2"):
        skin[name].append(blob(cams[name], speck, 0.012, 8))
    depth = float(cams["cam0"].project(speck[None])[1][0])
    assert blob_size_m(cams["cam0"], skin["cam0"][-1], depth) == pytest.approx(0.043, abs=0.002)

    def near(found, X):
        return [P for P, *_ in found if np.linalg.norm(P - X) < 0.02]

    plain = match_skin_blobs(skin, cams, 6)
    assert near(plain, speck) and max(P[2] for P, *_ in plain) == pytest.approx(speck[2], abs=0.02)
    gated = match_skin_blobs(skin, cams, 6, min_size_m=0.07)
    assert not near(gated, speck), gated
    assert near(gated, face) and all(near(gated, h) for h in hands), gated
    assert max(P[2] for P, *_ in gated) == pytest.approx(face[2], abs=0.02)


def test_an_oversized_view_of_a_start_up_point_takes_no_blob_from_the_face(cameras):
    """A view whose blob is too large at a point (``max_size_m``) sees that point without locating it,
    and takes nothing (:func:`match_skin_blobs`). Rotation scene seed 4: the right hand raised in front
    of the face is hidden by the head in cam2, whose skin blob there is the face and neck; at the hand's
    depth that blob is oversized, so it only saw the hand. The hand, matched first, still took the blob,
    and the face, whose own blob in cam2 it is, was dropped (the highest point shares no blob): the
    start-up took the hand for the face."""
    cams = {c.name: c for c in cameras}
    face = np.array([0.0, 0.0, 1.55])
    towards = cams["cam0"].center - face
    towards[2] = 0.0
    hand = face + 0.35 * towards / np.linalg.norm(towards) + np.array([0.0, 0.0, -0.12])

    def blob(cam, X, sigma_m, pixels, shift_px=(0.0, 0.0)):
        m, J = cam.project_jacobian(X[None])
        return Blob2D("skin", m[0] + np.asarray(shift_px), J[0] @ (np.eye(3) * sigma_m**2) @ J[0].T,
                      pixel_count=pixels)

    skin = {name: [blob(cam, face, 0.05, 600, (1.0, -1.0)), blob(cam, hand, 0.03, 150)]
            for name, cam in cams.items() if name != "cam2"}
    big = blob(cams["cam2"], face, 0.08, 900)
    skin["cam2"] = [big]
    depth = {n: float(cams["cam2"].project(X[None])[1][0]) for n, X in (("face", face), ("hand", hand))}
    sizes = {n: blob_size_m(cams["cam2"], big, d) for n, d in depth.items()}
    max_size_m = 0.5 * (sizes["face"] + sizes["hand"])  # the face's blob locates the face, not the hand
    assert sizes["face"] < max_size_m < sizes["hand"]

    found = match_skin_blobs(skin, cams, 6, max_size_m=max_size_m)
    by_point = {n: [(set(views), set(b.cameras)) for P, _, views, b in found if np.linalg.norm(P - X) < 0.03]
                for n, X in (("face", face), ("hand", hand))}
    assert by_point["hand"] == [(set(cams), {"cam0", "cam1", "cam3"})], found
    assert by_point["face"] == [(set(cams), set(cams))], found
    assert found[0][0][2] < face[2] - 0.1  # the hand was matched first


def _lone_hand_start(body, cameras):
    """The rotation scene's start (theta, true left and right hand blob centres, start-up blobs):
    the right hand raised in front of the chest, a few cm left of the body axis, the left hand
    hidden in every view."""
    theta = pose_at("rotation", 0.0, body)
    centres = body.blob_centres(theta)
    left, right = centres[body.blob_labels.index("l_hand")], centres[body.blob_labels.index("r_hand")]
    start = startup_blobs(body, cameras, theta)
    for cam in cameras:
        uv, _ = cam.project(left[None])
        hidden = min((b for b in start[cam.name] if b.label == "skin"), key=lambda b: np.linalg.norm(b.mean - uv[0]))
        start[cam.name] = [b for b in start[cam.name] if b is not hidden]
    return theta, left, right, start


@pytest.mark.parametrize("estimator", ["baseline", "kinematic"])
def test_the_verification_exchanges_a_lone_start_up_hand_put_on_the_wrong_side(body, cameras, estimator):
    """``tracking.verify_swap_groups`` (:meth:`Estimator._verify_facing`). The rotation scene's start:
    the right hand raised in front of the chest, a few cm left of the body axis, and the left hand
    hidden in every view. The start-up puts a lone hand on the side of the axis it lies on, so it
    starts as the left hand; the 2-D trackers then follow that labelling (the raised hand labelled
    'l_hand', the hanging one, once seen, 'r_hand'). With hands fitted exchanged during the
    verification the tracker switches to the right labels within a few frames; without ([]), the
    arms stay crossed, both hands 0.3 m or more off."""
    theta, left, right, start = _lone_hand_start(body, cameras)
    assert 0.0 < right[1] - theta[1] < 0.1 and right[2] > 1.2  # raised, just left of the axis
    true_blobs = blobs_2d(body, cameras, theta)
    swap = {"l_hand": "r_hand", "r_hand": "l_hand"}

    def followed(prediction):
        """The 2-D trackers' labels: each hand's blob takes the label of the predicted hand nearest it."""
        nearest = min(("l_hand", "r_hand"), key=lambda lab: np.linalg.norm(_hand(prediction, lab) - left))
        if nearest == "l_hand":
            return true_blobs
        return {name: [dataclasses.replace(b, label=swap.get(b.label, b.label)) for b in bl]
                for name, bl in true_blobs.items()}

    def run(**tracking):
        est = make_estimator(estimator, body, cameras, {"tracking": tracking})
        first = est.update(stamp(0), start)
        assert first.status == STATUS_TRACKING
        assert np.linalg.norm(_hand(first, "l_hand") - right) < 0.1  # the lone hand started as the left one
        for k in range(1, 12):
            e = est.update(stamp(k), followed(est.predict(stamp(k))))
        return np.linalg.norm(_hand(e, "l_hand") - left), np.linalg.norm(_hand(e, "r_hand") - right)

    assert min(run(verify_swap_groups=[])) > 0.3
    assert max(run()) < 0.05


@pytest.mark.parametrize("estimator", ["baseline", "kinematic"])
def test_the_hand_exchange_is_judged_on_recent_frames_too(body_shape_hands, cameras, estimator):
    """``tracking.verify_swap_recent_frames``: the start of the test above, with 2-px noise on the
    blobs, but the hanging left hand stays hidden for the first 12 frames, which fit either
    labelling about alike (cost ratios 0.6-1.2). Judged on the sums since the start alone (0),
    those frames hold the ratio up: the hands are exchanged at the fifth frame that shows the
    hanging hand; judged on the last 3 observed frames as well (the default), at the first
    (rotation scene seed 19, nine frames at 0.9-1.0: 16 frames after the start on the sums, 9 with
    the last 3)."""
    body = body_shape_hands  # the scene's geometry: see the fixture
    theta, left, right, start = _lone_hand_start(body, cameras)
    swap = {"l_hand": "r_hand", "r_hand": "l_hand"}
    hidden_frames = 12

    def followed(prediction, k, rng):
        """The 2-D trackers' labels (each hand's blob labelled as the predicted hand nearest it), the
        hanging hand's blob left out for the first ``hidden_frames`` frames."""
        nearest = min(("l_hand", "r_hand"), key=lambda lab: np.linalg.norm(_hand(prediction, lab) - left))
        out = {name: [dataclasses.replace(b, label=b.label if nearest == "l_hand" else swap.get(b.label, b.label))
                      for b in bl] for name, bl in blobs_2d(body, cameras, theta, rng, sigma_px=2.0).items()}
        if k <= hidden_frames:
            out = {name: [b for b in bl if b.label != nearest] for name, bl in out.items()}
        return out

    def frames_until_right(**tracking):
        rng = np.random.default_rng(0)
        est = make_estimator(estimator, body, cameras, {"tracking": tracking})
        assert est.update(stamp(0), start).status == STATUS_TRACKING
        for k in range(1, 26):
            e = est.update(stamp(k), followed(est.predict(stamp(k)), k, rng))
            if k > hidden_frames and max(np.linalg.norm(_hand(e, "l_hand") - left),
                                         np.linalg.norm(_hand(e, "r_hand") - right)) < 0.05:
                return k - hidden_frames
        return None

    on_sums, on_recent = frames_until_right(verify_swap_recent_frames=0), frames_until_right()
    print(f"frames from the hanging hand's first view to the exchange: {on_sums} on the sums, {on_recent} recent")
    assert on_sums >= 3 and on_recent == 1


def test_status_initializing_lost_and_recovery(body, cameras):
    cfg = {"tracking": {"lost_after_frames": 3}}
    est = make_estimator("kinematic", body, cameras, cfg)
    e = est.update(stamp(0), {c.name: [] for c in cameras})
    assert e.status == STATUS_INITIALIZING and e.blobs == [] and np.all(np.isnan(e.joints))
    assert est.predict(stamp(1)).status == STATUS_INITIALIZING
    theta = _test_pose(body)
    assert est.update(stamp(1), blobs_2d(body, cameras, theta)).status == STATUS_TRACKING
    hidden = tuple(body.blob_labels[2:])  # only two labels visible: too few
    statuses = [est.update(stamp(k), blobs_2d(body, cameras, theta, hide=hidden)).status for k in range(2, 6)]
    assert statuses == [STATUS_TRACKING, STATUS_TRACKING, STATUS_LOST, STATUS_LOST]
    assert est.predict(stamp(6)).status == STATUS_LOST
    e = est.update(stamp(6), blobs_2d(body, cameras, theta))
    assert e.status == STATUS_TRACKING
    assert np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean() < 0.03


@pytest.mark.parametrize("kind", ["baseline", "kinematic"])
def test_lost_without_relocalise_from_blobs_waits_for_a_reseed(body, cameras, kind):
    """tracking.relocalise_from_blobs false: the first start still uses the blobs, but once LOST the
    estimator stays LOST with every label in view until a re-seed restarts it."""
    est = make_estimator(kind, body, cameras, {"tracking": {"lost_after_frames": 2, "relocalise_from_blobs": False}})
    theta = _test_pose(body)
    assert est.update(stamp(0), blobs_2d(body, cameras, theta)).status == STATUS_TRACKING
    assert [est.update(stamp(k), {c.name: [] for c in cameras}).status for k in (1, 2)] == [STATUS_TRACKING,
                                                                                             STATUS_LOST]
    assert [est.update(stamp(k), blobs_2d(body, cameras, theta)).status for k in (3, 4)] == [STATUS_LOST] * 2
    assert est.reseed(stamp(4), body.joint_positions(theta))
    e = est.update(stamp(5), blobs_2d(body, cameras, theta))
    assert e.status == STATUS_TRACKING
    assert np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean() < 0.03


@pytest.mark.parametrize("kind", ["baseline", "kinematic"])
def test_reseed_from_another_estimators_joints_only_when_lost(body, cameras, kind):
    """ALGORITHMS.md §4: a body from elsewhere (the loose-limbed node) re-initialises a lost
    skeleton; while tracking it is ignored; bad joints are refused."""
    cfg = {"tracking": {"lost_after_frames": 2}}
    est = make_estimator(kind, body, cameras, cfg)
    theta = _test_pose(body)
    truth = body.joint_positions(theta)
    with pytest.raises(InputError, match="reseed joints"):
        est.reseed(stamp(0), truth[:5])
    with pytest.raises(InputError, match="reseed joints"):
        est.reseed(stamp(0), np.full_like(truth, np.nan))
    # not started: taken; the next frame's blobs are tracked from that pose
    rng = np.random.default_rng(3)
    assert est.reseed(stamp(0), truth + rng.normal(0.0, 0.01, truth.shape))
    assert est.predict(stamp(1)).status == STATUS_TRACKING
    e = est.update(stamp(1), blobs_2d(body, cameras, theta))
    assert e.status == STATUS_TRACKING
    assert np.linalg.norm(e.joints - truth, axis=1).mean() < 0.03
    # tracking: ignored
    assert not est.reseed(stamp(1), truth + 0.5)
    # lost (no blobs), then re-seeded at a new place: tracked there from the next frame
    for k in (2, 3, 4):
        e = est.update(stamp(k), {c.name: [] for c in cameras})
    assert e.status == STATUS_LOST
    moved = theta.copy()
    moved[0:2] += [0.4, -0.3]
    assert est.reseed(stamp(4), body.joint_positions(moved))
    p = est.predict(stamp(5))  # the prediction (the priors of the 2-D trackers) is already there
    assert p.status == STATUS_TRACKING
    trunk = [body.joint_names.index(n) for n in ("pelvis", "thorax", "head", "l_shoulder", "r_shoulder",
                                                   "l_hip", "r_hip")]  # the limbs: tracking.reseed_limb_sigma_m
    assert np.linalg.norm(p.joints - body.joint_positions(moved), axis=1)[trunk].mean() < 0.05
    e = est.update(stamp(5), blobs_2d(body, cameras, moved))
    assert e.status == STATUS_TRACKING
    assert np.linalg.norm(e.joints - body.joint_positions(moved), axis=1).mean() < 0.03


def test_a_reseed_holds_the_other_bodys_limbs_loosely(body, cameras):
    """tracking.reseed_limb_sigma_m: a re-seed takes the other estimator's trunk and head, but its
    elbows, wrists, knees and ankles only loosely (the loose-limbed body's arms were 0.4-0.8 m off
    in the recovery scene, and a re-seed that followed them kept the skeleton 270-330 mm off for
    10 frames after a blackout): wrists given 0.6 m off are not followed; held at the trunk's
    sigma (``limb_sigma_m``, as the benches' restart from the true joints does) they are."""
    theta = _test_pose(body)
    given = body.joint_positions(theta)
    wrists = [body.joint_names.index(n) for n in ("l_wrist", "r_wrist")]
    trunk = [body.joint_names.index(n) for n in ("pelvis", "thorax", "head", "l_hip", "r_hip")]
    given[wrists] += np.array([0.0, 0.0, 0.6])  # both hands "overhead", where they are not
    for limb_sigma, followed in ((None, False), (0.05, True)):
        est = make_estimator("baseline", body, cameras, {})
        assert est.reseed(stamp(0), given, limb_sigma_m=limb_sigma)
        joints = body.joint_positions(est.theta)
        assert np.linalg.norm(joints - given, axis=1)[trunk].max() < 0.05
        off = np.linalg.norm(joints - given, axis=1)[wrists].mean()
        assert (off < 0.15) if followed else (off > 0.4), (limb_sigma, off)


@pytest.mark.parametrize("kind", ["baseline", "kinematic"])
def test_a_frame_reseeded_for_keeps_the_reseed_over_start_up_blobs(body, cameras, kind):
    """The live loop re-seeds the skeleton for frame t before estimating t, but the 2-D trackers
    saw t without priors (the skeleton was lost), so t's blobs are start-up classes. The re-seeded
    body is t's estimate: fitting it to those blobs (a stray skin blob taken for a hand, nothing on
    the trunk) bent the recovery test's body ~0.7 m off at the head. A later frame's blobs do move it."""
    est = make_estimator(kind, body, cameras, {"tracking": {"lost_after_frames": 2, "relocalise_from_blobs": False}})
    theta = _test_pose(body)
    assert est.update(stamp(0), blobs_2d(body, cameras, theta)).status == STATUS_TRACKING
    for k in (1, 2):
        est.update(stamp(k), {c.name: [] for c in cameras})
    assert est.status == STATUS_LOST
    moved = theta.copy()
    moved[0:2] += [0.5, 0.2]
    startup = startup_blobs(body, cameras, moved)
    assert est.reseed(stamp(3), body.joint_positions(theta))  # the other estimator's body, 0.5 m off
    reseeded = body.joint_positions(est.theta)
    e = est.update(stamp(3), startup)
    assert e.status == STATUS_TRACKING
    assert np.abs(e.joints - reseeded).max() < 1e-9
    # the next frame's blobs (labelled, at the moved pose) are fitted as usual: most of the 0.54 m closed
    target = body.joint_positions(moved)
    assert np.linalg.norm(reseeded - target, axis=1).mean() > 0.5
    e = est.update(stamp(4), blobs_2d(body, cameras, moved))
    assert np.linalg.norm(e.joints - target, axis=1).mean() < 0.15


@pytest.mark.parametrize("follow_fit", [True, False])
def test_dynamic_estimator_tracks(body, cameras, follow_fit):
    """Both observation models of the full dynamics track a moving hand from noisy blobs: springs
    toward the raw tracker's fit of the frame (the default, ``dynamic.follow_fit``; its warm-up
    shortened to 3 frames, so the dynamics' own estimate is the output from then on) or toward the
    triangulated blobs themselves."""
    cfg = {"kinematic": {"warmup_frames": 3}, "dynamic": {"follow_fit": follow_fit}}
    est = make_estimator("dynamic", body, cameras, cfg)
    assert (est.raw is not None) == follow_fit
    rng = np.random.default_rng(1)
    errs, raw_differs = [], []
    for k in range(15):
        theta = pose_at("line", k / FPS, body)
        e = est.update(stamp(k), blobs_2d(body, cameras, theta, rng, 1.0))
        errs.append(np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean())
        if follow_fit:
            raw_differs.append(np.abs(e.joints - body.joint_positions(est.raw.theta)).max() > 1e-6)
        pred = est.predict(stamp(k + 1))
    assert e.status == STATUS_TRACKING and np.mean(errs[5:]) < 0.03
    assert [b.label for b in pred.blobs] == body.blob_labels
    if follow_fit:  # the raw tracker's estimate for the warm-up, then the dynamics' own
        assert not any(raw_differs[:3]) and all(raw_differs[4:])


def test_dynamic_estimator_survives_a_failed_integration_step(body, cameras, monkeypatch):
    """A sub-step whose constraint solve fails (LinAlgError) or turns non-finite is dropped:
    the pose is held with zero velocity and tracking goes on, finite (no crash, no NaN)."""
    est = make_estimator("dynamic", body, cameras, None)
    theta = pose_at("line", 0.0, body)
    est.update(stamp(0), blobs_2d(body, cameras, theta))
    real = est.solver.step_dynamic
    calls = {"n": 0}

    def flaky(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise np.linalg.LinAlgError("SVD did not converge")
        res = real(*args, **kw)
        if calls["n"] == 5:
            res.nu = np.full_like(res.nu, np.nan)
        return res

    monkeypatch.setattr(est.solver, "step_dynamic", flaky)
    for k in range(1, 6):
        theta = pose_at("line", k / FPS, body)
        est.predict(stamp(k))
        e = est.update(stamp(k), blobs_2d(body, cameras, theta))
    assert est.blowups == 2
    assert e.status == STATUS_TRACKING and np.all(np.isfinite(e.joints))
    assert np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean() < 0.05


def test_deterministic(body, cameras):
    outs = []
    for _ in range(2):
        est = make_estimator("kinematic", body, cameras, None)
        rng = np.random.default_rng(5)
        for k in range(4):
            e = est.update(stamp(k), blobs_2d(body, cameras, pose_at("line", k / FPS, body), rng, 1.0))
        outs.append((e.joints, est.predict(stamp(4)).joints))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


def test_config_file_and_errors(body, cameras):
    data = yaml.safe_load((config_dir() / "skeleton.yaml").read_text())
    assert load_skeleton_config(data) == SkeletonConfig()  # the file documents the defaults
    with pytest.raises(InputError, match="kinematic.bogus"):
        load_skeleton_config({"kinematic": {"bogus": 1}})
    with pytest.raises(InputError, match="unknown section"):
        load_skeleton_config({"kalman": {}})
    with pytest.raises(InputError, match="startup.start_xy"):
        load_skeleton_config({"startup": {"start_xy": [1.0, 2.0, 3.0]}})
    with pytest.raises(InputError, match="ground_sigma_m"):
        load_skeleton_config({"fit": {"ground_sigma_m": -0.1}})
    with pytest.raises(InputError, match="fit.tolerance"):
        load_skeleton_config({"fit": {"tolerance": 0.0}})
    with pytest.raises(InputError, match="measurement.view_outlier_chi2"):
        load_skeleton_config({"measurement": {"view_outlier_chi2": -1.0}})
    with pytest.raises(InputError, match="measurement.view_outlier_after_frames"):
        load_skeleton_config({"measurement": {"view_outlier_after_frames": -1}})
    with pytest.raises(InputError, match="tracking.verify_swap_recent_frames"):
        load_skeleton_config({"tracking": {"verify_swap_recent_frames": -1}})
    with pytest.raises(InputError, match="measurement.small_blob_fraction"):
        load_skeleton_config({"measurement": {"small_blob_fraction": -1e-4}})
    with pytest.raises(InputError, match="measurement.min_view_fraction"):
        load_skeleton_config({"measurement": {"min_view_fraction": -1e-4}})
    with pytest.raises(InputError, match="measurement.min_view_labels"):
        load_skeleton_config({"measurement": {"min_view_labels": "l_hand"}})
    with pytest.raises(InputError, match="min_view_labels' names 'tail'"):
        make_estimator("baseline", body, cameras, {"measurement": {"min_view_labels": ["tail"]}})
    with pytest.raises(InputError, match="hidden_labels' names 'tail'"):
        make_estimator("baseline", body, cameras, {"measurement": {"hidden_labels": ["tail"]}})
    with pytest.raises(InputError, match="measurement.hidden_miss_probability"):
        load_skeleton_config({"measurement": {"hidden_miss_probability": 1.0}})
    with pytest.raises(InputError, match="measurement.hidden_no_view_sigma_m"):
        load_skeleton_config({"measurement": {"hidden_no_view_sigma_m": -0.1}})
    pose2sim = yaml.safe_load((config_dir() / "pose2sim_skeleton.yaml").read_text())
    assert load_skeleton_config(pose2sim).fit.ground_sigma_m > 0  # the recording's file loads
    with pytest.raises(InputError, match="unknown estimator kind"):
        make_estimator("particle", body, cameras, None)
    with pytest.raises(InputError, match="rest_sigma_by_link"):
        make_estimator("baseline", body, cameras, {"prior": {"rest_sigma_by_link": {"tail": 1.0}}})
    with pytest.raises(InputError, match="facing_check_frames"):
        load_skeleton_config({"tracking": {"facing_check_frames": -1}})
    with pytest.raises(InputError, match="facing_min_size_ratio"):
        load_skeleton_config({"tracking": {"facing_min_size_ratio": 0.5}})
    with pytest.raises(InputError, match="facing_flip_cosine"):
        load_skeleton_config({"tracking": {"facing_flip_cosine": -2.0}})
    with pytest.raises(InputError, match="facing_label"):
        make_estimator("baseline", body, cameras, {"tracking": {"facing_label": "tail"}})
    with pytest.raises(InputError, match="tracking.facing_turn_groups' must be a list of lists"):
        load_skeleton_config({"tracking": {"facing_turn_groups": ["hand"]}})
    with pytest.raises(InputError, match="tracking.facing_turn_groups' names part 'tail'"):
        make_estimator("baseline", body, cameras, {"tracking": {"facing_turn_groups": [["hand"], ["tail"]]}})
    est = make_estimator("baseline", body, cameras, None)
    with pytest.raises(InputError, match="unknown camera 'cam9'"):
        est.update(0, {"cam9": []})


def test_a_sliver_is_left_out_where_two_views_see_the_part_whole(body, cameras):
    """``measurement.min_view_fraction``: a head or hand blob of fewer pixels than the fraction of its
    image is not triangulated where two or more other views see the part with at least that many;
    kept where fewer do, and for the labels the rule does not name."""
    est = make_estimator("baseline", body, cameras, None)
    m = est.cfg.measurement
    least = m.min_view_fraction * cameras[0].width * cameras[0].height  # 60 px at 640x480
    assert "r_hand" in m.min_view_labels and "torso" not in m.min_view_labels
    blobs = blobs_2d(body, cameras, pose_at("default", 0.0, body))
    assert all(b.pixel_count >= least for bl in blobs.values() for b in bl if b.label == "r_hand")

    def with_sliver(blobs, cam, label):
        out = {c: list(bl) for c, bl in blobs.items()}
        out[cam] = [dataclasses.replace(b, mean=b.mean + 30.0, pixel_count=int(least) - 1) if b.label == label
                    else b for b in out[cam]]
        return out

    def labels(out, cam):
        return [b.label for b in out[cam]]

    sliver = with_sliver(blobs, "cam0", "r_hand")
    kept = est._drop_small_views(sliver)
    assert "r_hand" not in labels(kept, "cam0")
    assert labels(kept, "cam0") == [lab for lab in labels(sliver, "cam0") if lab != "r_hand"]
    assert all(labels(kept, c) == labels(sliver, c) for c in ("cam1", "cam2", "cam3"))
    # seen whole in one other view only: the sliver's ray is kept
    one_other = {c: [b for b in bl if not (b.label == "r_hand" and c in ("cam2", "cam3"))] for c, bl in sliver.items()}
    assert "r_hand" in labels(est._drop_small_views(one_other), "cam0")
    # a label the rule does not name keeps its small blob
    torso = with_sliver(blobs, "cam0", "torso")
    assert "torso" in labels(est._drop_small_views(torso), "cam0")
    # off
    off = make_estimator("baseline", body, cameras, {"measurement": {"min_view_fraction": 0.0}})
    assert "r_hand" in labels(off._drop_small_views(sliver), "cam0")


def test_a_straight_arm_reaches_a_blob_that_needs_its_elbow_bent(body, cameras):
    """``BaselineEstimator._reach_for`` (a re-acquired hand's own dofs fitted to its new blob): from a
    straight arm, the elbow on its hinge limit, a plain fit cannot bend it toward a blob nearer the
    shoulder (occlusion seed 4, stop 52: the wrist held 170-300 mm off for 12 frames while the hand's
    3-D blob was right); started again with the elbow half bent, it reaches the blob."""
    est = make_estimator("baseline", body, cameras, None)
    names = list(body.dof_names)
    arm = [i for i, n in enumerate(names) if n.startswith(("r_upper_arm.", "r_forearm.", "r_hand."))]
    rest = pose_at("default", 0.0, body).copy()
    rest[arm] = 0.0  # the arm hanging straight
    bent = rest.copy()
    bent[[names.index("r_upper_arm.rz"), names.index("r_forearm.hinge")]] = np.radians(90.0)  # turned, bent
    b = list(body.blob_labels).index("r_hand")
    target = body.blob_centres(bent)[b]
    obs = {"r_hand": Blob3D("r_hand", target, np.eye(3) * 0.02**2, ("cam0", "cam1"))}
    f = est.cfg.fit
    plain, _, _ = fit_pose(body, rest, est._blob_targets(obs), est.kin.rest, est.rest_sigma_dof, rest,
                           f.previous_sigma_rad, f.max_nfev, 0.0, tolerance=f.tolerance,
                           free_dofs=est._own_dofs(["r_hand"], obs))
    assert np.linalg.norm(body.blob_centres(plain)[b] - target) > 0.3  # stuck straight
    reached = est._reach_for(["r_hand"], obs, rest)
    assert np.linalg.norm(body.blob_centres(reached)[b] - target) < 0.01
    assert reached[names.index("r_forearm.hinge")] > np.radians(45.0)
    assert np.array_equal(reached[:6], rest[:6])  # its own dofs only

def test_a_sliver_is_kept_where_the_whole_views_face_each_other(body, cameras):
    """``measurement.min_view_ray_angle_deg``: the views that see a part whole must fix its depth
    (two of their rays at least that far from parallel and anti-parallel) before its sliver elsewhere
    is left out. cam1 and cam3 face each other across the person; cam1 and cam2 see it at 90°."""
    strict = make_estimator("baseline", body, cameras, {"measurement": {"min_view_ray_angle_deg": 45.0}})
    any_two = make_estimator("baseline", body, cameras, {"measurement": {"min_view_ray_angle_deg": 0.0}})
    least = strict.cfg.measurement.min_view_fraction * cameras[0].width * cameras[0].height
    blobs = blobs_2d(body, cameras, pose_at("default", 0.0, body))
    blobs["cam0"] = [dataclasses.replace(b, pixel_count=int(least) - 1) if b.label == "r_hand" else b
                     for b in blobs["cam0"]]

    def without_r_hand(cam):
        return {c: [b for b in bl if not (b.label == "r_hand" and c == cam)] for c, bl in blobs.items()}

    def sliver_kept(est, blobs):
        return "r_hand" in [b.label for b in est._drop_small_views(blobs)["cam0"]]

    facing = without_r_hand("cam2")  # seen whole by cam1 and cam3 only
    across = without_r_hand("cam3")  # by cam1 and cam2
    assert sliver_kept(strict, facing) and not sliver_kept(any_two, facing)
    assert not sliver_kept(strict, across) and not sliver_kept(any_two, across)
    with pytest.raises(InputError, match="min_view_ray_angle_deg"):
        load_skeleton_config({"measurement": {"min_view_ray_angle_deg": 95.0}})


def test_baseline_fit_is_robust_to_one_mislabelled_blob(body, cameras):
    """A blob labelled on the wrong part (here: the torso blob 0.35 m off, e.g. claimed by a
    ghost) must not drag the whole body: the Cauchy loss of fit.robust_scale keeps the other
    parts in place, plain least squares (robust_scale 0) does not."""
    theta = _test_pose(body)
    means, covs = body.blob_gaussians(theta)
    wrong = means.copy()
    k = body.blob_labels.index("torso")
    wrong[k] += np.array([0.0, 0.35, 0.0])
    blobs = {}
    for cam in cameras:
        uv, J = cam.project_jacobian(wrong)
        blobs[cam.name] = [Blob2D(lab, uv[i], J[i] @ covs[i] @ J[i].T, pixel_count=200)
                           for i, lab in enumerate(body.blob_labels)]
    errs = {}
    for scale in (0.0, 3.0):
        est = make_estimator("baseline", body, cameras, {"fit": {"robust_scale": scale}})
        est.update(stamp(0), blobs_2d(body, cameras, theta))  # initialised on the true blobs
        e = est.update(stamp(1), blobs)
        errs[scale] = float(np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean())
    # (18 mm on the true blobs; the torso blob carries most of the torso's information)
    assert errs[3.0] < 0.05, errs
    assert errs[0.0] > 1.3 * errs[3.0], errs


def test_torso_shape_turns_the_heading_when_the_blob_means_cannot(body, cameras):
    """fit.axis_*: the person turns by 0.6 rad while only torso and head are seen (their centres
    lie nearly on the vertical axis, so their means barely tell the heading); the torso blob's 3-D
    extent (triangulation.blob_extent) gives its shoulder line and the baseline's torso follows the
    turn. Without the cue (axis_sigma_rad 0) the torso's heading stays 30 deg behind."""
    theta = _test_pose(body)
    turned = theta.copy()
    turned[5] += 0.6  # root rotation vector (0, 0, yaw): the yaw grows
    hide = ("pelvis", "l_hand", "r_hand", "l_thigh", "l_shin", "r_thigh", "r_shin")
    torso = body.link_index("torso")
    yaw_err = {}
    for sigma in (0.0, 0.35):
        est = make_estimator("baseline", body, cameras, {"fit": {"axis_sigma_rad": sigma},
                                                         "tracking": {"min_blobs": 2, "verify_frames": 0}})
        est.update(stamp(0), blobs_2d(body, cameras, theta))  # initialised on all blobs
        errs = []
        for k in range(1, 9):
            e = est.update(stamp(k), blobs_2d(body, cameras, turned, hide=hide))
            assert e.status == STATUS_TRACKING
            R = body.forward_kinematics(est.theta)[torso, :3, :3] @ body.forward_kinematics(turned)[torso, :3, :3].T
            errs.append(abs(math.atan2(R[1, 0], R[0, 0])))
        yaw_err[sigma] = max(errs)
    assert yaw_err[0.35] < 0.05 and yaw_err[0.0] > 0.4, yaw_err


def test_swapped_leg_labels_are_fitted_the_right_way_round(body_shape_hands, cameras):
    """fit.mirror_groups: a frame whose leg blobs carry each other's labels in every view (the
    two trouser legs passing each other) is fitted with the l_ and r_ blobs of thighs and shins
    exchanged too, and the lower-cost fit wins: the legs stay where they are; without the test
    (mirror_groups []) the fit bends them across (checked: knees and ankles 8.6 vs 368 mm off).
    Labels the right way round: the test changes nothing. With fit.mirror_prescreen_ratio 0 no
    exchanged start passes the pre-screen, and the fit is the one without the test. (fit.overlap_parts
    off: the body model's blob Gaussians, 1.5x the tracker's blobs, overlap in most views here.)"""
    body = body_shape_hands  # the scene's geometry: see the fixture
    theta = _test_pose(body)
    swap = {"l_thigh": "r_thigh", "r_thigh": "l_thigh", "l_shin": "r_shin", "r_shin": "l_shin"}
    swapped = {c: [Blob2D(swap.get(b.label, b.label), b.mean, b.cov, pixel_count=b.pixel_count) for b in bl]
               for c, bl in blobs_2d(body, cameras, theta).items()}
    legs = [body.joint_names.index(j) for j in ("l_knee", "r_knee", "l_ankle", "r_ankle")]
    err, right = {}, {}
    configs = {0: {"mirror_groups": []}, 1: {"mirror_groups": [["thigh", "shin"]]},
               "no screen": {"mirror_prescreen_ratio": 0.0}}
    for key, fit in configs.items():
        for labels in ("right", "swapped"):
            est = make_estimator("baseline", body, cameras, {"fit": {**fit, "overlap_parts": []}})
            est.update(stamp(0), blobs_2d(body, cameras, theta))  # initialised on the true blobs
            e = est.update(stamp(1), swapped if labels == "swapped" else blobs_2d(body, cameras, theta))
            if labels == "swapped":
                err[key] = float(np.linalg.norm(e.joints[legs] - body.joint_positions(theta)[legs], axis=1).mean())
            else:
                right[key] = e.joints
    np.testing.assert_array_equal(right[1], right[0])
    assert err[1] < 0.03, err
    assert err[0] > 3 * err[1], err
    assert err["no screen"] == err[0], err
    # The shins alone exchanged (the thighs labelled right: the trouser legs cross below the knees),
    # thighs 0.5 rad apart: the whole-leg group cannot put them back, the default's [shin] group
    # does. Its screen moves the knees alone, so it recovers only a crossing that the labelled fit's
    # hips still explain; this sudden one-frame crossing it recovers here, but not in the four other
    # poses tried (this test pose's thighs 0.6 rad apart; thighs 0-0.3 rad apart with the feet
    # 0.19-0.38 m apart): there the screen stays above fit.mirror_screen_ratio and the shins stay
    # crossed. A screen that also moved the hips recovered those, but in the loop it let wrong
    # exchanges win (default seed 25 29.2 -> 69.8 mm, docs/HISTORY.md stop 50).
    crossing = theta.copy()
    for name, value in {"l_thigh": [0.0, -0.3, 0.0], "r_thigh": [0.0, 0.2, 0.0]}.items():
        crossing[body.link(name).dof_slice] = value
    crossing = body.clip(crossing)
    shin_swap = {k: v for k, v in swap.items() if "shin" in k}
    shins = {c: [dataclasses.replace(b, label=shin_swap.get(b.label, b.label)) for b in bl]
             for c, bl in blobs_2d(body, cameras, crossing).items()}
    err_shins = {}
    for key, groups in (("legs", [["thigh", "shin"]]), ("default", None)):
        fit = {"overlap_parts": []} if groups is None else {"overlap_parts": [], "mirror_groups": groups}
        est = make_estimator("baseline", body, cameras, {"fit": fit})
        est.update(stamp(0), blobs_2d(body, cameras, crossing))
        e = est.update(stamp(1), shins)
        err_shins[key] = float(np.linalg.norm(e.joints[legs] - body.joint_positions(crossing)[legs], axis=1).mean())
    assert err_shins["default"] < 0.03, err_shins
    assert err_shins["legs"] > 3 * err_shins["default"], err_shins
    with pytest.raises(InputError, match="mirror_groups"):
        make_estimator("baseline", body, cameras, {"fit": {"mirror_groups": [["tail"]]}})
    with pytest.raises(InputError, match="mirror_groups"):
        make_estimator("baseline", body, cameras, {"fit": {"mirror_groups": ["thigh"]}})
    with pytest.raises(InputError, match="mirror_prescreen_ratio"):
        make_estimator("baseline", body, cameras, {"fit": {"mirror_prescreen_ratio": -1.0}})
    with pytest.raises(InputError, match="max_nfev"):
        make_estimator("baseline", body, cameras, {"fit": {"max_nfev": 0}})
    with pytest.raises(InputError, match="mirror_screen_abandon_ratio"):
        make_estimator("baseline", body, cameras, {"fit": {"mirror_screen_abandon_ratio": 1.0}})
    with pytest.raises(InputError, match="mirror_screen_abandon_after"):
        make_estimator("baseline", body, cameras, {"fit": {"mirror_screen_abandon_after": -1}})
    with pytest.raises(InputError, match="fit.overlap_parts"):
        make_estimator("baseline", body, cameras, {"fit": {"overlap_parts": ["tail"]}})
    with pytest.raises(InputError, match="fit.overlap_parts"):
        make_estimator("baseline", body, cameras, {"fit": {"overlap_parts": "shin"}})
    with pytest.raises(InputError, match="fit.overlap_chi2"):
        make_estimator("baseline", body, cameras, {"fit": {"overlap_chi2": -1.0}})


def test_a_leg_exchange_is_screened_by_the_knees_when_the_feet_carry_blobs(cameras):
    """fit.mirror_groups with a body whose feet carry blobs (config/pose2sim_body_model.yaml): the
    knees also move the foot blobs, which the exchange leaves labelled as they are, so before stop
    53 the [shin] hypothesis had no dofs of its own and went to the full fit every frame without a
    screen (on the make-demo recording 184 of the 321 body fits per 100 frames, none of them winning). The
    screen now moves the knees (the feet below them in its cost): shins exchanged in every view are
    still put back, and the pre-screen gates the hypothesis (with fit.mirror_prescreen_ratio 0 the
    fit is the one without the exchange, as for the default body)."""
    feet = load_body_model(config_dir() / "pose2sim_body_model.yaml")
    assert {"l_foot", "r_foot"} <= set(feet.blob_labels)
    theta = _test_pose(feet)
    for name, value in {"l_thigh": [0.0, -0.3, 0.0], "r_thigh": [0.0, 0.2, 0.0]}.items():
        theta[feet.dof_slice(name)] = value
    theta = feet.clip(theta)
    shin_swap = {"l_shin": "r_shin", "r_shin": "l_shin"}
    shins = {c: [dataclasses.replace(b, label=shin_swap.get(b.label, b.label)) for b in bl]
             for c, bl in blobs_2d(feet, cameras, theta).items()}
    legs = [feet.joint_names.index(j) for j in ("l_knee", "r_knee", "l_ankle", "r_ankle")]
    err, estimators = {}, {}
    for key, fit in (("default", {}), ("off", {"mirror_groups": []}), ("no screen", {"mirror_prescreen_ratio": 0.0})):
        est = estimators[key] = make_estimator("baseline", feet, cameras, {"fit": {**fit, "overlap_parts": []}})
        est.update(stamp(0), blobs_2d(feet, cameras, theta))
        e = est.update(stamp(1), shins)
        err[key] = float(np.linalg.norm(e.joints[legs] - feet.joint_positions(theta)[legs], axis=1).mean())
    obs = {label: Blob3D(label, np.zeros(3), np.eye(3)) for label in feet.blob_labels}
    screens = [sorted(feet.dof_names[d] for d in free) for _, free, _ in estimators["default"]._mirror_hypotheses(obs)]
    assert screens[1] == ["l_shin.hinge", "r_shin.hinge"], screens
    assert screens[0] and all(n.split(".")[0] in ("l_thigh", "r_thigh", "l_shin", "r_shin")
                              for n in screens[0]), screens
    assert err["default"] < 0.03, err
    assert err["off"] > 3 * err["default"], err
    assert err["no screen"] == err["off"], err


def test_overlapping_leg_blobs_are_left_out_of_that_view(body, cameras):
    """fit.overlap_parts: a view whose two shin blobs sit on each other (the legs passing)
    gives neither shin to the triangulation; the other views still place both shins (3 cm). Off
    with overlap_parts: []. (Legs spread: the body model's blob Gaussians overlap in most views at
    rest, and the side views see the thighs one behind the other.)"""
    theta = body.rest_pose()
    theta[body.dof_slice("l_thigh").start] = 0.3
    theta[body.dof_slice("r_thigh").start] = -0.3
    blobs = blobs_2d(body, cameras, theta)
    first = cameras[0].name
    left = next(b for b in blobs[first] if b.label == "l_shin")
    blobs[first] = [Blob2D(b.label, left.mean + [1.0, 0.0], b.cov, pixel_count=b.pixel_count)
                    if b.label == "r_shin" else b for b in blobs[first]]
    for parts, dropped in ((["shin"], {first: ["shin"]}), ([], {})):
        est = make_estimator("baseline", body, cameras, {"fit": {"overlap_parts": parts}})
        est.update(stamp(0), blobs)
        assert est.overlap_drops == dropped
        obs = est._triangulate(blobs, None)
        assert (first in obs["r_shin"].cameras) == (not dropped)
    true = dict(zip(body.blob_labels, body.blob_gaussians(theta)[0], strict=True))
    est = make_estimator("baseline", body, cameras, {"fit": {"overlap_parts": ["shin"]}})
    obs = est._triangulate(blobs, None)
    for lab in ("l_shin", "r_shin"):
        assert np.linalg.norm(obs[lab].mean - true[lab]) < 0.03


def test_ground_contact_keeps_a_foot_on_the_floor(body):
    """fit.ground_sigma_m: with the shin blobs pulled 0.3 m up (mislabelled onto the shorts), the
    plain fit lifts both feet off the floor; with the floor contact the lower ankle stays at its
    rest height above z = 0 and none goes below it."""
    ground = GroundContact.from_body(body, sigma=0.005)
    assert [body.joint_names[i] for i in range(len(body.joint_names))
            if body.joint_links[i] in ground.links] == ["l_ankle", "r_ankle"]
    rest = body.rest_pose()
    assert np.allclose(ground.residuals(body.forward_kinematics(rest)), 0.0)
    assert np.allclose(ground.height, body.joint_positions(rest)[[11, 14], 2])
    means, _ = body.blob_gaussians(rest)
    targets = []
    for k, lab in enumerate(body.blob_labels):
        y = means[k] + (np.array([0.0, 0.0, 0.3]) if lab.endswith("shin") else 0.0)
        link = body.link_names.index(lab)
        local = np.linalg.inv(body.forward_kinematics(rest)[link]) @ np.append(means[k], 1.0)
        targets.append(PointTarget(link, local[:3], y, np.eye(3) / 0.03**2))
    ankles = [body.joint_names.index(n) for n in ("l_ankle", "r_ankle")]
    lowest = {}
    for name, g in (("plain", None), ("ground", ground)):
        theta, _, _ = fit_pose(body, rest, targets, rest, 1.0, max_nfev=100, ground=g)
        lowest[name] = body.joint_positions(theta)[ankles, 2].min() - ground.height.min()
    assert lowest["plain"] > 0.06, lowest
    assert -0.01 < lowest["ground"] < 0.02, lowest


def test_upright_head_keeps_the_head_over_the_neck(body):
    """fit.upright_head_sigma_m: the face blob lies 6 cm from the neck pivot, so with the trunk pulled
    back (the torso blob mislabelled 8 cm behind, as with both arms overhead) the plain fit reaches the
    true face blob by pitching the head forward and puts the head joint far off; held upright, the
    head stays over the neck and its blob pulls the trunk back towards the truth."""
    rest = body.rest_pose()
    T = body.forward_kinematics(rest)
    means, _ = body.blob_gaussians(rest)
    targets = []
    for k, lab in enumerate(body.blob_labels):
        y = means[k] + (np.array([-0.08, 0.0, 0.0]) if lab == "torso" else 0.0)
        link = body.link_names.index(lab)
        local = (np.linalg.inv(T[link]) @ np.append(means[k], 1.0))[:3]
        targets.append(PointTarget(link, local, y, np.eye(3) / 0.02**2))
    head, thorax = body.joint_names.index("head"), body.joint_names.index("thorax")
    upright = UprightSegment.link_axis(body, 0.03, "head", "head")
    assert np.allclose(upright.residuals(T), 0.0)
    err = {}
    for name, term in (("plain", None), ("upright", upright)):
        theta, _, _ = fit_pose(body, rest, targets, rest, 1.0, max_nfev=100, ground=term)
        j = body.joint_positions(theta)
        err[name] = [float(np.linalg.norm(j[i] - body.joint_positions(rest)[i])) for i in (head, thorax)]
    assert err["upright"][0] < 0.5 * err["plain"][0], err
    assert err["upright"][1] < err["plain"][1], err


def test_upright_link_axis_names_what_the_body_lacks(body):
    """UprightSegment.link_axis refuses, in one line naming it, a link or joint the body model has
    not and a joint that is not on the link (the estimator checks for 'head' first; other callers
    rely on these errors)."""
    with pytest.raises(InputError, match="needs link 'crest'"):
        UprightSegment.link_axis(body, 0.03, "crest", "head")
    with pytest.raises(InputError, match="joint 'crown'"):
        UprightSegment.link_axis(body, 0.03, "head", "crown")
    with pytest.raises(InputError, match="joint 'l_wrist' is not on link 'head'"):
        UprightSegment.link_axis(body, 0.03, "head", "l_wrist")


def _noisy_blob_targets(body, rng, pose_sd: float, noise_sd: float):
    """A random pose about the rest pose (pelvis at 0.95 m) and its blob centres as PointTargets,
    each moved by N(0, noise_sd²) per axis, information 1 / (2 cm)²."""
    truth = body.clip(body.rest_pose() + rng.normal(0.0, pose_sd, body.n_dof))
    truth[2] = 0.95
    means, _ = body.blob_gaussians(truth)
    T = body.forward_kinematics(truth)
    targets = [PointTarget(int(link), (np.linalg.inv(T[link]) @ np.append(means[k], 1.0))[:3],
                           means[k] + rng.normal(0.0, noise_sd, 3), np.eye(3) / 0.02**2)
               for k, link in enumerate(body.blob_links)]
    return truth, targets


def test_analytic_and_numeric_jacobians_give_the_same_fit(body):
    """fit_pose(jacobian='analytic') (default) and 'numeric' (forward differences) reach the same pose
    and cost with every residual kind on: blob targets with a Cauchy loss, link goals (edge statistics,
    whose log map is linearised to first order), the floor contact and both regularisers."""
    rng = np.random.default_rng(1)
    truth, targets = _noisy_blob_targets(body, rng, 0.3, 0.01)
    T = body.forward_kinematics(truth)
    goal_links = np.array([body.link_names.index(n) for n in ("l_forearm", "l_hand", "r_forearm", "r_hand")])
    reference = np.array([T[i] @ exp_se3(rng.normal(0.0, 0.03, 6)) for i in goal_links])
    goals = LinkGoals(goal_links, inverse_se3(reference), rng.normal(0.0, 0.02, (4, 6)),
                      np.tile(5.0 * np.eye(6), (4, 1, 1)))
    start = body.clip(truth + rng.normal(0.0, 0.1, body.n_dof))
    kw = dict(rest=body.rest_pose(), rest_sigma=0.5, previous=start, previous_sigma=0.3, robust_scale=3.0,
              link_goals=goals, ground=GroundContact.from_body(body, 0.01), max_nfev=200)
    fits = {j: fit_pose(body, start, targets, jacobian=j, **kw) for j in ("analytic", "numeric")}
    np.testing.assert_allclose(fits["analytic"][0], fits["numeric"][0], atol=1e-4)
    assert abs(fits["analytic"][1] - fits["numeric"][1]) < 1e-6 * fits["numeric"][1]
    assert np.linalg.norm(fits["analytic"][0] - start) > 0.05  # the fit did move
    with pytest.raises(ValueError, match="jacobian"):
        fit_pose(body, start, targets, jacobian="exact")


def test_whitener_of_a_stack_equals_one_per_matrix_bit_for_bit():
    """fit_pose whitens its targets in one batched eigh; each U must be the single matrix's, and
    C-contiguous (a strided U changes einsum's summation order, and so the fits' last bits)."""
    from artrack.body_fit import _whitener

    rng = np.random.default_rng(4)
    X = rng.normal(size=(40, 3, 3))
    info = X @ np.swapaxes(X, 1, 2)
    info[3] = np.diag([4.0, 0.0, -1e-9])  # a singular one: the eigenvalues floored
    U = _whitener(info)
    assert U.flags.c_contiguous
    for k in range(len(info)):
        w, V = np.linalg.eigh(0.5 * (info[k] + info[k].T))
        assert np.array_equal(U[k], (V * np.sqrt(np.maximum(w, 1e-12))).T)
    np.testing.assert_allclose(np.swapaxes(U, 1, 2) @ U, info, atol=1e-6)


def test_fit_pose_over_some_dofs_holds_the_others(body):
    """fit_pose(free_dofs=...): the held dofs stay at the start exactly; when the truth differs from
    the start only in the free dofs (the legs' hips and knees), the conditional fit reaches it; with
    the root held 0.1 m off, its cost stays far above the full fit's (which puts the root back)."""
    rng = np.random.default_rng(4)
    start = body.clip(body.rest_pose() + rng.normal(0.0, 0.2, body.n_dof))
    start[2] = 0.95
    legs = [body.link_names.index(n) for n in ("l_thigh", "l_shin", "r_thigh", "r_shin")]
    others = [0] + [int(i) for i in body.blob_links if i not in legs]  # the root and the other blobs' links
    free = np.flatnonzero(body.dof_moves_link[legs].any(0) & ~body.dof_moves_link[others].any(0))
    assert 0 < free.size < body.n_dof - 6
    truth = start.copy()
    truth[free] = body.clip(start + rng.normal(0.0, 0.3, body.n_dof))[free]
    means, _ = body.blob_gaussians(truth)
    T = body.forward_kinematics(truth)
    targets = [PointTarget(int(link), (np.linalg.inv(T[link]) @ np.append(means[k], 1.0))[:3], means[k],
                           np.eye(3) / 0.02**2) for k, link in enumerate(body.blob_links)]
    kw = dict(max_nfev=200, tolerance=1e-10)
    theta_c, cost_c, cov_c = fit_pose(body, start, targets, free_dofs=free, **kw)
    held = np.setdiff1d(np.arange(body.n_dof), free)
    np.testing.assert_array_equal(theta_c[held], start[held])
    assert np.all(cov_c[held] == 0) and np.all(cov_c[:, held] == 0)
    np.testing.assert_allclose(body.joint_positions(theta_c), body.joint_positions(truth), atol=1e-4)
    assert cost_c < 1e-8
    moved = truth.copy()
    moved[0] += 0.1  # the root held 0.1 m off: only the full fit can put it back
    _, cost_held, _ = fit_pose(body, moved, targets, free_dofs=free, **kw)
    _, cost_full, _ = fit_pose(body, moved, targets, **kw)
    assert cost_full < 1e-3 and cost_held > 1.0, (cost_full, cost_held)


def test_fit_pose_evaluate_only_gives_the_cost_at_the_start(body):
    """fit_pose(evaluate_only=True) (the leg screen's pre-screen) returns the start, unmoved, and the
    cost scipy reports there, robust loss and regularisers included: equal to a fit stopped after its
    first evaluation, and above the converged fit's cost."""
    rng = np.random.default_rng(5)
    truth, targets = _noisy_blob_targets(body, rng, 0.2, 0.02)
    start = body.clip(truth + rng.normal(0.0, 0.1, body.n_dof))
    for scale in (3.0, 0.0):
        kw = dict(rest=body.rest_pose(), rest_sigma=0.5, previous=start, previous_sigma=0.3, robust_scale=scale)
        theta_e, cost_e, cov_e = fit_pose(body, start, targets, evaluate_only=True, **kw)
        np.testing.assert_allclose(theta_e, start, atol=1e-6)
        assert not cov_e.any()
        _, cost_1, _ = fit_pose(body, start, targets, max_nfev=1, **kw)
        _, cost_fit, _ = fit_pose(body, start, targets, max_nfev=100, **kw)
        assert cost_e == pytest.approx(cost_1, rel=1e-12), scale
        assert cost_fit < 0.5 * cost_e, (scale, cost_fit, cost_e)


def test_fit_pose_abandons_a_fit_still_above_the_cost_given(body):
    """fit_pose(abandon=(k, c)) (the leg screen's early exit) stops after iteration k when the cost
    is still above c, returning that iteration's pose and cost (below the start's, above the
    converged fit's); a fit below c by then runs on to the same result as without it."""
    rng = np.random.default_rng(6)
    truth, targets = _noisy_blob_targets(body, rng, 0.2, 0.02)
    start = body.clip(truth + rng.normal(0.0, 0.15, body.n_dof))
    kw = dict(rest=body.rest_pose(), rest_sigma=0.5, previous=start, previous_sigma=0.3, robust_scale=3.0,
              max_nfev=100)
    _, cost_start, _ = fit_pose(body, start, targets, evaluate_only=True, **kw)
    theta_full, cost_full, _ = fit_pose(body, start, targets, **kw)
    theta_a, cost_a, _ = fit_pose(body, start, targets, abandon=(2, 0.0), **kw)
    assert cost_full < cost_a < cost_start, (cost_full, cost_a, cost_start)
    assert not np.allclose(theta_a, theta_full)
    theta_n, cost_n, _ = fit_pose(body, start, targets, abandon=(2, 10 * cost_start), **kw)
    np.testing.assert_array_equal(theta_n, theta_full)
    assert cost_n == cost_full


def test_exchange_sides_mirrors_the_legs_across_the_sagittal_plane(body):
    """The leg test's screen starts from the labelled legs exchanged and mirrored: with the pelvis
    upright at the origin, the left knee and ankle land where the right ones were with y negated
    (and back); exchanging twice is the identity; the other joints do not move."""
    rng = np.random.default_rng(2)
    theta = body.rest_pose()
    theta[:6] = 0.0
    for name in ("l_thigh", "r_thigh", "l_shin", "r_shin"):
        lk = body.link(name)
        other = body.link("r_" + name[2:] if name.startswith("l_") else "l_" + name[2:])
        sign = np.array([-1.0, 1.0, -1.0]) if lk.joint == "ball" else np.ones(1)  # the mirror of each dof
        lo = np.maximum(lk.lower, np.where(sign > 0, other.lower, -other.upper))  # within both sides' limits
        hi = np.minimum(lk.upper, np.where(sign > 0, other.upper, -other.lower))
        theta[lk.dof_slice] = rng.uniform(lo, hi)
    out = exchange_sides(body, theta, {"l_thigh", "r_thigh", "l_shin", "r_shin"})
    J = {n: i for i, n in enumerate(body.joint_names)}
    before, after = body.joint_positions(theta), body.joint_positions(out)
    flip = np.array([1.0, -1.0, 1.0])
    for a, b in (("l_knee", "r_knee"), ("l_ankle", "r_ankle")):
        np.testing.assert_allclose(after[J[a]], flip * before[J[b]], atol=1e-9)
        np.testing.assert_allclose(after[J[b]], flip * before[J[a]], atol=1e-9)
    others = [J[n] for n in J if n not in ("l_knee", "r_knee", "l_ankle", "r_ankle")]
    np.testing.assert_allclose(after[others], before[others], atol=1e-12)
    np.testing.assert_allclose(exchange_sides(body, out, {"l_thigh", "r_thigh", "l_shin", "r_shin"}), theta,
                               atol=1e-12)


def test_kinematic_keeps_fast_limbs_when_the_wave_starts(body, cameras):
    """ALGORITHMS.md §1 (Kalman filters as goals): from exact blobs (1 px noise) the kinematic
    tracker must follow the default motion where the walk stops and both hands start waving
    (t = 4.5 .. 6.5 s). With too little process noise the hand filters fell behind, the
    innovation gate rejected every later measurement and the hands coasted away for good
    (mean error 131 mm, hands > 1 m off); the baseline stays under 20 mm here."""
    rng = np.random.default_rng(3)
    est = make_estimator("kinematic", body, cameras, None)
    t0, errs = 4.5, []
    for k in range(60):
        theta = pose_at("default", t0 + k / FPS, body)
        e = est.update(stamp(k), blobs_2d(body, cameras, theta, rng, 1.0))
        errs.append(np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean())
        est.predict(stamp(k + 1))
    assert e.status == STATUS_TRACKING
    assert np.mean(errs) < 0.03 and max(errs) < 0.06, np.round(errs, 3)


def test_kinematic_is_robust_to_one_consistently_mislabelled_blob(body, cameras):
    """ALGORITHMS.md §1 (measurement step of the Kalman + constraints tracker): while the
    person walks, the left-thigh blob is labelled on the right shin for 20 frames (a
    mislabelled leg, as on rendered scenes). Each filter alone judges its blob only against
    its own prediction, so the thigh filter follows the consistent outlier and tears the hips
    round (mean error 141 mm); classified against one robust body fit of the frame
    (kinematic.outlier_fit_scale) before the filters' update, the outlier barely pulls and the
    body stays near the truth (23 mm; the baseline's Cauchy fit: 51 mm)."""
    rng = np.random.default_rng(5)
    thetas = [pose_at("default", 1.0 + k / FPS, body) for k in range(25)]
    frames = []
    for k, theta in enumerate(thetas):
        means, covs = body.blob_gaussians(theta)
        if k >= 5:  # the first frames are right: initialised and settled on the true blobs
            means = means.copy()
            means[body.blob_labels.index("l_thigh")] = means[body.blob_labels.index("r_shin")]
        blobs = {}
        for cam in cameras:
            uv, J = cam.project_jacobian(means)
            blobs[cam.name] = [
                Blob2D(lab, uv[i] + rng.normal(scale=1.0, size=2), J[i] @ covs[i] @ J[i].T, pixel_count=200)
                for i, lab in enumerate(body.blob_labels)
            ]
        frames.append(blobs)
    errs = {}
    for scale, manoeuvre in ((0.0, 1.0), (3.0, 1.0), (3.0, 10.0)):
        # the filters from the first frame (no warm-up on the raw tracker's estimate): they are tested here;
        # the adaptive process noise must not take the outlier for a manoeuvre (the fit does not explain it)
        config = {"kinematic": {"outlier_fit_scale": scale, "warmup_frames": 0, "maneuver_max_scale": manoeuvre}}
        est = make_estimator("kinematic", body, cameras, config)
        e_k = []
        for k, (theta, blobs) in enumerate(zip(thetas, frames, strict=True)):
            e = est.update(stamp(k), blobs)
            est.predict(stamp(k + 1))
            e_k.append(float(np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean()))
        assert e.status == STATUS_TRACKING
        errs[scale, manoeuvre] = (float(np.mean(e_k[5:])), max(e_k[5:]))
    for key in ((3.0, 1.0), (3.0, 10.0)):
        assert errs[key][0] < 0.035 and errs[key][1] < 0.05, errs
    assert errs[0.0, 1.0][0] > 3.0 * errs[3.0, 1.0][0], errs


def test_kinematic_filters_warm_up_on_the_raw_trackers_estimate(body, cameras):
    """kinematic.fit_source baseline: the raw tracker runs beside the filters on the same blobs;
    for the first warmup_frames updates after initialisation its estimate and prediction are the
    output, then the filters' own (a consistent skeleton, close to the truth, not the raw fit)."""
    warmup = 5
    est = make_estimator("kinematic", body, cameras, {"kinematic": {"warmup_frames": warmup}})
    assert est.raw is not None and est.raw.kind == "baseline"
    rng = np.random.default_rng(3)
    thetas = [pose_at("default", 1.0 + k / FPS, body) for k in range(16)]
    kin = BodyKinematics(body)
    for k, theta in enumerate(thetas):
        e = est.update(stamp(k), blobs_2d(body, cameras, theta, rng, 1.0))
        pred = est.predict(stamp(k + 1))
        raw_e, raw_pred = est.raw._estimate(stamp(k)), est.raw.predict(stamp(k + 1))
        assert e.status == est.raw.status == STATUS_TRACKING
        same = np.array_equal(e.joints, raw_e.joints)
        # the first warmup frames, the initialising one included
        assert same == (k < warmup), k
        assert np.array_equal(pred.joints, raw_pred.joints) == (k < warmup), k
        if k >= 2:  # (the start-up frames label some blobs only)
            assert np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean() < 0.025, k
        if not same:
            p = np.array([lk.position for lk in e.links])
            R = np.array([lk.rotation for lk in e.links])
            assert np.linalg.norm(kin.solver().residual(p, R)) < 1e-9
    assert est.timings_ms["outlier_fit"] > 0  # the raw tracker's update is counted as the outlier fit
    # a reset starts the warm-up again (so does any re-initialisation, _initialise); the own fit has no raw tracker
    est.reset()
    assert est._filter_frames == 0 and est.raw.theta is None
    assert make_estimator("kinematic", body, cameras, {"kinematic": {"fit_source": "own"}}).raw is None
    assert make_estimator("dynamic", body, cameras, {"dynamic": {"follow_fit": False}}).raw is None
    with pytest.raises(InputError, match="kinematic.fit_source"):
        make_estimator("kinematic", body, cameras, {"kinematic": {"fit_source": "bogus"}})


def test_kinematic_reuses_the_raw_trackers_view_association_of_the_same_blobs(body, cameras):
    """The view association (``measurement.view_association``) is a function of the labelled 2-D
    blobs alone: the kinematic estimator takes the raw tracker's of the same frame when the raw
    tracker ran it on the very same blob objects, and runs its own on any other input (here: the
    raw tracker's ``fit.overlap_parts`` screen left leg pairs out). Either way it equals
    associate_views of its input (one camera holds the shins the wrong way round)."""
    wrong = cameras[1].name
    exchange = {"l_shin": "r_shin", "r_shin": "l_shin"}
    for overlap_parts in ([], ["thigh", "shin"]):
        est = make_estimator("kinematic", body, cameras, {"fit": {"overlap_parts": overlap_parts}})
        m = est.cfg.measurement
        assert "shin" in m.view_association
        rng = np.random.default_rng(7)
        checked = exchanged = 0
        for k in range(4):
            blobs = blobs_2d(body, cameras, pose_at("default", 1.0 + k / FPS, body), rng, 1.0)
            blobs[wrong] = [dataclasses.replace(b, label=exchange.get(b.label, b.label)) for b in blobs[wrong]]
            est._association = None
            est.update(stamp(k), blobs)
            if est._association is None:  # (a track's first frame: the filters start at the raw tracker's pose)
                continue
            seen, (out, swaps) = est._association
            # the raw tracker's answer when its screen dropped nothing (it drops legs in every frame here)
            assert (est._association[1] is est.raw._association[1]) == (not est.raw.overlap_drops), k
            want, want_swaps = associate_views(seen, est.cameras, m.view_association, m.view_association_margin_chi2)
            assert swaps == want_swaps and set(swaps) <= {wrong}, k
            labels = {c: [b.label for b in bl] for c, bl in out.items()}
            assert labels == {c: [b.label for b in bl] for c, bl in want.items()}, k
            checked += 1
            exchanged += bool(swaps)
        assert checked == 3 and exchanged >= 2 and bool(est.raw.overlap_drops) == bool(overlap_parts)


def test_view_outlier_test_waits_for_the_track_to_settle(body, cameras):
    """``measurement.view_outlier_chi2`` leaves out a view whose label sits on something else (here
    the left hand's, 40 px below the hand in one camera), but only from the
    ``view_outlier_after_frames``-th frame of a track on: before, all four views are triangulated
    (a new track's labels may agree on the wrong thing); a re-initialised track waits again."""
    after = 3
    est = make_estimator("baseline", body, cameras, {"measurement": {"view_outlier_after_frames": after}})
    rng = np.random.default_rng(4)
    wrong = cameras[1].name

    def frame(k):
        blobs = blobs_2d(body, cameras, pose_at("default", 1.0 + k / FPS, body), rng, 0.5)
        blobs[wrong] = [dataclasses.replace(b, mean=np.asarray(b.mean) + [0.0, 40.0]) if b.label == "l_hand" else b
                        for b in blobs[wrong]]
        return blobs

    used = []
    for k in range(8):
        threshold = est._view_outlier_threshold()
        est.update(stamp(k), frame(k))
        used.append((threshold, est._triangulation[1]["l_hand"].cameras))
    assert [t for t, _ in used] == [0.0] * (after + 1) + [4.0] * (8 - after - 1)
    for threshold, cams in used:
        assert cams == tuple(c.name for c in cameras if threshold == 0.0 or c.name != wrong)
    est.initialisations += 1  # as a re-initialisation does: the new track waits again
    assert est._view_outlier_threshold() == 0.0


def test_kinematic_takes_the_raw_trackers_triangulations_that_needed_no_prior(body, cameras):
    """Triangulated from the very same associated blobs, a label whose rays meet does not depend on
    the priors: the kinematic estimator takes the raw tracker's result for it, and triangulates
    only the others (here the left hand, seen by one camera: its depth comes from the prior) with
    its own priors. The result equals triangulate_blobs of all of its input with its priors, in the
    same order: bit for bit where the rays met, to 1e-12 for the hand (solved in a smaller batch, the
    cameras' projections take another BLAS path); the hand's differs from the raw tracker's. (The
    negative evidence, which moves a one-view hand's prior first, is off here.)"""
    est = make_estimator("kinematic", body, cameras, {"fit": {"overlap_parts": []},
                                                      "measurement": {"hidden_labels": []}})
    rng = np.random.default_rng(3)
    one_view = cameras[0].name
    checked = 0
    for k in range(5):
        blobs = blobs_2d(body, cameras, pose_at("default", 1.0 + k / FPS, body), rng, 1.0)
        blobs = {c: [b for b in bl if b.label != "l_hand" or c == one_view] for c, bl in blobs.items()}
        priors = est._triangulation_priors(stamp(k)) if est.theta is not None else None
        outlier_chi2 = est.raw._view_outlier_threshold()  # the labels whose rays meet are the raw tracker's
        est.raw._triangulation = est._triangulation = None
        est.update(stamp(k), blobs)
        if est._triangulation is None or est.raw._triangulation is None:
            continue  # (a track's first frame: the filters start at the raw tracker's pose)
        seen, got, _ = est._triangulation
        _, raw_obs, raw_free = est.raw._triangulation
        m = est.cfg.measurement
        want = triangulate_blobs(seen, est.cameras, priors, view_outlier_chi2=outlier_chi2,
                                 small_blob_fraction=m.small_blob_fraction)
        assert list(got) == list(want), k
        for lab, blob in want.items():
            if lab in raw_free:
                assert np.array_equal(got[lab].mean, blob.mean) and np.array_equal(got[lab].cov, blob.cov), (k, lab)
            np.testing.assert_allclose(got[lab].mean, blob.mean, rtol=0, atol=1e-12)
            np.testing.assert_allclose(got[lab].cov, blob.cov, rtol=1e-12, atol=0)
            assert got[lab].cameras == blob.cameras, (k, lab)
        assert "l_hand" in got and "l_hand" not in raw_free and got["l_hand"].cameras == (one_view,)
        assert all(got[lab] is raw_obs[lab] for lab in raw_free)
        assert np.linalg.norm(got["l_hand"].mean - raw_obs["l_hand"].mean) > 1e-6
        checked += 1
    assert checked >= 3


def test_kinematic_link_covariance_is_the_constrained_inverse(body, cameras):
    """The links' published covariance (N (Nᵀ H N)⁻¹ Nᵀ, N a null-space basis of the joints'
    Jacobian) equals the top-left block of the inverse KKT matrix [[H, Jᵀ], [J, 0]]⁻¹ of the
    same soft-term information H: an independent formula for the same constrained inverse."""
    est = make_estimator("kinematic", body, cameras, {"kinematic": {"warmup_frames": 2}})
    rng = np.random.default_rng(5)
    for k in range(4):
        est.update(stamp(k), blobs_2d(body, cameras, pose_at("default", 1.0 + k / FPS, body), rng, 1.0))
    kin = est.kin
    B = len(kin.blob_labels)
    _, terms = est._soft_terms(
        est.blob_kf.position, est.blob_kf.position_cov(), est.link_kf.x[:, :3], est.link_kf.position_cov(),
        est.R,
    )
    got = est._link_covariance(est.p, est.R, terms)
    _, K, _ = soft_energy_terms(kin.n_links, est.p, est.R, terms(est.p, est.R))
    n = 6 * kin.n_links
    H = np.zeros((n, n))
    for i in range(kin.n_links):
        H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = K[i] + 1e-6 * np.eye(6)
    J = assemble(kin.constraints, est.p, est.R)[1].toarray()
    m = J.shape[0]
    kkt = np.block([[H, J.T], [J, np.zeros((m, m))]])
    C = np.linalg.inv(kkt)[:n, :n]
    want = np.array([C[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(kin.n_links)])
    assert B > 0 and got.shape == (kin.n_links, 6, 6)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9 * np.abs(want).max())


def test_kinematic_filters_restart_with_the_raw_trackers_new_track(body, cameras):
    """kinematic.follow_raw_track: when the raw tracker starts a new track (here: it is reset
    after 12 frames and relocalises from the next frame's blobs, as after a loss or a face turn),
    the filters restart at its pose and warm up again, so the raw estimate is the output for
    warmup_frames frames; with the option off the filters keep their own track."""
    warmup, restart_at = 4, 12
    outputs = {}
    for follow in (True, False):
        est = make_estimator("kinematic", body, cameras,
                             {"kinematic": {"warmup_frames": warmup, "follow_raw_track": follow}})
        rng = np.random.default_rng(5)
        same = []
        for k in range(restart_at + 8):
            if k == restart_at:
                est.raw.reset()
            theta = pose_at("default", 1.0 + k / FPS, body)
            e = est.update(stamp(k), blobs_2d(body, cameras, theta, rng, 1.0))
            est.predict(stamp(k + 1))
            same.append(bool(np.array_equal(e.joints, est.raw._estimate(stamp(k)).joints)))
            assert e.status == STATUS_TRACKING
            if k >= 2:
                assert np.linalg.norm(e.joints - body.joint_positions(theta), axis=1).mean() < 0.03, (follow, k)
        outputs[follow] = same
        assert est.raw.initialisations == 2
        assert est.raw_restarts == ([stamp(0), stamp(restart_at)] if follow else [])
    # the raw estimate leads during each warm-up: from the start and, when following, after the restart
    first = [True] * warmup + [False] * (restart_at - warmup)
    assert outputs[True] == first + [True] * warmup + [False] * (8 - warmup)
    assert outputs[False] == first + [False] * 8
    # the filters no longer run their own face checks while following a tracking raw tracker
    est = make_estimator("kinematic", body, cameras, {"kinematic": {"warmup_frames": warmup}})
    est.update(stamp(0), blobs_2d(body, cameras, pose_at("default", 1.0, body), np.random.default_rng(1), 1.0))
    assert est._verify_left == 0 and est.raw._verify_left > 0
    # a switch must be a YAML bool: bool("false") would have turned it on
    with pytest.raises(InputError, match="kinematic.follow_raw_track' must be true or false"):
        make_estimator("kinematic", body, cameras, {"kinematic": {"follow_raw_track": "false"}})


def test_kinematic_orientation_from_fit_holds_the_heading_through_swapped_legs(body, cameras):
    """kinematic.orientation_from_fit (stop 28): the walk with the legs' l_/r_ labels exchanged in
    every view for half a second (frames 20-34), as the 2-D trackers do where the trouser legs
    pass. The blob filters measure positions only; with the links' orientation springs pulled to
    their extrapolated previous rotation the solver turned the body round to meet the swapped
    legs and took long to come back (checked, default springs 0.08 rad: mean error 122 mm,
    shoulder-line yaw 58 deg off on average; 101 mm and 62 deg at 0.3 rad); pulled to the frame's
    robust body fit (its own track) it holds (49 mm, 20 deg; 53 mm, 24 deg at 0.3 rad).
    Since stop 34 the raw tracker's estimate is the output for the filters' first warmup_frames
    (40): those frames are the same in both runs, so the runs are scored after them, where the
    filters (and this switch) decide the output (stop 36, seed 7: 15 mm, 2.7 deg against 51 mm,
    33 deg; over the whole run, warm-up included, 47 / 67 mm: the solver's round-off moved the
    switched-off run between 67 and 108 mm there)."""
    swap = {"l_thigh": "r_thigh", "r_thigh": "l_thigh", "l_shin": "r_shin", "r_shin": "l_shin"}
    ls, rs = body.joint_names.index("l_shoulder"), body.joint_names.index("r_shoulder")

    def yaw(joints):
        v = joints[ls] - joints[rs]
        return math.degrees(math.atan2(v[1], v[0]))

    result, raw_led = {}, {}
    for flag in (False, True):
        rng = np.random.default_rng(7)
        est = make_estimator("kinematic", body, cameras, {"kinematic": {"orientation_from_fit": flag}})
        errs, yaw_errs = [], []
        for k in range(90):
            theta = pose_at("default", 0.5 + k / FPS, body)
            blobs = blobs_2d(body, cameras, theta, rng, 1.0)
            if 20 <= k < 35:
                blobs = {c: [dataclasses.replace(b, label=swap.get(b.label, b.label)) for b in bl]
                         for c, bl in blobs.items()}
            e = est.update(stamp(k), blobs)
            est.predict(stamp(k + 1))
            truth = body.joint_positions(theta)
            errs.append(float(np.linalg.norm(e.joints - truth, axis=1).mean()))
            yaw_errs.append(abs((yaw(e.joints) - yaw(truth) + 180.0) % 360.0 - 180.0))
        assert e.status == STATUS_TRACKING
        led = est.cfg.kinematic.warmup_frames  # the filters lead from here on (the raw tracker before)
        raw_led[flag] = errs[:led]
        result[flag] = (float(np.mean(errs[led:])), float(np.mean(yaw_errs[led:])))
    np.testing.assert_allclose(raw_led[True], raw_led[False])  # the raw-led frames: the same in both runs
    assert result[True][0] < 0.03 and result[True][1] < 10.0, result  # (seeds 6-11: 14-15 mm, 1.7-2.7 deg)
    assert result[False][0] > 1.5 * result[True][0] and result[False][1] > 1.8 * result[True][1], result


def _head_sized(body, cameras, blobs, theta):
    """``blobs`` with each view's head blob sized as the face shows it: about four times more
    pixels in the views the face looks at than behind (the neck under the hair), / distance²."""
    E = body.forward_kinematics(theta)[body.link_names.index("head")]
    forward = E[:2, 0] / np.linalg.norm(E[:2, 0])
    out = {}
    for cam in cameras:
        d = np.asarray(cam.center, float) - E[:3, 3]
        cos = float(forward @ d[:2]) / float(np.linalg.norm(d[:2]))
        n = int(round((300 + 900 * max(cos, 0.0)) * 16.0 / float(d @ d)))
        out[cam.name] = [Blob2D(b.label, b.mean, b.cov, pixel_count=n) if b.label == "head" else b
                         for b in blobs[cam.name]]
    return out


def test_facing_agreement_reads_the_facing_from_the_head_blob_sizes(body, cameras):
    """facing_agreement: head blobs larger (scaled to 1 m) in the views the head's forward axis
    points to give a cosine near +1; the same sizes for a head turned round near -1, for a head
    turned a quarter round near 0 (a sideways error is no reason to turn round); fewer than three
    views, or sizes alike from every side, say nothing (None)."""
    theta = _test_pose(body)
    link = body.link_names.index("head")
    blobs = _head_sized(body, cameras, blobs_2d(body, cameras, theta), theta)
    head = {name: b for name, bl in blobs.items() for b in bl if b.label == "head"}
    cams = {c.name: c for c in cameras}
    E = body.forward_kinematics(theta)[link]

    def turned(angle):
        c, s = math.cos(angle), math.sin(angle)
        out = E.copy()
        out[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ E[:3, :3]  # about the world's z
        return out

    assert facing_agreement(head, cams, E) > 0.9
    assert facing_agreement(head, cams, turned(math.pi)) < -0.9
    assert abs(facing_agreement(head, cams, turned(math.pi / 2))) < 0.3
    assert facing_agreement(dict(list(head.items())[:2]), cams, E) is None
    # facing_direction: the way itself, read from the sizes alone (the posed heading plays no part)
    way = facing_direction(head, cams, E[:3, 3])
    forward = E[:2, 0] / np.linalg.norm(E[:2, 0])
    assert abs(np.linalg.norm(way) - 1.0) < 1e-9 and math.degrees(math.acos(float(way @ forward))) < 5
    assert np.allclose(facing_direction(head, cams, turned(2.0)[:3, 3]), way)
    # sizes alike from every side (at most 2x apart at 1 m): no facing to read
    alike = {name: Blob2D("head", b.mean, b.cov, pixel_count=200) for name, b in head.items()}
    assert facing_agreement(alike, cams, E) is None


def test_a_body_tracked_facing_backwards_is_turned_round(body, cameras):
    """tracking.facing_*: started facing the wrong way with every l_/r_ label swapped to match
    (the blob positions fit either way round), the body is turned round once the head blob's
    sizes have disagreed with its facing for facing_check_frames frames (for facing_quick_frames
    when they disagree as clearly as here), also while the start-up verification runs; the 2-D
    labels then follow (as the projected priors make them) and the pose is right. With the check
    off it stays backwards."""
    theta = _test_pose(body)
    truth = body.joint_positions(theta)
    swap = {lab: ("r_" + lab[2:] if lab[:2] == "l_" else "l_" + lab[2:]) if lab[:2] in ("l_", "r_") else lab
            for lab in body.blob_labels}
    right = _head_sized(body, cameras, blobs_2d(body, cameras, theta), theta)
    swapped = {c: [Blob2D(swap[b.label], b.mean, b.cov, pixel_count=b.pixel_count) for b in bl]
               for c, bl in right.items()}

    def heading_error(e):
        R = e.links[0].rotation
        err = math.atan2(R[1, 0], R[0, 0]) - theta[5]
        return abs(math.degrees((err + math.pi) % (2 * math.pi) - math.pi))

    # the check also runs from the first tracked frame while the start-up verification does (verify 20;
    # here one that never turns the body itself, flip_cost_ratio 0)
    for frames, quick, verify in ((15, 0, 0), (15, 0, 20), (15, 5, 0), (15, 5, 20), (0, 5, 0)):
        # (without the upright head, fit.upright_head_sigma_m: held upright, the head's blob behind the neck
        # in this swapped start turns the start 31 deg from backwards, where the face sizes' cosine, -0.86,
        # meets the quick turn's -0.85 only later; this test is of the check, from exactly backwards)
        est = make_estimator("baseline", body, cameras, {"fit": {"upright_head_sigma_m": 0.0}, "tracking": {
            "verify_frames": verify, "flip_cost_ratio": 0.0, "facing_check_frames": frames,
            "facing_quick_frames": quick}})
        e = est.update(stamp(0), swapped)
        assert heading_error(e) > 150  # backwards, every side swapped
        for k in range(1, 21):
            e = est.update(stamp(k), right if est.facing_flips else swapped)
        if frames:
            assert len(est.facing_flips) == 1, (quick, verify, est.facing_flips)
            # the full window of 15 frames, or the quick one of 5 (the first cosine comes with frame 0)
            assert stamp((quick or frames) - 1) <= est.facing_flips[0] <= stamp(quick or frames), (quick, verify)
            assert heading_error(e) < 10
            assert np.linalg.norm(e.joints - truth, axis=1).mean() < 0.03
        else:
            assert not est.facing_flips and heading_error(e) > 150


def test_the_face_turn_keeps_hand_labels_already_on_their_sides(body, cameras):
    """tracking.facing_turn_groups: a heading that drifted round while the hands' own labels stayed
    right (distractor seed 21, stop 64: the trunk turned ~135 deg during the legs' swap, the hands
    10-40 mm off) is turned round by the face check; exchanging every label there put both hands
    0.5-0.6 m off, on the other's side. With [[hand]] the turn keeps the hands' labels where the
    left hand already lies left of the right one at the heading turned to: here, so the wrists are
    right. With [] (every label exchanged) the right hand's blob becomes the left hand. (A body
    facing backwards with every label swapped, the usual case, is exchanged as before: the test
    above.)"""
    theta = _test_pose(body)
    truth = body.joint_positions(theta)
    wrists = [body.joint_names.index("l_wrist"), body.joint_names.index("r_wrist")]

    def relabel(blobs, parts):
        return {c: [Blob2D(mirror_label(b.label) if b.label[2:] in parts else b.label, b.mean, b.cov,
                           pixel_count=b.pixel_count) for b in bl] for c, bl in blobs.items()}

    right = _head_sized(body, cameras, blobs_2d(body, cameras, theta), theta)
    sided = {lab[2:] for lab in body.blob_labels if lab[:2] in ("l_", "r_")}
    swapped = relabel(right, sided)  # a body facing backwards, every side swapped to match
    hands_right = relabel(right, sided - {"hand"})  # the hands' labels right, the rest swapped
    for groups in ([["hand"]], []):
        est = make_estimator("baseline", body, cameras, {"fit": {"upright_head_sigma_m": 0.0}, "tracking": {
            "verify_frames": 0, "facing_turn_groups": groups}})
        e = est.update(stamp(0), swapped)
        k = 1
        while not est.facing_flips and k < 20:
            e = est.update(stamp(k), hands_right)
            k += 1
        assert len(est.facing_flips) == 1, groups
        # at the turn: the right hand's blob (the left one is out of the backwards body's reach: the
        # reach gate dropped it) taken as the right hand, or, exchanged, as the left
        wrist_err = np.linalg.norm(e.joints[wrists] - truth[wrists], axis=1)
        if groups:
            assert wrist_err[1] < 0.01, wrist_err
            assert "r_hand" in est.last_observed and "l_hand" not in est.last_observed
            e = est.update(stamp(k), hands_right)  # in reach now: both hands follow their labels
            assert np.linalg.norm(e.joints[wrists] - truth[wrists], axis=1).max() < 0.05
        else:
            assert wrist_err.min() > 0.2, wrist_err
            assert "l_hand" in est.last_observed and "r_hand" not in est.last_observed


def _skin_blobs_at(cameras, points):
    """{camera: ['skin' Blob2D]}: unlabelled skin blobs (3 cm spread) at 3-D ``points`` in every view."""
    out = {}
    for cam in cameras:
        m, J = cam.project_jacobian(np.asarray(points, float).reshape(-1, 3))
        out[cam.name] = [Blob2D("skin", m[k], J[k] @ (np.eye(3) * 0.03**2) @ J[k].T, pixel_count=300)
                         for k in range(len(m))]
    return out


def test_a_lost_hand_is_reacquired_from_unlabelled_skin_blobs(body, cameras):
    """tracking.reacquire_*: the left hand rises overhead in one frame, faster than its prior, so its
    2-D labels find nothing and the blob trackers report the unlabelled skin they see ('skin' blobs).
    Where those meet within the arm's reach of the left shoulder the hand is found again and the arm
    follows; a skin point at the face (near the observed head blob) and one out of reach (another
    person's hand) are not taken. With reacquire_labels: [] the hand stays where it was lost."""
    down = _test_pose(body)
    up = down.copy()
    up[body.dof_slice("l_upper_arm")] = [2.45, -0.15, 0.0]  # the default motion's wave, overhead
    up[body.dof_slice("l_forearm")] = [0.24]
    labels = body.blob_labels
    hand_up = body.blob_centres(up)[labels.index("l_hand")]
    face = body.blob_centres(up)[labels.index("head")] + np.array([0.06, 0.0, 0.0])
    far = hand_up + np.array([0.0, -2.5, -0.6])
    skin = _skin_blobs_at(cameras, [face, hand_up, far])
    lost = {c: bl + skin[c] for c, bl in blobs_2d(body, cameras, up, hide=("l_hand",)).items()}
    wrist = body.joint_names.index("l_wrist")
    for labels_cfg in (["l_hand", "r_hand"], []):
        est = make_estimator("baseline", body, cameras, {"tracking": {"reacquire_labels": labels_cfg}})
        for k in range(3):
            e = est.update(stamp(k), blobs_2d(body, cameras, down))
        for k in range(3, 5):
            e = est.update(stamp(k), lost)
        err = float(np.linalg.norm(e.joints[wrist] - body.joint_positions(up)[wrist]))
        if labels_cfg:
            assert est.reacquired == ["l_hand"]
            assert err < 0.05, err
            assert np.linalg.norm(e.joints - body.joint_positions(up), axis=1).mean() < 0.03
        else:
            assert est.reacquired == [] and err > 0.5, err
    # only skin at the face and out of reach: nothing is taken
    est = make_estimator("baseline", body, cameras, None)
    for k in range(3):
        est.update(stamp(k), blobs_2d(body, cameras, down))
    skin = _skin_blobs_at(cameras, [face, far])
    est.update(stamp(3), {c: bl + skin[c] for c, bl in blobs_2d(body, cameras, up, hide=("l_hand",)).items()})
    assert est.reacquired == []


def test_a_hand_beside_the_pelvis_is_reacquired(body, cameras):
    """tracking.reacquire_separation_m keeps re-acquired hands away from the other skin-coloured parts
    only (the head, the other hand): skin blobs can be no other part's. A left hand lost by the hip,
    0.13 m from the pelvis' observed 3-D blob and within the arm's reach, is found there (stop 42;
    before, the pelvis' blob kept it from being found, and a hand behind the back stayed lost)."""
    theta = _test_pose(body)
    labels = body.blob_labels
    pelvis = body.blob_centres(theta)[labels.index("pelvis")]
    point = pelvis + np.array([-0.12, 0.05, 0.0])
    est = make_estimator("baseline", body, cameras, None)
    t = est.cfg.tracking
    assert np.linalg.norm(point - pelvis) < t.reacquire_separation_m
    shoulder = body.forward_kinematics(theta)[body.link_index("l_upper_arm"), :3, 3]
    assert np.linalg.norm(point - shoulder) < t.reacquire_reach_margin * est._reacquire_chain["l_hand"][1]
    for k in range(3):
        est.update(stamp(k), blobs_2d(body, cameras, theta))
    skin = _skin_blobs_at(cameras, [point])
    est.update(stamp(3), {c: bl + skin[c] for c, bl in blobs_2d(body, cameras, theta, hide=("l_hand",)).items()})
    assert "pelvis" in est.last_observed
    assert est.reacquired == ["l_hand"]
    np.testing.assert_allclose(est.last_observed["l_hand"].mean, point, atol=0.01)


@pytest.mark.parametrize("margin", [1.3, 0.0])
def test_a_hand_observed_out_of_reach_is_not_used(body, cameras, margin):
    """tracking.reach_gate_margin: in every view the left hand's label sits on skin 1.2 m to the
    person's side (another person's face), so its views agree on a 3-D blob far out of the arm's
    reach. With the gate (1.3 x the reach from the shoulder) that blob is not used: the frame's
    estimate is the one the fit gives with the hand unseen; without it (0) the fit pulls the arm
    towards the far blob."""
    theta = _test_pose(body)
    hand = body.blob_centres(theta)[body.blob_labels.index("l_hand")]
    far = hand + np.array([0.0, 1.2, 0.0])
    hidden = blobs_2d(body, cameras, theta, hide=("l_hand",))
    moved = {c: bl + [dataclasses.replace(b, label="l_hand") for b in _skin_blobs_at(cameras, [far])[c]]
             for c, bl in hidden.items()}
    wrist = body.joint_names.index("l_wrist")
    result = {}
    for name, frame in (("hidden", hidden), ("moved", moved)):
        est = make_estimator("baseline", body, cameras, {"tracking": {"reach_gate_margin": margin}})
        for k in range(3):
            est.update(stamp(k), blobs_2d(body, cameras, theta))
        result[name] = est.update(stamp(3), frame).joints[wrist]
    to_far = {k: float(np.linalg.norm(w - far)) for k, w in result.items()}
    if margin > 0:
        assert "l_hand" not in est.last_observed
        assert np.allclose(result["moved"], result["hidden"], atol=1e-9), to_far
    else:
        assert "l_hand" in est.last_observed
        assert to_far["moved"] < to_far["hidden"] - 0.2, to_far


@pytest.mark.parametrize("labels, after_frames, gated",
                         [(["l_shin"], 0, True), ([], 0, False), (["l_shin"], 10, False)])
def test_a_shin_observed_out_of_its_legs_reach_is_not_used(body, cameras, labels, after_frames, gated):
    """tracking.reach_gate_labels: in every view the left shin's label sits 1.2 m in front of the
    shin (another leg, the trunk), out of the leg's reach from the hip (1.3 x hip -> knee -> shin
    blob). Gated, that blob is not used: the estimate is the one with the shin unseen. Not gated
    (no such labels, or the track younger than ``reach_gate_after_frames``), the fit takes it."""
    theta = _test_pose(body)
    k_shin = body.blob_labels.index("l_shin")
    far = body.blob_centres(theta)[k_shin] + np.array([1.2, 0.0, 0.0])
    hidden = blobs_2d(body, cameras, theta, hide=("l_shin",))
    moved = {c: bl + [dataclasses.replace(b, label="l_shin") for b in _skin_blobs_at(cameras, [far])[c]]
             for c, bl in hidden.items()}
    ankle = body.joint_names.index("l_ankle")
    cfg = {"tracking": {"reach_gate_labels": labels, "reach_gate_after_frames": after_frames}}
    result = {}
    for name, frame in (("hidden", hidden), ("moved", moved)):
        est = make_estimator("baseline", body, cameras, cfg)
        for k in range(3):
            est.update(stamp(k), blobs_2d(body, cameras, theta))
        result[name] = est.update(stamp(3), frame).joints[ankle]
    to_far = {k: float(np.linalg.norm(w - far)) for k, w in result.items()}
    if gated:
        assert "l_shin" not in est.last_observed
        assert np.allclose(result["moved"], result["hidden"], atol=1e-9), to_far
    else:
        assert "l_shin" in est.last_observed
        assert to_far["moved"] < to_far["hidden"] - 0.1, to_far


def test_reacquire_config_errors(body, cameras):
    with pytest.raises(InputError, match="fit.predict_velocity_links"):
        make_estimator("baseline", body, cameras, {"fit": {"predict_velocity_links": ["l_wing"]}})
    with pytest.raises(InputError, match="fit.predict_velocity_gain"):
        load_skeleton_config({"fit": {"predict_velocity_smoothing": 0.0}})
    with pytest.raises(InputError, match="tracking.reacquire_labels"):
        make_estimator("baseline", body, cameras, {"tracking": {"reacquire_labels": ["l_wing"]}})
    with pytest.raises(InputError, match="tracking.reacquire_separation_m"):
        load_skeleton_config({"tracking": {"reacquire_separation_m": -1.0}})
    with pytest.raises(InputError, match="tracking.reach_gate_margin"):
        load_skeleton_config({"tracking": {"reach_gate_margin": -1.0}})
    with pytest.raises(InputError, match="tracking.reach_gate_labels"):
        make_estimator("baseline", body, cameras, {"tracking": {"reach_gate_labels": ["l_wing"]}})
    with pytest.raises(InputError, match="tracking.reach_gate_after_frames"):
        load_skeleton_config({"tracking": {"reach_gate_after_frames": -1}})
    with pytest.raises(InputError, match="startup.person_gap_m"):
        load_skeleton_config({"startup": {"person_gap_m": -0.5}})


def test_baseline_prediction_extrapolates_the_joint_velocities(body, cameras):
    """fit.predict_velocity_*: the baseline's prediction moves the joint dofs and the root's position
    on by predict_velocity_gain times their smoothed velocity (a leg swinging forward is predicted
    part of the way to where it goes, so the projected priors lag it less); the root's rotation is
    not extrapolated, and a (re)initialisation forgets the velocity."""
    thetas = []
    for k in range(12):  # the right knee flexes and the body walks along x at constant rates
        theta = _test_pose(body)
        theta[0] += 0.03 * k
        theta[body.dof_slice("r_shin")] = [0.3 + 0.05 * k]
        thetas.append(theta)
    knee, ankle = body.joint_names.index("r_knee"), body.joint_names.index("r_ankle")
    lead = {}
    for gain in (0.0, 0.5, 1.0):
        est = make_estimator("baseline", body, cameras, {"fit": {"predict_velocity_gain": gain}})
        for k in range(11):
            e = est.update(stamp(k), blobs_2d(body, cameras, thetas[k]))
        pred = est.predict(stamp(11))
        step = body.joint_positions(thetas[11]) - body.joint_positions(thetas[10])
        lead[gain] = [float((pred.joints[j] - e.joints[j]) @ step[j] / (step[j] @ step[j])) for j in (knee, ankle)]
        np.testing.assert_allclose(pred.links[0].rotation, e.links[0].rotation, atol=1e-12)
    np.testing.assert_allclose(lead[0.0], 0.0, atol=1e-9)  # zero velocity: the prediction stays
    np.testing.assert_allclose(lead[0.5], 0.5, atol=0.1)  # half a frame ahead
    np.testing.assert_allclose(lead[1.0], 1.0, atol=0.15)  # a whole frame ahead
    est._initialise(stamp(11), thetas[11], {})
    np.testing.assert_allclose(est.predict(stamp(12)).joints, body.joint_positions(thetas[11]), atol=1e-9)


def test_kinematic_takes_the_edges_into_its_orientation_fit(body, cameras):
    """ALGORITHMS.md §2 "Fusion" in the Kalman + constraints skeleton: the edge statistics enter
    the frame's robust body fit that gives the links their orientations
    (``kinematic.orientation_from_fit``). The person walks with both hand blobs hidden, so only
    the constraints and the rest pose place the forearms; edge statistics that measure every
    link's true motion from the prediction bring the wrists to the truth, and without them the
    wrists stay off."""
    from artrack.edge_fusion import LinkEdgeStatistics
    from artrack.lie import log_se3
    from artrack.pipeline import link_poses

    rng = np.random.default_rng(7)
    wrists = [body.joint_names.index("l_wrist"), body.joint_names.index("r_wrist")]
    L = len(body.links)
    errs = {}
    for use_edges in (False, True):
        est = make_estimator("kinematic", body, cameras, None)
        err = []
        for k in range(30):
            theta = pose_at("default", 1.0 + k / FPS, body)
            edges = None
            if k > 0:  # the loop's cycle: the prediction for this frame (the edges' reference)
                ref = link_poses(est.predict(stamp(k)))
            if use_edges and k > 0:
                xi = log_se3(np.einsum("lij,ljk->lik", inverse_se3(ref), body.forward_kinematics(theta)))
                info = np.tile(np.eye(6) * 1e4, (L, 1, 1))
                edges = LinkEdgeStatistics(ref, info, np.einsum("lij,lj->li", info, xi), np.full(L, 50), ("all",))
            e = est.update(stamp(k), blobs_2d(body, cameras, theta, rng, 1.0, hide=("l_hand", "r_hand")), edges)
            if k >= 10:
                err.append(np.linalg.norm(e.joints[wrists] - body.joint_positions(theta)[wrists], axis=1).mean())
        errs[use_edges] = float(np.mean(err))
    assert errs[True] < 0.5 * errs[False], errs  # measured: 160 mm without, 6 mm with


def _arm_behind_the_back(body):
    """(the rest pose at the origin, the same with the right arm reaching behind the back): in the
    first three views of the ``cameras`` ring only cam0 sees that hand (model shapes as occluders)."""
    rest = body.rest_pose()
    rest[0:3] = [0.0, 0.0, 0.95]
    back = rest.copy()
    back[body.dof_slice("r_upper_arm")] = [0.5, 0.6, 0.0]
    back[body.dof_slice("r_forearm")] = [2.0]
    return rest, back


@pytest.mark.parametrize("labels", [[], ["r_hand"]])
def test_a_hand_one_view_finds_takes_a_depth_the_silent_views_allow(body_shape_hands, cameras, labels):
    """``measurement.hidden_labels`` (artrack.hidden): the hand behind the back is found by cam0
    alone; its prediction (at the side, where cam1 and cam2 would have seen it) moves along
    cam0's ray to where they would not have."""
    body = body_shape_hands  # the scene's geometry: see the fixture
    rest, back = _arm_behind_the_back(body)
    three = cameras[:3]
    est = make_estimator("baseline", body, three, {"measurement": {"hidden_labels": labels},
                                                   "fit": {"overlap_parts": []}})
    for k in range(3):
        est.update(stamp(k), blobs_2d(body, three, rest))
    found = {c: [b for b in bl if b.label != "r_hand" or c == "cam0"] for c, bl in blobs_2d(body, three, back).items()}
    e = est.update(stamp(3), found)
    assert est.last_observed["r_hand"].cameras == ("cam0",)
    w = body.joint_names.index("r_wrist")
    err = float(np.linalg.norm(e.joints[w] - body.joint_positions(back)[w]))
    assert (err < 0.12) if labels else (err > 0.18), err  # measured 0.101 / 0.218 m


@pytest.mark.parametrize("sigma", [0.0, 0.1])
def test_a_hand_no_view_finds_is_measured_where_fewer_views_would_see_it(body_shape_hands, cameras, sigma):
    """``measurement.hidden_no_view_sigma_m``: a pseudo-measurement (no cameras) at the likeliest
    point given that no view found the hand, to that sigma; none when 0."""
    body = body_shape_hands  # the scene's geometry: see the fixture
    rest, back = _arm_behind_the_back(body)
    three = cameras[:3]
    est = make_estimator("baseline", body, three, {"measurement": {"hidden_labels": ["r_hand"],
                                                                   "hidden_no_view_sigma_m": sigma},
                                                   "fit": {"overlap_parts": []}})
    for k in range(3):
        est.update(stamp(k), blobs_2d(body, three, rest))
    predicted = est._triangulation_priors(stamp(3))["r_hand"].mean
    caps = est._hidden_capsules("r_hand")  # the occluders it is judged with: the pose before the update
    est.update(stamp(3), blobs_2d(body, three, back, hide=("r_hand",)))
    got = est.last_observed.get("r_hand")
    if sigma == 0:
        assert got is None
        return
    assert got is not None and got.cameras == ()
    np.testing.assert_allclose(est.measurement_cov(got), np.eye(3) * sigma**2, atol=1e-12)
    n_seen = [sum(visible_points(c, x[None], "r_hand", caps)[0] for c in three) for x in (predicted, got.mean)]
    assert n_seen[1] < n_seen[0], n_seen


def test_kinematic_filters_follow_a_manoeuvre_that_the_body_fit_explains(body, cameras):
    """Adaptive process noise (``kinematic.maneuver_max_scale``, Bar-Shalom et al. 2001, §11.2):
    where the walk stops and both hands start waving (t = 4.5 .. 6.5 s, 1 px noise), a hand's blob
    leaves its constant-acceleration prediction. The frame's body fit explains the blob, so the
    innovation is a manoeuvre, not an outlier: the filter's process noise grows with it and the hand
    follows instead of lagging behind the soft innovation gate."""
    hands = [body.joint_names.index(n) for n in ("l_wrist", "r_wrist")]
    errs = {}
    for scale in (1.0, 10.0):
        rng = np.random.default_rng(3)
        est = make_estimator("kinematic", body, cameras, {"kinematic": {"maneuver_max_scale": scale,
                                                                        "warmup_frames": 0}})
        e_k = []
        for k in range(60):
            theta = pose_at("default", 4.5 + k / FPS, body)
            e = est.update(stamp(k), blobs_2d(body, cameras, theta, rng, 1.0))
            est.predict(stamp(k + 1))
            e_k.append(float(np.linalg.norm(e.joints[hands] - body.joint_positions(theta)[hands], axis=1).mean()))
        assert e.status == STATUS_TRACKING
        errs[scale] = float(np.mean(e_k[10:]))
    # measured: 25.8 mm without, 24.7 with (blobs with 1-px noise in 640x480 views: little lag to take off)
    assert errs[10.0] < 0.97 * errs[1.0], errs
