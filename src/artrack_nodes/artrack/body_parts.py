"""The loose-limbed body's 10 parts: tapered cylinders mapped onto the body model (ALGORITHMS.md §4 Model).

Each part is a rigid 6-DOF node: state = proximal point (world, m) + unit
quaternion (scipy ``xyzw``, world_from_part). A part's frame is the frame of
its body-model link (link frames are aligned with the world at the rest
pose, limbs hang along -z), except that the torso part has its origin at the
pelvis origin and the torso link's rotation (one cylinder pelvis -> neck).

Geometry comes from the body model (``config/body_model.yaml``): the axis runs
from the link origin to its distal point, the proximal radius is the largest
capsule radius among the link's shapes (``Shape.as_capsule``) and the distal
radius the smaller of that and the child link's radius (tapering limbs); the
torso's cross-section is elliptic (its ellipsoid's depth and width). The
15 output joints (``BodyModel.joint_names``) are rigid points of the parts,
found at the rest pose, so a set of part poses scores with evaluation.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .body_model import BodyModel

#: the 10 parts, in node order
PART_NAMES = ("torso", "head", "l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm",
              "l_thigh", "l_shin", "r_thigh", "r_shin")
#: undirected spatial edges (parent, child) between adjacent parts
SPATIAL_EDGES = (("torso", "head"), ("torso", "l_upper_arm"), ("l_upper_arm", "l_forearm"),
                 ("torso", "r_upper_arm"), ("r_upper_arm", "r_forearm"), ("torso", "l_thigh"),
                 ("l_thigh", "l_shin"), ("torso", "r_thigh"), ("r_thigh", "r_shin"))
#: left/right mirror of each part (shouters do not tell left from right)
MIRROR = {"l_upper_arm": "r_upper_arm", "l_forearm": "r_forearm", "l_thigh": "r_thigh", "l_shin": "r_shin"}
MIRROR.update({v: k for k, v in list(MIRROR.items())})
_CHILD_LINK = {"l_upper_arm": "l_forearm", "l_forearm": "l_hand", "r_upper_arm": "r_forearm",
               "r_forearm": "r_hand", "l_thigh": "l_shin", "l_shin": "l_foot", "r_thigh": "r_shin",
               "r_shin": "r_foot"}
#: where the head cylinder starts along its axis (m): the neck is thinner than the head
_HEAD_START = 0.05


@dataclass
class PartGeometry:
    """Tapered cylinders of the parts, all arrays indexed by part (P = 10).

    axis (P, 3) unit axis in the part frame; start, end (P,) m along the axis
    (the cylinder spans start..end from the part origin); r_start, r_end (P,)
    radii (m) at the two ends; link (P,) body-model link index whose rotation
    the part carries; origin_link (P,) the link whose origin is the part
    origin; section (P, 2) cross-section scale along the part's x and y axes
    (1, 1: circular; the torso is elliptic, see part_geometry); joint_part
    (J,), joint_point (J, 3): each output joint as a point of
    a part (part frame, m); joint_names (J,).
    """

    names: tuple[str, ...]
    axis: np.ndarray
    start: np.ndarray
    end: np.ndarray
    r_start: np.ndarray
    r_end: np.ndarray
    link: np.ndarray
    origin_link: np.ndarray
    section: np.ndarray
    joint_part: np.ndarray
    joint_point: np.ndarray
    joint_names: list[str]

    @property
    def n_parts(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    @property
    def length(self) -> np.ndarray:
        """(P,) cylinder lengths, m."""
        return self.end - self.start


def _link_radius(body: BodyModel, name: str) -> float:
    return max(sh.as_capsule()[2] for sh in body.link(name).shapes)


def part_geometry(body: BodyModel) -> PartGeometry:
    """The 10 tapered cylinders and the joint map of ``body`` (standard link names required)."""
    axis, start, end, r0, r1, link, origin, section = [], [], [], [], [], [], [], []
    for name in PART_NAMES:
        lk = body.link(name)
        if name == "torso":
            length = float(lk.offset[2] + lk.end[2])  # pelvis origin -> neck
            a = np.array([0.0, 0.0, 1.0])
            s, e = 0.0, length
            ra = rb = _link_radius(body, "torso")
            # elliptic cross-section from the torso's largest ellipsoid (depth x, width y): a circular
            # cylinder would leave the torso's twist, and with it the shoulders and hips, unobservable
            ell = max((sh for sh in lk.shapes if sh.kind == "ellipsoid"), key=lambda sh: float(np.prod(sh.radii)))
            section.append(ell.radii[:2] / ra)
            origin.append(body.link_index("pelvis"))
        else:
            a = lk.end / np.linalg.norm(lk.end)
            s, e = (_HEAD_START if name == "head" else 0.0), lk.length
            ra = _link_radius(body, name)
            rb = min(ra, _link_radius(body, _CHILD_LINK[name])) if name in _CHILD_LINK else ra
            section.append(np.ones(2))
            origin.append(body.link_index(name))
        axis.append(a)
        start.append(s)
        end.append(e)
        r0.append(ra)
        r1.append(rb)
        link.append(body.link_index(name))
    origin_link = np.array(origin, int)
    # Output joints as rigid part points, found at the rest pose (all frames world-aligned there).
    joints_rest = body.joint_positions(body.rest_pose())
    T = body.forward_kinematics(body.rest_pose())
    origins = T[origin_link, :3, 3]
    part_of_link = {}
    for p, name in enumerate(PART_NAMES):
        part_of_link[name] = p
    part_of_link["pelvis"] = PART_NAMES.index("torso")
    for child, parent in (("l_hand", "l_forearm"), ("r_hand", "r_forearm"), ("l_foot", "l_shin"),
                          ("r_foot", "r_shin")):
        part_of_link[child] = PART_NAMES.index(parent)
    jp = np.array([part_of_link[body.link_names[li]] for li in body.joint_links], int)
    jpt = joints_rest - origins[jp]
    return PartGeometry(names=PART_NAMES, axis=np.array(axis), start=np.array(start), end=np.array(end),
                        r_start=np.array(r0), r_end=np.array(r1), link=np.array(link, int),
                        origin_link=origin_link, section=np.array(section), joint_part=jp, joint_point=jpt,
                        joint_names=list(body.joint_names))


def parts_from_theta(body: BodyModel, geometry: PartGeometry, theta: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Part poses of body poses theta (..., n_dof): positions (..., P, 3) m and quaternions (..., P, 4) xyzw."""
    T = body.forward_kinematics(theta)
    pos = T[..., :3, 3][..., geometry.origin_link, :]
    R = T[..., geometry.link, :3, :3]
    quat = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(*R.shape[:-2], 4)
    return pos, quat


