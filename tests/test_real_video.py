"""The real Qualisys recording (Pose2Sim Demo_SinglePerson, /work/shared/DATA.md) on a short,
downscaled excerpt: the calibration conversion proved by reprojection of a point triangulated
across the four views, the working-resolution intrinsics, and automatic start-up of tracking."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from artrack.cameras import Camera, load_calibration
from artrack.silhouette import colour_marker, marker_centre, triangulate_point
from artrack.video import open_videos

REPO = Path(__file__).resolve().parents[1]
DEMO = Path(os.environ.get("ARTRACK_CACHE", REPO / ".cache")) / "pose2sim/Pose2Sim/Demo_SinglePerson"
CALIB = DEMO / "calibration/Calib.qca.txt"
needs_demo = pytest.mark.skipif(not CALIB.is_file(),
                                reason="Pose2Sim demo data missing: run scripts/fetch_pose2sim.sh (make test does)")

#: quarter resolution (272x480): the excerpt stays cheap
SCALE = 0.25
#: frames of the excerpt used for the calibration check (0.0, 0.67 and 1.33 s into the clip)
CHECK_FRAMES = (0, 40, 80)


def _videos(scale: float = SCALE, max_frames: int | None = None):
    cams = load_calibration(CALIB)
    return open_videos([DEMO / f"videos/{c.name}.mp4" for c in cams], cams, scale, max_frames=max_frames)


#: the man's cyan cap: hue 84..100 (OpenCV 0..180), saturation >= 120; the blue mats (hue ~108)
#: and everything else fall outside
CAP_LOW, CAP_HIGH = (84, 120, 60), (100, 255, 255)


def _cap_centre(image_bgr: np.ndarray) -> np.ndarray:
    """Pixel centroid of the man's cyan cap (the largest region in the cap's HSV range)."""
    uv = marker_centre(image_bgr, CAP_LOW, CAP_HIGH)
    assert uv is not None, "no cyan pixels"
    return uv


def _triangulate(cameras: list[Camera], uv: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint of the four viewing rays and each view's reprojection error (camera order), px."""
    X, errors = triangulate_point(cameras, uv)
    return X, np.array([errors[c.name] for c in cameras])


@pytest.fixture(scope="module")
def cap_observations():
    videos = _videos(max_frames=max(CHECK_FRAMES) + 1)
    obs = [{name: _cap_centre(img) for name, img in images.items()}
           for index, _, images in videos if index in CHECK_FRAMES]
    return videos.cameras, obs


@needs_demo
def test_calibration_conversion_reprojects_a_triangulated_point(cap_observations):
    """The cap, triangulated from all four views, reprojects within 4 px RMS at quarter
    resolution (16 px at full: DATA.md's 8-17 px for this calibration), sits 1.4-1.9 m above
    the treadmill's top (z = 0), and the same check rejects plausible conversion mistakes."""
    cameras, obs = cap_observations

    def rms(cams: list[Camera]) -> tuple[float, list[np.ndarray]]:
        errs, points = [], []
        for uv in obs:
            X, e = _triangulate(cams, uv)
            errs.append(e)
            points.append(X)
        return float(np.sqrt(np.mean(np.square(errs)))), points

    good, points = rms(cameras)
    assert good < 4.0
    for X in points:
        assert 1.4 < X[2] < 1.9  # a cap on a standing man, metres above the treadmill
        assert np.hypot(X[0], X[1]) < 2.0  # on the plate, near the origin
    # Mistakes the check must catch: Qualisys axes used as OpenCV axes (no diag(1, -1, -1)),
    # the rotation transposed, the focal length off by 5 %.
    flip = np.diag([1.0, -1.0, -1.0])

    def variant(make) -> list[Camera]:
        out = []
        for c in cameras:
            R, t = make(flip @ c.R, c.center)
            out.append(Camera(c.name, c.width, c.height, c.K, c.dist, R, t))
        return out

    assert rms(variant(lambda M, C: (M, -M @ C)))[0] > 20.0
    assert rms(variant(lambda M, C: (flip @ M.T, -(flip @ M.T) @ C)))[0] > 20.0
    focal = [Camera(c.name, c.width, c.height, np.diag([1 / 1.05, 1 / 1.05, 1.0]) @ c.K, c.dist, c.R, c.t)
             for c in cameras]
    assert rms(focal)[0] > 1.5 * good


@needs_demo
def test_working_resolution_scales_the_intrinsics(cap_observations):
    """At half resolution the cap centre found in the downscaled image is where the scaled
    camera projects the point triangulated at quarter resolution (the intrinsics follow the
    image; the residual is the calibration's, not the scaling's)."""
    cameras, obs = cap_observations
    X, e_quarter = _triangulate(cameras, obs[0])
    half = _videos(0.5, max_frames=1)
    (_, _, images), = list(half)
    for c in half.cameras:
        assert (c.width, c.height) == (544, 960)
        uv = c.project(X[None])[0][0]
        err = np.linalg.norm(uv - _cap_centre(images[c.name]))
        quarter_err = float(e_quarter[[k.name for k in cameras].index(c.name)])
        assert err < 2.0 * quarter_err + 3.0  # ~2x the quarter-scale residual, in half-scale px


