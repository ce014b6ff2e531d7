"""Ground-truth-free checks: reference foreground, model silhouettes, IoU, joints inside, speeds."""

from __future__ import annotations

import numpy as np

from artrack.body_model import load_body_model
from artrack.cameras import Camera
from artrack.silhouette import (
    BodySilhouette,
    iou,
    joint_speeds,
    joints_inside,
    reference_foreground,
    shifted_iou,
    tolerant_overlap,
)
from artrack.synth import Renderer, default_rig
from artrack.types import BodyEstimate, LinkEstimate


def test_reference_foreground_finds_a_moving_square_without_ghosts():
    rng = np.random.default_rng(0)
    room = rng.integers(0, 255, (40, 80, 3), dtype=np.uint8)
    frames, truth = [], []
    for t in range(60):
        img = room.copy()
        x = t  # the square moves 1 px per frame across the room
        img[10:20, x:x + 10] = (0, 200, 0)
        m = np.zeros((40, 80), bool)
        m[10:20, x:x + 10] = True
        frames.append({"cam": img})
        truth.append(m)
    refs = reference_foreground(frames, block=10, min_gap=15, open_px=1)
    for t in (0, 30, 59):
        assert iou(refs[t]["cam"], truth[t]) > 0.95  # where it is, and no ghost where it was


def test_iou_inside_and_speeds():
    a = np.zeros((10, 10), bool)
    a[:5] = True
    b = np.zeros((10, 10), bool)
    b[2:7] = True
    assert iou(a, b) == 30 / 70
    assert iou(np.zeros((3, 3), bool), np.zeros((3, 3), bool)) == 1.0
    cam = Camera("c", 100, 100, np.array([[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]]))
    mask = np.zeros((100, 100), bool)
    mask[40:60, 40:60] = True
    J = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [np.nan, 0, 0], [0.0, 0.0, -2.0]])
    np.testing.assert_array_equal(joints_inside(cam, J, mask), [True, False, False, False])
    stamps = np.array([0, 100_000_000, 200_000_000])
    joints = np.zeros((3, 2, 3))
    joints[1, 0, 0] = 0.5
    joints[2, 0, 0] = 0.5
    joints[2, 1] = np.nan
    s = joint_speeds(stamps, joints)
    np.testing.assert_allclose(s[:, 0], [5.0, 0.0])
    assert s[0, 1] == 0.0 and np.isnan(s[1, 1])


def test_tolerant_overlap_and_shifted_iou():
    """A 10 x 10 square against the same square 2 px to the right: strict IoU 80 / 120; within 2 px
    every pixel of each lies near the other, within 1 px 90 %; the shifted IoU is that same 80 / 120.
    A model pixel far from the reference counts against the first share only."""
    a = np.zeros((20, 30), bool)
    a[5:15, 5:15] = True
    b = np.zeros((20, 30), bool)
    b[5:15, 7:17] = True
    assert iou(a, b) == shifted_iou(a, 2) == 80 / 120
    assert tolerant_overlap(b, a, 2) == (1.0, 1.0)
    np.testing.assert_allclose(tolerant_overlap(b, a, 1), (0.9, 0.9))
    assert tolerant_overlap(b, a, 0) == (0.8, 0.8)
    far = b.copy()
    far[0, 29] = True
    on, covered = tolerant_overlap(far, a, 2)
    assert on == 100 / 101 and covered == 1.0
    assert tolerant_overlap(np.zeros_like(a), a, 2) == (1.0, 0.0)
    assert shifted_iou(a, 0) == 1.0 and shifted_iou(a, 30) == 0.0


def test_body_silhouette_matches_the_renderer_at_the_same_pose():
    """Masks from an estimate's link poses equal the synthetic renderer's labels at that pose."""
    body = load_body_model()
    cams = default_rig(2, 160, 120)
    theta = body.rest_pose()
    T = body.forward_kinematics(theta)
    links = [LinkEstimate(n, T[i, :3, 3], T[i, :3, :3]) for i, n in enumerate(body.link_names)]
    est = BodyEstimate(0, list(body.joint_names), body.joint_positions(theta), links, [])
    masks = BodySilhouette(body, cams).masks(est)
    _, labels = Renderer(body, cams).render(theta, noise_sigma=0.0, labels=True)
    for c, lab in zip(cams, labels, strict=True):
        assert masks[c.name].any()
        assert iou(masks[c.name], lab > 0) > 0.99
    assert BodySilhouette(body, cams).masks(BodyEstimate(0, [], np.zeros((0, 3)), [], [])) is None
