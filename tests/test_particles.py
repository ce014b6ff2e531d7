"""Tests of the §3 particle filter: priors, likelihood, depth scenes, point-cloud messages
(ALGORITHMS.md §3)."""

from __future__ import annotations

import numpy as np
import pytest

from artrack.body_model import load_body_model
from artrack.particles import (
    ParticleConfig,
    ParticleFilter,
    Stick2D,
    Stick3D,
    gamma_on_stick,
    stick_point,
)
from artrack.pointcloud import (
    crop_box,
    half_capsule_sq_distance,
    marker_error,
    points_from_depth,
    raycast_depth,
    workspace_box,
    world_from_camera_points,
)
from artrack.stick_scene import generate_stick_scene, rgbd_camera, stick_length, stick_trajectory


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def camera():
    return rgbd_camera()


@pytest.fixture(scope="module")
def frames(body, camera):
    """The first 6 frames (0.4 s at 15 fps) of the side-to-side stick scene."""
    return list(generate_stick_scene("stick_side", seed=1, fps=15.0, duration_s=0.4, camera=camera, body=body,
                                     colour=False))


def _filter(body, frame, prior, n=300, **kw):
    pf = ParticleFilter(body, frame.theta, ParticleConfig(prior=prior, n_particles=n, seed=3, **kw))
    pf.gamma[:] = gamma_on_stick(frame.stick[0], frame.stick[1], pf.manifold.hands(pf.theta[:1])[0])
    return pf


def _seg_dist(p, a, b):
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _points(frame, camera):
    lo, hi = workspace_box(frame.theta[:3])
    return crop_box(world_from_camera_points(camera, frame.points_cam), lo, hi)


def test_stick3d_puts_both_hands_on_the_stick_in_every_particle(body, frames, camera):
    pf = _filter(body, frames[0], "stick3d")
    for f in frames[1:3]:
        _, stats = pf.step(_points(f, camera), camera.center, Stick3D(f.stick[0], f.stick[1]))
        hands = pf.manifold.hands(pf.theta)                     # the particles drawn from the prior
        d = _seg_dist(hands, f.stick[0], f.stick[1])            # (n, 2)
        assert d.max() < 0.006, d.max()                         # sigma_hand = 1 mm
        assert np.all((pf.theta >= pf.manifold.lower) & (pf.theta <= pf.manifold.upper))
        assert stats.prior == "stick3d" and stats.hand_stick_distance < 0.002
    # the hands' stick positions diffuse but stay in [0, 1]
    assert np.all((pf.gamma >= 0) & (pf.gamma <= 1)) and pf.gamma.std() > 0


def test_gp_prior_ignores_the_stick(body, frames, camera):
    pf = _filter(body, frames[0], "gp")
    f = frames[1]
    pf.step(_points(f, camera), camera.center, Stick3D(f.stick[0], f.stick[1]))
    d = _seg_dist(pf.manifold.hands(pf.theta), f.stick[0], f.stick[1])
    assert d.max() > 0.03
    assert np.all((pf.theta >= pf.manifold.lower) & (pf.theta <= pf.manifold.upper))


def test_stick2d_puts_hands_on_the_viewing_rays_of_the_stick_image(body, frames, camera):
    pf = _filter(body, frames[0], "stick2d")
    f = frames[1]
    uv, _ = camera.project(f.stick)
    pf.step(_points(f, camera), camera.center, Stick2D(uv[0], uv[1], camera))
    hands_uv, _ = camera.project(pf.manifold.hands(pf.theta).reshape(-1, 3))
    # pixel distance of every projected hand to the stick's image segment: a few mm at 2.5 m ≈ < 2 px
    assert _seg_dist(np.c_[hands_uv, np.zeros(len(hands_uv))], np.r_[uv[0], 0], np.r_[uv[1], 0]).max() < 2.0
    # but not necessarily on the 3-D stick (depth along the ray is free)
    assert _seg_dist(pf.manifold.hands(pf.theta), f.stick[0], f.stick[1]).max() > 0.004


