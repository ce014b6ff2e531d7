"""Conversion between core data (artrack.types, Camera) and ROS messages.

One adapter serves both worlds: the live graph passes rclpy message classes,
the offline pipeline and the bag tools pass rosbags' pure-Python classes. Both
accept every field as a keyword, so each converter builds messages through a
:class:`MsgFactory` that maps a type name (``"artrack_msgs/msg/TrackedBody"``)
to a class. Nothing here imports rclpy.

Stamps are integer nanoseconds; all float fields are float64 on the wire, so a
round trip is exact (tested), which is what lets the live graph and
``artrack track`` agree to the last bit.
"""

from __future__ import annotations

import array
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from .cameras import Camera
from .errors import CalibrationError
from .types import BEHIND_CAMERA, Blob2D, Blob3D, BodyEstimate, LinkEstimate, Prior2D, all_finite

WORLD_FRAME = "world"


class MsgFactory:
    """Builds messages by type name from a class lookup (rclpy or rosbags).

    bytes_field: how a ``uint8[]`` field (image, point cloud data) takes an array of bytes:
    rosbags keeps numpy arrays; rclpy's setters copy an ``array.array('B')`` as it is but read
    anything else element by element (a 272×480 BGR image: ~37 ms).
    """

    def __init__(self, lookup: Callable[[str], type],
                 bytes_field: Callable[[np.ndarray], Any] = lambda a: a):
        self._lookup = lookup
        self._cache: dict[str, type] = {}
        self.bytes_field = bytes_field

    def cls(self, name: str) -> type:
        if name not in self._cache:
            self._cache[name] = self._lookup(name)
        return self._cache[name]

    def __call__(self, _type_name: str, /, **fields: Any) -> Any:
        # positional-only: message fields such as LinkState.name pass through **fields
        return self.cls(_type_name)(**fields)


def rclpy_factory() -> MsgFactory:
    """Factory over the generated rclpy message modules (needs the workspace)."""

    def lookup(name: str) -> type:
        pkg, sub, cls = name.split("/")
        return getattr(importlib.import_module(f"{pkg}.{sub}"), cls)

    return MsgFactory(lookup, lambda a: array.array("B", np.ascontiguousarray(a, np.uint8).tobytes()))


def rosbags_factory() -> MsgFactory:
    """Factory over rosbags' typestore with the artrack types registered."""
    from .bags import typestore

    store = typestore()
    return MsgFactory(lambda name: store.types[name])


# --------------------------------------------------------------------- time


def time_msg(f: MsgFactory, stamp_ns: int) -> Any:
    """builtin_interfaces/Time from integer nanoseconds."""
    stamp_ns = int(stamp_ns)
    return f("builtin_interfaces/msg/Time", sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)


def ns_from_time(t: Any) -> int:
    """Integer nanoseconds from a builtin_interfaces/Time."""
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def header_msg(f: MsgFactory, stamp_ns: int, frame_id: str) -> Any:
    """std_msgs/Header with the stamp (integer ns) and frame id."""
    return f("std_msgs/msg/Header", stamp=time_msg(f, stamp_ns), frame_id=frame_id)


def _arr(values: Any, n: int | None = None) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64).reshape(-1)
    if n is not None and a.size != n:
        raise ValueError(f"expected {n} values, got {a.size}")
    return a


