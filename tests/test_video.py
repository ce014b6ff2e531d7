"""Video input: synchronised MP4s, calibration size checks (incl. the Qualisys 8-px case), scaling."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from artrack.cameras import Camera
from artrack.errors import InputError
from artrack.video import open_videos


def _camera(name: str, w: int, h: int) -> Camera:
    K = np.array([[1.1 * w, 0.0, w / 2 - 0.5], [0.0, 1.1 * w, h / 2 - 0.5], [0.0, 0.0, 1.0]])
    return Camera(name, w, h, K)


def _level(cam_index: int, frame: int) -> int:
    return 30 + 60 * frame + 15 * cam_index


def _write_mp4(path: Path, w: int, h: int, n: int, fps: float, cam_index: int) -> Path:
    """Flat grey frames whose level encodes (camera, frame), plus a white right-hand column."""
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    assert vw.isOpened()
    for i in range(n):
        img = np.full((h, w, 3), _level(cam_index, i), np.uint8)
        img[:, -2:] = 255
        vw.write(img)
    vw.release()
    return path


def test_synchronised_frames_and_stamps(tmp_path):
    paths = [_write_mp4(tmp_path / f"cam{i}.mp4", 64, 48, 4 if i == 0 else 3, 25.0, i) for i in range(2)]
    cams = [_camera("cam01", 64, 48), _camera("cam02", 64, 48)]
    videos = open_videos(paths, cams)
    assert videos.fps == pytest.approx(25.0)
    assert all(a is b for a, b in zip(videos.cameras, cams, strict=True))
    frames = list(videos)
    assert [i for i, _, _ in frames] == [0, 1, 2]  # stops with the shortest video
    assert [s for _, s, _ in frames] == [0, 40_000_000, 80_000_000]
    for i, _, images in frames:
        assert list(images) == ["cam01", "cam02"]
        for k, name in enumerate(images):
            img = images[name]
            assert img.shape == (48, 64, 3) and img.dtype == np.uint8
            assert abs(float(np.median(img[:, :40])) - _level(k, i)) <= 4
    assert len(list(videos)) == 3  # re-iterable
    # mapping form + options
    v2 = open_videos({"cam02": paths[1]}, cams, fps=50.0, start_stamp_ns=10, max_frames=2)
    got = list(v2)
    assert [s for _, s, _ in got] == [10, 20_000_010]
    assert list(got[0][2]) == ["cam02"]


def test_qualisys_narrow_video_is_padded(tmp_path):
    path = _write_mp4(tmp_path / "narrow.mp4", 56, 48, 2, 30.0, 0)
    cam = _camera("cam03", 64, 48)  # calibrated 8 px wider than the video
    videos = open_videos([path], [cam])
    np.testing.assert_array_equal(videos.cameras[0].K, cam.K)
    _, _, images = next(iter(videos))
    img = images["cam03"]
    assert img.shape == (48, 64, 3)
    assert img[:, 56:].min() > 200  # the right edge column replicated
    too_narrow = _write_mp4(tmp_path / "narrower.mp4", 54, 48, 2, 30.0, 0)
    with pytest.raises(InputError, match=r"narrower.mp4: video is 54x48 but camera 'cam03' .* for 64x48"):
        open_videos([too_narrow], [cam])


def test_size_mismatch_and_scaling(tmp_path):
    path = _write_mp4(tmp_path / "a.mp4", 64, 48, 2, 30.0, 1)
    with pytest.raises(InputError, match=r"a.mp4: video is 64x48 but camera 'big' is calibrated for 128x96"):
        open_videos([path], [_camera("big", 128, 96)])
    with pytest.raises(InputError, match="a.mp4: video is 64x48 but camera 'wide' is calibrated for 64x40"):
        open_videos([path], [_camera("wide", 64, 40)])
    cam = _camera("cam01", 64, 48)
    with pytest.raises(InputError, match="pass the calibrated cameras"):
        open_videos([path], [cam.scaled(0.5)], 0.5)
    videos = open_videos([path], [cam], scale=0.5)
    wc = videos.cameras[0]
    assert (wc.width, wc.height) == (32, 24)
    np.testing.assert_allclose(wc.K, cam.scaled(0.5).K)
    _, _, images = next(iter(videos))
    assert images["cam01"].shape == (24, 32, 3)
    assert abs(float(np.median(images["cam01"][:, :20])) - _level(1, 0)) <= 4


def test_bad_inputs(tmp_path):
    path = _write_mp4(tmp_path / "a.mp4", 64, 48, 2, 30.0, 0)
    other = _write_mp4(tmp_path / "b.mp4", 64, 48, 2, 24.0, 0)
    cam = _camera("cam01", 64, 48)
    with pytest.raises(InputError, match=r"video for unknown camera 'cam07' \(calibration has: cam01\)"):
        open_videos({"cam07": path}, [cam])
    with pytest.raises(InputError, match=r"missing.mp4: video file not found \(camera 'cam01'\)"):
        open_videos([tmp_path / "missing.mp4"], [cam])
    with pytest.raises(InputError, match="2 video file.*one per camera"):
        open_videos([path, path], [cam])
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    with pytest.raises(InputError, match="junk.mp4: cannot open video"):
        open_videos([tmp_path / "junk.mp4"], [cam])
    with pytest.raises(InputError, match="b.mp4: frame rate 24 differs"):
        open_videos([path, other], [cam, _camera("cam02", 64, 48)])
    assert open_videos([path, other], [cam, _camera("cam02", 64, 48)], fps=30.0).fps == 30.0
    with pytest.raises(InputError, match="scale"):
        open_videos([path], [cam], scale=0.0)


# ------------------------------------------------------------------ real data (Pose2Sim demo)
def _pose2sim_demo() -> Path:
    import os

    return (Path(os.environ.get("ARTRACK_CACHE", Path(__file__).resolve().parents[1] / ".cache"))
            / "pose2sim/Pose2Sim/Demo_SinglePerson")


@pytest.mark.skipif(not (_pose2sim_demo() / "calibration/Calib.qca.txt").is_file(),
                    reason="Pose2Sim demo data missing: run scripts/fetch_pose2sim.sh (make test does)")
def test_real_four_camera_recording_decodes_at_the_calibrated_size():
    """The real Qualisys recording (portrait 1080x1920, 60 fps): each video matches its
    camera's calibrated size, frames come synchronised, scaled, and hold a real picture."""
    from artrack.cameras import load_calibration

    demo = _pose2sim_demo()
    cams = load_calibration(demo / "calibration/Calib.qca.txt")
    videos = open_videos([demo / f"videos/{c.name}.mp4" for c in cams], cams, 0.25, max_frames=3)
    assert videos.fps == pytest.approx(60.0, abs=0.5)
    # calibrated 1088x1920 (Qualisys fov_video; the videos are 1080 wide, the 8-px case), scaled
    assert [(c.width, c.height) for c in cams] == [(1088, 1920)] * 4
    assert [(c.width, c.height) for c in videos.cameras] == [(272, 480)] * 4
    frames = list(videos)
    assert len(frames) == 3
    for index, stamp, images in frames:
        assert stamp == videos.stamp_ns(index)
        assert sorted(images) == [c.name for c in cams]
        for img in images.values():
            assert img.shape == (480, 272, 3) and img.dtype == np.uint8
            assert float(img.std()) > 10.0  # a real scene, not a blank frame
