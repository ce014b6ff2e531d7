"""Calibrated cameras: pinhole + OpenCV lens distortion, world -> image.

Used by the feedback projection and the triangulation of ALGORITHMS.md §1
("Inverse observation model", "3-D blobs"); the camera model itself is the
standard OpenCV one (``cv2.projectPoints`` / ``cv2.undistortPoints``).

Convention: OpenCV optical frame (x right, y down, z forward);
``x_cam = R @ X_world + t`` (R, t are cam_from_world, metres). Pixels have
(0, 0) at the centre of the top-left pixel (OpenCV).

Calibration files (``load_calibration`` dispatches on the extension):

* ``.yaml`` / ``.yml`` with a top-level ``cameras:`` list — our rig YAML
  (see ``config/rig_example.yaml``; written by ``save_rig_yaml``);
* ``.yaml`` / ``.yml`` with ``image_width`` — a ROS camera_info YAML
  (camera_calibration_parsers format); extrinsics are the identity unless the
  file carries the optional extra keys ``R`` (3x3, cam_from_world) and ``t`` (3, m);
* ``.toml`` — Pose2Sim ``Calib.toml`` (one table per camera: name, size [w, h],
  matrix, distortions (4 or 5), rotation (Rodrigues, cam_from_world), translation (m));
* ``.qca.txt`` — Qualisys calibration XML, converted as /work/shared/DATA.md states.

Every malformed input raises :class:`artrack.errors.CalibrationError` with one
line naming the file and the missing or bad field.
"""

from __future__ import annotations

import math
import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from .config import parse_yaml, yaml_error_text
from .errors import CalibrationError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: no .toml calibrations
    tomllib = None

__all__ = [
    "Camera",
    "load_calibration",
    "save_rig_yaml",
]

#: Termination of OpenCV's iterative undistortion (rays): enough iterations
#: that rays re-project onto their pixels to ~1e-9 px for ordinary lenses.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def _dist5(values: Any, where: str) -> np.ndarray:
    """Distortion coefficients -> (5,) OpenCV (k1, k2, p1, p2, k3).

    Accepts 0 (no distortion), 4 (k3 = 0), 5, or more coefficients when every one beyond the fifth
    is zero (e.g. an all-zero rational_polynomial tail). ``where`` prefixes errors.
    """
    try:
        d = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{where}: distortion is not a list of numbers ({exc})") from None
    if d.size == 0:  # ROS: an empty D means no distortion
        d = np.zeros(5)
    elif d.size == 4:
        d = np.concatenate([d, [0.0]])
    elif d.size > 5:
        if np.any(d[5:] != 0.0):
            raise CalibrationError(
                f"{where}: distortion has {d.size} coefficients with non-zero terms beyond k3; "
                "only plumb_bob (k1, k2, p1, p2, k3) is supported"
            )
        d = d[:5]
    elif d.size != 5:
        raise CalibrationError(f"{where}: distortion needs 4 or 5 coefficients, got {d.size}")
    if not np.all(np.isfinite(d)):
        raise CalibrationError(f"{where}: distortion has non-finite values")
    return d


