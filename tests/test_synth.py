"""Tests of artrack.motion (scripted poses) and artrack.synth (rig, renderer, scenes)."""

from __future__ import annotations

import numpy as np
import pytest

from artrack import motion
from artrack.body_model import load_body_model
from artrack.errors import ArtrackError
from artrack.synth import (
    OTHER_PERSON_LABEL,
    Renderer,
    SceneConfig,
    default_rig,
    generate_scene,
    render,
)


@pytest.fixture(scope="module")
def body():
    return load_body_model()


@pytest.fixture(scope="module")
def small_rig():
    return default_rig(4, 320, 240)


@pytest.fixture(scope="module")
def label_renderer(body, small_rig):
    return Renderer(body, small_rig, seed=0)


# ---------------------------------------------------------------- motion
def test_motion_names_and_unknown():
    names = motion.motion_names()
    for n in ("default", "self_occlusion", "line", "rotation", "distractor"):
        assert n in names
    with pytest.raises(ArtrackError, match="unknown motion 'moonwalk'"):
        motion.pose_at("moonwalk", 0.0)


@pytest.mark.parametrize("name", ["default", "self_occlusion", "distractor"])
def test_motion_limits_floor_smoothness(body, name):
    dt = 1.0 / 60.0
    ts = np.arange(0.0, 10.0, dt)
    theta = motion.trajectory(name, ts, body)
    assert theta.shape == (len(ts), body.n_dof)
    assert np.all(body.within_limits(theta))
    # feet on the floor (soft contact: lowest sole point within a centimetre of z = 0)
    idx, pts = motion._sole_points(body)
    soles = body.transform_points(body.forward_kinematics(theta), idx, pts)[..., 2]
    assert np.all(np.abs(soles.min(axis=1)) < 0.01)
    # smooth: bounded joint accelerations and jerk, no jumps anywhere
    J = body.joint_positions(theta)
    acc = np.linalg.norm(np.diff(J, 2, axis=0), axis=-1) / dt**2
    jerk = np.linalg.norm(np.diff(J, 3, axis=0), axis=-1) / dt**3
    assert acc.max() < 60.0
    assert jerk.max() < 1200.0
    if name != "distractor":
        assert np.all(np.linalg.norm(theta[:, :2], axis=1) < 1.5)


def test_default_contains_walk_wave_reach(body):
    jn = body.joint_names
    J = lambda t: dict(zip(jn, body.joint_positions(motion.pose_at("default", t, body)), strict=True))  # noqa: E731
    # walking: the pelvis travels and returns to the origin facing +x
    assert np.linalg.norm(J(2.5)["pelvis"][:2]) > 0.8
    assert np.linalg.norm(J(motion.T_WALK_END)["pelvis"][:2]) < 0.05
    # waving: both wrists above the head
    w = J(6.2)
    assert w["l_wrist"][2] > w["head"][2] + 0.2 and w["r_wrist"][2] > w["head"][2] + 0.2
    # reaching: right wrist on the left of the body (y > 0 facing +x), then back
    r = J(8.7)
    assert r["r_wrist"][1] > r["pelvis"][1] + 0.1
    assert J(9.99)["r_wrist"][1] < J(9.99)["pelvis"][1] - 0.15


def test_line_motion(body):
    ts = np.linspace(0.0, motion.LINE_PERIOD_S, 41)
    W = body.joint_positions(motion.trajectory("line", ts, body))[:, body.joint_names.index("r_wrist")]
    a, b = W.min(axis=0), W.max(axis=0)
    d = (b - a) / np.linalg.norm(b - a)
    off = (W - W[0]) - np.outer((W - W[0]) @ d, d)
    assert np.abs(off).max() < 0.002  # on a straight line
    path = np.linalg.norm(np.diff(W, axis=0), axis=1).sum()
    assert path / motion.LINE_PERIOD_S == pytest.approx(0.3, rel=0.05)


def test_rotation_motion(body):
    ts = np.linspace(0.0, motion.CIRCLE_PERIOD_S, 30, endpoint=False)
    W = body.joint_positions(motion.trajectory("rotation", ts, body))[:, body.joint_names.index("r_wrist")]
    c = W.mean(axis=0)
    r = np.linalg.norm(W - c, axis=1)
    assert r == pytest.approx(np.full_like(r, motion.CIRCLE_RADIUS), abs=0.003)


def test_distractor_passes_near_target(body):
    ts = np.arange(0.0, 10.0, 0.1)
    tgt = motion.trajectory("default", ts, body)[:, :2]
    dis = motion.trajectory("distractor", ts, body)[:, :2]
    dmin = np.linalg.norm(tgt - dis, axis=1).min()
    assert 0.5 < dmin < 1.6


