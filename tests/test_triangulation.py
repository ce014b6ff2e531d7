"""Covariance-weighted triangulation of 2-D blobs (artrack.triangulation)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from artrack.cameras import Camera
from artrack.errors import InputError
from artrack.triangulation import (
    associate_views,
    blob_extent,
    drop_overlapping_pairs,
    midpoint,
    midpoints,
    triangulate_blob,
    triangulate_blobs,
)
from artrack.types import Blob2D, Blob3D

K = np.array([[900.0, 0.0, 639.5], [0.0, 910.0, 359.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.01])


def ring_cameras(n: int = 4) -> list[Camera]:
    """n cameras on a 4 m ring, 2.2 m high, looking at (0, 0, 1)."""
    cams = []
    for i in range(n):
        a = math.radians(45 + 360 / n * i)
        eye = [4 * math.cos(a), 4 * math.sin(a), 2.2]
        cams.append(Camera.look_at(f"cam{i + 1:02d}", 1280, 720, K, eye, [0, 0, 1.0], dist=DIST))
    return cams


def covs_2d(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """Random anisotropic 2-D covariances, 1-4 px standard deviations."""
    out = []
    for _ in range(n):
        a = rng.uniform(0, np.pi)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        out.append(R @ np.diag(rng.uniform(1.0, 4.0, 2) ** 2) @ R.T)
    return out


def observe(cams: list[Camera], X: np.ndarray, covs: list[np.ndarray], label: str = "head"):
    return [
        (cam, Blob2D(label, cam.project(X)[0][0], cov, pixel_count=100))
        for cam, cov in zip(cams, covs, strict=True)
    ]


def test_midpoint_of_intersecting_rays():
    X = np.array([0.2, -0.1, 1.3])
    origins = np.array([[3.0, 0, 1], [0, 3.0, 2], [-2.0, -2, 0.5]])
    dirs = X - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    P, spread = midpoint(origins, dirs)
    np.testing.assert_allclose(P, X, atol=1e-12)
    assert spread > 0.1


def test_midpoints_of_many_bundles_equal_one_at_a_time():
    """The batched ray midpoints (the view association's hypotheses at once) are bit for bit
    :func:`midpoint` of each bundle, parallel bundles (least-squares fallback) included."""
    rng = np.random.default_rng(4)
    origins = rng.uniform(-3.0, 3.0, (7, 4, 3))
    dirs = rng.normal(size=(7, 4, 3))
    dirs[2] = dirs[2, 0]  # four parallel rays: no spread
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
    X, spread = midpoints(origins, dirs)
    for p in range(7):
        Xp, sp = midpoint(origins[p], dirs[p])
        assert np.array_equal(X[p], Xp) and spread[p] == sp
        if p != 2:  # the normal equations written out
            proj = [np.eye(3) - np.outer(d, d) for d in dirs[p]]
            want = np.linalg.solve(sum(proj), sum(P @ o for P, o in zip(proj, origins[p], strict=True)))
            np.testing.assert_allclose(X[p], want, atol=1e-9)
    assert spread[2] < 1e-12 and np.all(np.delete(spread, 2) > 1e-3)


def test_exact_recovery_without_noise():
    rng = np.random.default_rng(11)
    cams = ring_cameras()
    for _ in range(10):
        X = rng.uniform([-0.7, -0.7, 0.2], [0.7, 0.7, 1.9])
        for subset in (cams, cams[:2], cams[1:4]):
            blob = triangulate_blob(observe(subset, X, covs_2d(rng, len(subset))))
            assert blob is not None and blob.label == "head"
            np.testing.assert_allclose(blob.mean, X, atol=1e-8)
            assert blob.cameras == tuple(c.name for c in subset)
            assert np.all(np.linalg.eigvalsh(blob.cov) > 0)


def test_covariance_is_consistent_with_pixel_noise():
    """Seeded Monte-Carlo: the spread of estimates from noisy 2-D means matches the
    returned covariance (inverse information)."""
    rng = np.random.default_rng(12)
    cams = ring_cameras()
    X = np.array([0.25, -0.15, 1.4])
    covs = covs_2d(rng, len(cams))
    clean = observe(cams, X, covs)
    predicted = triangulate_blob(clean).cov
    n = 1500
    est = np.empty((n, 3))
    for i in range(n):
        noisy = [(cam, Blob2D("head", rng.multivariate_normal(b.mean, b.cov), b.cov)) for cam, b in clean]
        est[i] = triangulate_blob(noisy).mean
    err = est - X
    assert np.linalg.norm(err.mean(axis=0)) < 4 * np.sqrt(np.trace(predicted) / n)  # unbiased
    empirical = np.cov(err.T)
    assert np.linalg.norm(empirical - predicted) / np.linalg.norm(predicted) < 0.12
    # Normalised errors are chi² with 3 dof: mean 3 (std of the mean sqrt(6 / n) = 0.063).
    d2 = np.einsum("ni,ij,nj->n", err, np.linalg.inv(predicted), err)
    assert d2.mean() == pytest.approx(3.0, abs=0.25)


def test_single_view_needs_a_prior_and_takes_depth_from_it():
    cam = ring_cameras()[0]
    X = np.array([0.1, 0.2, 1.2])
    obs = observe([cam], X, [np.eye(2)])  # 1 px: ~5 mm across the ray at 4.3 m
    assert triangulate_blob(obs) is None

    prior_mean = X + np.array([0.05, -0.08, 0.06])  # wrong mostly across the ray
    prior = Blob3D("head", prior_mean, np.eye(3) * 0.1**2)
    blob = triangulate_blob(obs, prior)
    assert blob is not None and blob.cameras == ("cam01",)
    origin, d = cam.rays(obs[0][1].mean[None])
    d = d[0]
    # On the ray (the pixel is certain compared with a 10 cm prior) ...
    off_ray = (blob.mean - origin) - ((blob.mean - origin) @ d) * d
    assert np.linalg.norm(off_ray) < 2e-3
    # ... at the depth of the prior mean along that ray, with the prior's variance along it.
    assert (blob.mean - origin) @ d == pytest.approx((prior_mean - origin) @ d, abs=2e-3)
    assert d @ blob.cov @ d == pytest.approx(0.1**2, rel=0.02)
    # The view pins the two directions across the ray: 1 px at depth z is z / f metres.
    z = cam.project(blob.mean)[1][0]
    lateral = np.linalg.eigvalsh(blob.cov)[:2]
    np.testing.assert_allclose(lateral, (z / 905.0) ** 2, rtol=0.1)


def test_prior_is_ignored_with_two_views_unless_asked():
    rng = np.random.default_rng(14)
    cams = ring_cameras()[:2]
    X = np.array([0.0, 0.0, 1.0])
    obs = observe(cams, X, covs_2d(rng, 2))
    prior = Blob3D("head", X + 0.1, np.eye(3) * 0.05**2)
    np.testing.assert_allclose(triangulate_blob(obs, prior).mean, X, atol=1e-8)
    fused = triangulate_blob(obs, prior, fuse_prior=True)
    assert np.linalg.norm(fused.mean - X) > 1e-6
    assert np.all(np.linalg.eigvalsh(triangulate_blob(obs).cov - fused.cov) > -1e-15)  # more information


def test_triangulate_blobs_groups_by_label():
    cams = ring_cameras()
    heads = np.array([0.0, 0.1, 1.7])
    hand = np.array([0.4, -0.2, 1.1])
    foot = np.array([0.1, 0.1, 0.1])
    by_cam = {}
    for i, cam in enumerate(cams):
        blobs = [Blob2D("head", cam.project(heads)[0][0], np.eye(2) * 4, pixel_count=300)]
        if i < 2:
            blobs.append(Blob2D("left_hand", cam.project(hand)[0][0], np.eye(2) * 2, pixel_count=80))
        if i == 3:
            blobs.append(Blob2D("left_foot", cam.project(foot)[0][0], np.eye(2), pixel_count=50))
            # a second, smaller "head" candidate in the same camera is ignored
            blobs.append(Blob2D("head", np.array([10.0, 10.0]), np.eye(2), pixel_count=5))
        by_cam[cam.name] = blobs
    out = triangulate_blobs(by_cam, {c.name: c for c in cams})
    assert set(out) == {"head", "left_hand"}  # foot: one view, no prior
    np.testing.assert_allclose(out["head"].mean, heads, atol=1e-8)
    np.testing.assert_allclose(out["left_hand"].mean, hand, atol=1e-8)
    assert out["left_hand"].cameras == ("cam01", "cam02")
    priors = {"left_foot": Blob3D("left_foot", foot + 0.02, np.eye(3) * 0.05**2)}
    out = triangulate_blobs(by_cam, cams, priors)
    assert out["left_foot"].cameras == ("cam04",)
    with pytest.raises(InputError, match="cam99"):
        triangulate_blobs({"cam99": []}, cams)


def test_view_behind_the_camera_is_dropped():
    """A spurious blob in a camera that faces away from the point: its ray cannot meet the
    others in front of it, so that view is dropped and the rest still triangulate exactly."""
    cams = ring_cameras()[:3]
    X = np.array([0.0, 0.0, 1.0])
    obs = observe(cams, X, [np.eye(2)] * 3)
    away = Camera.look_at("away", 1280, 720, K, [0.5, 0.0, 1.0], [2.0, 0.0, 1.0])
    assert away.project(X)[1][0] < 0
    obs.append((away, Blob2D("head", np.array([639.5, 359.5]), np.eye(2))))
    blob = triangulate_blob(obs)
    assert blob is not None and "away" not in blob.cameras
    np.testing.assert_allclose(blob.mean, X, atol=1e-8)


def test_labels_solved_together_equal_each_solved_alone():
    """triangulate_blobs runs all labels' Gauss–Newton steps together (one projection per camera
    and step); each label's result must equal triangulating it alone, whatever views, noise and
    priors the others have. 20 steps: labels stop at different steps, so later steps run on
    subsets."""
    rng = np.random.default_rng(7)
    cams = ring_cameras()
    for _ in range(20):
        by_cam = {c.name: [] for c in cams}
        alone = {}
        priors = {}
        for label in ("head", "left_hand", "right_hand", "torso", "left_foot"):
            X = rng.normal([0.0, 0.0, 1.0], 0.4)
            views = rng.choice(len(cams), size=rng.integers(1, len(cams) + 1), replace=False)
            obs = []
            for i, cov in zip(sorted(views), covs_2d(rng, len(views)), strict=True):
                uv = cams[i].project(X)[0][0] + rng.normal(0.0, 3.0, 2)
                b = Blob2D(label, uv, cov, pixel_count=100)
                by_cam[cams[i].name].append(b)
                obs.append((cams[i], b))
            priors[label] = Blob3D(label, X + rng.normal(0.0, 0.05, 3), np.eye(3) * 0.1**2)
            alone[label] = triangulate_blob(obs, priors[label], iterations=20)
        together = triangulate_blobs(by_cam, cams, priors, iterations=20)
        assert set(together) == {k for k, v in alone.items() if v is not None}
        for label, blob in together.items():
            np.testing.assert_allclose(blob.mean, alone[label].mean, atol=1e-9)
            np.testing.assert_allclose(blob.cov, alone[label].cov, rtol=1e-7, atol=1e-12)
            assert blob.cameras == alone[label].cameras


def test_batched_gauss_newton_equals_one_point_at_a_time():
    """The batched Gauss–Newton core from starts ~2 m off (so steps are halved and points stop
    at different steps, leaving later steps to subsets): each point's result equals its own run."""
    from artrack.triangulation import _gauss_newton

    rng = np.random.default_rng(11)
    cams = ring_cameras()
    n = 12
    X_true = rng.normal([0.0, 0.0, 1.0], 0.4, (n, 3))
    uvs = np.zeros((n, len(cams), 2))
    infos = np.zeros((n, len(cams), 2, 2))
    for b in range(n):
        views = rng.choice(len(cams), size=rng.integers(2, len(cams) + 1), replace=False)
        for c, cov in zip(views, covs_2d(rng, len(views)), strict=True):
            uvs[b, c] = cams[c].project(X_true[b])[0][0] + rng.normal(0.0, 5.0, 2)
            infos[b, c] = np.linalg.inv(cov)
    prior_mean = X_true + rng.normal(0.0, 0.1, (n, 3))
    prior_info = np.where(rng.random(n)[:, None, None] < 0.5, np.eye(3) / 0.2**2, 0.0)
    X0 = X_true + rng.normal(0.0, 2.0, (n, 3))
    X, H, _ = _gauss_newton(X0, cams, uvs, infos, prior_mean, prior_info, 8)
    for b in range(n):
        Xb, Hb, _ = _gauss_newton(X0[b:b + 1], cams, uvs[b:b + 1], infos[b:b + 1], prior_mean[b:b + 1],
                                  prior_info[b:b + 1], 8)
        np.testing.assert_allclose(X[b], Xb[0], atol=1e-10)
        np.testing.assert_allclose(H[b], Hb[0], rtol=1e-9)


