"""The tracked body in REP 155 form (ROS4HRI): TF frames, joint angles and a URDF.

REP 155 names a tracked body by a string id and publishes it as TF frames rooted at
``body_<id>``; this module turns a :class:`~artrack.types.BodyEstimate` into

- the TF tree ``world -> body_<id>`` (root at the mid-hip, axes of the pelvis link: x
  forward, y left, z up, REP 103) ``-> pelvis_<id> -> torso_<id> -> ...``: one frame per
  body-model link suffixed ``_<id>``; a ball joint is split into three revolute joints
  (intrinsic x-y-z Euler angles) through two intermediate frames ``<link>_x_<id>`` and
  ``<link>_y_<id>``; a hinge is one revolute joint about the model's axis;
- one frame per output joint (the 15 joints of TrackedBody.joints), named
  ``<joint>_<id>`` as the joint frames of ROS4HRI's human_description (``l_elbow_<id>``,
  ``head_<id>``, ...), a child of its link frame placed exactly at the joint. A link whose
  name is taken by a joint frame elsewhere is called ``<link>_link_<id>`` (the head link:
  its origin is the neck, the ``head`` joint the head centre); a joint at the origin of the
  link of the same name (``pelvis``) is that link frame;
- the revolute joint angles (sensor_msgs/JointState) and a URDF with the tracked body's
  dimensions, such that robot_state_publisher fed with both reproduces the same tree.

The transforms are computed from the estimate's link poses (exact relative transforms),
so composing them gives back the estimate's links and joints to rounding error; the
joint angles and the URDF reproduce them as well when the estimate is a rigid body of the
model (a hinge rotation off its axis is kept exactly in TF, its angle is the projection).

ROS-free: plain data here; :func:`tf_message` etc. build messages through a MsgFactory.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np
from scipy.spatial.transform import Rotation

from .body_model import BodyModel
from .messages import MsgFactory, header_msg
from .types import STATUS_TRACKING, BodyEstimate

#: REP 155 topics (the per-body ones take the id).
TRACKED_TOPIC = "/humans/bodies/tracked"
TF_TOPIC = "/tf"


def body_topic(body_id: str, leaf: str) -> str:
    """/humans/bodies/<id>/<leaf>: joint_states, urdf."""
    return f"/humans/bodies/{body_id}/{leaf}"


@dataclass
class FrameTransform:
    """parent_from_child: ``translation`` (3,) m and ``rotation`` (3, 3)."""

    parent: str
    child: str
    translation: np.ndarray
    rotation: np.ndarray

    def quaternion(self) -> np.ndarray:
        """(x, y, z, w), as geometry_msgs/Quaternion."""
        return Rotation.from_matrix(self.rotation).as_quat()


@dataclass
class JointRotations:
    """:meth:`BodyFrames.joint_rotations`: per non-root link (model order) ``relative`` (translation
    (3,), rotation (3, 3)) in its parent's frame and ``angles`` (L-1, 3) intrinsic x-y-z, rad."""

    relative: list[tuple[np.ndarray, np.ndarray]]
    angles: np.ndarray


def _rel(p_parent, R_parent, p_child, R_child) -> tuple[np.ndarray, np.ndarray]:
    return R_parent.T @ (p_child - p_parent), R_parent.T @ R_child


def _is_zero(v: np.ndarray) -> bool:
    return bool(np.all(np.abs(v) < 1e-12))


