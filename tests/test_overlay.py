"""Overlay drawing: projected skeleton, blob / prior ellipses, montage, MP4, `artrack overlay`."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from artrack.bags import read_scene, write_scene_bag
from artrack.cameras import Camera
from artrack.errors import InputError
from artrack.overlay import (
    BONES,
    TRUTH_COLOR,
    draw_body,
    montage,
    render_overlay,
    write_montage_png,
    write_mp4,
)
from artrack.types import OFF_IMAGE, Blob2D, Prior2D

NAMES = ["pelvis", "thorax", "head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
         "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle"]  # fmt: skip


def _camera(w: int = 160, h: int = 120) -> Camera:
    K = np.array([[1.5 * w, 0, (w - 1) / 2], [0, 1.5 * w, (h - 1) / 2], [0, 0, 1.0]])
    return Camera.look_at("cam01", w, h, K, eye=[4.0, 0.0, 1.0], target=[0.0, 0.0, 1.0])


def _skeleton() -> np.ndarray:
    """(15, 3) a standing T-ish pose facing +x, world m."""
    p = {
        "pelvis": [0, 0, 1.0], "thorax": [0, 0, 1.4], "head": [0, 0, 1.7],
        "l_shoulder": [0, 0.2, 1.4], "l_elbow": [0, 0.45, 1.4], "l_wrist": [0, 0.7, 1.4],
        "r_shoulder": [0, -0.2, 1.4], "r_elbow": [0, -0.45, 1.4], "r_wrist": [0, -0.7, 1.4],
        "l_hip": [0, 0.1, 0.95], "l_knee": [0, 0.1, 0.5], "l_ankle": [0, 0.1, 0.08],
        "r_hip": [0, -0.1, 0.95], "r_knee": [0, -0.1, 0.5], "r_ankle": [0, -0.1, 0.08],
    }  # fmt: skip
    return np.array([p[n] for n in NAMES], dtype=float)


def _near(img: np.ndarray, uv, color, radius: int = 1, tol: int = 40) -> bool:
    u, v = int(round(uv[0])), int(round(uv[1]))
    patch = img[max(0, v - radius) : v + radius + 1, max(0, u - radius) : u + radius + 1]
    patch = patch.reshape(-1, 3).astype(int)
    return bool((np.abs(patch - np.array(color)).max(axis=1) <= tol).any())


def test_draw_body_skeleton():
    cam = _camera()
    img = np.full((120, 160, 3), 40, np.uint8)
    joints = _skeleton()
    out = draw_body(img, cam, joints, NAMES, color=(0, 220, 0), frame=12)
    assert out is not img and img.max() == 40  # input untouched
    uv, _ = cam.project(joints)
    idx = {n: i for i, n in enumerate(NAMES)}
    for a, b in BONES:  # bone midpoints in the (left/centre) or darker (right) colour
        if np.linalg.norm(uv[idx[a]] - uv[idx[b]]) < 12:
            continue  # short bones are covered by the joint dots
        mid = (uv[idx[a]] + uv[idx[b]]) / 2
        col = (0, 121, 0) if b.startswith("r_") else (0, 220, 0)
        assert _near(out, mid, col), (a, b)
    assert (out[:20, :60] > 200).any()  # the camera name / frame label
    # NaN joints and joints behind the camera are skipped, not drawn at garbage places
    bad = joints.copy()
    bad[idx["head"]] = np.nan
    bad[idx["l_wrist"]] = [10.0, 0.7, 1.4]  # behind the camera (x > 4)
    out2 = draw_body(img, cam, bad, NAMES, color=(0, 220, 0), camera_label="")
    assert not _near(out2, (uv[idx["thorax"]] + uv[idx["head"]]) / 2 + [0, -3], (0, 220, 0), radius=0)
    assert _near(out2, (uv[idx["l_shoulder"]] + uv[idx["l_elbow"]]) / 2, (0, 220, 0))
    with pytest.raises(ValueError, match="15 joints for 3 joint names"):
        draw_body(img, cam, joints, NAMES[:3])


def test_blob_and_prior_ellipses():
    cam = _camera()
    img = np.zeros((120, 160, 3), np.uint8)
    cov = np.array([[100.0, 0.0], [0.0, 9.0]])  # sigma 10 px along u, 3 px along v
    blob = Blob2D("head", np.array([80.0, 60.0]), cov)
    out = draw_body(img, cam, None, [], blobs2d=[blob], camera_label="")
    lit = out.max(axis=2) > 60
    assert lit[60, 99:102].any() and lit[60, 58:62].any()  # 2 sigma = 20 px on either side
    assert not lit[60, 108:].any()  # nothing at 3 sigma
    assert lit[53:55, 80].any() or lit[54:57, 80].any()  # 2 sigma = 6 px up
    # priors: dashed (only part of the ring lit), off-image ones skipped
    prior = Prior2D("head", np.array([80.0, 60.0]), np.array([[400.0, 0.0], [0.0, 400.0]]), 0.9)
    out = draw_body(img, cam, None, [], priors=[prior], camera_label="")
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    ring = out[np.round(60 + 40 * np.sin(t)).astype(int) % 120, np.round(80 + 40 * np.cos(t)).astype(int)]
    frac = (ring.max(axis=1) > 60).mean()
    assert 0.3 < frac < 0.85, frac
    hidden = Prior2D("head", np.array([80.0, 60.0]), np.eye(2) * 400, 0.9, visibility=OFF_IMAGE)
    assert draw_body(img, cam, None, [], priors=[hidden], camera_label="").max() == 0


def test_montage_and_files(tmp_path):
    a = np.full((20, 30, 3), 50, np.uint8)
    b = np.full((40, 60, 3), 150, np.uint8)  # resized to the first tile's size
    c = np.full((20, 30), 250, np.uint8)  # grey -> BGR
    m = montage([a, b, c], cols=2)
    assert m.shape == (40, 60, 3)
    assert m[5, 5, 0] == 50 and m[5, 35, 0] == 150 and m[25, 5, 0] == 250 and m[25, 35, 0] == 0
    assert montage([a], cols=5).shape == (20, 30, 3)
    with pytest.raises(ValueError):
        montage([], 2)
    png = write_montage_png([a, b], tmp_path / "m" / "x.png", cols=1)
    assert cv2.imread(str(png)).shape == (40, 30, 3)

    frames = [np.full((48, 64, 3), 20 * i, np.uint8) for i in range(5)]
    assert write_mp4(iter(frames), tmp_path / "v.mp4", fps=10) == 5
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 5 and cap.get(cv2.CAP_PROP_FPS) == pytest.approx(10)
    cap.release()
    with pytest.raises(InputError, match="empty.mp4: no frames"):
        write_mp4(iter([]), tmp_path / "empty.mp4")

    def boom():
        yield frames[0]
        raise RuntimeError("render failed")

    with pytest.raises(RuntimeError):
        write_mp4(boom(), tmp_path / "half.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m", "v.mp4"]  # nothing half-written


def test_render_overlay(tmp_path):
    cams = [_camera(), Camera.look_at("cam02", 160, 120, _camera().K, [0.0, 4.0, 1.2], [0.0, 0.0, 1.0])]
    rng = np.random.default_rng(0)
    frames = [
        SimpleNamespace(stamp_ns=1000 + i * 33_333_333, joints=_skeleton() + [0.02 * i, 0, 0],
                        images={c.name: rng.integers(0, 60, (120, 160, 3), dtype=np.uint8) for c in cams})
        for i in range(4)
    ]
    write_scene_bag(tmp_path / "s.mcap", cams, frames, joint_names=NAMES)
    scene = read_scene(tmp_path / "s.mcap")
    truth = scene.truth
    pred = (truth.stamps + 1000, NAMES, truth.joints + 0.03)
    png = render_overlay(scene, pred, tmp_path / "o.png", cols=2)
    img = cv2.imread(str(png))
    assert img.shape == (120, 320, 3)
    green = (np.abs(img.astype(int) - TRUTH_COLOR).max(axis=2) < 40).sum()
    magenta = ((img[..., 0] > 200) & (img[..., 2] > 200) & (img[..., 1] < 120)).sum()
    assert green > 100 and magenta > 100
    assert render_overlay(scene, None, tmp_path / "o.mp4", frames="1:3").is_file()
    cap = cv2.VideoCapture(str(tmp_path / "o.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 2
    cap.release()
    render_overlay(scene, None, tmp_path / "last.png", frames="-1")
    with pytest.raises(InputError, match="outside the 4 frames"):
        render_overlay(scene, None, tmp_path / "x.png", frames="9")
    with pytest.raises(InputError, match="expected an index"):
        render_overlay(scene, None, tmp_path / "x.png", frames="a-b")
    with pytest.raises(InputError, match=r"x.gif: output must end in .png or .mp4"):
        render_overlay(scene, None, tmp_path / "x.gif")