def test_kkb_reports_the_share_of_particles_at_the_rejection_cap(body, frames, camera):
    f = frames[1]
    stick = Stick3D(f.stick[0], f.stick[1])
    pf = _filter(body, frames[0], "kkb", n=50, kkb_threshold=1e-4, kkb_max_rejections=30)
    _, st = pf.step(_points(f, camera), camera.center, stick)
    assert st.kkb_capped_share == 1.0 and st.kkb_mean_rejections == 30
    pf = _filter(body, frames[0], "kkb", n=50, kkb_threshold=0.5, kkb_max_rejections=30)
    _, st = pf.step(_points(f, camera), camera.center, stick)
    assert st.kkb_capped_share == 0.0
    pf = _filter(body, frames[0], "kkb", n=50, kkb_threshold=0.03, kkb_max_rejections=5000)
    _, st = pf.step(_points(f, camera), camera.center, stick)
    ok = _seg_dist(pf.manifold.hands(pf.theta), f.stick[0], f.stick[1]).max(axis=1) < 0.03 + 1e-9
    assert ok.mean() >= 1.0 - st.kkb_capped_share - 1e-9      # every uncapped particle holds the stick


def test_filter_tracks_a_few_frames_deterministically(body, frames, camera):
    """The core on 5 frames with p_stick3d, 200 particles: close to the truth, and repeatable."""
    runs = []
    for _ in range(2):
        pf = _filter(body, frames[0], "stick3d", n=200)
        errs, ests = [], []
        for f in frames[1:]:
            est, _ = pf.step(_points(f, camera), camera.center, Stick3D(f.stick[0], f.stick[1]))
            errs.append(marker_error(body, est, f.theta))
            ests.append(est)
        runs.append(np.array(ests))
        assert np.mean(errs) < 0.02, errs
    np.testing.assert_array_equal(runs[0], runs[1])


def test_no_stick_falls_back_to_the_projected_prior(body, frames, camera):
    pf = _filter(body, frames[0], "stick3d", n=50)
    _, st = pf.step(_points(frames[1], camera), camera.center, None)
    assert st.prior == "proj"


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="prior"):
        ParticleConfig(prior="nope").check()
    with pytest.raises(ValueError, match="sigma_hand"):
        ParticleConfig(sigma_hand=0.0).check()


# ---------------------------------------------------------------------- likelihood and scenes
def test_half_capsule_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    p0 = np.array([[[0.0, 0.0, 0.0]]])
    p1 = np.array([[[0.0, 0.0, 0.4]]])
    r = np.array([0.05])
    cam = np.array([3.0, 0.5, 0.2])
    # dense samples of the capsule surface (cylinder part and caps), keep the half facing the camera
    phi, z = np.meshgrid(np.linspace(0, 2 * np.pi, 361), np.linspace(0.0, 0.4, 201))
    surf = np.stack([0.05 * np.cos(phi), 0.05 * np.sin(phi), z], axis=-1).reshape(-1, 3)
    w = cam - np.array([0.0, 0.0, 0.2])
    w[2] = 0.0
    w /= np.linalg.norm(w)
    surf = surf[(surf[:, :2] @ w[:2]) >= 0]
    pts = rng.uniform([-0.2, -0.2, 0.05], [0.2, 0.2, 0.35], (100, 3))
    view = cam - pts
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    d2 = half_capsule_sq_distance(pts, view, p0, p1, r)[0, 0]
    brute = np.min(np.linalg.norm(pts[:, None] - surf[None], axis=-1), axis=1) ** 2
    # the brute force keeps the half facing the camera as seen from the capsule's centre, the
    # model the half facing each point's own line of sight: they differ by millimetres here
    np.testing.assert_allclose(np.sqrt(d2), np.sqrt(brute), atol=0.004)


def test_depth_of_a_stick_lies_on_its_surface(camera):
    a, b = np.array([0.3, -0.5, 1.2]), np.array([0.3, 0.5, 1.3])
    depth, label = raycast_depth(load_body_model(), None, camera, stick=(a, b))
    assert (label == 2).sum() > 50
    pts = world_from_camera_points(camera, points_from_depth(np.where(label == 2, depth, np.nan), camera))
    np.testing.assert_allclose(_seg_dist(pts, a, b), 0.015, atol=1e-4)
    floor = world_from_camera_points(camera, points_from_depth(np.where(label == 0, depth, np.nan), camera))
    on_room = (np.abs(floor[:, 2]) < 1e-3) | (np.abs(floor[:, 2] - 3.0) < 1e-3) | (np.abs(floor[:, :2]).max(1) > 5.49)
    assert np.all(on_room)  # floor, ceiling or walls