@dataclass
class Camera:
    """One calibrated camera.

    K: (3, 3) intrinsics, px; dist: (5,) OpenCV (k1, k2, p1, p2, k3);
    R: (3, 3) and t: (3,) the cam_from_world rigid transform (m).
    width, height: image size, px.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        where = f"camera '{self.name}'"
        try:
            self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
            self.R = np.asarray(self.R, dtype=float).reshape(3, 3)
            self.t = np.asarray(self.t, dtype=float).reshape(3)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: bad K, R or t shape ({exc})") from None
        self.dist = _dist5(self.dist, where)
        self.width = int(self.width)
        self.height = int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"{where}: image size {self.width}x{self.height} is not positive")
        if not (np.all(np.isfinite(self.K)) and np.all(np.isfinite(self.R)) and np.all(np.isfinite(self.t))):
            raise CalibrationError(f"{where}: K, R or t has non-finite values")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CalibrationError(f"{where}: K has non-positive focal length")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-5) or np.linalg.det(self.R) < 0:
            raise CalibrationError(f"{where}: R is not a rotation matrix")

    # ------------------------------------------------------------------ geometry
    @property
    def frame_id(self) -> str:
        """TF frame id of this camera's optical frame."""
        return f"{self.name}_optical_frame"

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in the world frame, m."""
        return -self.R.T @ self.t

    @property
    def rvec(self) -> np.ndarray:
        """(3,) Rodrigues vector of R (cam_from_world), rad."""
        # cv2.Rodrigues: ~50x cheaper than scipy's Rotation (this runs on every projection)
        return cv2.Rodrigues(np.ascontiguousarray(self.R, dtype=float))[0].reshape(3)

    @property
    def cam_from_world(self) -> np.ndarray:
        """(4, 4) homogeneous cam_from_world transform (m)."""
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T

    @property
    def world_from_cam(self) -> np.ndarray:
        """(4, 4) homogeneous world_from_cam transform (m): the optical frame's pose in the world."""
        T = np.eye(4)
        T[:3, :3] = self.R.T
        T[:3, 3] = self.center
        return T

    @property
    def P(self) -> np.ndarray:
        """(3, 4) pinhole projection matrix ``K [R | t]`` (ignores distortion)."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    def _cv_project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """cv2.projectPoints: (N, 3) world -> uv (N, 2) and OpenCV's (2N, 15) Jacobian."""
        pts = np.ascontiguousarray(points_world, dtype=float).reshape(-1, 1, 3)
        uv, J = cv2.projectPoints(pts, self.rvec, self.t, self.K, self.dist)
        return uv.reshape(-1, 2), J

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points into the (distorted) image.

        points_world: (N, 3) m in the world frame (a single (3,) point is taken as N = 1).
        Returns uv: (N, 2) px and depth: (N,) m, the optical-frame z (<= 0: behind the
        camera, where uv is meaningless).
        """
        X = np.asarray(points_world, dtype=float).reshape(-1, 3)
        depth = X @ self.R[2] + self.t[2]
        if X.shape[0] == 0:
            return np.zeros((0, 2)), depth
        uv, _ = self._cv_project(X)
        return uv, depth

    def project_jacobian(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projection and its Jacobian d(uv)/d(X_world), through the lens distortion.

        points_world: (N, 3) m, world frame. Returns uv: (N, 2) px and J: (N, 2, 3) px/m.
        Uses OpenCV's d(uv)/d(tvec) (columns 3:6 of the projectPoints Jacobian):
        since x_cam = R X + t, d(uv)/dX = d(uv)/dt · R.
        """
        X = np.asarray(points_world, dtype=float).reshape(-1, 3)
        if X.shape[0] == 0:
            return np.zeros((0, 2)), np.zeros((0, 2, 3))
        uv, Jcv = self._cv_project(X)
        duv_dt = Jcv[:, 3:6].reshape(-1, 2, 3)
        return uv, duv_dt @ self.R

    def normalized_from_pixel(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (x/z, y/z) of pixels: (N, 2) px -> (N, 2)."""
        uv = np.ascontiguousarray(uv, dtype=float).reshape(-1, 1, 2)
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        xy = cv2.undistortPoints(uv, self.K, self.dist, criteria=_UNDISTORT_CRITERIA)
        return xy.reshape(-1, 2)

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Viewing rays of pixels (lens distortion removed).

        uv: (N, 2) px. Returns origin: (3,) the camera centre (world, m) and
        directions: (N, 3) unit vectors in the world frame.
        """
        xy = self.normalized_from_pixel(uv)
        d_cam = np.hstack([xy, np.ones((xy.shape[0], 1))])
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        return self.center, d_cam @ self.R  # rows of (R.T @ d)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel inside the image grown by ``margin`` px on each side."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        lo = -0.5 - margin
        return (
            (uv[:, 0] >= lo)
            & (uv[:, 0] <= self.width - 0.5 + margin)
            & (uv[:, 1] >= lo)
            & (uv[:, 1] <= self.height - 0.5 + margin)
        )

    def scaled(self, factor: float) -> Camera:
        """The same camera at a working resolution ``factor`` times the calibrated one.

        Image size becomes round(factor * size). With pixel centres at integers
        (OpenCV; what cv2.resize assumes), u' = factor (u + 0.5) - 0.5, so
        fx' = factor fx, cx' = factor (cx + 0.5) - 0.5 (same for y). Distortion
        (in normalised coordinates) and extrinsics are unchanged.
        """
        s = float(factor)
        if not (s > 0 and math.isfinite(s)):
            raise ValueError(f"camera '{self.name}': scale factor must be positive, got {factor}")
        K = self.K.copy()
        K[0, 0] *= s
        K[0, 1] *= s
        K[1, 1] *= s
        K[0, 2] = s * (K[0, 2] + 0.5) - 0.5
        K[1, 2] = s * (K[1, 2] + 0.5) - 0.5
        return Camera(
            self.name,
            max(1, round(self.width * s)),
            max(1, round(self.height * s)),
            K,
            self.dist.copy(),
            self.R.copy(),
            self.t.copy(),
        )

    @classmethod
    def look_at(
        cls,
        name: str,
        width: int,
        height: int,
        K: np.ndarray,
        eye: np.ndarray,
        target: np.ndarray,
        up: np.ndarray = (0.0, 0.0, 1.0),
        dist: np.ndarray | None = None,
    ) -> Camera:
        """Camera at ``eye`` (world, m) whose optical axis points at ``target`` (world, m),
        image x to the right and y down with respect to the world ``up`` direction."""
        eye = np.asarray(eye, dtype=float)
        z = np.asarray(target, dtype=float) - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, np.asarray(up, dtype=float))
        if np.linalg.norm(x) < 1e-9:
            raise ValueError(f"camera '{name}': viewing direction is parallel to up")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.vstack([x, y, z])
        return cls(name, width, height, K, np.zeros(5) if dist is None else dist, R, -R @ eye)

    # ------------------------------------------------------------ ROS interop
    def camera_info_fields(self) -> dict[str, Any]:
        """Fields of a sensor_msgs/CameraInfo for this camera (plain Python lists).

        Returns dict(width, height, distortion_model='plumb_bob', d (5), k (9, row-major),
        r (9, identity: monocular), p (12, ``[K | 0]``)). Extrinsics travel separately
        (``/cameras/<cam>/extrinsics``).
        """
        p = np.hstack([self.K, np.zeros((3, 1))])
        return {
            "width": int(self.width),
            "height": int(self.height),
            "distortion_model": "plumb_bob",
            "d": [float(x) for x in self.dist],
            "k": [float(x) for x in self.K.reshape(-1)],
            "r": [float(x) for x in np.eye(3).reshape(-1)],
            "p": [float(x) for x in p.reshape(-1)],
        }

    @classmethod
    def from_camera_info(
        cls,
        name: str,
        width: int,
        height: int,
        k: Sequence[float],
        d: Sequence[float],
        R: np.ndarray | None = None,
        t: np.ndarray | None = None,
    ) -> Camera:
        """Camera from CameraInfo fields: k (9, row-major K), d (plumb_bob, 4 or 5),
        and the cam_from_world R (3, 3) and t (3,) m (identity / zero when None)."""
        k = np.asarray(k, dtype=float).reshape(-1)
        if k.size != 9:
            raise CalibrationError(f"camera '{name}': camera_info k needs 9 values, got {k.size}")
        return cls(
            name,
            int(width),
            int(height),
            k.reshape(3, 3),
            _dist5(d, f"camera '{name}'"),
            np.eye(3) if R is None else R,
            np.zeros(3) if t is None else t,
        )


