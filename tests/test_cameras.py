"""Camera model and calibration loaders (artrack.cameras)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from artrack.cameras import Camera, load_calibration, save_rig_yaml
from artrack.errors import CalibrationError

REPO = Path(__file__).resolve().parents[1]
DIST = np.array([-0.12, 0.05, 0.0005, -0.0003, 0.01])
K_EXAMPLE = np.array([[900.0, 0.0, 639.5], [0.0, 910.0, 359.5], [0.0, 0.0, 1.0]])


def ring_cameras(n: int = 4, dist: np.ndarray = DIST) -> list[Camera]:
    """n cameras on a 4 m ring, 2.2 m high, looking at (0, 0, 1)."""
    cams = []
    for i in range(n):
        a = math.radians(45 + 360 / n * i)
        eye = [4 * math.cos(a), 4 * math.sin(a), 2.2]
        cams.append(Camera.look_at(f"cam{i + 1:02d}", 1280, 720, K_EXAMPLE, eye, [0, 0, 1.0], dist=dist))
    return cams


def random_points(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform([-0.8, -0.8, 0.2], [0.8, 0.8, 1.9], size=(n, 3))


# ------------------------------------------------------------------- geometry
def test_project_matches_pinhole_without_distortion():
    rng = np.random.default_rng(1)
    cam = ring_cameras(dist=np.zeros(5))[0]
    X = random_points(rng, 50)
    uv, depth = cam.project(X)
    x_cam = X @ cam.R.T + cam.t
    np.testing.assert_allclose(depth, x_cam[:, 2], atol=1e-12)
    u = cam.K[0, 0] * x_cam[:, 0] / x_cam[:, 2] + cam.K[0, 2]
    v = cam.K[1, 1] * x_cam[:, 1] / x_cam[:, 2] + cam.K[1, 2]
    np.testing.assert_allclose(uv, np.c_[u, v], atol=1e-9)
    # look_at: the target lands on the principal point, camera centre is the eye.
    uv0, _ = cam.project([0, 0, 1.0])
    np.testing.assert_allclose(uv0[0], cam.K[:2, 2], atol=1e-9)
    np.testing.assert_allclose(cam.center, [2 * math.sqrt(2), 2 * math.sqrt(2), 2.2], atol=1e-12)


def test_project_behind_camera_has_negative_depth_and_empty_input():
    cam = ring_cameras()[0]
    _, depth = cam.project(2 * cam.center)  # behind: the camera looks inwards
    assert depth[0] < 0
    uv, depth = cam.project(np.zeros((0, 3)))
    assert uv.shape == (0, 2) and depth.shape == (0,)


def test_jacobian_matches_finite_differences_with_distortion():
    rng = np.random.default_rng(2)
    for cam in ring_cameras(dist=np.array([-0.3, 0.12, 0.002, -0.003, -0.02])):
        X = random_points(rng, 20)
        uv, J = cam.project_jacobian(X)
        np.testing.assert_allclose(uv, cam.project(X)[0], atol=1e-12)
        h = 1e-6
        J_fd = np.empty_like(J)
        for k in range(3):
            dX = np.zeros(3)
            dX[k] = h
            J_fd[:, :, k] = (cam.project(X + dX)[0] - cam.project(X - dX)[0]) / (2 * h)
        np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-4)


def test_rays_reproject_onto_the_same_pixels():
    rng = np.random.default_rng(3)
    for cam in ring_cameras():
        uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(200, 2))
        origin, dirs = cam.rays(uv)
        np.testing.assert_allclose(origin, cam.center, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
        for s in (0.5, 3.0):
            uv2, depth = cam.project(origin + s * dirs)
            assert np.all(depth > 0)
            np.testing.assert_allclose(uv2, uv, atol=1e-6)


def test_scaled_camera_projects_to_resized_pixels():
    rng = np.random.default_rng(4)
    cam = ring_cameras()[1]
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (640, 360)
    X = random_points(rng, 30)
    uv, _ = cam.project(X)
    uv_half, _ = half.project(X)
    np.testing.assert_allclose(uv_half, 0.5 * (uv + 0.5) - 0.5, atol=1e-9)
    np.testing.assert_allclose(half.R, cam.R)
    np.testing.assert_allclose(half.dist, cam.dist)


def test_camera_info_fields_round_trip():
    cam = ring_cameras()[2]
    f = cam.camera_info_fields()
    assert f["distortion_model"] == "plumb_bob" and len(f["d"]) == 5 and len(f["k"]) == 9
    assert len(f["r"]) == 9 and len(f["p"]) == 12 and (f["width"], f["height"]) == (1280, 720)
    back = Camera.from_camera_info(cam.name, f["width"], f["height"], f["k"], f["d"], cam.R, cam.t)
    for a in ("K", "dist", "R", "t"):
        np.testing.assert_array_equal(getattr(back, a), getattr(cam, a))
    assert back.frame_id == "cam03_optical_frame"


def test_invalid_camera_values_raise():
    with pytest.raises(CalibrationError, match="not a rotation"):
        Camera("bad", 10, 10, np.eye(3), R=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(CalibrationError, match="distortion"):
        Camera("bad", 10, 10, np.eye(3), dist=[0.1, 0.2, 0.3])


# ------------------------------------------------------------------- loaders
def _assert_same_cameras(a: list[Camera], b: list[Camera], atol: float = 0.0) -> None:
    assert [c.name for c in a] == [c.name for c in b]
    for ca, cb in zip(a, b, strict=True):
        assert (ca.width, ca.height) == (cb.width, cb.height)
        for f in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(ca, f), getattr(cb, f), atol=atol, rtol=0)


def test_rig_yaml_round_trip(tmp_path):
    cams = ring_cameras()
    path = tmp_path / "sub" / "rig.yaml"
    save_rig_yaml(cams, path)
    _assert_same_cameras(load_calibration(path), cams)  # exact: floats written with repr
    assert not [p for p in path.parent.iterdir() if p.name != "rig.yaml"]  # no temp file left


def test_example_rig_loads():
    cams = load_calibration(REPO / "config" / "rig_example.yaml")
    assert [c.name for c in cams] == ["cam01", "cam02", "cam03", "cam04"]
    for c in cams:
        uv, depth = c.project([0.0, 0.0, 1.0])
        assert depth[0] > 4 and np.allclose(uv[0], c.K[:2, 2], atol=0.5)


def test_ros_camera_info_yaml(tmp_path):
    path = tmp_path / "left.yaml"
    path.write_text(
        "image_width: 640\n"
        "image_height: 480\n"
        "camera_name: narrow_stereo\n"
        "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 319.5, 0, 505, 239.5, 0, 0, 1]\n"
        "distortion_model: plumb_bob\n"
        "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.2, 0.05, 0.001, 0.002, 0.0]\n"
        "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
        "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [500, 0, 319.5, 0, 0, 505, 239.5, 0, 0, 0, 1, 0]\n"
    )
    (cam,) = load_calibration(path)
    assert cam.name == "narrow_stereo" and (cam.width, cam.height) == (640, 480)
    np.testing.assert_array_equal(cam.K, [[500, 0, 319.5], [0, 505, 239.5], [0, 0, 1]])
    np.testing.assert_array_equal(cam.dist, [-0.2, 0.05, 0.001, 0.002, 0.0])
    np.testing.assert_array_equal(cam.R, np.eye(3))
    np.testing.assert_array_equal(cam.t, np.zeros(3))


def test_pose2sim_toml(tmp_path):
    rvec = np.array([1.9, -0.4, 0.3])
    t = np.array([0.1, 0.9, 4.2])
    path = tmp_path / "Calib.toml"
    path.write_text(
        '[cam_1]\nname = "cam01"\nsize = [ 1088.0, 1920.0]\n'
        "matrix = [ [ 1681.2, 0.0, 532.9], [ 0.0, 1681.0, 948.1], [ 0.0, 0.0, 1.0]]\n"
        "distortions = [ -0.04, 0.13, 0.0006, 0.0007]\n"
        f"rotation = [ {rvec[0]}, {rvec[1]}, {rvec[2]}]\n"
        f"translation = [ {t[0]}, {t[1]}, {t[2]}]\nfisheye = false\n\n"
        "[metadata]\nadjusted = false\nerror = 0.0\n"
    )
    (cam,) = load_calibration(path)
    assert cam.name == "cam01" and (cam.width, cam.height) == (1088, 1920)
    np.testing.assert_allclose(cam.R, Rotation.from_rotvec(rvec).as_matrix(), atol=1e-15)
    np.testing.assert_array_equal(cam.t, t)
    np.testing.assert_array_equal(cam.dist, [-0.04, 0.13, 0.0006, 0.0007, 0.0])
    np.testing.assert_allclose(cam.rvec, rvec, atol=1e-12)


QCA_TEMPLATE = """<?xml version='1.0' encoding='ASCII'?>
<calibration type="regular">
  <cameras>
    <camera active="1" model="none" serial="camA" viewrotation="0">
      <fov_video bottom="1919" left="8" right="1095" top="0"/>
      <transform r11="{M[0][0]}" r12="{M[0][1]}" r13="{M[0][2]}" r21="{M[1][0]}" r22="{M[1][1]}"
                 r23="{M[1][2]}" r31="{M[2][0]}" r32="{M[2][1]}" r33="{M[2][2]}"
                 x="{C[0]}" y="{C[1]}" z="{C[2]}"/>
      <intrinsic centerPointU="34110.5" {fu} focalLengthV="107588.8" radialDistortion1="-0.046"
                 radialDistortion2="0.14" radialDistortion3="0.0" skew="0.0"
                 tangentalDistortion1="0.0006" tangentalDistortion2="0.0007" centerPointV="60680.8"/>
    </camera>
  </cameras>