def test_stick_scene_ground_truth_is_consistent(body, frames, camera):
    for motion in ("stick_side", "stick_sword"):
        th, st = stick_trajectory(motion, 15.0, 20, body)
        np.testing.assert_allclose(np.linalg.norm(st[:, 0] - st[:, 1], axis=1), stick_length(motion), atol=1e-9)
        pf = ParticleFilter(body, th[0], ParticleConfig(n_particles=1))
        hands = np.array([pf.manifold.hands(pf.manifold.active(t)[None])[0] for t in th])
        assert _seg_dist(hands, st[:, None, 0], st[:, None, 1]).max() < 1e-9
        lim = pf.manifold
        act = lim.active(th)
        assert np.all((act >= lim.lower - 1e-9) & (act <= lim.upper + 1e-9))
    f = frames[2]
    # the noisy points of the person lie near the true skin: the likelihood of the truth beats a bent elbow
    pts = _points(f, camera)
    pf = ParticleFilter(body, f.theta, ParticleConfig(n_particles=2))
    full = np.stack([f.theta, f.theta])
    full[1, body.dof_slice("l_forearm")] += 0.4
    ll = pf.skin.log_likelihood(full, pts, camera.center, 0.02, 0.08**2)
    assert ll[0] > ll[1]
    assert marker_error(body, f.theta, f.theta) < 1e-9


def test_stick_point_and_gamma_round_trip():
    a, b = np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 1.0])
    g = np.array([0.0, 0.25, 1.0])
    np.testing.assert_allclose(gamma_on_stick(a, b, stick_point(a, b, g)), g)
    np.testing.assert_allclose(stick_point(a, b, 1.0), a)


def test_pointcloud_and_stick_messages_round_trip():
    from artrack.messages import (
        pointcloud_msg,
        points_from_pointcloud_msg,
        rosbags_factory,
        stick_from_pose_msg,
        stick_pose_msg,
    )

    f = rosbags_factory()
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    msg = pointcloud_msg(f, pts, 123, "rgbd_optical_frame")
    assert msg.header.frame_id == "rgbd_optical_frame" and msg.width == 100 and msg.point_step == 12
    np.testing.assert_array_equal(points_from_pointcloud_msg(msg), pts.astype(float))
    # a foreign layout: float64 fields, padding, big-endian, two rows, one NaN point
    rec = np.zeros((2, 3), dtype=np.dtype({"names": ["z", "x", "y"], "formats": [">f8", ">f8", ">f8"],
                                           "offsets": [0, 8, 16], "itemsize": 32}))
    rec["x"], rec["y"], rec["z"] = 1.0, 2.0, 3.0
    rec["x"][1, 2] = np.nan
    fields = [f("sensor_msgs/msg/PointField", name=n, offset=o, datatype=8, count=1)
              for n, o in (("z", 0), ("x", 8), ("y", 16))]
    foreign = f("sensor_msgs/msg/PointCloud2", header=msg.header, height=2, width=3, fields=fields,
                is_bigendian=True, point_step=32, row_step=96, data=rec.view(np.uint8).reshape(-1), is_dense=False)
    got = points_from_pointcloud_msg(foreign)
    assert got.shape == (5, 3) and np.all(got == [1.0, 2.0, 3.0])
    bad = f("sensor_msgs/msg/PointCloud2", header=msg.header, height=1, width=100, fields=fields[:2],
            is_bigendian=False, point_step=12, row_step=1200, data=msg.data, is_dense=True)
    with pytest.raises(ValueError, match="'y'"):
        points_from_pointcloud_msg(bad)
    a, b = np.array([0.3, 0.4, 1.2]), np.array([0.1, -0.5, 1.0])
    m = stick_pose_msg(f, a, b, 5, "world")
    a2, b2 = stick_from_pose_msg(m, float(np.linalg.norm(a - b)))
    np.testing.assert_allclose(a2, a, atol=1e-12)
    np.testing.assert_allclose(b2, b, atol=1e-12)