def test_blob_extent_recovers_the_3d_shape_from_its_projections():
    """A 3-D Gaussian's 2-D covariances J S Jᵀ in three or more views give S back (the linear
    least squares is exact on exact projections); two views do not determine it (None); noise on
    the 2-D shapes leaves the widest horizontal axis (a torso's shoulder line) within a few degrees."""
    rng = np.random.default_rng(5)
    cams = ring_cameras()
    for _ in range(5):
        X = rng.uniform([-0.5, -0.5, 0.8], [0.5, 0.5, 1.4])
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        S = R @ np.diag(rng.uniform(0.05, 0.2, 3) ** 2) @ R.T
        for subset in (cams, cams[:3], cams[1:4]):
            J = [c.project_jacobian(X[None])[1][0] for c in subset]
            obs = [(c, Blob2D("torso", c.project(X)[0][0], j @ S @ j.T)) for c, j in zip(subset, J, strict=True)]
            np.testing.assert_allclose(blob_extent(obs, X), S, atol=1e-10)
        assert blob_extent(obs[:2], X) is None
    # a torso 0.30 m across the shoulders, 0.22 m deep, turned 0.7 rad; 2-D shapes 10 % off
    yaw = 0.7
    Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    S = Rz @ np.diag([0.11, 0.15, 0.18]) ** 2 @ Rz.T
    X = np.array([0.1, -0.2, 1.2])
    obs = []
    for c in cams:
        j = c.project_jacobian(X[None])[1][0]
        C = j @ S @ j.T
        E = np.diag(1.0 + rng.uniform(-0.1, 0.1, 2))
        obs.append((c, Blob2D("torso", c.project(X)[0][0], E @ C @ E)))
    vals, vecs = np.linalg.eigh(blob_extent(obs, X)[:2, :2])
    lateral = np.array([-math.sin(yaw), math.cos(yaw)])
    assert abs(float(vecs[:, 1] @ lateral)) > math.cos(math.radians(8.0))