def _point(f: MsgFactory, p: np.ndarray) -> Any:
    return f("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _xyz(p: Any) -> list[float]:
    return [p.x, p.y, p.z]


# -------------------------------------------------------------------- blobs


def blob_array_msg(
    f: MsgFactory,
    stamp_ns: int,
    camera: str,
    frame_id: str,
    blobs: list[Blob2D],
    prior_stamp_ns: int | None = None,
) -> Any:
    """artrack_msgs/Blob2DArray for one camera image."""
    items = [
        f(
            "artrack_msgs/msg/Blob2D",
            label=b.label,
            mean=_arr(b.mean, 2),
            covariance=_arr(b.cov, 4),
            color_mean=_arr(b.color_mean, 3),
            color_covariance=_arr(b.color_cov, 9),
            pixel_count=int(b.pixel_count),
        )
        for b in blobs
    ]
    used = prior_stamp_ns is not None
    return f(
        "artrack_msgs/msg/Blob2DArray",
        header=header_msg(f, stamp_ns, frame_id),
        camera_name=camera,
        blobs=items,
        prior_used=used,
        prior_stamp=time_msg(f, prior_stamp_ns if used else 0),
        prior_staleness=(stamp_ns - prior_stamp_ns) * 1e-9 if used else 0.0,
    )


def _check_finite(items: list, fields: tuple[str, ...], what: str) -> None:
    """ValueError naming the first message field that holds NaN or infinity."""
    if all_finite(*(getattr(item, name) for item in items for name in fields)):
        return  # one test for the whole message; the loop below only names the culprit
    for i, item in enumerate(items):
        for name in fields:
            if not all_finite(getattr(item, name)):
                raise ValueError(f"{what}[{i}].{name} is not finite")


def blobs_from_msg(msg: Any) -> tuple[int, str, list[Blob2D]]:
    """(stamp_ns, camera_name, blobs) from an artrack_msgs/Blob2DArray; ValueError names a bad field."""
    blobs = [
        Blob2D(
            label=b.label,
            mean=np.array(b.mean, dtype=np.float64),
            cov=np.array(b.covariance, dtype=np.float64).reshape(2, 2),
            color_mean=np.array(b.color_mean, dtype=np.float64),
            color_cov=np.array(b.color_covariance, dtype=np.float64).reshape(3, 3),
            pixel_count=int(b.pixel_count),
        )
        for b in msg.blobs
    ]
    _check_finite(blobs, ("mean", "cov", "color_mean", "color_cov"), "blobs")
    return ns_from_time(msg.header.stamp), msg.camera_name, blobs


def prior_array_msg(f: MsgFactory, stamp_ns: int, camera: str, frame_id: str, priors: list[Prior2D]) -> Any:
    """artrack_msgs/BlobPrior2DArray; ``stamp_ns`` is the frame the priors predict."""
    items = [
        f(
            "artrack_msgs/msg/BlobPrior2D",
            label=p.label,
            mean=_arr(p.mean, 2),
            covariance=_arr(p.cov, 4),
            confidence=float(p.confidence),
            visibility=int(p.visibility),
        )
        for p in priors
    ]
    return f(
        "artrack_msgs/msg/BlobPrior2DArray",
        header=header_msg(f, stamp_ns, frame_id),
        camera_name=camera,
        priors=items,
    )


def priors_from_msg(msg: Any) -> tuple[int, str, list[Prior2D]]:
    """(predicted stamp_ns, camera_name, priors) from a BlobPrior2DArray; ValueError names a bad field."""
    stamp = ns_from_time(msg.header.stamp)
    priors = [
        Prior2D(
            label=p.label,
            mean=np.array(p.mean, dtype=np.float64),
            cov=np.array(p.covariance, dtype=np.float64).reshape(2, 2),
            confidence=float(p.confidence),
            visibility=int(p.visibility),
            stamp_ns=stamp,
        )
        for p in msg.priors
    ]
    _check_finite(priors, ("confidence",), "priors")
    # a prior behind the camera carries NaN mean and covariance by design (projection.py)
    if all_finite(*(a for p in priors if p.visibility != BEHIND_CAMERA for a in (p.mean, p.cov))):
        return stamp, msg.camera_name, priors
    for i, p in enumerate(priors):
        if p.visibility != BEHIND_CAMERA and not all_finite(p.mean, p.cov):
            raise ValueError(f"priors[{i}] ({p.label!r}) has a non-finite mean or covariance "
                             "but is not behind the camera")
    return stamp, msg.camera_name, priors


# --------------------------------------------------------------------- body


def body_msg(f: MsgFactory, est: BodyEstimate, frame_id: str = WORLD_FRAME, body_id: int = 0) -> Any:
    """artrack_msgs/TrackedBody from a BodyEstimate (world frame)."""
    links = []
    # all links' quaternions (x, y, z, w) in one scipy call
    quats = Rotation.from_matrix(np.array([lk.rotation for lk in est.links])).as_quat() if est.links else []
    for link, q in zip(est.links, quats, strict=True):
        pose = f(
            "geometry_msgs/msg/Pose",
            position=_point(f, link.position),
            orientation=f("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        v, w = link.velocity, link.angular_velocity
        twist = f(
            "geometry_msgs/msg/Twist",
            linear=f("geometry_msgs/msg/Vector3", x=float(v[0]), y=float(v[1]), z=float(v[2])),
            angular=f("geometry_msgs/msg/Vector3", x=float(w[0]), y=float(w[1]), z=float(w[2])),
        )
        links.append(
            f("artrack_msgs/msg/LinkState", name=link.name, pose=pose, velocity=twist, covariance=_arr(link.cov, 36))
        )
    return f(
        "artrack_msgs/msg/TrackedBody",
        header=header_msg(f, est.stamp_ns, frame_id),
        body_id=int(body_id),
        status=int(est.status),
        quality=float(est.quality),
        links=links,
        joint_names=list(est.joint_names),
        joints=[_point(f, p) for p in np.asarray(est.joints, dtype=np.float64).reshape(-1, 3)],
        blob_labels=[b.label for b in est.blobs],
        blob_means=[_point(f, b.mean) for b in est.blobs],
        blob_covariances=np.concatenate([_arr(b.cov, 9) for b in est.blobs]) if est.blobs else np.zeros(0),
    )


def body_from_msg(msg: Any) -> BodyEstimate:
    """BodyEstimate from an artrack_msgs/TrackedBody."""
    links = []
    quats = [[ls.pose.orientation.x, ls.pose.orientation.y, ls.pose.orientation.z, ls.pose.orientation.w]
             for ls in msg.links]
    rotations = Rotation.from_quat(quats).as_matrix() if quats else []  # one scipy call
    for ls, rotation in zip(msg.links, rotations, strict=True):
        links.append(
            LinkEstimate(
                name=ls.name,
                position=np.array(_xyz(ls.pose.position)),
                rotation=rotation,
                velocity=np.array(_xyz(ls.velocity.linear)),
                angular_velocity=np.array(_xyz(ls.velocity.angular)),
                cov=np.array(ls.covariance, dtype=np.float64).reshape(6, 6),
            )
        )
    covs = np.array(msg.blob_covariances, dtype=np.float64).reshape(-1, 3, 3)
    blobs = [
        Blob3D(label=label, mean=np.array(_xyz(m)), cov=covs[i].copy())
        for i, (label, m) in enumerate(zip(msg.blob_labels, msg.blob_means, strict=True))
    ]
    return BodyEstimate(
        stamp_ns=ns_from_time(msg.header.stamp),
        joint_names=list(msg.joint_names),
        joints=np.array([_xyz(p) for p in msg.joints], dtype=np.float64).reshape(-1, 3),
        links=links,
        blobs=blobs,
        status=int(msg.status),
        quality=float(msg.quality),
    )


# ------------------------------------------------------------------ edge statistics


def _pose_msg(f: MsgFactory, E: np.ndarray) -> Any:
    q = Rotation.from_matrix(E[:3, :3]).as_quat()  # x, y, z, w
    return f("geometry_msgs/msg/Pose", position=_point(f, E[:3, 3]),
             orientation=f("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))


def edge_stats_msg(f: MsgFactory, stamp_ns: int, camera: str, frame_id: str, link_names: list[str],
                   stats: Any | None, reference_stamp_ns: int) -> Any:
    """artrack_msgs/LinkEdgeStatistics from :class:`artrack.edge_fusion.LinkEdgeStatistics`
    (all body links, in ``link_names`` order; ``stats`` None: an empty message, nothing measured)."""
    if stats is None:
        links, ref, info, eta, found = [], [], np.zeros(0), np.zeros(0), np.zeros(0, np.uint32)
    else:
        links = list(link_names)
        ref = [_pose_msg(f, E) for E in np.asarray(stats.reference, dtype=np.float64)]
        info = _arr(stats.information)
        eta = _arr(stats.information_vector)
        found = np.asarray(stats.samples_found, dtype=np.uint32)
    return f("artrack_msgs/msg/LinkEdgeStatistics", header=header_msg(f, stamp_ns, frame_id), camera_name=camera,
             reference_stamp=time_msg(f, reference_stamp_ns), links=links, reference=ref, information=info,
             information_vector=eta, samples_found=found)


def edge_stats_from_msg(msg: Any, link_names: list[str]) -> tuple[int, str, Any | None]:
    """(stamp_ns, camera_name, LinkEdgeStatistics or None when empty) from a LinkEdgeStatistics
    message for a body with ``link_names``; ValueError names a bad field."""
    from .edge_fusion import LinkEdgeStatistics

    stamp = ns_from_time(msg.header.stamp)
    n = len(msg.links)
    if n == 0:
        return stamp, msg.camera_name, None
    if list(msg.links) != list(link_names):
        raise ValueError(f"field 'links' {list(msg.links)[:3]}... does not list the body's links in order")
    info = np.array(msg.information, dtype=np.float64)
    eta = np.array(msg.information_vector, dtype=np.float64)
    for name, arr, size in (("information", info, 36 * n), ("information_vector", eta, 6 * n),
                            ("reference", msg.reference, n), ("samples_found", msg.samples_found, n)):
        if len(arr) != size:
            raise ValueError(f"field '{name}' has {len(arr)} values, expected {size}")
    if not (np.all(np.isfinite(info)) and np.all(np.isfinite(eta))):
        raise ValueError("field 'information' or 'information_vector' is not finite")
    ref = np.tile(np.eye(4), (n, 1, 1))
    ref[:, :3, :3] = Rotation.from_quat([[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
                                         for p in msg.reference]).as_matrix()
    for i, pose in enumerate(msg.reference):
        ref[i, :3, 3] = _xyz(pose.position)
    stats = LinkEdgeStatistics(ref, info.reshape(n, 6, 6), eta.reshape(n, 6),
                               np.array(msg.samples_found, dtype=np.int64), (msg.camera_name,))
    return stamp, msg.camera_name, stats


# ------------------------------------------------------------------ cameras


def camera_info_msg(f: MsgFactory, camera: Camera, stamp_ns: int) -> Any:
    """sensor_msgs/CameraInfo (plumb_bob) with P = K [I | 0]."""
    P = np.zeros((3, 4))
    P[:, :3] = camera.K
    roi = f("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return f(
        "sensor_msgs/msg/CameraInfo",
        header=header_msg(f, stamp_ns, camera.frame_id),
        height=int(camera.height),
        width=int(camera.width),
        distortion_model="plumb_bob",
        d=_arr(camera.dist),
        k=_arr(camera.K, 9),
        r=_arr(np.eye(3), 9),
        p=_arr(P, 12),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def extrinsics_msg(f: MsgFactory, camera: Camera, stamp_ns: int, world_frame: str = WORLD_FRAME) -> Any:
    """geometry_msgs/TransformStamped world -> camera optical frame (world_from_camera)."""
    world_from_cam_R = camera.R.T
    c = camera.center
    q = Rotation.from_matrix(world_from_cam_R).as_quat()
    tf = f(
        "geometry_msgs/msg/Transform",
        translation=f("geometry_msgs/msg/Vector3", x=float(c[0]), y=float(c[1]), z=float(c[2])),
        rotation=f("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]),
    )
    return f(
        "geometry_msgs/msg/TransformStamped",
        header=header_msg(f, stamp_ns, world_frame),
        child_frame_id=camera.frame_id,
        transform=tf,
    )


def camera_from_msgs(name: str, info: Any, extrinsics: Any | None) -> Camera:
    """Camera from a CameraInfo (ROS 2 ``k``/``d`` or ROS 1 ``K``/``D``) and, optionally,
    its world->optical TransformStamped. Raises CalibrationError on malformed fields or a
    distortion model other than plumb_bob / rational_polynomial (the OpenCV model)."""
    k = getattr(info, "k", None)
    k = info.K if k is None else k
    d = getattr(info, "d", None)
    d = info.D if d is None else d
    model = str(getattr(info, "distortion_model", "plumb_bob") or "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial") and len(d):
        raise CalibrationError(f"camera '{name}' field 'distortion_model' is '{model}', "
                               "only plumb_bob / rational_polynomial are supported")
    R, t = None, None
    if extrinsics is not None:
        tr = extrinsics.transform
        q = tr.rotation
        world_from_cam = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        R = world_from_cam.T
        t = -R @ np.array([tr.translation.x, tr.translation.y, tr.translation.z])
    return Camera.from_camera_info(name, int(info.width), int(info.height), k, np.asarray(d, dtype=float), R, t)


# ------------------------------------------------------------------- images


@dataclass(frozen=True)
class ImageEncoding:
    """A sensor_msgs/Image encoding: its channel count and the conversion to BGR (None: already BGR)."""

    channels: int
    to_bgr: Callable[[np.ndarray], np.ndarray] | None


def _swap_rb(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(img[..., 2::-1])


ENCODINGS = {
    "bgr8": ImageEncoding(3, None),
    "rgb8": ImageEncoding(3, _swap_rb),
    "bgra8": ImageEncoding(4, lambda a: np.ascontiguousarray(a[..., :3])),
    "rgba8": ImageEncoding(4, lambda a: _swap_rb(a[..., :3])),
    "mono8": ImageEncoding(1, lambda a: np.ascontiguousarray(np.repeat(a, 3, axis=2))),
}


def image_msg(f: MsgFactory, image_bgr: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/Image (bgr8) from an (H, W, 3) uint8 BGR array."""
    img = np.ascontiguousarray(image_bgr, dtype=np.uint8)
    h, w = img.shape[:2]
    return f(
        "sensor_msgs/msg/Image",
        header=header_msg(f, stamp_ns, frame_id),
        height=h,
        width=w,
        encoding="bgr8",
        is_bigendian=0,
        step=w * 3,
        data=f.bytes_field(img.reshape(-1)),
    )


def bgr_from_image_msg(msg: Any, where: str = "image") -> np.ndarray:
    """(H, W, 3) uint8 BGR from a sensor_msgs/Image; ValueError names the bad field."""
    enc = ENCODINGS.get(msg.encoding)
    if enc is None:
        raise ValueError(f"{where}: unsupported encoding '{msg.encoding}' (field 'encoding')")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, dtype=np.uint8)
    if step < w * enc.channels or data.size < h * step:
        raise ValueError(f"{where}: data has {data.size} bytes, expected {h}x{step} (fields 'height'/'step')")
    img = data[: h * step].reshape(h, step)[:, : w * enc.channels].reshape(h, w, enc.channels)
    return img.copy() if enc.to_bgr is None else enc.to_bgr(img)


# --------------------------------------------------------------------- point clouds and objects (§3)

#: sensor_msgs/PointField datatypes we read (FLOAT32, FLOAT64)
_POINTFIELD_DTYPES = {7: "f4", 8: "f8"}


def pointcloud_msg(f: MsgFactory, points: np.ndarray, stamp_ns: int, frame_id: str) -> Any:
    """sensor_msgs/PointCloud2 (unorganised, fields x, y, z float32, little-endian) from (K, 3) points, m."""
    pts = np.ascontiguousarray(np.asarray(points, dtype="<f4").reshape(-1, 3))
    fields = [f("sensor_msgs/msg/PointField", name=n, offset=4 * k, datatype=7, count=1)
              for k, n in enumerate("xyz")]
    return f(
        "sensor_msgs/msg/PointCloud2",
        header=header_msg(f, stamp_ns, frame_id),
        height=1,
        width=len(pts),
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=12 * len(pts),
        data=f.bytes_field(pts.view(np.uint8).reshape(-1)),
        is_dense=bool(np.all(np.isfinite(pts))),
    )


def points_from_pointcloud_msg(msg: Any, where: str = "points") -> np.ndarray:
    """(K, 3) float64 finite points from a sensor_msgs/PointCloud2 with float x, y, z fields
    (any point_step / row_step / endianness; NaN points dropped). ValueError names the bad field."""
    byname = {fl.name: fl for fl in msg.fields}
    for n in "xyz":
        if n not in byname:
            raise ValueError(f"{where}: no '{n}' in field 'fields'")
        if int(byname[n].datatype) not in _POINTFIELD_DTYPES:
            raise ValueError(f"{where}: field '{n}' has datatype {byname[n].datatype}, expected FLOAT32 (7) "
                             "or FLOAT64 (8) (field 'fields')")
    h, w = int(msg.height), int(msg.width)
    step, row = int(msg.point_step), int(msg.row_step)
    endian = ">" if msg.is_bigendian else "<"
    dtype = np.dtype({"names": list("xyz"),
                      "formats": [endian + _POINTFIELD_DTYPES[int(byname[n].datatype)] for n in "xyz"],
                      "offsets": [int(byname[n].offset) for n in "xyz"], "itemsize": step})
    if step < dtype.itemsize or max(int(byname[n].offset) for n in "xyz") + 4 > step:
        raise ValueError(f"{where}: 'point_step' {step} too small for the x, y, z offsets")
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, dtype=np.uint8)
    if row < w * step or data.size < h * row:
        raise ValueError(f"{where}: data has {data.size} bytes, expected {h} rows of {row} "
                         "(fields 'row_step'/'height')")
    rows = data[: h * row].reshape(h, row)[:, : w * step]
    rec = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(float)
    return pts[np.all(np.isfinite(pts), axis=1)]


def stick_pose_msg(f: MsgFactory, a: np.ndarray, b: np.ndarray, stamp_ns: int, frame_id: str = WORLD_FRAME) -> Any:
    """geometry_msgs/PoseStamped of a stick from b to a (m): position = the midpoint, the
    orientation turns the x axis onto (a − b) / |a − b|. The length travels as a parameter."""
    a, b = _arr(a, 3), _arr(b, 3)
    d = a - b
    x = d / max(float(np.linalg.norm(d)), 1e-12)
    q = Rotation.align_vectors(x[None], np.array([[1.0, 0.0, 0.0]]))[0].as_quat()
    c = 0.5 * (a + b)
    return f("geometry_msgs/msg/PoseStamped", header=header_msg(f, stamp_ns, frame_id),
             pose=f("geometry_msgs/msg/Pose", position=_point(f, c),
                    orientation=f("geometry_msgs/msg/Quaternion", x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                  w=float(q[3]))))


def stick_from_pose_msg(msg: Any, length: float, where: str = "stick") -> tuple[np.ndarray, np.ndarray]:
    """(a (3,), b (3,)) end points of a stick of ``length`` m from a PoseStamped (see stick_pose_msg)."""
    o = msg.pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], float)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
        raise ValueError(f"{where}: field 'pose.orientation' is not a rotation")
    c = np.array(_xyz(msg.pose.position), float)
    if not np.all(np.isfinite(c)):
        raise ValueError(f"{where}: field 'pose.position' is not finite")
    x = Rotation.from_quat(q / np.linalg.norm(q)).apply([1.0, 0.0, 0.0])
    return c + 0.5 * length * x, c - 0.5 * length * x