</calibration>
"""


def _qca_text(fu: str = 'focalLengthU="107599.7"') -> tuple[str, np.ndarray, np.ndarray]:
    M = Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix()
    C = np.array([1460.2, -1909.2, 1896.5])
    return QCA_TEMPLATE.format(M=M.tolist(), C=C.tolist(), fu=fu), M, C


def test_qualisys_qca(tmp_path):
    text, M, C = _qca_text()
    path = tmp_path / "Calib.qca.txt"
    path.write_text(text)
    (cam,) = load_calibration(path)
    assert cam.name == "camA" and (cam.width, cam.height) == (1088, 1920)
    np.testing.assert_allclose(
        cam.K, [[107599.7 / 64, 0, 34110.5 / 64 - 8], [0, 107588.8 / 64, 60680.8 / 64], [0, 0, 1]], rtol=1e-15
    )
    np.testing.assert_allclose(cam.dist, np.array([-0.046, 0.14, 0.0006, 0.0007, 0.0]) / 64, rtol=1e-15)
    np.testing.assert_allclose(cam.R, np.diag([1.0, -1.0, -1.0]) @ M, atol=1e-15)
    np.testing.assert_allclose(cam.center, C / 1000, atol=1e-12)
    # A point on the Qualisys camera's -z axis (its viewing direction) is in front, on the principal ray.
    X = C / 1000 + M.T @ np.array([0.0, 0.0, -2.0])
    uv, depth = cam.project(X)
    assert depth[0] == pytest.approx(2.0)
    np.testing.assert_allclose(uv[0], cam.K[:2, 2], atol=1e-9)
    (raw,) = load_calibration(path, qca_raw_distortion=True)
    np.testing.assert_allclose(raw.dist, cam.dist * 64, rtol=1e-15)


# ------------------------------------------------------------------- errors
def _one_line_error(path: Path) -> str:
    with pytest.raises(CalibrationError) as info:
        load_calibration(path)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    return msg


def test_missing_field_errors_name_file_and_field(tmp_path):
    toml = tmp_path / "calib.toml"
    toml.write_text(
        '[cam02]\nname = "cam02"\nsize = [ 1088.0, 1920.0]\ndistortions = [0.0, 0.0, 0.0, 0.0]\n'
        "rotation = [0.0, 0.0, 0.0]\ntranslation = [0.0, 0.0, 1.0]\n"
    )
    assert _one_line_error(toml).endswith("calib.toml: camera 'cam02' has no field 'matrix'")

    rig = tmp_path / "rig.yaml"
    save_rig_yaml(ring_cameras(2), rig)
    rig.write_text(rig.read_text().replace("  K:\n", "  Kx:\n", 1))
    assert _one_line_error(rig).endswith("rig.yaml: camera 'cam01' has no field 'K'")

    qca = tmp_path / "x.qca.txt"
    qca.write_text(_qca_text(fu="")[0])
    assert _one_line_error(qca).endswith("x.qca.txt: camera 'camA' has no field 'intrinsic.focalLengthU'")

    info = tmp_path / "info.yaml"
    info.write_text("image_width: 640\nimage_height: 480\ncamera_name: c\n")
    assert _one_line_error(info).endswith("info.yaml: camera 'c' has no field 'camera_matrix'")


def test_bad_values_and_formats_raise_one_line(tmp_path):
    rig = tmp_path / "rig.yaml"
    save_rig_yaml(ring_cameras(1), rig)
    rig.write_text(rig.read_text().replace("width: 1280", "width: -3"))
    assert "field 'width'" in _one_line_error(rig)

    bad_r = tmp_path / "bad_r.yaml"
    cam = ring_cameras(1)[0]
    save_rig_yaml([cam], bad_r)
    bad_r.write_text(bad_r.read_text().replace(repr(float(cam.R[0, 0])), "3.0", 1))
    assert "R is not a rotation" in _one_line_error(bad_r)

    for name, text in [
        ("broken.yaml", "cameras: [\n"),
        ("empty.yaml", "something: 1\n"),
        ("broken.toml", "[cam\n"),
        ("broken.qca.txt", "<calibration><cameras>"),
        ("calib.json", "{}"),
    ]:
        p = tmp_path / name
        p.write_text(text)
        _one_line_error(p)
    _one_line_error(tmp_path / "does_not_exist.yaml")


# ------------------------------------------------------------------- real data (Pose2Sim demo)
QCA_REAL = (
    Path(os.environ.get("ARTRACK_CACHE", REPO / ".cache"))
    / "pose2sim/Pose2Sim/Demo_SinglePerson/calibration/Calib.qca.txt"
)


@pytest.mark.skipif(not QCA_REAL.is_file(), reason=f"{QCA_REAL} missing: run scripts/fetch_pose2sim.sh")
def test_real_qualisys_calibration_is_sane():
    cams = load_calibration(QCA_REAL)
    assert [c.name for c in cams] == ["cam01", "cam02", "cam03", "cam04"]
    # cam01 intrinsics as DATA.md states (1/64 px, fov_video offsets 0).
    c1 = cams[0]
    np.testing.assert_allclose(
        c1.K,
        [[107599.671875 / 64, 0, 34110.316406 / 64], [0, 107588.828125 / 64, 60680.792969 / 64], [0, 0, 1]],
        rtol=1e-12,
    )
    np.testing.assert_allclose(c1.center, [1.4602323709212087, -1.9091590482454608, 1.8965058524092062])
    # Pose2Sim's converter chain (R transposed, world_to_camera_persp, rotate_cam pi about x).
    import xml.etree.ElementTree as ET

    nodes = ET.parse(QCA_REAL).getroot().findall("cameras/camera")
    for cam, node in zip(cams, nodes, strict=True):
        tr = node.find("transform")
        M = np.array([[float(tr.get(f"r{r}{c}")) for c in "123"] for r in "123"])
        C = np.array([float(tr.get(a)) for a in "xyz"]) / 1000
        r_read = M.reshape(3, 3).T  # read_qca: "by-column to by-line"
        r, t = r_read.T, -r_read.T @ C  # world_to_camera_persp
        rx = np.diag([1.0, -1.0, -1.0])  # rotate_cam(ang_x=pi)
        np.testing.assert_allclose(cam.R, rx @ r, atol=1e-15)
        np.testing.assert_allclose(cam.t, rx @ t, atol=1e-14)
    for cam in cams:
        assert (cam.width, cam.height) == (1088, 1920)
        assert 2.5 < np.linalg.norm(cam.center) < 6.0  # metres from the origin
        assert 1.0 < cam.center[2] < 3.0  # above the floor, below the ceiling
        assert cam.R[2] @ np.array([0.0, 0.0, 1.0]) < -0.2  # optical axis looks down
        # Treadmill origin and points 1 m / 1.8 m above it are in every image, in front.
        uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.8]]))
        assert np.all(depth > 2.0) and np.all(cam.in_image(uv))
        assert uv[0, 1] > uv[1, 1] > uv[2, 1]  # up in the world is up in the (upright, portrait) image