def test_associate_views_exchanges_the_pair_in_the_view_that_holds_it_the_wrong_way_round():
    """Two shins 0.2 m apart seen by four cameras; one camera's tracker holds their labels the
    wrong way round. Triangulated as labelled, each 3-D shin mixes both legs; the view
    association exchanges that camera's pair back (the rays then meet) and leaves consistent
    labels alone, even with 1 px noise. A margin above the error gain keeps the labels."""
    rng = np.random.default_rng(3)
    cams = ring_cameras()
    left, right = np.array([0.0, 0.1, 0.5]), np.array([0.0, -0.1, 0.5])
    cov = np.diag([4.0, 25.0])  # 2 x 5 px, a narrow upright blob

    def blobs(swap_in: set[str]):
        out = {}
        for cam in cams:
            uv = {lab: cam.project(X)[0][0] + rng.normal(0.0, 1.0, 2)
                  for lab, X in (("l_shin", left), ("r_shin", right))}
            if cam.name in swap_in:
                uv = {"l_shin": uv["r_shin"], "r_shin": uv["l_shin"]}
            out[cam.name] = [Blob2D(lab, m, cov, pixel_count=100) for lab, m in uv.items()]
        return out

    by_name = {c.name: c for c in cams}
    for swap_in in ({"cam03"}, {"cam01"}, {"cam02", "cam04"}):
        mixed = blobs(swap_in)
        fixed, swapped = associate_views(mixed, by_name, ["shin"], margin_chi2=4.0)
        # cam01 is the reference: exchanging it is the same association as exchanging all the others
        expect = swap_in if "cam01" not in swap_in else {c.name for c in cams} - swap_in
        assert set(swapped) == expect and all(v == ["shin"] for v in swapped.values())
        tri = triangulate_blobs(fixed, cams)
        consistent = sorted([tri["l_shin"].mean, tri["r_shin"].mean], key=lambda x: -x[1])
        np.testing.assert_allclose(consistent, [left, right], atol=0.01)
        before = triangulate_blobs(mixed, cams)
        assert np.linalg.norm(before["l_shin"].mean - left) > 0.03  # as labelled: mixed
        _, kept = associate_views(mixed, by_name, ["shin"], margin_chi2=1e9)
        assert kept == {}
    fixed, swapped = associate_views(blobs(set()), by_name, ["shin"], margin_chi2=4.0)
    assert swapped == {}