def joints_from_parts(geometry: PartGeometry, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """The output joints (..., J, 3) world (m) of part poses pos (..., P, 3), quat (..., P, 4)."""
    pos = np.asarray(pos, float)
    quat = np.asarray(quat, float)
    R = Rotation.from_quat(quat.reshape(-1, 4)).as_matrix().reshape(*quat.shape[:-1], 3, 3)
    Rj = R[..., geometry.joint_part, :, :]
    return pos[..., geometry.joint_part, :] + np.einsum("...jab,jb->...ja", Rj, geometry.joint_point)


def cylinder_points(geometry: PartGeometry, part: int, pos: np.ndarray, quat: np.ndarray,
                    n_axial: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis samples of part ``part`` at poses pos (N, 3), quat (N, 4).

    Returns centres (N, n_axial, 3) world points on the axis, radii (n_axial,) m
    and the world axis direction (N, 3).
    """
    s = np.linspace(0.0, 1.0, n_axial + 2)[1:-1]
    along = geometry.start[part] + s * (geometry.end[part] - geometry.start[part])
    radii = geometry.r_start[part] + s * (geometry.r_end[part] - geometry.r_start[part])
    axis_w = Rotation.from_quat(quat).apply(geometry.axis[part])
    centres = pos[:, None, :] + along[None, :, None] * axis_w[:, None, :]
    return centres, radii, axis_w
