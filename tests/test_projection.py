"""Feedback projection of 3-D blobs into 2-D priors (artrack.projection)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from artrack.cameras import Camera
from artrack.projection import (
    DEFAULT_CENTRE_OCCLUSION_LABELS,
    DEFAULT_OCCLUSION_SURFACE_SIGMA,
    Capsule,
    confidence_from_covariance,
    occluded,
    project_gaussian,
    project_priors,
)
from artrack.types import BEHIND_CAMERA, OCCLUDED, OFF_IMAGE, VISIBLE, Blob3D, BodyEstimate, LinkEstimate

K = np.array([[900.0, 0.0, 639.5], [0.0, 910.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.25, 0.1, 0.002, -0.003, -0.01])


def ring_cameras(n: int = 4, dist: np.ndarray = DIST) -> list[Camera]:
    cams = []
    for i in range(n):
        a = math.radians(45 + 360 / n * i)
        eye = [4 * math.cos(a), 4 * math.sin(a), 2.2]
        cams.append(Camera.look_at(f"cam{i + 1:02d}", 1280, 720, K, eye, [0, 0, 1.0], dist=dist))
    return cams


def test_projected_covariance_matches_monte_carlo():
    """First-order J Σ Jᵀ (through the distortion) vs 20000 projected samples."""
    rng = np.random.default_rng(7)
    cam = ring_cameras()[0]
    # A point near the image corner, where the distortion matters most.
    corner_ray = cam.rays(np.array([[60.0, 50.0]]))[1][0]
    mean = cam.center + 4.0 * corner_ray
    A = rng.normal(size=(3, 3))
    cov = 0.01**2 * (A @ A.T + 0.5 * np.eye(3))  # anisotropic, ~1-2 cm
    mean2, cov2, depth = project_gaussian(cam, mean, cov)
    assert depth > 3.0
    samples = rng.multivariate_normal(mean, cov, size=20000)
    uv, _ = cam.project(samples)
    np.testing.assert_allclose(mean2, cam.project(mean)[0][0], atol=1e-9)
    assert np.linalg.norm(uv.mean(axis=0) - mean2) < 0.1  # px
    cov_mc = np.cov(uv.T)
    assert np.linalg.norm(cov2 - cov_mc) / np.linalg.norm(cov_mc) < 0.03
    # ... and the distortion is not negligible there: the pinhole Jacobian would be off.
    pinhole = Camera(cam.name, cam.width, cam.height, cam.K, np.zeros(5), cam.R, cam.t)
    _, cov2_pinhole, _ = project_gaussian(pinhole, mean, cov)
    assert np.linalg.norm(cov2_pinhole - cov_mc) / np.linalg.norm(cov_mc) > 0.1


def test_confidence_is_a_decreasing_map_into_unit_interval():
    assert confidence_from_covariance(np.zeros((3, 3))) == 1.0
    s = 0.01
    vals = [confidence_from_covariance(np.eye(3) * v, s) for v in (1e-5, 1e-4, 1e-3, 1e-2, 1.0)]
    assert all(0.0 <= v <= 1.0 for v in vals) and vals == sorted(vals, reverse=True)
    assert confidence_from_covariance(np.diag([s, 0, 0]), s) == pytest.approx(math.exp(-1))
    assert confidence_from_covariance(np.full((3, 3), np.nan)) == 0.0


def _blob(label: str, mean, sigma: float = 0.03) -> Blob3D:
    return Blob3D(label, np.asarray(mean, float), np.eye(3) * sigma**2)


def test_visible_priors_for_every_camera_and_blob():
    cams = ring_cameras()
    blobs = [_blob("head", [0, 0, 1.7]), _blob("left_hand", [0.3, 0.2, 1.0], 0.05)]
    priors = project_priors(blobs, {c.name: c for c in cams}, stamp_ns=123)
    assert list(priors) == [c.name for c in cams]
    for cam in cams:
        ps = priors[cam.name]
        assert [p.label for p in ps] == ["head", "left_hand"]
        for p, b in zip(ps, blobs, strict=True):
            assert p.visibility == VISIBLE and p.stamp_ns == 123
            np.testing.assert_allclose(p.mean, cam.project(b.mean)[0][0])
            assert p.confidence == pytest.approx(confidence_from_covariance(b.cov))
            assert np.all(np.linalg.eigvalsh(p.cov) > 0)
        assert ps[0].confidence > ps[1].confidence  # vaguer prediction, lower confidence


def test_behind_camera_and_off_image():
    cam = ring_cameras()[0]
    behind = _blob("behind", cam.center + 1.0 * (cam.center - np.array([0, 0, 1.0])) / 4)
    # In front, but far to the side of the view (about 60 degrees off-axis, outside the FOV).
    side_dir = cam.R.T @ np.array([math.sin(math.radians(60)), 0.0, math.cos(math.radians(60))])
    side = _blob("side", cam.center + 3.0 * side_dir)
    # Just outside the right image border but within the default margin (5 % of 1280 px = 64 px).
    near_edge = _blob("near_edge", cam.center + 3.0 * cam.rays(np.array([[1300.0, 360.0]]))[1][0])
    (ps,) = project_priors([behind, side, near_edge], [cam], 5).values()
    assert ps[0].visibility == BEHIND_CAMERA and ps[0].confidence == 0.0 and np.all(np.isnan(ps[0].mean))
    assert ps[1].visibility == OFF_IMAGE and ps[1].confidence == 0.0
    assert ps[2].visibility == VISIBLE and ps[2].mean[0] == pytest.approx(1300.0, abs=1e-3)
    (ps,) = project_priors([near_edge], [cam], 5, margin=10.0).values()
    assert ps[0].visibility == OFF_IMAGE


def test_priors_behind_the_camera_cross_the_wire():
    """The NaN mean of a BEHIND_CAMERA prior is by design: the message conversion the nodes
    use keeps it, and still refuses NaN on a prior that claims to be visible."""
    from artrack.messages import prior_array_msg, priors_from_msg, rosbags_factory

    cam = ring_cameras()[0]
    behind = _blob("behind", cam.center + 1.0 * (cam.center - np.array([0, 0, 1.0])) / 4)
    front = _blob("front", np.array([0.0, 0.0, 1.0]))
    (ps,) = project_priors([behind, front], [cam], 5).values()
    f = rosbags_factory()
    _, _, back = priors_from_msg(prior_array_msg(f, 5, cam.name, cam.frame_id, ps))
    assert back[0].visibility == BEHIND_CAMERA and np.all(np.isnan(back[0].mean))
    np.testing.assert_array_equal(back[1].mean, ps[1].mean)
    ps[0].visibility = VISIBLE
    with pytest.raises(ValueError, match=r"priors\[0\] \('behind'\) has a non-finite mean"):
        priors_from_msg(prior_array_msg(f, 5, cam.name, cam.frame_id, ps))


def test_off_image_when_distortion_would_fold_the_point_back_in():
    """A strong barrel polynomial maps far off-axis points back inside the image; they must
    still be OFF_IMAGE."""
    cam = Camera.look_at("wide", 1280, 720, K, [0, -4, 1], [0, 0, 1], dist=[-0.2, 0, 0, 0, 0])
    x_n = 2.3  # normalised radius beyond the fold (1 - 0.2 r² < 0)
    X = cam.center + cam.R.T @ np.array([x_n, 0.0, 1.0]) * 2.0
    uv, _ = cam.project(X)
    assert cam.in_image(uv)[0]  # the polynomial folded it into the image...
    (ps,) = project_priors([_blob("far", X)], [cam], 0).values()
    assert ps[0].visibility == OFF_IMAGE  # ...but it is not visible.


def test_occlusion_by_a_nearer_capsule_but_not_by_own_link():
    cam = ring_cameras()[0]
    hand = np.array([0.0, 0.0, 1.0])
    toward_cam = (cam.center - hand) / np.linalg.norm(cam.center - hand)
    side = np.cross(toward_cam, [0, 0, 1.0])
    side /= np.linalg.norm(side)
    # Torso capsule 0.5 m in front of the hand (towards the camera), across the line of sight.
    mid = hand + 0.5 * toward_cam
    torso = Capsule("torso", mid - 0.3 * side, mid + 0.3 * side, 0.12)
    own = Capsule("hand", hand - 0.05 * toward_cam, hand + 0.4 * toward_cam, 0.05)
    behind_hand = ("back", hand - 0.5 * toward_cam - 0.3 * side, hand - 0.5 * toward_cam + 0.3 * side, 0.12)
    blobs = [_blob("hand", hand)]

    (ps,) = project_priors(blobs, [cam], 0, occluders=[torso]).values()
    assert ps[0].visibility == OCCLUDED and ps[0].confidence > 0
    (ps,) = project_priors(blobs, [cam], 0, occluders=[own, behind_hand]).values()
    assert ps[0].visibility == VISIBLE  # own link and a capsule behind the blob do not occlude
    # The torso is off the line of sight of another camera on the other side of the ring.
    other = ring_cameras()[1]
    assert not occluded(other.center, hand, "hand", [torso])
    # A neighbouring link touching the blob (within occlusion_margin) does not occlude.
    forearm = Capsule("forearm", hand + 0.02 * toward_cam - 0.3 * side, hand + 0.02 * toward_cam, 0.02)
    assert not occluded(cam.center, hand, "hand", [forearm])
    assert occluded(cam.center, hand, "hand", [forearm], occlusion_margin=0.0)


def test_body_estimate_input_uses_its_blobs_and_stamp():
    cams = ring_cameras(2)
    est = BodyEstimate(
        stamp_ns=42, joint_names=[], joints=np.zeros((0, 3)), links=[], blobs=[_blob("head", [0, 0, 1.7])]
    )
    priors = project_priors(est, cams)
    assert set(priors) == {"cam01", "cam02"}
    assert all(ps[0].stamp_ns == 42 and ps[0].label == "head" for ps in priors.values())


class _Shape:
    def __init__(self, p0, p1, radius):
        self.p0, self.p1, self.radius = np.asarray(p0, float), np.asarray(p1, float), radius

    def as_capsule(self):
        return self.p0, self.p1, self.radius


class _Link:
    def __init__(self, name, shapes):
        self.name, self.shapes = name, shapes


class _Body:
    """The part of BodyModel that projection uses: links with names and shapes."""

    links = [
        _Link("torso", [_Shape([0, 0, 0], [0, 0, 0.5], 0.15)]),
        _Link("hand", [_Shape([0, 0, -0.05], [0, 0, 0.05], 0.04)]),
    ]


def test_body_estimate_with_body_model_gives_occlusion_and_link_confidence():
    """ARCHITECTURE.md form project_priors(prediction, cameras, body): occluders from the
    model's shapes at the predicted link poses, confidence from the links' covariance."""
    cam = ring_cameras()[0]
    hand = np.array([0.0, 0.0, 1.0])
    toward_cam = (cam.center - hand) / np.linalg.norm(cam.center - hand)
    torso_origin = hand + 0.5 * toward_cam - np.array([0, 0, 0.25])  # torso segment crosses the ray
    links = [
        LinkEstimate("torso", torso_origin, np.eye(3), cov=np.eye(6) * 1e-4),
        LinkEstimate("hand", hand, np.eye(3), cov=np.eye(6) * 4e-3),
    ]
    est = BodyEstimate(7, [], np.zeros((0, 3)), links, [_blob("hand", hand, 0.05), _blob("torso", hand, 0.2)])
    priors = project_priors(est, [cam], _Body())
    hand_prior, torso_prior = priors["cam01"]
    assert hand_prior.visibility == OCCLUDED and hand_prior.stamp_ns == 7
    assert hand_prior.confidence == pytest.approx(confidence_from_covariance(np.eye(3) * 4e-3))
    assert torso_prior.confidence == pytest.approx(confidence_from_covariance(np.eye(3) * 1e-4))
    # Without the body there are no occluders.
    assert project_priors(est, [cam])["cam01"][0].visibility == VISIBLE


def _sight_line_clearance(C, X, caps, margin=0.05):
    """Brute-force reference for ``occluded``: min over capsules of (distance from the sight
    line C -> X shortened by ``margin``, sampled at 4000 points, to the capsule axis) - radius."""
    v = X - C
    if np.linalg.norm(v) <= margin:  # the camera is within the margin: nothing can hide the blob
        return np.inf
    end = X - v / np.linalg.norm(v) * margin
    pts = C + np.linspace(0.0, 1.0, 4000)[:, None] * (end - C)
    best = np.inf
    for c in caps:
        d = c.p1 - c.p0
        t = np.clip((pts - c.p0) @ d / max(d @ d, 1e-12), 0.0, 1.0)
        best = min(best, float(np.min(np.linalg.norm(pts - (c.p0 + t[:, None] * d), axis=1))) - c.radius)
    return best


def test_all_blobs_of_a_camera_at_once_equal_one_blob_at_a_time():
    """project_priors projects and occlusion-tests all blobs of a camera in one go; every prior
    must equal the per-blob definition: project_gaussian for mean and covariance, and occluded
    exactly when the sight line passes within a radius of another label's capsule axis (a
    sampled brute-force reference; random blobs, capsules and a camera inside the scene,
    so that every visibility code occurs). The sight line stops 2 sigma of the blob along it short
    of its mean (at least 5 cm), the hands' 5 cm short (``centre_occlusion_labels``)."""
    rng = np.random.default_rng(5)
    cams = ring_cameras()
    cams.append(Camera.look_at("inside", 1280, 720, K, [0.3, 0.0, 1.0], [2.0, 0.0, 1.0]))
    labels = ["head", "torso", "left_hand", "right_hand", "left_foot", "right_foot"]
    seen = set()
    for _ in range(40):
        blobs = []
        for label in labels:
            A = rng.normal(size=(3, 3)) * 0.1
            blobs.append(Blob3D(label, rng.normal([0.0, 0.0, 1.0], 0.8), A @ A.T))
        caps = [Capsule(str(rng.choice(labels)), rng.normal([0.0, 0.0, 1.0], 0.5),
                        rng.normal([0.0, 0.0, 1.0], 0.5), float(rng.uniform(0.02, 0.2))) for _ in range(10)]
        caps.append(Capsule("torso", np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), 0.1))  # a sphere
        hands = ("left_hand", "right_hand")
        out = project_priors(blobs, cams, 7, occluders=caps, occlusion_surface_sigma=2.0, centre_occlusion_labels=hands)
        for cam in cams:
            for blob, prior in zip(blobs, out[cam.name], strict=True):
                seen.add(prior.visibility)
                if prior.visibility == BEHIND_CAMERA:
                    assert cam.project(blob.mean)[1][0] <= 1e-3
                    continue
                mean2, cov2, _ = project_gaussian(cam, blob.mean, blob.cov)
                np.testing.assert_allclose(prior.mean, mean2, atol=1e-9)
                np.testing.assert_allclose(prior.cov, cov2, rtol=1e-9, atol=1e-9)
                if prior.visibility != OFF_IMAGE:
                    d = (blob.mean - cam.center) / np.linalg.norm(blob.mean - cam.center)
                    stop = 0.05 if blob.label in hands else max(0.05, 2.0 * float(np.sqrt(d @ blob.cov @ d)))
                    gap = _sight_line_clearance(cam.center, blob.mean, [c for c in caps if c.label != blob.label],
                                                stop)
                    if abs(gap) > 1e-3:  # not grazing: the sampled reference is decisive
                        assert (prior.visibility == OCCLUDED) == (gap < 0.0)
                    assert prior.confidence == confidence_from_covariance(blob.cov)
    assert seen == {VISIBLE, OCCLUDED, OFF_IMAGE, BEHIND_CAMERA}