def test_view_outlier_rejection_leaves_out_the_view_whose_label_sits_on_something_else():
    """A hand seen by five cameras; in one (then two) of them its 2-D tracker follows something
    else 40 px away (a knee). Triangulated from all views the 3-D hand lies between the two; with
    ``view_outlier_chi2`` the disagreeing views are left out one by one and the hand comes back
    onto the truth, seen by the others. Consistent views with pixel noise are all kept, and a
    blob of two views is never tested (nothing to outvote)."""
    rng = np.random.default_rng(8)
    cams = ring_cameras(5)
    X = np.array([0.1, 0.2, 1.1])
    cov = np.diag([9.0, 9.0])  # a 3 px hand

    def blobs(wrong: set[str]) -> dict[str, list[Blob2D]]:
        out = {}
        for cam in cams:
            uv = cam.project(X)[0][0] + rng.normal(0.0, 0.5, 2) + (np.array([0.0, 40.0]) if cam.name in wrong else 0.0)
            out[cam.name] = [Blob2D("l_hand", uv, cov, pixel_count=60)]
        return out

    for wrong in ({"cam02"}, {"cam02", "cam04"}):
        seen = blobs(wrong)
        plain = triangulate_blobs(seen, cams)["l_hand"]
        robust = triangulate_blobs(seen, cams, view_outlier_chi2=9.0)["l_hand"]
        assert np.linalg.norm(plain.mean - X) > 0.02 and len(plain.cameras) == 5
        assert np.linalg.norm(robust.mean - X) < 0.005
        assert set(robust.cameras) == {c.name for c in cams} - wrong
    clean = triangulate_blobs(blobs(set()), cams, view_outlier_chi2=9.0)["l_hand"]
    assert len(clean.cameras) == 5 and np.linalg.norm(clean.mean - X) < 0.005
    two = {c: bl for c, bl in blobs({"cam02"}).items() if c in ("cam01", "cam02")}
    assert triangulate_blobs(two, cams, view_outlier_chi2=9.0)["l_hand"].cameras == ("cam01", "cam02")


