"""RViz / Foxglove views of a tracked body: visualization_msgs/MarkerArray and geometry_msgs/PoseArray.

Markers (namespaces ``<prefix>/...``, world frame of the body's header):
- ``bones``: LINE_LIST, each link from its origin to its distal end (body model ``end``);
- ``joints``: SPHERE_LIST of the 15 output joints;
- ``blobs``: one SPHERE per 3-D blob, shaped as its covariance ellipsoid (``sigmas`` standard
  deviations along the principal axes: scale = 2 * sigmas * sqrt(eigenvalue));
- ``predicted_blobs``: the same for the prediction of this frame (the 3-D priors that
  feedback projection turns into the 2-D priors, ALGORITHMS.md §1), translucent;
- ``status``: a text above the head (id, tracking status, quality).
The array starts with a DELETEALL, so a view shows exactly the newest body.
ROS-free: messages are built through a MsgFactory (artrack.messages).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .body_model import BodyModel
from .messages import MsgFactory, header_msg
from .types import STATUS_INITIALIZING, STATUS_LOST, STATUS_TRACKING, BodyEstimate, all_finite

# visualization_msgs/Marker constants
SPHERE, LINE_LIST, SPHERE_LIST, TEXT_VIEW_FACING = 2, 5, 7, 9
ADD, DELETEALL = 0, 3
STATUS_NAMES = {STATUS_INITIALIZING: "initializing", STATUS_TRACKING: "tracking", STATUS_LOST: "lost"}


def ellipsoid(cov: np.ndarray, sigmas: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(diameters (3,), world_from_axes rotation (3, 3), right-handed) of the ``sigmas`` ellipsoid
    of a 3x3 covariance: cov = R diag((diameters / (2 sigmas))²) Rᵀ."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    if np.linalg.det(V) < 0:
        V[:, 0] = -V[:, 0]
    return 2.0 * sigmas * np.sqrt(np.clip(w, 0.0, None)), V


class MarkerBuilder:
    """Builds the marker and pose arrays of a body; ``f`` a MsgFactory."""

    def __init__(self, f: MsgFactory, body: BodyModel, prefix: str = "artrack", sigmas: float = 1.0,
                 lifetime_s: float = 0.0):
        self.f = f
        self.body = body
        self.prefix = prefix
        self.sigmas = sigmas
        self.lifetime_s = lifetime_s
        self.ends = {lk.name: np.asarray(lk.end, float) for lk in body.links}

    # ------------------------------------------------------------------ pieces
    def _point(self, p):
        return self.f("geometry_msgs/msg/Point", x=float(p[0]), y=float(p[1]), z=float(p[2]))

    def _color(self, r, g, b, a=1.0):
        return self.f("std_msgs/msg/ColorRGBA", r=float(r), g=float(g), b=float(b), a=float(a))

    def _pose(self, p=(0.0, 0.0, 0.0), R=None, q=None):
        """geometry_msgs/Pose at p with rotation R, or with its quaternion q (x, y, z, w) if given."""
        if q is None:
            q = Rotation.from_matrix(R).as_quat() if R is not None else np.array([0.0, 0.0, 0.0, 1.0])
        return self.f("geometry_msgs/msg/Pose", position=self._point(p),
                      orientation=self.f("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3]))

    def _marker(self, header, ns: str, mid: int, kind: int, scale, color, pose=None, points=(), text=""):
        sec = int(self.lifetime_s)
        return self.f("visualization_msgs/msg/Marker", header=header, ns=f"{self.prefix}/{ns}", id=int(mid),
                      type=kind, action=ADD, pose=pose if pose is not None else self._pose(),
                      scale=self.f("geometry_msgs/msg/Vector3", x=float(scale[0]), y=float(scale[1]),
                                   z=float(scale[2])),
                      color=color, points=list(points), text=text,
                      lifetime=self.f("builtin_interfaces/msg/Duration", sec=sec,
                                      nanosec=int(round((self.lifetime_s - sec) * 1e9))))

    def _blob_markers(self, header, ns: str, blobs, color) -> list:
        kept = [(i, b) for i, b in enumerate(blobs) if all_finite(b.mean, b.cov)]
        if not kept:
            return []
        axes = [ellipsoid(np.asarray(b.cov, float), self.sigmas) for _, b in kept]
        quats = Rotation.from_matrix(np.stack([R for _, R in axes])).as_quat()  # (one call for all)
        return [self._marker(header, ns, i, SPHERE, d, color, pose=self._pose(b.mean, q=q), text=b.label)
                for (i, b), (d, _), q in zip(kept, axes, quats, strict=True)]

    # ------------------------------------------------------------------ arrays
    def marker_array(self, est: BodyEstimate, frame_id: str, body_id: str = "0",
                     prediction: BodyEstimate | None = None):
        """visualization_msgs/MarkerArray of ``est`` (and the ``prediction`` of its frame)."""
        f = self.f
        header = header_msg(f, est.stamp_ns, frame_id)
        clear = f("visualization_msgs/msg/Marker", header=header, ns="", id=0, action=DELETEALL)
        markers = [clear]
        seg = []
        for lk in est.links:
            if lk.name in self.ends and all_finite(lk.position, lk.rotation):
                seg += [self._point(lk.position), self._point(lk.position + lk.rotation @ self.ends[lk.name])]
        if seg:
            markers.append(self._marker(header, "bones", 0, LINE_LIST, (0.02, 0, 0), self._color(0.9, 0.9, 0.2),
                                        points=seg))
        joints = np.asarray(est.joints, float).reshape(-1, 3)
        pts = [self._point(p) for p in joints if all_finite(p)]
        if pts:
            markers.append(self._marker(header, "joints", 0, SPHERE_LIST, (0.05, 0.05, 0.05),
                                        self._color(1.0, 0.3, 0.1), points=pts))
        markers += self._blob_markers(header, "blobs", est.blobs, self._color(0.2, 0.6, 1.0, 0.6))
        if prediction is not None:
            markers += self._blob_markers(header, "predicted_blobs", prediction.blobs, self._color(0.2, 1.0, 0.3, 0.3))
        top = joints[list(est.joint_names).index("head")] if "head" in est.joint_names else None
        if top is not None and all_finite(top):
            text = f"body {body_id}: {STATUS_NAMES.get(int(est.status), est.status)} q={est.quality:.2f}"
            markers.append(self._marker(header, "status", 0, TEXT_VIEW_FACING, (0, 0, 0.1), self._color(1, 1, 1),
                                        pose=self._pose(top + np.array([0.0, 0.0, 0.3])), text=text))
        return f("visualization_msgs/msg/MarkerArray", markers=markers)

    def pose_array(self, est: BodyEstimate, frame_id: str):
        """geometry_msgs/PoseArray of the link frames (body-model link order, finite ones)."""
        links = [lk for lk in est.links if all_finite(lk.position, lk.rotation)]
        quats = Rotation.from_matrix(np.stack([lk.rotation for lk in links])).as_quat() if links else []
        poses = [self._pose(lk.position, q=q) for lk, q in zip(links, quats, strict=True)]
        return self.f("geometry_msgs/msg/PoseArray", header=header_msg(self.f, est.stamp_ns, frame_id), poses=poses)
