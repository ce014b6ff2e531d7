"""Articulated body model: links, joints, limits, shapes, blob features, forward kinematics.

The model is read from ``config/body_model.yaml`` (see that file for the
schema). It is a kinematic tree of rigid links in topological order (root
first). Each link frame has its origin at the link's proximal joint; at the
rest pose all link frames are aligned with the world (body upright facing +x,
x forward, y left, z up; limbs hang along -z).

Pose vector ``theta`` (n_dof,), radians and metres::

    [root xyz (3, world, m), root rotation vector (3, world_from_root),
     then each non-root link's dofs in link order:
       ball  -> 3: rotation vector of parent_from_link (relative to the parent),
       hinge -> 1: angle about the link's ``axis`` (parent frame)]

Forward kinematics is vectorised over any leading batch shape (``(..., n_dof)``)
with a Python loop over the links only, so 500 particles cost one call.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from .config import parse_yaml, yaml_error_text
from .errors import BodyModelError
from .lie import cross, left_jacobian_so3, skew
from .types import Blob3D

JOINT_TYPES = ("free", "ball", "hinge")
N_DOF = {"free": 6, "ball": 3, "hinge": 1}
SHAPE_TYPES = ("capsule", "ellipsoid", "sphere")
DEFAULT_COLOUR_CLASSES = ("skin", "shirt", "trousers", "shoes", "hair")
CONFIG_NAME = "body_model.yaml"
AUTO = "auto"  # a blob centre / radii derived from the link's shapes
#: the limb joints (elbows, wrists, knees, ankles), by the end of their names (l_elbow, r_elbow, ...)
LIMB_JOINT_KINDS = ("elbow", "wrist", "knee", "ankle")


def limb_joint_indices(joint_names) -> list[int]:
    """Indices of the limb joints (:data:`LIMB_JOINT_KINDS`) in ``joint_names``: the joints the
    blob tracker infers and the edges observe (the benches' "limbs"), which a re-seed holds loosely."""
    return [i for i, name in enumerate(joint_names) if name.split("_")[-1] in LIMB_JOINT_KINDS]


@dataclass
class Shape:
    """One solid primitive in its link's frame (m).

    kind: 'capsule' (p0, p1 segment end points, radius), 'ellipsoid' (centre,
    radii (3,) semi-axes along the link axes) or 'sphere' (centre, radius).
    colour: colour class for rendering.
    """

    kind: str
    colour: str
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radii: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.0

    def as_capsule(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(p0 (3,), p1 (3,), radius) of a capsule approximating this shape (link frame).

        Spheres are zero-length capsules; an ellipsoid becomes a capsule along
        its longest semi-axis with the mean of the two others as radius.
        """
        if self.kind == "capsule":
            return self.p0.copy(), self.p1.copy(), float(self.radius)
        if self.kind == "sphere":
            return self.centre.copy(), self.centre.copy(), float(self.radius)
        order = np.argsort(self.radii)
        r = float(0.5 * (self.radii[order[0]] + self.radii[order[1]]))
        half = max(float(self.radii[order[2]]) - r, 0.0)
        axis = np.zeros(3)
        axis[order[2]] = half
        return self.centre - axis, self.centre + axis, r


@dataclass
class BlobFeature:
    """A coloured blob carried by a link: colour class, centre (3,) in the link
    frame (m) and radii (3,) 1-sigma extents along the link axes (m).

    In the YAML either may be ``auto``: the mean and the per-axis standard deviation of the
    link's visible surface in the blob's colour, seen from cameras around the body at rest
    (ALGORITHMS.md §1: a blob is the Gaussian of its pixels; a hand-set centre in the middle of
    a shape misses what hides part of it, e.g. hair over the face, the pelvis over a thigh)."""

    colour: str
    centre: np.ndarray
    radii: np.ndarray
    #: the fields given as 'auto' in the YAML, derived from the link's shapes
    #: (:func:`artrack.body_quadrics.visible_surface_gaussian`)
    derived: tuple[str, ...] = ()


@dataclass
class Link:
    """One rigid link of the tree.

    offset: (3,) origin of this link in the parent frame (root: rest world
    position); axis: (3,) unit hinge axis (zeros unless hinge); lower/upper:
    (n_dof,) limits; rest: (n_dof,) rest-pose dof values; end: (3,) distal
    point in the link frame; dof_slice: this link's slice of theta.
    """

    name: str
    parent: str | None
    joint: str
    offset: np.ndarray
    axis: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    rest: np.ndarray
    end: np.ndarray
    colour: str
    shapes: list[Shape]
    blob: BlobFeature | None = None
    dof_slice: slice = field(default_factory=lambda: slice(0, 0))

    @property
    def n_dof(self) -> int:
        """Number of degrees of freedom of this link's joint."""
        return N_DOF[self.joint]

    @property
    def length(self) -> float:
        """Bone length |end|, m."""
        return float(np.linalg.norm(self.end))


class BodyModel:
    """The articulated body (see module docstring for frames and theta layout).

    Attributes: links (topological order, root first), link_names,
    parent_index (L,) int (-1 for the root), n_dof, lower/upper (n_dof,),
    dof_names (n_dof,), joint_names (J,), joint_links (J,) link index,
    joint_points (J, 3) link frame, blob_labels (B,), blob_links (B,),
    colour_classes.
    """

    def __init__(
        self,
        links: list[Link],
        joints: list[tuple[str, int, np.ndarray]],
        colour_classes: tuple[str, ...] = DEFAULT_COLOUR_CLASSES,
        name: str = "body",
        source: str = "<memory>",
    ):
        self.name = name
        self.source = source
        self.links = links
        self.link_names = [lk.name for lk in links]
        index = {n: i for i, n in enumerate(self.link_names)}
        self.parent_index = np.array([-1 if lk.parent is None else index[lk.parent] for lk in links], int)
        self.colour_classes = tuple(colour_classes)
        start = 0
        dof_names: list[str] = []
        for lk in links:
            lk.dof_slice = slice(start, start + lk.n_dof)
            start += lk.n_dof
            if lk.joint == "free":
                dof_names += [f"{lk.name}.{c}" for c in ("x", "y", "z", "rx", "ry", "rz")]
            elif lk.joint == "ball":
                dof_names += [f"{lk.name}.{c}" for c in ("rx", "ry", "rz")]
            else:
                dof_names.append(f"{lk.name}.hinge")
        self.n_dof = start
        self.dof_names = dof_names
        self.lower = np.concatenate([lk.lower for lk in links])
        self.upper = np.concatenate([lk.upper for lk in links])
        self.joint_names = [j[0] for j in joints]
        self.joint_links = np.array([j[1] for j in joints], int)
        self.joint_points = np.array([j[2] for j in joints], float).reshape(-1, 3)
        self.blob_links = np.array([i for i, lk in enumerate(links) if lk.blob is not None], int)
        self.blob_labels = [links[i].name for i in self.blob_links]
        self._blob_centres = np.array([links[i].blob.centre for i in self.blob_links], float).reshape(-1, 3)
        self._blob_radii = np.array([links[i].blob.radii for i in self.blob_links], float).reshape(-1, 3)
        self._offsets = np.array([lk.offset for lk in links], float)
        # Jacobian bookkeeping: the link each dof moves, and which links each link carries.
        self._dof_link = np.concatenate([np.full(lk.n_dof, i) for i, lk in enumerate(links)]).astype(int)
        carries = np.eye(len(links), dtype=bool)
        for i in range(len(links)):
            if self.parent_index[i] >= 0:
                carries[i] |= carries[self.parent_index[i]]
        #: (L, L) bool: link a is link l or an ancestor of l (l lies on a's subtree)
        self.link_carried_by = carries
        #: (L, n_dof) bool: dof d moves link l
        self.dof_moves_link = carries[:, self._dof_link]
        rv = [np.arange(lk.dof_slice.start + (3 if lk.joint == "free" else 0), lk.dof_slice.stop)
              for lk in links if lk.joint in ("free", "ball")]
        hinge = [lk.dof_slice.start for lk in links if lk.joint == "hinge"]
        self._dof_kinds = (
            np.array(rv, int).reshape(-1, 3),  # rotation-vector dofs, 3 per link (root: its last 3)
            np.array([i for i, lk in enumerate(links) if lk.joint in ("free", "ball")], int),
            np.array(hinge, int),
            np.array([i for i, lk in enumerate(links) if lk.joint == "hinge"], int),
            np.array([lk.axis for lk in links if lk.joint == "hinge"], float).reshape(-1, 3),
            np.concatenate([np.arange(lk.dof_slice.start, lk.dof_slice.start + 3)
                            for lk in links if lk.joint == "free"] or [np.zeros(0)]).astype(int),
        )
        # Forward-kinematics bookkeeping: hinge generators K and K², the roots' translation dofs,
        # and the links grouped by depth in the tree (parents before children).
        hinge_axes = self._dof_kinds[4]
        k = skew(hinge_axes)
        self._hinge_k = (k, k @ k)
        roots = [i for i in range(len(links)) if self.parent_index[i] < 0]
        self._fk_roots = (np.array(roots, int),
                          np.array([np.arange(links[i].dof_slice.start, links[i].dof_slice.start + 3)
                                    for i in roots], int).reshape(-1, 3))
        depth = np.zeros(len(links), int)
        for i in range(len(links)):
            if self.parent_index[i] >= 0:
                depth[i] = depth[self.parent_index[i]] + 1
        self._fk_levels = [(np.flatnonzero(depth == d), self.parent_index[depth == d])
                           for d in range(1, int(depth.max(initial=0)) + 1)]
        # Flattened capsule view of all shapes.
        p0, p1, rad, li, col = [], [], [], [], []
        for i, lk in enumerate(links):
            for sh in lk.shapes:
                a, b, r = sh.as_capsule()
                p0.append(a)
                p1.append(b)
                rad.append(r)
                li.append(i)
                col.append(sh.colour)
        self._cap_p0 = np.array(p0, float).reshape(-1, 3)
        self._cap_p1 = np.array(p1, float).reshape(-1, 3)
        self._cap_radius = np.array(rad, float)
        self._cap_link = np.array(li, int)
        self._cap_colour = col

    # ------------------------------------------------------------------ basics
    def __repr__(self) -> str:
        return f"BodyModel({self.name!r}, {len(self.links)} links, {self.n_dof} dof, from {self.source})"

    def link_index(self, name: str) -> int:
        """Index of the link called ``name`` (KeyError if unknown)."""
        return self.link_names.index(name)

    def link(self, name: str) -> Link:
        """The link called ``name``."""
        return self.links[self.link_index(name)]

    def dof_slice(self, name: str) -> slice:
        """Slice of theta holding the dofs of link ``name``."""
        return self.link(name).dof_slice

    def rest_pose(self) -> np.ndarray:
        """(n_dof,) rest pose: root at its YAML offset, upright, all joints at their rest values."""
        return np.concatenate([lk.rest for lk in self.links]).astype(float)

    def clip(self, theta: np.ndarray) -> np.ndarray:
        """theta (..., n_dof) clipped to the joint limits (a new array)."""
        return np.clip(theta, self.lower, self.upper)

    def within_limits(self, theta: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(...,) bool: every dof of theta (..., n_dof) lies within its limits (± tol)."""
        theta = np.asarray(theta, float)
        return np.all((theta >= self.lower - tol) & (theta <= self.upper + tol), axis=-1)

    # --------------------------------------------------------------- kinematics
    def forward_kinematics(self, theta: np.ndarray) -> np.ndarray:
        """World poses of all links.

        theta: (..., n_dof). Returns world_from_link (..., L, 4, 4): rotation
        block = world_from_link rotation, translation = link origin in the
        world (m).
        """
        theta = np.asarray(theta, float)
        if theta.shape[-1] != self.n_dof:
            raise ValueError(f"theta has {theta.shape[-1]} dofs, body model {self.name!r} has {self.n_dof}")
        batch = theta.shape[:-1]
        flat = theta.reshape(-1, self.n_dof)
        n = flat.shape[0]
        n_links = len(self.links)
        rv_cols, rv_links, hinge_cols, hinge_links, _, _ = self._dof_kinds
        # Link-major (L, n, 4, 4), first parent_from_link: the fixed offsets, all rotation vectors
        # (ball joints and the root) in one scipy call, all hinges by Rodrigues' formula at once.
        T = np.empty((n_links, n, 4, 4))
        T[:, :, 3, :3] = 0.0
        T[:, :, 3, 3] = 1.0
        T[:, :, :3, 3] = self._offsets[:, None, :]
        if len(rv_links):
            mats = Rotation.from_rotvec(flat[:, rv_cols].reshape(-1, 3)).as_matrix()
            T[rv_links, :, :3, :3] = mats.reshape(n, len(rv_links), 3, 3).swapaxes(0, 1)
        if len(hinge_links):
            k, kk = self._hinge_k
            ang = flat[:, hinge_cols].T[..., None, None]  # (hinges, n, 1, 1)
            T[hinge_links, :, :3, :3] = np.eye(3) + np.sin(ang) * k[:, None] + (1.0 - np.cos(ang)) * kk[:, None]
        roots, root_cols = self._fk_roots
        T[roots, :, :3, 3] = flat[:, root_cols].swapaxes(0, 1)
        # The tree level by level (all links of one depth at once): world_from_link =
        # world_from_parent @ parent_from_link, in place (a level's parents are all done).
        for idx, par in self._fk_levels:
            T[idx] = T[par] @ T[idx]
        return T.swapaxes(0, 1).reshape(*batch, n_links, 4, 4)

    def dof_twists(self, theta: np.ndarray, world_from_link: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """World velocities of the dofs at theta (n_dof,): (v (n_dof, 3), w (n_dof, 3)) such that a point y
        (world, m) on a link that dof d moves (:attr:`dof_moves_link`) moves by ``(v_d + w_d × y) dθ_d``.

        Root translation: ``v = e_k``, ``w = 0``. A rotation about the link origin o with world angular
        velocity w: ``v = o × w``; ball and root rotation vectors: ``w = R_link J_r(θ_link)`` (the right
        Jacobian of SO(3), ``J_r(θ) = J_l(−θ)``, :func:`artrack.lie.left_jacobian_so3`), hinges: ``w = R_link axis``."""
        theta = np.asarray(theta, float).reshape(self.n_dof)
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        rv, rv_link, hinge, hinge_link, hinge_axis, trans = self._dof_kinds
        w = np.zeros((self.n_dof, 3))
        if len(rv):
            W = T[rv_link, :3, :3] @ left_jacobian_so3(-theta[rv])  # columns: world axes of the 3 dofs
            w[rv] = np.swapaxes(W, 1, 2)
        if len(hinge):
            w[hinge] = np.einsum("hij,hj->hi", T[hinge_link, :3, :3], hinge_axis)
        v = cross(T[self._dof_link, :3, 3], w)
        v[trans] = np.eye(3)[np.arange(len(trans)) % 3]
        return v, w

    def point_jacobian(self, theta: np.ndarray, link_idx: np.ndarray, points: np.ndarray,
                       world_from_link: np.ndarray | None = None,
                       twists: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(P, 3, n_dof): d(world position)/d(theta) of link-frame points (P, 3) on links link_idx (P,);
        ``twists``: :meth:`dof_twists` at theta if already computed."""
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        link_idx = np.asarray(link_idx, int)
        x = self.transform_points(T, link_idx, np.asarray(points, float).reshape(-1, 3))
        v, w = self.dof_twists(theta, T) if twists is None else twists
        vel = v[None] + cross(w[None], x[:, None, :])  # (P, n_dof, 3)
        return np.swapaxes(vel * self.dof_moves_link[link_idx][..., None], 1, 2)

    def link_twist_jacobian(self, theta: np.ndarray, link_idx: np.ndarray,
                            world_from_link: np.ndarray | None = None,
                            twists: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(G, 6, n_dof): the links' motions in their own frames per unit dof, ``(v, w)`` as in
        :mod:`artrack.lie` (``E(θ + dθ) ≈ E(θ) exp(J dθ)``); ``twists`` as for :meth:`point_jacobian`."""
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        link_idx = np.asarray(link_idx, int)
        v, w = self.dof_twists(theta, T) if twists is None else twists
        R, o = T[link_idx, :3, :3], T[link_idx, :3, 3]
        lin = v[None] + cross(w[None], o[:, None, :])  # (G, n_dof, 3): velocity of each link origin
        out = np.concatenate([np.einsum("gji,gdj->gid", R, lin), np.einsum("gji,dj->gid", R, w)], axis=1)
        return out * self.dof_moves_link[link_idx][:, None, :]

    @staticmethod
    def transform_points(world_from_link: np.ndarray, link_idx: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Map link-frame points to the world.

        world_from_link: (..., L, 4, 4); link_idx: (P,) int; points: (P, 3) in
        their link frames. Returns (..., P, 3) world, m.
        """
        T = world_from_link[..., link_idx, :, :]
        return np.einsum("...pij,pj->...pi", T[..., :3, :3], points) + T[..., :3, 3]

    def joint_positions(self, theta: np.ndarray, world_from_link: np.ndarray | None = None) -> np.ndarray:
        """(..., J, 3) world positions (m) of the output joints ``joint_names`` for theta (..., n_dof).

        Pass ``world_from_link`` (from forward_kinematics) to skip recomputing it.
        """
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        return self.transform_points(T, self.joint_links, self.joint_points)

    def link_end_points(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bone segments: (origins (..., L, 3), ends (..., L, 3)) in the world, m."""
        T = self.forward_kinematics(theta)
        ends = np.array([lk.end for lk in self.links])
        return T[..., :3, 3], self.transform_points(T, np.arange(len(self.links)), ends)

    def blob_centres(self, theta: np.ndarray, world_from_link: np.ndarray | None = None) -> np.ndarray:
        """(..., B, 3) world centres (m) of the blob features, in ``blob_labels`` order."""
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        return self.transform_points(T, self.blob_links, self._blob_centres)

    def blob_gaussians(self, theta: np.ndarray,
                       world_from_link: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Blob features as world Gaussians: (means (..., B, 3) m, covs (..., B, 3, 3) m²).

        cov = R diag(radii²) Rᵀ with R the link's world rotation.
        """
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        means = self.transform_points(T, self.blob_links, self._blob_centres)
        R = T[..., self.blob_links, :3, :3]
        covs = np.einsum("...ij,...j,...kj->...ik", R, self._blob_radii**2, R)
        return means, covs

    def blobs3d(self, theta: np.ndarray) -> list[Blob3D]:
        """Ground-truth 3-D blobs (one per blob label) for a single pose theta (n_dof,)."""
        means, covs = self.blob_gaussians(np.asarray(theta, float).reshape(self.n_dof))
        return [Blob3D(label=lab, mean=means[k].copy(), cov=covs[k].copy())
                for k, lab in enumerate(self.blob_labels)]

    def capsules(self, theta: np.ndarray,
                 world_from_link: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
        """All shapes as world capsules (ellipsoids/spheres approximated, see Shape.as_capsule).

        Returns p0 (..., S, 3), p1 (..., S, 3) world segment end points (m),
        radius (S,) m, link index (S,) int, colour class list (S,).
        """
        T = self.forward_kinematics(theta) if world_from_link is None else world_from_link
        p0 = self.transform_points(T, self._cap_link, self._cap_p0)
        p1 = self.transform_points(T, self._cap_link, self._cap_p1)
        return p0, p1, self._cap_radius.copy(), self._cap_link.copy(), list(self._cap_colour)


# ---------------------------------------------------------------------- loading
def default_config_path(name: str = CONFIG_NAME) -> Path:
    """Locate a config file: $ARTRACK_CONFIG_DIR, then <repo>/config relative to
    this file, then the installed share/artrack_nodes/config (ament_index)."""
    tried = []
    env = os.environ.get("ARTRACK_CONFIG_DIR")
    if env:
        p = Path(env) / name
        if p.is_file():
            return p
        tried.append(str(p))
    p = Path(__file__).resolve().parent.parent.parent.parent / "config" / name
    if p.is_file():
        return p
    tried.append(str(p))
    try:
        from ament_index_python.packages import get_package_share_directory

        p = Path(get_package_share_directory("artrack_nodes")) / "config" / name
        if p.is_file():
            return p
        tried.append(str(p))
    except Exception:  # noqa: BLE001 - ament not importable or package not installed
        tried.append("ament_index share/artrack_nodes/config")
    raise BodyModelError(f"{name}: not found (tried {', '.join(tried)})")


def load_body_model(path: str | os.PathLike | None = None) -> BodyModel:
    """Load and validate a body model YAML (default: see default_config_path).

    Raises BodyModelError naming the file, the link and the field on any
    inconsistency.
    """
    path = default_config_path() if path is None else Path(path)
    return body_model_from_dict(_read_model_yaml(Path(path), ()), source=str(path))


def _read_model_yaml(path: Path, chain: tuple[str, ...]) -> Any:
    """The parsed YAML of a body model file, with ``extends`` resolved (schema at the top of
    config/body_model.yaml): the base file's mapping (path relative to this file's folder),
    this file's other top-level fields replacing the base's, then ``link_overrides``
    ({link name: {field: value}}) replacing fields of the named links."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise BodyModelError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    try:
        data = parse_yaml(text)
    except yaml.YAMLError as exc:
        raise BodyModelError(f"{path}: not valid YAML ({yaml_error_text(exc)})") from exc
    if not isinstance(data, dict) or "extends" not in data:
        if isinstance(data, dict) and "link_overrides" in data:
            raise BodyModelError(f"{path}: field 'link_overrides' needs 'extends' (the body model it changes)")
        return data
    base_name = data["extends"]
    if not isinstance(base_name, str) or not base_name:
        raise BodyModelError(f"{path}: field 'extends' must be a file name, got {base_name!r}")
    base_path = (path.parent / base_name).resolve()
    if str(base_path) in chain:
        raise BodyModelError(f"{path}: 'extends' loops back to {base_path}")
    base = _read_model_yaml(base_path, (*chain, str(path.resolve())))
    if not isinstance(base, dict):
        raise BodyModelError(f"{base_path} (extended by {path}): top level must be a mapping")
    merged = {**base, **{k: v for k, v in data.items() if k not in ("extends", "link_overrides")}}
    overrides = data.get("link_overrides") or {}
    if not isinstance(overrides, dict):
        raise BodyModelError(f"{path}: field 'link_overrides' must map link names to fields")
    links = [dict(lk) if isinstance(lk, dict) else lk for lk in merged.get("links") or []]
    by_name = {lk.get("name"): lk for lk in links if isinstance(lk, dict)}
    for name, fields in overrides.items():
        if name not in by_name:
            raise BodyModelError(f"{path}: link_overrides: unknown link '{name}' (not in {base_path.name})")
        if not isinstance(fields, dict) or "name" in fields or "parent" in fields:
            raise BodyModelError(f"{path}: link_overrides.{name}: must be a mapping of link fields "
                                 "(not 'name' or 'parent')")
        by_name[name].update(fields)
    merged["links"] = links
    return merged


def body_model_from_dict(data: Any, source: str = "<dict>") -> BodyModel:
    """Build a BodyModel from the parsed YAML mapping (schema in config/body_model.yaml)."""
    if not isinstance(data, dict):
        raise BodyModelError(f"{source}: top level must be a mapping with 'links' and 'joints'")
    colours = tuple(data.get("colour_classes") or DEFAULT_COLOUR_CLASSES)
    raw_links = data.get("links")
    if not isinstance(raw_links, list) or not raw_links:
        raise BodyModelError(f"{source}: field 'links' must be a non-empty list")
    links: list[Link] = []
    seen: dict[str, int] = {}
    for k, raw in enumerate(raw_links):
        link = _parse_link(raw, k, seen, colours, source)
        seen[link.name] = k
        links.append(link)
    raw_joints = data.get("joints")
    if not isinstance(raw_joints, list) or not raw_joints:
        raise BodyModelError(f"{source}: field 'joints' must be a non-empty list")
    joints = []
    names = set()
    for k, rj in enumerate(raw_joints):
        if not isinstance(rj, dict) or "name" not in rj or "link" not in rj:
            raise BodyModelError(f"{source}: joints[{k}] needs fields 'name', 'link', 'point'")
        jn = str(rj["name"])
        if jn in names:
            raise BodyModelError(f"{source}: joint '{jn}' defined twice")
        names.add(jn)
        if rj["link"] not in seen:
            raise BodyModelError(f"{source}: joint '{jn}' names unknown link '{rj['link']}'")
        pt = _vec(rj.get("point", [0.0, 0.0, 0.0]), 3, source, f"joint '{jn}'", "point")
        joints.append((jn, seen[rj["link"]], pt))
    body = BodyModel(links, joints, colours, name=str(data.get("name", "body")), source=source)
    if not any(lk.blob is not None and lk.blob.derived for lk in links):
        return body
    key = json.dumps(data, sort_keys=True, default=str)
    gaussians = _DERIVED_BLOBS.get(key)
    if gaussians is None:
        from .body_quadrics import visible_surface_gaussian  # that module builds on this one

        gaussians = {}
        for k, lk in enumerate(links):
            if lk.blob is not None and lk.blob.derived:
                try:
                    gaussians[k] = visible_surface_gaussian(body, k, lk.blob.colour)
                except ValueError as exc:
                    raise BodyModelError(f"{source}: link '{lk.name}' field 'blob': 'auto' needs a visible "
                                         f"shape of the blob's colour ({exc})") from exc
        _DERIVED_BLOBS[key] = gaussians
    for k, (mean, cov) in gaussians.items():
        blob = links[k].blob
        if "centre" in blob.derived:
            blob.centre = mean.copy()
        if "radii" in blob.derived:
            blob.radii = np.sqrt(np.diag(cov))
    return BodyModel(links, joints, colours, name=str(data.get("name", "body")), source=source)


#: derived blob Gaussians per body-model document (JSON text): ~0.3 s to derive, loaded often
_DERIVED_BLOBS: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {}


def _vec(value: Any, n: int, source: str, where: str, fld: str) -> np.ndarray:
    try:
        arr = np.asarray(value, float)
    except (TypeError, ValueError) as exc:
        raise BodyModelError(f"{source}: {where} field '{fld}' must be {n} numbers, got {value!r}") from exc
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise BodyModelError(f"{source}: {where} field '{fld}' must be {n} finite numbers, got {value!r}")
    return arr


def _colour(value: Any, colours: tuple[str, ...], source: str, where: str, fld: str) -> str:
    if value not in colours:
        raise BodyModelError(f"{source}: {where} field '{fld}': unknown colour class {value!r} "
                             f"(expected one of {', '.join(colours)})")
    return str(value)


def _parse_link(raw: Any, k: int, seen: dict[str, int], colours: tuple[str, ...], source: str) -> Link:
    if not isinstance(raw, dict) or "name" not in raw:
        raise BodyModelError(f"{source}: links[{k}] must be a mapping with a 'name'")
    name = str(raw["name"])
    where = f"link '{name}'"
    if name in seen:
        raise BodyModelError(f"{source}: {where} defined twice")
    parent = raw.get("parent")
    if parent is None:
        if k != 0:
            raise BodyModelError(f"{source}: {where} has no parent, but only the first link (the root) may")
    else:
        parent = str(parent)
        if k == 0:
            raise BodyModelError(f"{source}: {where} is the first link (the root): "
                                 "it must have 'parent: null'")
        if parent not in seen:
            raise BodyModelError(f"{source}: {where} names unknown parent '{parent}'"
                                 " (parents must be listed before their children)")
    joint = raw.get("joint")
    if joint not in JOINT_TYPES:
        raise BodyModelError(f"{source}: {where} field 'joint': unknown joint type {joint!r} "
                             f"(expected one of {', '.join(JOINT_TYPES)})")
    if (joint == "free") != (k == 0):
        raise BodyModelError(f"{source}: {where} field 'joint': only the root link has a 'free' joint")
    n = N_DOF[joint]
    offset = _vec(raw.get("offset", [0.0, 0.0, 0.0]), 3, source, where, "offset")
    axis = np.zeros(3)
    if joint == "hinge":
        if "axis" not in raw:
            raise BodyModelError(f"{source}: {where} field 'axis' is required for a hinge joint")
        axis = _vec(raw["axis"], 3, source, where, "axis")
        norm = np.linalg.norm(axis)
        if norm < 1e-9:
            raise BodyModelError(f"{source}: {where} field 'axis' must be non-zero")
        axis = axis / norm
    limits = raw.get("limits")
    if limits is None:
        raise BodyModelError(f"{source}: {where} field 'limits' is missing ({n} [lower, upper] pairs)")
    try:
        lim = np.asarray(limits, float)
    except (TypeError, ValueError) as exc:
        raise BodyModelError(f"{source}: {where} field 'limits' must be {n} [lower, upper] pairs") from exc
    if lim.shape != (n, 2):
        got = len(limits) if isinstance(limits, list) else limits
        raise BodyModelError(f"{source}: {where} field 'limits': expected {n} [lower, upper] pairs for a "
                             f"{joint} joint, got {got}")
    if np.any(lim[:, 0] > lim[:, 1]):
        raise BodyModelError(f"{source}: {where} field 'limits': lower > upper")
    if joint == "free":
        rest = np.concatenate([offset, np.zeros(3)])
    else:
        rest = np.zeros(n)
    if "rest" in raw:
        rest = _vec(raw["rest"], n, source, where, "rest")
    if np.any(rest < lim[:, 0]) or np.any(rest > lim[:, 1]):
        raise BodyModelError(f"{source}: {where} field 'rest' lies outside 'limits'")
    end = _vec(raw.get("end", [0.0, 0.0, 0.0]), 3, source, where, "end")
    colour = _colour(raw.get("colour", colours[0]), colours, source, where, "colour")
    shapes = []
    raw_shapes = raw.get("shapes") or []
    if not isinstance(raw_shapes, list):
        raise BodyModelError(f"{source}: {where} field 'shapes' must be a list")
    for s, rs in enumerate(raw_shapes):
        fld = f"shapes[{s}]"
        if not isinstance(rs, dict):
            raise BodyModelError(f"{source}: {where} field '{fld}' must be a mapping")
        kind = rs.get("type")
        if kind not in SHAPE_TYPES:
            raise BodyModelError(f"{source}: {where} field '{fld}.type': unknown shape {kind!r} "
                                 f"(expected one of {', '.join(SHAPE_TYPES)})")
        sc = _colour(rs.get("colour", colour), colours, source, where, f"{fld}.colour")
        sh = Shape(kind=kind, colour=sc)
        if kind == "capsule":
            sh.p0 = _vec(rs.get("p0", [0.0, 0.0, 0.0]), 3, source, where, f"{fld}.p0")
            sh.p1 = _vec(rs.get("p1", end), 3, source, where, f"{fld}.p1")
            sh.radius = _positive(rs.get("radius"), source, where, f"{fld}.radius")
        elif kind == "sphere":
            sh.centre = _vec(rs.get("centre", [0.0, 0.0, 0.0]), 3, source, where, f"{fld}.centre")
            sh.radius = _positive(rs.get("radius"), source, where, f"{fld}.radius")
        else:
            sh.centre = _vec(rs.get("centre", [0.0, 0.0, 0.0]), 3, source, where, f"{fld}.centre")
            sh.radii = _vec(rs.get("radii"), 3, source, where, f"{fld}.radii")
            if np.any(sh.radii <= 0):
                raise BodyModelError(f"{source}: {where} field '{fld}.radii' must be positive")
        shapes.append(sh)
    blob = None
    if raw.get("blob") is not None:
        rb = raw["blob"]
        if not isinstance(rb, dict):
            raise BodyModelError(f"{source}: {where} field 'blob' must be a mapping")
        # 'auto': derived from the link's shapes once the whole body is known (body_model_from_dict)
        derived = tuple(f for f in ("centre", "radii") if rb.get(f) == AUTO)
        blob = BlobFeature(
            colour=_colour(rb.get("colour", colour), colours, source, where, "blob.colour"),
            centre=np.zeros(3) if "centre" in derived
            else _vec(rb.get("centre", [0.0, 0.0, 0.0]), 3, source, where, "blob.centre"),
            radii=np.ones(3) if "radii" in derived else _vec(rb.get("radii"), 3, source, where, "blob.radii"),
            derived=derived,
        )
        if np.any(blob.radii <= 0):
            raise BodyModelError(f"{source}: {where} field 'blob.radii' must be positive")
    return Link(name=name, parent=parent, joint=joint, offset=offset, axis=axis, lower=lim[:, 0].copy(),
                upper=lim[:, 1].copy(), rest=rest, end=end, colour=colour, shapes=shapes, blob=blob)


def _positive(value: Any, source: str, where: str, fld: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise BodyModelError(f"{source}: {where} field '{fld}' must be a positive number, "
                             f"got {value!r}") from exc
    if not v > 0:
        raise BodyModelError(f"{source}: {where} field '{fld}' must be positive, got {value!r}")
    return v