def test_drop_overlapping_pairs_leaves_the_crossing_legs_to_the_views_that_tell_them_apart():
    """Two shins 0.3 m apart nearly along cam01's (and cam03's) line of sight (8° off): there
    they overlap, and a tracker that shares their pixels out by the priors reports both blobs
    pulled to the middle. Triangulated as reported, both 3-D shins are pulled towards each
    other; with the overlapping views left out, cam02 and cam04 (which see the pair side by
    side) put each shin back. Views where the pair does not overlap, a pair with one blob only,
    and ``max_chi2`` 0 are left alone."""
    cams = ring_cameras()
    axis = np.array([math.cos(math.radians(53)), math.sin(math.radians(53)), 0.0])
    centre = np.array([0.0, 0.0, 0.5])
    true = {"l_shin": centre + 0.15 * axis, "r_shin": centre - 0.15 * axis}
    cov = np.diag([16.0, 400.0])  # 4 x 20 px: an upright shin
    reported = {}
    for cam in cams:
        uv = {lab: cam.project(X)[0][0] for lab, X in true.items()}
        mid = 0.5 * (uv["l_shin"] + uv["r_shin"])
        if cam.name in ("cam01", "cam03"):  # overlapping there: both blobs pulled to the middle
            uv = {lab: 0.8 * mid + 0.2 * m for lab, m in uv.items()}
        reported[cam.name] = [Blob2D(lab, m, cov, pixel_count=200) for lab, m in uv.items()]
        reported[cam.name].append(Blob2D("head", cam.project(np.array([0.0, 0.0, 1.6]))[0][0], cov, pixel_count=200))

    kept, dropped = drop_overlapping_pairs(reported, ["shin"], 4.0)
    assert dropped == {"cam01": ["shin"], "cam03": ["shin"]}
    assert [b.label for b in kept["cam01"]] == ["head"] and len(kept["cam02"]) == 3
    after, before = triangulate_blobs(kept, cams), triangulate_blobs(reported, cams)
    for lab, X in true.items():
        assert np.linalg.norm(after[lab].mean - X) < 1e-3
        assert np.linalg.norm(before[lab].mean - X) > 0.01  # the merged views pull it to the middle (17 mm)
        assert sorted(after[lab].cameras) == ["cam02", "cam04"]

    assert drop_overlapping_pairs(reported, ["shin"], 0.0)[1] == {}
    assert drop_overlapping_pairs(reported, ["thigh"], 4.0)[1] == {}
    one_side = {c: [b for b in bl if b.label != "r_shin"] for c, bl in reported.items()}
    assert drop_overlapping_pairs(one_side, ["shin"], 4.0)[1] == {}