def test_self_occlusion_hides_hand_in_two_views(body, label_renderer):
    hand = body.link_index("r_hand") + 1
    ts = np.arange(4.5, 8.0, 0.1)
    hidden = []
    for t in ts:
        _, labels = label_renderer.render(motion.pose_at("self_occlusion", t, body), noise_sigma=0.0,
                                          labels=True)
        counts = np.array([(lab == hand).sum() for lab in labels])
        hidden.append(np.sum(counts < 0.1 * 30) >= 2)  # ~30 px of hand at 320x240 when visible
    hidden = np.array(hidden)
    assert hidden.sum() * 0.1 >= 0.9
    # and the hand is visible in 3+ views before and after
    theta = motion.pose_at("self_occlusion", 4.5, body)
    _, labels = label_renderer.render(theta, noise_sigma=0.0, labels=True)
    assert sum((lab == hand).sum() > 10 for lab in labels) >= 3


# ---------------------------------------------------------------- synth
def test_default_rig():
    cams = default_rig()
    assert [c.name for c in cams] == ["cam01", "cam02", "cam03", "cam04"]
    for c in cams:
        assert (c.width, c.height) == (640, 480)
        assert 450 < c.K[0, 0] < 550
        assert c.dist[0] == pytest.approx(-0.05, abs=0.01)
        r = np.linalg.norm(c.center[:2])
        assert 3.5 < r < 4.5 and 1.5 <= c.center[2] <= 2.0
        uv, depth = c.project(np.array([[0.0, 0.0, 0.9]]))
        assert depth[0] > 0
        assert abs(uv[0, 0] - 320) < 60 and abs(uv[0, 1] - 240) < 60
    assert len({tuple(np.round(c.center, 3)) for c in cams}) == 4
    assert [c.name for c in default_rig(12, 160, 120)][-1] == "cam12"


def test_fewer_than_four_cameras_stand_at_the_first_corners_of_the_ring():
    """Two or three cameras are the first corners of the 4-camera rig (the same poses), so two
    cameras look at the person 90° apart instead of facing each other along one line (where a
    point's two rays meet at grazing angles); more than four spread evenly round the ring."""
    four = default_rig(4, 320, 240)
    for n in (1, 2, 3):
        for c, c4 in zip(default_rig(n, 320, 240), four[:n], strict=True):
            np.testing.assert_allclose(c.center, c4.center, atol=1e-12)
            np.testing.assert_allclose(c.R, c4.R, atol=1e-12)
    a, b = (np.arctan2(c.center[1], c.center[0]) for c in default_rig(2, 320, 240))
    assert np.degrees(abs(b - a)) == pytest.approx(90.0, abs=1e-6)
    axes = [c.R[2] for c in default_rig(2, 320, 240)]  # optical axes
    assert abs(float(axes[0] @ axes[1])) < 0.2, "not facing each other"
    six = default_rig(6, 320, 240)
    gaps = np.diff(np.unwrap([np.arctan2(c.center[1], c.center[0]) for c in six]))
    np.testing.assert_allclose(np.degrees(gaps), 60.0, atol=1e-6)


def test_render_person_in_every_view(body, small_rig, label_renderer):
    theta = motion.pose_at("default", 0.0, body)
    imgs, labels = label_renderer.render(theta, noise_sigma=0.0, labels=True)
    assert len(imgs) == 4
    for cam, img, lab in zip(small_rig, imgs, labels, strict=True):
        assert img.shape == (240, 320, 3) and img.dtype == np.uint8
        bg = label_renderer.background(cam)
        person = lab > 0
        assert 1500 < person.sum() < 8000
        # the person changes the pixels, the background is textured (not uniform)
        assert np.abs(img.astype(int) - bg).sum(axis=2)[person].mean() > 20
        assert bg.reshape(-1, 3).std(axis=0).min() > 10
        # head and both hands are labelled in every view at the start (standing, facing +x)
        for name in ("head", "torso", "l_thigh"):
            assert (lab == body.link_index(name) + 1).sum() > 20
    # distractor pixels get their own label
    _, labels = label_renderer.render(theta, [motion.pose_at("distractor", 5.0, body)], noise_sigma=0.0,
                                      labels=True)
    assert any((lab == OTHER_PERSON_LABEL).sum() > 500 for lab in labels)