class BodyFrames:
    """Frame names, TF, joint angles and URDF of one tracked body (``body_id`` a string)."""

    def __init__(self, body: BodyModel, body_id: str):
        self.body = body
        self.id = str(body_id)
        s = f"_{self.id}"
        self.root = f"body{s}"
        joint_link = {n: int(k) for n, k in zip(body.joint_names, body.joint_links, strict=True)}
        at_origin = {n: _is_zero(p) for n, p in zip(body.joint_names, body.joint_points, strict=True)}
        self.link_frame: dict[str, str] = {}
        for k, name in enumerate(body.link_names):
            clash = name in joint_link and not (joint_link[name] == k and at_origin[name])
            self.link_frame[name] = f"{name}_link{s}" if clash else f"{name}{s}"
        self.joint_frame: dict[str, str] = {}
        self.joint_frame_is_link: dict[str, bool] = {}
        for n in body.joint_names:
            link = body.link_names[joint_link[n]]
            same = n == link and at_origin[n]
            self.joint_frame[n] = self.link_frame[link] if same else f"{n}{s}"
            self.joint_frame_is_link[n] = same
        names = [self.root, *self.link_frame.values(),
                 *(f for n, f in self.joint_frame.items() if not self.joint_frame_is_link[n])]
        for lk in body.links:
            if lk.joint == "ball":
                names += [f"{lk.name}_x{s}", f"{lk.name}_y{s}"]
        if len(names) != len(set(names)):
            raise ValueError(f"frame names of body '{self.id}' collide: {sorted(names)}")

    # ------------------------------------------------------------------ checks
    @staticmethod
    def publishable(est: BodyEstimate) -> bool:
        """Tracked, with finite link poses and joints (start-up and lost bodies are not published)."""
        return (est.status == STATUS_TRACKING and len(est.links) > 0
                and bool(np.all(np.isfinite(est.joints)))
                and all(np.all(np.isfinite(lk.position)) and np.all(np.isfinite(lk.rotation)) for lk in est.links))

    def _poses(self, est: BodyEstimate) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        poses = {lk.name: (np.asarray(lk.position, float), np.asarray(lk.rotation, float)) for lk in est.links}
        missing = [n for n in self.body.link_names if n not in poses]
        if missing:
            raise ValueError(f"estimate has no link '{missing[0]}' (field links)")
        return poses

    def mid_hip(self, est: BodyEstimate) -> np.ndarray:
        """Root position: midpoint of l_hip and r_hip (the root link's origin without them)."""
        names = list(est.joint_names)
        if "l_hip" in names and "r_hip" in names:
            j = np.asarray(est.joints, float)
            return 0.5 * (j[names.index("l_hip")] + j[names.index("r_hip")])
        root = self.body.link_names[0]
        return self._poses(est)[root][0].copy()

    # ------------------------------------------------------------------ TF
    def joint_rotations(self, est: BodyEstimate) -> JointRotations:
        """Each non-root link's pose in its parent's frame and its intrinsic x-y-z angles, once for
        both :meth:`transforms` and :meth:`joint_state` (one scipy call for all links)."""
        poses = self._poses(est)
        rel = [_rel(*poses[lk.parent], *poses[lk.name]) for lk in self.body.links[1:]]
        angles = self._euler(np.stack([R for _, R in rel])) if rel else np.zeros((0, 3))
        return JointRotations(rel, angles)

    def transforms(self, est: BodyEstimate, world_frame: str,
                   rotations: JointRotations | None = None) -> list[FrameTransform]:
        """The body's TF tree, parent before child (world -> body_<id> -> links -> joints);
        ``rotations``: :meth:`joint_rotations` of ``est`` if already computed."""
        body = self.body
        poses = self._poses(est)
        root_link = body.link_names[0]
        p_root, R_root = poses[root_link]
        mid = self.mid_hip(est)
        s = f"_{self.id}"
        out = [FrameTransform(world_frame, self.root, mid, R_root),
               FrameTransform(self.root, self.link_frame[root_link], R_root.T @ (p_root - mid), np.eye(3))]
        rot = self.joint_rotations(est) if rotations is None else rotations
        for lk, (t, R), (a, b, _) in zip(body.links[1:], rot.relative, rot.angles, strict=True):
            parent, child = self.link_frame[lk.parent], self.link_frame[lk.name]
            if lk.joint == "ball":
                out += [FrameTransform(parent, f"{lk.name}_x{s}", t, _rx(a)),
                        FrameTransform(f"{lk.name}_x{s}", f"{lk.name}_y{s}", np.zeros(3), _ry(b)),
                        # Rz(c) up to rounding; the remainder keeps the composition exact
                        FrameTransform(f"{lk.name}_y{s}", child, np.zeros(3), _ry(b).T @ _rx(a).T @ R)]
            else:
                out.append(FrameTransform(parent, child, t, R))
        joints = np.asarray(est.joints, float)
        for i, n in enumerate(est.joint_names):
            if n not in self.joint_frame or self.joint_frame_is_link[n]:
                continue
            link = body.link_names[int(body.joint_links[body.joint_names.index(n)])]
            p, R = poses[link]
            out.append(FrameTransform(self.link_frame[link], self.joint_frame[n], R.T @ (joints[i] - p), np.eye(3)))
        return out

    @staticmethod
    def _euler(R: np.ndarray) -> np.ndarray:
        """Intrinsic x-y-z angles: R = Rx(a) Ry(b) Rz(c); R (3, 3) or a stack (N, 3, 3) (one scipy call,
        the same values as one by one)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # gimbal lock: still a valid decomposition
            return Rotation.from_matrix(R).as_euler("XYZ")

    # ------------------------------------------------------------------ joint angles
    def joint_state(self, est: BodyEstimate, rotations: JointRotations | None = None) -> tuple[list[str], np.ndarray]:
        """Revolute joint names of the URDF and their angles (rad); ``rotations``: as for
        :meth:`transforms`."""
        s = f"_{self.id}"
        names, values = [], []
        links = self.body.links[1:]
        if not links:
            return names, np.zeros(0)
        rot = self.joint_rotations(est) if rotations is None else rotations
        hinges = [k for k, lk in enumerate(links) if lk.joint != "ball"]
        rotvecs = dict(zip(hinges, Rotation.from_matrix(np.stack([rot.relative[k][1] for k in hinges])).as_rotvec(),
                           strict=True)) if hinges else {}
        for k, (lk, abc) in enumerate(zip(links, rot.angles, strict=True)):
            if lk.joint == "ball":
                names += [f"{lk.name}_x{s}", f"{lk.name}_y{s}", f"{lk.name}_z{s}"]
                values += list(abc)
            else:
                names.append(f"{lk.name}{s}")
                values.append(float(rotvecs[k] @ lk.axis))
        return names, np.asarray(values, float)

    # ------------------------------------------------------------------ URDF
    def dimensions(self, est: BodyEstimate, transforms: list[FrameTransform] | None = None) -> np.ndarray:
        """(L + J, 3) link offsets in their parent frames and joint points in their link frames,
        as measured on this estimate (what the URDF states); ``transforms``: its :meth:`transforms`
        if already computed."""
        tfs = self.transforms(est, "world") if transforms is None else transforms
        return np.array([tf.translation for tf in tfs[1:]], float)

    def urdf(self, est: BodyEstimate) -> str:
        """URDF of the tracked body: link offsets and joint points measured on ``est``, bones of
        the model's lengths drawn as cylinders, the model's hinge limits."""
        body = self.body
        s = f"_{self.id}"
        tfs = {tf.child: tf for tf in self.transforms(est, "world")}
        lines = ['<?xml version="1.0"?>', f"<robot name={quoteattr('human' + s)}>",
                 f"  <!-- artrack tracked body '{self.id}' (REP 155 frames); drive with "
                 f"{body_topic(self.id, 'joint_states')} -->", f"  <link name={quoteattr(self.root)}/>"]

        def link(name: str, visual: str = "") -> None:
            lines.append(f"  <link name={quoteattr(name)}>{visual}</link>" if visual
                         else f"  <link name={quoteattr(name)}/>")

        def joint(name, kind, parent, child, xyz, axis=None, limits=None) -> None:
            x = " ".join(f"{v:.9g}" for v in xyz)
            extra = f'<axis xyz="{" ".join(f"{v:.9g}" for v in axis)}"/>' if axis is not None else ""
            if limits is not None:
                extra += f'<limit lower="{limits[0]:.9g}" upper="{limits[1]:.9g}" effort="0" velocity="0"/>'
            lines.append(f"  <joint name={quoteattr(name)} type=\"{kind}\"><parent link={quoteattr(parent)}/>"
                         f"<child link={quoteattr(child)}/><origin xyz=\"{x}\" rpy=\"0 0 0\"/>{extra}</joint>")

        for k, lk in enumerate(body.links):
            frame = self.link_frame[lk.name]
            link(frame, _bone_visual(lk))
            if k == 0:
                joint(f"{lk.name}_fixed{s}", "fixed", self.root, frame, tfs[frame].translation)
                continue
            parent = self.link_frame[lk.parent]
            if lk.joint == "ball":
                link(f"{lk.name}_x{s}")
                link(f"{lk.name}_y{s}")
                joint(f"{lk.name}_x{s}", "continuous", parent, f"{lk.name}_x{s}", tfs[f"{lk.name}_x{s}"].translation,
                      (1, 0, 0))
                joint(f"{lk.name}_y{s}", "continuous", f"{lk.name}_x{s}", f"{lk.name}_y{s}", (0, 0, 0), (0, 1, 0))
                joint(f"{lk.name}_z{s}", "continuous", f"{lk.name}_y{s}", frame, (0, 0, 0), (0, 0, 1))
            else:
                joint(f"{lk.name}{s}", "revolute", parent, frame, tfs[frame].translation, lk.axis,
                      (float(lk.lower[0]), float(lk.upper[0])))
        for n in body.joint_names:
            if self.joint_frame_is_link[n]:
                continue
            frame = self.joint_frame[n]
            link(frame)
            joint(f"{n}_fixed{s}", "fixed", tfs[frame].parent, frame, tfs[frame].translation)
        lines.append("</robot>")
        return "\n".join(lines) + "\n"


def _rx(a: float) -> np.ndarray:
    return Rotation.from_rotvec([a, 0.0, 0.0]).as_matrix()


def _ry(b: float) -> np.ndarray:
    return Rotation.from_rotvec([0.0, b, 0.0]).as_matrix()


def _rz(c: float) -> np.ndarray:
    return Rotation.from_rotvec([0.0, 0.0, c]).as_matrix()


def _bone_visual(lk) -> str:
    """A cylinder from the link origin to its end point (the bone), radius of its first shape."""
    length = float(np.linalg.norm(lk.end))
    if length < 1e-6:
        return ""
    radius = lk.shapes[0].as_capsule()[2] if lk.shapes else 0.03
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        R = Rotation.align_vectors([lk.end / length], [[0.0, 0.0, 1.0]])[0]
    rpy = R.as_euler("xyz")  # URDF rpy: fixed-axis roll, pitch, yaw
    c = lk.end / 2
    return (f'<visual><origin xyz="{c[0]:.6g} {c[1]:.6g} {c[2]:.6g}" rpy="{rpy[0]:.6g} {rpy[1]:.6g} {rpy[2]:.6g}"/>'
            f'<geometry><cylinder length="{length:.6g}" radius="{radius:.6g}"/></geometry></visual>')


# ---------------------------------------------------------------------- messages


def transform_stamped_msg(f: MsgFactory, tf: FrameTransform, stamp_ns: int, q: np.ndarray | None = None):
    """geometry_msgs/TransformStamped; q: ``tf.quaternion()`` if already computed."""
    q = tf.quaternion() if q is None else q
    t = tf.translation
    return f("geometry_msgs/msg/TransformStamped", header=header_msg(f, stamp_ns, tf.parent), child_frame_id=tf.child,
             transform=f("geometry_msgs/msg/Transform",
                         translation=f("geometry_msgs/msg/Vector3", x=float(t[0]), y=float(t[1]), z=float(t[2])),
                         rotation=f("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2], w=q[3])))


def tf_message(f: MsgFactory, transforms: list[FrameTransform], stamp_ns: int):
    """tf2_msgs/TFMessage. The quaternions in one batched call (the same values as one by one, ~20x
    faster for a body's ~60 transforms)."""
    quats = Rotation.from_matrix(np.stack([tf.rotation for tf in transforms])).as_quat() if transforms else []
    return f("tf2_msgs/msg/TFMessage",
             transforms=[transform_stamped_msg(f, tf, stamp_ns, q) for tf, q in zip(transforms, quats, strict=True)])


def ids_list_msg(f: MsgFactory, ids: list[str], stamp_ns: int, frame_id: str = ""):
    """hri_msgs/IdsList (REP 155 /humans/bodies/tracked)."""
    return f("hri_msgs/msg/IdsList", header=header_msg(f, stamp_ns, frame_id), ids=list(ids))


def joint_state_msg(f: MsgFactory, names: list[str], positions: np.ndarray, stamp_ns: int, frame_id: str = ""):
    """sensor_msgs/JointState (positions only)."""
    return f("sensor_msgs/msg/JointState", header=header_msg(f, stamp_ns, frame_id), name=list(names),
             position=[float(v) for v in positions], velocity=[], effort=[])