def test_a_blob_is_occluded_when_its_near_surface_is_hidden_not_its_centre():
    """The pelvis' blob centre lies inside the body, behind the tops of its own thighs' capsules as
    seen from the front: tested to its centre (occlusion_surface_sigma 0) it is OCCLUDED, tested
    to its near surface (2 sigma of the blob along the line of sight) VISIBLE. A hand at the same
    place stays OCCLUDED (``centre_occlusion_labels``), and a blob far behind a capsule stays
    OCCLUDED under either test."""
    cam = Camera.look_at("front", 1280, 720, K, [3.0, 0.0, 0.9], [0.0, 0.0, 0.9])
    thigh = Capsule("l_thigh", np.array([0.10, 0.0, 0.9]), np.array([0.10, 0.0, 0.5]), 0.07)
    pelvis = Blob3D("pelvis", np.array([0.0, 0.0, 0.88]), np.diag([0.11, 0.16, 0.11]) ** 2)
    hand = Blob3D("l_hand", pelvis.mean, np.diag([0.11, 0.16, 0.11]) ** 2)
    far = Blob3D("torso", np.array([-0.6, 0.0, 0.88]), np.diag([0.11, 0.16, 0.11]) ** 2)
    vis = {s: [p.visibility for p in project_priors([pelvis, hand, far], [cam], 1, occluders=[thigh],
                                                     occlusion_surface_sigma=s)["front"]] for s in (0.0, 2.0)}
    assert vis[0.0] == [OCCLUDED, OCCLUDED, OCCLUDED]
    assert vis[2.0] == [VISIBLE, OCCLUDED, OCCLUDED]
    assert DEFAULT_OCCLUSION_SURFACE_SIGMA == 2.0 and "l_hand" in DEFAULT_CENTRE_OCCLUSION_LABELS