def test_render_noise_seeded(body, small_rig):
    theta = motion.pose_at("rest", 0.0, body)
    a = render(body, theta, small_rig, seed=1, noise_sigma=3.0, frame_index=5)
    b = render(body, theta, small_rig, seed=1, noise_sigma=3.0, frame_index=5)
    c = render(body, theta, small_rig, seed=1, noise_sigma=3.0, frame_index=6)
    clean = render(body, theta, small_rig, seed=1, noise_sigma=0.0)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0])
    diff = a[0].astype(float) - clean[0]
    assert 2.0 < diff.std() < 4.0


def test_generate_scene_deterministic_and_ground_truth(body):
    cfg = SceneConfig(width=160, height=120, fps=10.0, duration_s=0.3, seed=4, distractor=True)
    f1 = list(generate_scene(cfg, body))
    f2 = list(generate_scene(cfg, body))
    assert len(f1) == 3
    for a, b in zip(f1, f2, strict=True):
        assert a.index == b.index and a.stamp_ns == b.stamp_ns
        assert a.images.keys() == b.images.keys() == {"cam01", "cam02", "cam03", "cam04"}
        assert all(np.array_equal(a.images[k], b.images[k]) for k in a.images)
        assert np.array_equal(a.theta, b.theta)
    assert f1[1].stamp_ns - f1[0].stamp_ns == 100_000_000
    fr = f1[2]
    assert fr.joints.shape == (15, 3)
    assert np.allclose(fr.joints, body.joint_positions(fr.theta))
    assert [b.label for b in fr.blobs3d] == body.blob_labels
    assert len(fr.extra_thetas) == 1
    other = list(generate_scene(SceneConfig(width=160, height=120, fps=10.0, duration_s=0.1, seed=5), body))
    assert not np.array_equal(other[0].images["cam01"], f1[0].images["cam01"])
    assert SceneConfig(occlusion=True).motion_name == "self_occlusion"


def test_empty_start_shows_the_room_then_the_person(body, tmp_path):
    """SceneConfig.empty_s: the room is empty (no ground truth) until the person appears, and
    the motion's clock starts then, so a background model can learn a clean room first."""
    from artrack.bags import read_scene, write_scene_bag
    from artrack.motion import pose_at
    from artrack.synth import scene_cameras

    cfg = SceneConfig(width=160, height=120, fps=10.0, duration_s=0.5, seed=4, motion="line", empty_s=0.2)
    frames = list(generate_scene(cfg, body))
    assert [f.theta is None for f in frames] == [True, True, False, False, False]
    room = Renderer(body, scene_cameras(cfg), cfg.seed).render(None, (), 0.0)
    person = Renderer(body, scene_cameras(cfg), cfg.seed).render(pose_at("line", 0.0, body), (), 0.0)
    for f in frames[:2]:  # the empty room, up to noise
        assert np.abs(f.images["cam01"].astype(int) - room[0]).mean() < 3.0
    assert np.abs(person[0].astype(int) - room[0]).max() > 100  # the person would show
    np.testing.assert_allclose(frames[2].theta, pose_at("line", 0.0, body))
    np.testing.assert_allclose(frames[4].theta, pose_at("line", 0.2, body))
    path = tmp_path / "empty.mcap"
    write_scene_bag(path, scene_cameras(cfg), frames, joint_names=body.joint_names)
    scene = read_scene(path)
    assert scene.n_frames == 5
    assert list(scene.truth.stamps) == [f.stamp_ns for f in frames[2:]]


def test_blackout_shows_the_empty_room_and_keeps_the_truth(body):
    """SceneConfig.blackout (artrack synth --blackout START:SECONDS): every camera sees the empty room
    in [START, START + SECONDS) while the person goes on moving and the ground truth is kept."""
    from artrack.synth import scene_cameras

    cfg = SceneConfig(width=160, height=120, fps=10.0, duration_s=0.5, seed=4, motion="line", blackout=(0.2, 0.2))
    assert [cfg.blacked_out(i) for i in range(5)] == [False, False, True, True, False]
    frames = list(generate_scene(cfg, body))
    plain = list(generate_scene(SceneConfig(width=160, height=120, fps=10.0, duration_s=0.5, seed=4, motion="line"),
                                body))
    room = Renderer(body, scene_cameras(cfg), cfg.seed).render(None, (), 0.0)
    for f, p in zip(frames, plain, strict=True):
        np.testing.assert_allclose(f.joints, p.joints)  # the truth goes on through the blackout
        same = all(np.array_equal(f.images[c], p.images[c]) for c in f.images)
        # the room up to pixel noise (sigma 2) everywhere; the person would differ by > 100 somewhere
        empty = max(np.abs(f.images[c].astype(int) - r).max() for c, r in zip(f.images, room, strict=True)) < 30
        assert (same, empty) == ((False, True) if cfg.blacked_out(f.index) else (True, False)), f.index