# =========================================================================== loaders
def load_calibration(path: str | os.PathLike, *, qca_raw_distortion: bool = False) -> list[Camera]:
    """Load cameras from a calibration file, dispatching on the extension.

    ``.yaml``/``.yml``: rig YAML (top-level ``cameras:``) or ROS camera_info YAML
    (``image_width``); ``.toml``: Pose2Sim Calib.toml; ``.qca.txt``: Qualisys.
    Returns the cameras in file order. Raises CalibrationError (one line naming
    the file and field) on any malformed input.

    qca_raw_distortion: Qualisys only. False (default, DATA.md / Pose2Sim): the
    distortion attributes are divided by 64 like the intrinsics; True: used as
    written (see ``_load_qca``).
    """
    p = Path(path)
    where = str(path)
    if not p.is_file():
        raise CalibrationError(f"{where}: calibration file not found")
    lower = p.name.lower()
    if lower.endswith(".qca.txt"):
        cams = _load_qca(p, where, raw_distortion=qca_raw_distortion)
    elif lower.endswith((".yaml", ".yml")):
        cams = _load_yaml(p, where)
    elif lower.endswith(".toml"):
        cams = _load_toml(p, where)
    else:
        raise CalibrationError(
            f"{where}: unknown calibration format (expected .yaml, .yml, .toml or .qca.txt)"
        )
    if not cams:
        raise CalibrationError(f"{where}: no cameras found")
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CalibrationError(f"{where}: duplicate camera name(s) {', '.join(dup)}")
    return cams