def test_config_files_mirror_the_defaults():
    """config/particle_tracker.yaml and config/object_features.yaml hold exactly the defaults."""
    import dataclasses
    from pathlib import Path

    from artrack.config import load_dataclass_yaml
    from artrack.stick_detection import StickDetectorConfig

    cfg_dir = Path(__file__).resolve().parents[1] / "config"
    got = load_dataclass_yaml(cfg_dir / "particle_tracker.yaml", ParticleConfig)
    for fld in dataclasses.fields(ParticleConfig):
        a, b = getattr(got, fld.name), getattr(ParticleConfig(), fld.name)
        assert (list(a) == list(b)) if isinstance(b, tuple) else a == b, fld.name
    got = load_dataclass_yaml(cfg_dir / "object_features.yaml", StickDetectorConfig)
    for fld in dataclasses.fields(StickDetectorConfig):
        a, b = getattr(got, fld.name), getattr(StickDetectorConfig(), fld.name)
        assert (list(a) == list(b)) if isinstance(b, tuple) else a == b, fld.name


def test_stick_detector_finds_the_rendered_stick(body, camera):
    from artrack.stick_detection import detect_stick

    for motion in ("stick_side", "stick_sword"):
        fr = next(generate_stick_scene(motion, seed=4, fps=15.0, duration_s=0.2, camera=camera, body=body))
        det = detect_stick(fr.image)
        uv, _ = camera.project(fr.stick)
        n = np.array([-(uv[1] - uv[0])[1], (uv[1] - uv[0])[0]])
        n /= np.linalg.norm(n)
        assert det is not None and det.pixel_count > 50
        assert abs((det.a_uv - uv[0]) @ n) < 2.0 and abs((det.b_uv - uv[0]) @ n) < 2.0
        # the visible end points: within a few pixels of the projected ends (in either order)
        ends = np.stack([det.a_uv, det.b_uv])
        inside = [p for p in uv if camera.in_image(p[None])[0]]
        for p in inside:
            assert np.linalg.norm(ends - p, axis=1).min() < 6.0
    assert detect_stick(np.zeros((60, 80, 3), np.uint8)) is None


def test_stick2d_end_order_does_not_matter(body, frames, camera):
    f = frames[1]
    uv, _ = camera.project(f.stick)
    runs = []
    for a, b in ((uv[0], uv[1]), (uv[1], uv[0])):
        pf = _filter(body, frames[0], "stick2d", n=60)
        est, _ = pf.step(_points(f, camera), camera.center, Stick2D(a, b, camera))
        runs.append(est)
    np.testing.assert_allclose(runs[0], runs[1], atol=1e-12)


def test_synth_writes_a_stick_scene_bag(tmp_path):
    from artrack.bags import open_bag, read_body_topic
    from artrack.cli import main
    from artrack.messages import points_from_pointcloud_msg, stick_from_pose_msg

    out = tmp_path / "stick.mcap"
    assert main(["synth", "--motion", "stick_sword", "--width", "160", "--height", "120", "--fps", "15",
                 "--duration", "0.2", "--out", str(out), "--quiet"]) == 0
    with open_bag(out) as bag:
        counts = bag.message_counts()
        assert counts["/cameras/rgbd/points"] == counts["/artrack/stick"] == counts["/cameras/rgbd/image_raw"] == 3
        pts = [points_from_pointcloud_msg(m) for _, _, m in bag.messages(["/cameras/rgbd/points"])]
        sticks = [stick_from_pose_msg(m, stick_length("stick_sword")) for _, _, m in bag.messages(["/artrack/stick"])]
    assert all(len(p) > 100 and np.all(p[:, 2] > 0.5) for p in pts)      # optical frame, in front
    th, st = stick_trajectory("stick_sword", 15.0, 3)
    np.testing.assert_allclose(np.array(sticks), st, atol=1e-9)
    assert len(read_body_topic(out, "/artrack/ground_truth").stamps) == 3
    assert main(["synth", "--motion", "stick_nope", "--out", str(tmp_path / "x.mcap")]) == 1