@needs_demo
def test_bag_from_videos_writes_compressed_images_and_camera_info(tmp_path):
    """`artrack bag-from-videos` on a 3-frame excerpt: CompressedImage + CameraInfo (scaled
    intrinsics) + extrinsics per camera, stamped index / 60 fps, readable as a scene."""
    from artrack.bags import open_bag, read_scene
    from artrack.cli import main

    out = tmp_path / "excerpt.mcap"
    videos = [str(DEMO / f"videos/cam0{i}.mp4") for i in range(1, 5)]
    assert main(["bag-from-videos", "--videos", *videos, "--calib", str(CALIB), "--scale", str(SCALE),
                 "--max-frames", "3", "--out", str(out), "--quiet"]) == 0
    with open_bag(out) as bag:
        topics = bag.topics()
    for name in ("cam01", "cam02", "cam03", "cam04"):
        assert topics[f"/cameras/{name}/image_raw/compressed"] == "sensor_msgs/msg/CompressedImage"
        assert topics[f"/cameras/{name}/camera_info"] == "sensor_msgs/msg/CameraInfo"
        assert topics[f"/cameras/{name}/extrinsics"] == "geometry_msgs/msg/TransformStamped"
    scene = read_scene(out)
    expected = _videos(max_frames=3)
    for got, want in zip(scene.cameras, expected.cameras, strict=True):
        assert (got.name, got.width, got.height) == (want.name, 272, 480)
        np.testing.assert_allclose(got.K, want.K, rtol=1e-12)
        np.testing.assert_allclose(got.R, want.R, atol=1e-12)
        np.testing.assert_allclose(got.t, want.t, atol=1e-12)
    frames = list(scene.frames())
    assert [s for s, _ in frames] == [0, 16_666_667, 33_333_333]
    for (_, images), (_, _, raw) in zip(frames, expected, strict=True):
        for name, img in images.items():
            assert img.shape == (480, 272, 3)
            assert np.abs(img.astype(int) - raw[name]).mean() < 4.0  # JPEG of the same picture
    # bad input: one line naming the file, exit 1, nothing written
    assert main(["bag-from-videos", "--videos", *videos[:2], "--calib", str(tmp_path / "none.qca.txt"),
                 "--out", str(tmp_path / "bad.mcap")]) == 1
    assert not (tmp_path / "bad.mcap").exists()


@needs_demo
def test_tracking_starts_automatically_on_the_person():
    """With the recording's config file (config/pose2sim_demo.yaml) and no hand-given pose, the
    closed loop starts tracking within the first 20 frames, and the body it starts from is on
    the man: its head joint (the head's centre) within 0.3 m of the cyan cap triangulated
    independently (the cap's centroid sits ~0.12 m above the head's centre), its pelvis within
    0.35 m of the cap horizontally (he stands upright) and 0.6-1.2 m above the treadmill."""
    from artrack.body_model import load_body_model
    from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config

    videos = _videos(max_frames=20)
    body = load_body_model()
    config = load_pipeline_config(fps=videos.fps, blob_config=str(REPO / "config" / "pose2sim_demo.yaml"))
    pipe = ClosedLoopPipeline(body, videos.cameras, config)
    for _, stamp, images in videos:
        est = pipe.step(stamp, images).estimate
        if est.links:
            break
    else:
        pytest.fail("no estimate within the first 20 frames")
    cap, errors = colour_marker(videos.cameras, images, CAP_LOW, CAP_HIGH)
    assert cap is not None and len(errors) == 4
    head = est.joints[body.joint_names.index("head")]
    pelvis = est.joints[body.joint_names.index("pelvis")]
    assert np.linalg.norm(head - cap) < 0.3
    assert np.linalg.norm(pelvis[:2] - cap[:2]) < 0.35
    assert 0.6 < pelvis[2] < 1.2


@needs_demo
@pytest.mark.parametrize("camera", ["cam01", "cam02", "cam03", "cam04"])
def test_tracking_starts_from_one_camera(camera):
    """One camera alone (config/skeleton.yaml's few_cameras settings: depth from the floor and an
    upright trunk) starts on the man within the first 20 frames too: the pelvis within 0.35 m
    horizontally of the cap that the four views triangulate (0.06-0.26 m at the first estimate)
    and 0.6-1.2 m above the treadmill. (Its head is 0.2-0.8 m from the cap then: depth along
    the head's ray is what one view cannot see.)"""
    from artrack.body_model import load_body_model
    from artrack.pipeline import ClosedLoopPipeline, load_pipeline_config

    videos = _videos(max_frames=20)
    body = load_body_model()
    config = load_pipeline_config(fps=videos.fps, blob_config=str(REPO / "config" / "pose2sim_demo.yaml"))
    pipe = ClosedLoopPipeline(body, [c for c in videos.cameras if c.name == camera], config)
    for _, stamp, images in videos:
        est = pipe.step(stamp, {camera: images[camera]}).estimate
        if est.links:
            break
    else:
        pytest.fail(f"no estimate from {camera} alone within the first 20 frames")
    cap, _ = colour_marker(videos.cameras, images, CAP_LOW, CAP_HIGH)
    assert cap is not None
    pelvis = est.joints[body.joint_names.index("pelvis")]
    assert np.linalg.norm(pelvis[:2] - cap[:2]) < 0.35
    assert 0.6 < pelvis[2] < 1.2


@needs_demo
def test_an_unknown_tracking_camera_is_one_line_and_exit_1():
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(REPO / "bench" / "real_video.py"), "--demo", str(DEMO), "--max-frames",
                          "2", "--track-cameras", "cam09", "--quiet"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("real_video: --track-cameras: no camera 'cam09'"), out.stderr