def _field(d: Any, key: str, where: str, what: str) -> Any:
    if not isinstance(d, dict) or key not in d or d[key] is None:
        raise CalibrationError(f"{where}: {what} has no field '{key}'")
    return d[key]


def _array(value: Any, shape: tuple[int, ...], where: str, what: str, key: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {what} field '{key}' is not numeric") from None
    if a.size != int(np.prod(shape)):
        raise CalibrationError(f"{where}: {what} field '{key}' has {a.size} values, expected shape {shape}")
    a = a.reshape(shape)
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{where}: {what} field '{key}' has non-finite values")
    return a


def _int(value: Any, where: str, what: str, key: str) -> int:
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {what} field '{key}' is not a number") from None
    if not f.is_integer() or f <= 0:
        raise CalibrationError(f"{where}: {what} field '{key}' must be a positive integer, got {value}")
    return int(f)


def _make_camera(where: str, what: str, **kw: Any) -> Camera:
    """Build a Camera, re-labelling its validation errors with the file name."""
    try:
        return Camera(**kw)
    except CalibrationError as exc:
        msg = str(exc)
        prefix = f"camera '{kw['name']}': "
        msg = msg.removeprefix(prefix)
        raise CalibrationError(f"{where}: {what} {msg}") from None


def _load_yaml(p: Path, where: str) -> list[Camera]:
    try:
        data = parse_yaml(p.read_text())
    except UnicodeDecodeError:
        raise CalibrationError(f"{where}: not valid YAML (not a text file, not UTF-8)") from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{where}: not valid YAML ({yaml_error_text(exc)})") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{where}: expected a mapping with 'cameras' or 'image_width' at top level")
    if "cameras" in data:
        return _rig_from_dict(data, where)
    if "image_width" in data:
        return [_camera_info_from_dict(data, where, default_name=p.name.split(".")[0])]
    raise CalibrationError(f"{where}: file has no field 'cameras' (rig YAML) or 'image_width' (camera_info)")


def _rig_from_dict(data: dict, where: str) -> list[Camera]:
    cams_raw = data["cameras"]
    if not isinstance(cams_raw, list):
        raise CalibrationError(f"{where}: field 'cameras' must be a list")
    cams = []
    for i, c in enumerate(cams_raw):
        if not isinstance(c, dict):
            raise CalibrationError(f"{where}: cameras[{i}] is not a mapping")
        what = f"cameras[{i}]"
        name = str(_field(c, "name", where, what))
        what = f"camera '{name}'"
        cams.append(
            _make_camera(
                where,
                what,
                name=name,
                width=_int(_field(c, "width", where, what), where, what, "width"),
                height=_int(_field(c, "height", where, what), where, what, "height"),
                K=_array(_field(c, "K", where, what), (3, 3), where, what, "K"),
                dist=_array(_field(c, "dist", where, what), (5,), where, what, "dist"),
                R=_array(_field(c, "R", where, what), (3, 3), where, what, "R"),
                t=_array(_field(c, "t", where, what), (3,), where, what, "t"),
            )
        )
    return cams