def test_a_small_blob_counts_less_by_its_pixel_count():
    """``small_blob_fraction``: a view's information is multiplied by n / (n + n0), n0 = the fraction
    times the image area; the same as triangulating with each blob's covariance divided by that
    weight. A sliver of a hidden part (few pixels, a small extent, its mean 12 px off) pulls the
    point less than by its extent alone; a blob of many pixels keeps (nearly) its weight."""
    cams = ring_cameras()
    X = np.array([0.1, -0.2, 1.1])
    by_cam = {}
    for i, cam in enumerate(cams):
        uv = cam.project(X)[0][0]
        if i == 3:  # the sliver
            by_cam[cam.name] = [Blob2D("l_hand", uv + [12.0, 0.0], np.eye(2) * 1.0, pixel_count=6)]
        else:
            by_cam[cam.name] = [Blob2D("l_hand", uv, np.eye(2) * 9.0, pixel_count=400 + 100 * i)]
    fraction = 40.0 / (1280 * 720)  # n0 = 40 px
    weighted = triangulate_blobs(by_cam, cams, small_blob_fraction=fraction)["l_hand"]
    scaled = {c: [Blob2D(b.label, b.mean, b.cov * (b.pixel_count + 40.0) / b.pixel_count, pixel_count=b.pixel_count)
                  for b in bl] for c, bl in by_cam.items()}
    np.testing.assert_allclose(weighted.mean, triangulate_blobs(scaled, cams)["l_hand"].mean, atol=1e-9)
    np.testing.assert_allclose(weighted.cov, triangulate_blobs(scaled, cams)["l_hand"].cov, rtol=1e-6, atol=1e-12)
    plain = triangulate_blobs(by_cam, cams)["l_hand"]
    assert np.linalg.norm(weighted.mean - X) < 0.7 * np.linalg.norm(plain.mean - X)  # 30 mm against 48
    with_many = {c: [Blob2D(b.label, b.mean, b.cov, pixel_count=10**6) for b in bl] for c, bl in by_cam.items()}
    np.testing.assert_allclose(triangulate_blobs(with_many, cams, small_blob_fraction=fraction)["l_hand"].mean,
                               triangulate_blobs(with_many, cams)["l_hand"].mean, atol=1e-4)