def _matrix_field(d: dict, key: str, where: str, what: str, shape: tuple[int, int]) -> np.ndarray:
    """camera_calibration_parsers matrix ``{rows, cols, data}`` -> array of ``shape``."""
    m = _field(d, key, where, what)
    data = _field(m, "data", where, f"{what} field '{key}'")
    return _array(data, shape, where, what, key)


def _camera_info_from_dict(data: dict, where: str, default_name: str) -> Camera:
    name = str(data.get("camera_name") or default_name)
    what = f"camera '{name}'"
    width = _int(_field(data, "image_width", where, what), where, what, "image_width")
    height = _int(_field(data, "image_height", where, what), where, what, "image_height")
    K = _matrix_field(data, "camera_matrix", where, what, (3, 3))
    model = str(data.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CalibrationError(
            f"{where}: {what} field 'distortion_model' is '{model}', only plumb_bob is supported"
        )
    dm = _field(data, "distortion_coefficients", where, what)
    d = _dist5(_field(dm, "data", where, f"{what} field 'distortion_coefficients'"), f"{where}: {what}")
    R = np.eye(3) if data.get("R") is None else _array(data["R"], (3, 3), where, what, "R")
    t = np.zeros(3) if data.get("t") is None else _array(data["t"], (3,), where, what, "t")
    return _make_camera(where, what, name=name, width=width, height=height, K=K, dist=d, R=R, t=t)


def _load_toml(p: Path, where: str) -> list[Camera]:
    if tomllib is None:
        raise CalibrationError(f"{where}: reading .toml calibrations needs Python >= 3.11 (tomllib)")
    try:
        data = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{where}: not valid TOML ({exc})") from None
    from scipy.spatial.transform import Rotation  # lazy: scipy.spatial is slow to import

    cams = []
    for key, c in data.items():
        if key == "metadata" or not isinstance(c, dict):
            continue
        what = f"camera '{key}'"
        name = str(_field(c, "name", where, what))
        what = f"camera '{name}'"
        size = _array(_field(c, "size", where, what), (2,), where, what, "size")
        if c.get("fisheye", False):
            raise CalibrationError(
                f"{where}: {what} field 'fisheye' is true; fisheye lenses are not supported"
            )
        K = _array(_field(c, "matrix", where, what), (3, 3), where, what, "matrix")
        d = _dist5(_field(c, "distortions", where, what), f"{where}: {what} field 'distortions'")
        rvec = _array(_field(c, "rotation", where, what), (3,), where, what, "rotation")
        t = _array(_field(c, "translation", where, what), (3,), where, what, "translation")
        cams.append(
            _make_camera(
                where,
                what,
                name=name,
                width=_int(size[0], where, what, "size[0]"),
                height=_int(size[1], where, what, "size[1]"),
                K=K,
                dist=d,
                R=Rotation.from_rotvec(rvec).as_matrix(),
                t=t,
            )
        )
    return cams


#: Qualisys camera axes (x right, y up, looking along -z) -> OpenCV optical axes.
_OPENCV_FROM_QUALISYS = np.diag([1.0, -1.0, -1.0])


def _load_qca(p: Path, where: str, raw_distortion: bool = False) -> list[Camera]:
    """Qualisys .qca.txt -> cameras, exactly as /work/shared/DATA.md states.

    fx = focalLengthU/64, fy = focalLengthV/64, cx = centerPointU/64 - fov_video.left,
    cy = centerPointV/64 - fov_video.top; size from fov_video (right-left+1, bottom-top+1);
    distortion (k1, k2, p1, p2, k3) = (radialDistortion1, radialDistortion2,
    tangentalDistortion1, tangentalDistortion2, radialDistortion3) / 64 (as Pose2Sim's
    converter; < 0.05 px from the raw values); M = [[r11 r12 r13], [r21 ...], ...]
    row-major with X_qcam = M (X_world - C), C = (x, y, z) mm; R = diag(1, -1, -1) M,
    t = -R C / 1000.

    ``raw_distortion=True`` skips the division by 64 of the distortion. On the
    Pose2Sim demo cameras the two differ by < 0.6 px within 300 px of the principal
    point, 1.5-1.8 px median over the image and 5-9 px in the corners; free
    checkerboard calibrations of those cameras (the wheel's intrinsics images, same
    focal length) give k1 = -0.03..-0.05, i.e. close to the raw values.
    """
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise CalibrationError(f"{where}: not valid XML ({exc})") from None
    nodes = root.findall("cameras/camera")
    if not nodes:
        raise CalibrationError(f"{where}: no <cameras><camera> elements")

    def num(elem: ET.Element | None, attr: str, what: str, tag: str) -> float:
        if elem is None:
            raise CalibrationError(f"{where}: {what} has no element '{tag}'")
        v = elem.get(attr)
        if v is None:
            raise CalibrationError(f"{where}: {what} has no field '{tag}.{attr}'")
        try:
            f = float(v)
        except ValueError:
            raise CalibrationError(f"{where}: {what} field '{tag}.{attr}' is not a number: {v!r}") from None
        if not math.isfinite(f):
            raise CalibrationError(f"{where}: {what} field '{tag}.{attr}' is not finite")
        return f

    cams = []
    for i, node in enumerate(nodes):
        if node.get("active", "1") == "0":
            continue
        name = node.get("serial")
        if not name:
            raise CalibrationError(f"{where}: camera #{i + 1} has no field 'serial'")
        what = f"camera '{name}'"
        fov = node.find("fov_video")
        left, right = num(fov, "left", what, "fov_video"), num(fov, "right", what, "fov_video")
        top, bottom = num(fov, "top", what, "fov_video"), num(fov, "bottom", what, "fov_video")
        intr = node.find("intrinsic")
        fx = num(intr, "focalLengthU", what, "intrinsic") / 64.0
        fy = num(intr, "focalLengthV", what, "intrinsic") / 64.0
        cx = num(intr, "centerPointU", what, "intrinsic") / 64.0 - left
        cy = num(intr, "centerPointV", what, "intrinsic") / 64.0 - top
        k3 = 0.0
        if intr is not None and intr.get("radialDistortion3") is not None:
            k3 = num(intr, "radialDistortion3", what, "intrinsic")
        dist = np.array(
            [
                num(intr, "radialDistortion1", what, "intrinsic"),
                num(intr, "radialDistortion2", what, "intrinsic"),
                num(intr, "tangentalDistortion1", what, "intrinsic"),
                num(intr, "tangentalDistortion2", what, "intrinsic"),
                k3,
            ]
        ) / (1.0 if raw_distortion else 64.0)
        tr = node.find("transform")
        M = np.array([[num(tr, f"r{r}{c}", what, "transform") for c in (1, 2, 3)] for r in (1, 2, 3)])
        C_mm = np.array([num(tr, a, what, "transform") for a in ("x", "y", "z")])
        R = _OPENCV_FROM_QUALISYS @ M
        t = -R @ C_mm / 1000.0
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        cams.append(
            _make_camera(
                where,
                what,
                name=name,
                width=round(right - left + 1),
                height=round(bottom - top + 1),
                K=K,
                dist=dist,
                R=R,
                t=t,
            )
        )
    return cams


# =========================================================================== saving
def _rig_dict(cameras: Iterable[Camera]) -> dict[str, Any]:
    return {
        "cameras": [
            {
                "name": c.name,
                "width": int(c.width),
                "height": int(c.height),
                "K": c.K.tolist(),
                "dist": c.dist.tolist(),
                "R": c.R.tolist(),
                "t": c.t.tolist(),
            }
            for c in cameras
        ]
    }


def save_rig_yaml(cameras: Iterable[Camera], path: str | os.PathLike) -> None:
    """Write cameras as our rig YAML (``load_calibration`` reads it back exactly).

    Written to a temporary file in the same directory, then renamed, so a failure
    leaves no half-written file. Floats are written with full (repr) precision.
    """
    p = Path(path)
    text = (
        "# artrack rig calibration: x_cam = R @ X_world + t (OpenCV optical frame, metres);\n"
        "# K (3x3 px), dist (k1, k2, p1, p2, k3).\n"
        + yaml.safe_dump(_rig_dict(cameras), sort_keys=False, default_flow_style=None, width=200)
    )
    p.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
