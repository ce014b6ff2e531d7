"""The estimators' common frame (ALGORITHMS.md §1): the 3-D blobs, the tracking life cycle, start-up.

``Estimator`` is the base of the three estimators (``artrack.skeleton.make_estimator``): the
baseline (``baseline_estimator``) and the Kalman-filtered skeleton, kinematic or with full
dynamics (``kalman_skeleton``). It triangulates the labelled 2-D blobs of a frame into 3-D blobs
(with the gates and screens below), starts, verifies, re-acquires and loses the track, and leaves
the frame's pose to the subclass (``_initialise``, ``_step``, ``_estimate``, ``_predict``).
``BodyKinematics`` maps the body model's theta to free rigid link poses and back for the
constraint solver. The shared rules follow; the subclasses' own are in their modules.

Representation: the skeleton state is the world pose of every link
(``constraints.py``: each link a free rigid body, joints as constraints), so
joints hold exactly (‖c‖ < 1e-9) and bone lengths are rigid. The output is
read back as the body model's theta (relative rotations, clipped to the limits)
and re-evaluated by the body model's forward kinematics, so ``joints`` and
``links`` are always exactly consistent with the body model.

Blob covariances in the output (``measurement.blob_cov``): ``'shape+state'``
(default) is the blob's spatial extent (body model radii, rotated) plus the
state covariance of its centre (P_post for the estimate, P_prior for the
prediction) — the spatial prior the 2-D pixel classifier needs; ``'state'`` is
the state covariance only.

Start-up (``STATUS_INITIALIZING`` until a pose exists): from labelled blobs
(≥ ``tracking.min_blobs`` labels) a multi-start fit over the heading; otherwise
from the start-up classes: the ``foreground`` blob is triangulated to the body
centre, ``skin`` blobs are matched across views (candidate correspondences seeded
from camera pairs, extended to the other views, scored by reprojection error,
picked greedily; a speck, none of whose blobs is ``startup.min_skin_size_m`` large, is no
candidate; an oversized blob only sees a point, and takes nothing from another; with
``startup.start_radius_m`` > 0 only those within that horizontal
distance of ``startup.start_xy``: the person standing there when several are in view;
and, with ``startup.person_gap_m`` > 0, grouped into people by their horizontal gaps, of
which the fullest group whose face is nearest ``start_xy`` is kept, :func:`nearest_person`),
the highest becomes the head (face), the two others the hands (a hand must be
matched in ``startup.min_hand_views`` views: a point only two views agree on is more
often a skin-coloured ghost; a view where the two hands merge into one blob counts for
both, ``startup.share_taken_views``);
the heading is taken from the face's horizontal offset from the body axis and
from the line between the hands (whose two perpendicular choices are tried), and
the rest pose rotated about z is fitted for each candidate, held near that heading
(``startup.heading_sigma_rad``), keeping the most consistent. When one camera
alone sees the person (:func:`one_view_start_points`, ``startup.one_view_depth_sigma_m``) no ray
meets another: the body is placed where the foreground centroid's ray comes down to the rest
pose's centroid height (standing on z = 0), the face and hands on their rays at that depth, held
to the rays only, and the heading comes from the hand line alone. For
``tracking.verify_frames`` frames after any initialisation the
mirrored hypothesis (heading + π, left <-> right) is fitted too and taken over if
it explains the labelled blobs much better (knees and elbows bend one way only); so are, heading
kept, the hands with their labels exchanged (``tracking.verify_swap_groups``): a lone start-up
hand raised in front of the chest is put on the side of the body axis it lies on, which can be wrong.
While tracking, from the first frame on (alongside that verification), the face
check (``tracking.facing_*``, :func:`facing_agreement`) turns a body that faces
backwards, with every left/right label swapped to match, round: the head's skin
blob is the face in the views it looks at and only the neck behind it, so its
sizes tell the facing that the blob positions cannot. A heading can also drift round while
the hands' own labels stay right; at the turn the hands (``tracking.facing_turn_groups``)
keep their labels where the left one lies left of the right one at the new heading.
A hand lost by its 2-D labels (one that moved faster than its prediction, so the
gates around the prior found nothing) is re-acquired (``tracking.reacquire_*``,
:meth:`Estimator._reacquire`) where the views' unlabelled skin blobs meet within
the arm's reach of its shoulder, away from the other observed blobs; the baseline
first fits the arm alone to it, since the robust fit would take a target that far
from the old pose for an outlier. The opposite case, a hand's labels that agree across
views (two or more) on a point beyond the arm's reach (``tracking.reach_gate_margin`` times it, from
the shoulder of the current pose: the label sits on another person's face), is not used
(:meth:`Estimator._gate_reach`), and the hand may then be re-acquired.
``STATUS_LOST`` after ``tracking.lost_after_frames`` consecutive frames with fewer
than ``tracking.min_blobs`` usable blobs (triangulated; for the Kalman tracker:
passing the innovation gate); while lost, ``predict`` carries no blobs (so the
2-D trackers fall back to their start-up classes) and the tracker re-initialises
as at start-up (unless ``tracking.relocalise_from_blobs`` is false: then only
``reseed`` — another estimator's body, e.g. the loose-limbed one — restarts it).

One or two cameras (``few_cameras`` in config/skeleton.yaml, applied by
:meth:`SkeletonConfig.for_cameras` to an estimator given at most ``few_cameras.max_cameras``): every
blob (one camera) or many (two) are then seen by one view, and such a blob's depth along the ray is
the prediction's (the prior it was triangulated with), which fed back on itself and, with one
camera, ran away (metres within seconds). The body fits count such blobs across their ray only
(``measurement.one_view_depth_sigma_m`` along it), the kinematic filters take their depth from
the frame's body fit (the ray's point nearest that fit's blob), and the fits get what one view
lacks: the floor contact (``fit.ground_sigma_m``) and an upright trunk (``fit.upright_sigma_m``,
:class:`UprightSegment`): on descending rays, a body standing on the floor has one depth.

Units: metres, radians, seconds (stamps in integer ns); world frame z up.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np

from .body_fit import BodyTerms, GroundContact, LinkGoals, PointTarget, UprightSegment, fit_pose, mirror_label
from .body_model import BodyModel, limb_joint_indices
from .cameras import Camera
from .constraints import BallJoints, ConstraintSolver, HingeAxes, exp_so3, log_so3
from .errors import InputError
from .hidden import hide
from .projection import Capsule, off_image_margin_px, visible_points
from .skeleton_config import FOREGROUND, SKIN, load_skeleton_config
from .startup import (
    facing_direction,
    forward_xy,
    match_skin_blobs,
    nearest_in_gate,
    nearest_person,
    one_view_start_points,
    ray_information,
    root_heading,
)
from .triangulation import associate_views, drop_slivers, triangulate_blobs
from .types import (
    STATUS_INITIALIZING,
    STATUS_LOST,
    STATUS_TRACKING,
    Blob2D,
    Blob3D,
    BodyEstimate,
    LinkEstimate,
    all_finite,
)

__all__ = ["BodyKinematics", "Estimator", "n_seen"]


# =========================================================================== body kinematics
class BodyKinematics:
    """The body model as free rigid links + joint constraints (ALGORITHMS.md §1).

    p (L, 3): link origins (proximal joints), R (L, 3, 3): world_from_link
    rotations. ``constraints``: for each non-root link a ball joint
    (PointCoincidence of the parent's attachment point ``offset`` with the
    child's origin) and, for hinges, a HingeAxis about the hinge axis.
    masses (L,) kg, inertias (L, 3, 3) about the centre of mass, com (L, 3)
    link frame: from the link shapes at 1000 kg/m³.
    """

    def __init__(self, body: BodyModel):
        self.body = body
        self.n_links = len(body.links)
        self.parent = np.asarray(body.parent_index, int)
        child = np.flatnonzero(self.parent >= 0)
        hinge = np.array([i for i in child if body.links[i].joint == "hinge"], int)
        self.constraints: list = [
            BallJoints(
                self.parent[child], [body.links[i].offset for i in child], child, np.zeros((child.size, 3))
            )
        ]
        if hinge.size:
            axes = np.array([body.links[i].axis for i in hinge])
            self.constraints.append(HingeAxes(self.parent[hinge], axes, hinge, axes))
        self.masses, self.inertias, self.com = _mass_properties(body)
        self.blob_links = np.asarray(body.blob_links, int)
        self.blob_labels = list(body.blob_labels)
        self.blob_local = np.array([body.links[i].blob.centre for i in self.blob_links], float).reshape(-1, 3)
        self.blob_index = {lab: k for k, lab in enumerate(self.blob_labels)}
        self.rest = body.rest_pose()
        self.rest_local = np.array(
            [self.local_rotation(i, self.rest[lk.dof_slice]) for i, lk in enumerate(body.links)]
        )
        self.non_root_dofs = np.zeros(body.n_dof, bool)
        self.non_root_dofs[6:] = True
        self.link_of_dof = np.zeros(body.n_dof, int)  # (n_dof,) the link each dof belongs to
        for i, lk in enumerate(body.links):
            self.link_of_dof[lk.dof_slice] = i
        # theta_from_poses: the non-root links' dof columns, by joint kind (index into links[1:])
        non_root = list(enumerate(body.links[1:]))
        self._ball = np.array([j for j, lk in non_root if lk.joint == "ball"], int)
        self._ball_dofs = np.array([np.arange(lk.dof_slice.start, lk.dof_slice.start + 3) for _, lk in non_root
                                    if lk.joint == "ball"], int).reshape(-1, 3)
        self._hinge = np.array([j for j, lk in non_root if lk.joint != "ball"], int)
        self._hinge_dofs = np.array([lk.dof_slice.start for _, lk in non_root if lk.joint != "ball"], int)
        self._hinge_axes = np.array([lk.axis for _, lk in non_root if lk.joint != "ball"], float).reshape(-1, 3)

    def solver(self, method: str = "cg") -> ConstraintSolver:
        """A ConstraintSolver over this body's links and joints."""
        return ConstraintSolver(self.n_links, self.constraints, self.masses, self.inertias, method, self.com)

    def poses(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics: theta (n_dof,) -> p (L, 3), R (L, 3, 3)."""
        T = self.body.forward_kinematics(np.asarray(theta, float))
        return T[:, :3, 3].copy(), T[:, :3, :3].copy()

    def local_rotation(self, i: int, dofs: np.ndarray) -> np.ndarray:
        """(3, 3) parent_from_link rotation of link i for its dofs (root: world_from_root)."""
        lk = self.body.links[i]
        dofs = np.asarray(dofs, float)
        if lk.joint == "free":
            return exp_so3(dofs[3:6])
        if lk.joint == "ball":
            return exp_so3(dofs)
        return exp_so3(lk.axis * float(dofs[0]))

    def theta_from_poses(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Relative joint values of link poses (inverse of FK for consistent poses; the
        non-root positions are implied by the joints). Not clipped to the limits."""
        theta = np.zeros(self.body.n_dof)
        theta[0:3] = p[0]
        rel = np.swapaxes(R[self.parent[1:]], 1, 2) @ R[1:]
        w = log_so3(np.concatenate([R[:1], rel[self._ball]]))  # the root's rotation, then the balls'
        theta[3:6] = w[0]
        if self._ball.size:
            theta[self._ball_dofs] = w[1:]
        if self._hinge.size:  # the angle about the hinge axis
            Rr = rel[self._hinge]
            vee = 0.5 * np.stack(
                [Rr[:, 2, 1] - Rr[:, 1, 2], Rr[:, 0, 2] - Rr[:, 2, 0], Rr[:, 1, 0] - Rr[:, 0, 1]], axis=1
            )
            cos = 0.5 * (np.trace(Rr, axis1=1, axis2=2) - 1.0)
            theta[self._hinge_dofs] = np.arctan2(np.einsum("ni,ni->n", vee, self._hinge_axes), cos)
        return theta

    def blob_points(self, p: np.ndarray, R: np.ndarray) -> np.ndarray:
        """(B, 3) world blob centres of link poses."""
        return p[self.blob_links] + np.einsum("bij,bj->bi", R[self.blob_links], self.blob_local)

    def body_centroid_local(self) -> np.ndarray:
        """(3,) mass centroid of the rest pose in the root link frame, m."""
        p, R = self.poses(self.rest)
        com_w = p + np.einsum("lij,lj->li", R, self.com)
        c = (self.masses[:, None] * com_w).sum(0) / self.masses.sum()
        return R[0].T @ (c - p[0])


def _mass_properties(body: BodyModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Masses (L,) kg, inertias about the CoM (L, 3, 3) kg m², CoM (L, 3) link frame, from the
    shapes (each as its capsule) at the density of water; a link without shapes gets 0.1 kg."""
    n = len(body.links)
    masses, inertias, com = np.full(n, 0.1), np.tile(np.eye(3) * 1e-4, (n, 1, 1)), np.zeros((n, 3))
    for i, lk in enumerate(body.links):
        parts = []
        for sh in lk.shapes:
            a, b, r = sh.as_capsule()
            length = float(np.linalg.norm(b - a))
            vol = math.pi * r * r * length + 4.0 / 3.0 * math.pi * r**3
            if sh.kind == "ellipsoid":
                vol = 4.0 / 3.0 * math.pi * float(np.prod(sh.radii))
            axis = (b - a) / length if length > 1e-9 else np.zeros(3)
            parts.append((1000.0 * vol, 0.5 * (a + b), r, length, axis))
        if not parts:
            continue
        m = sum(q[0] for q in parts)
        c = sum(q[0] * q[1] for q in parts) / m
        inertia = np.zeros((3, 3))
        for ms, cs, r, length, axis in parts:
            d = cs - c
            inertia += ms * (0.4 * r * r * np.eye(3) + length**2 / 12.0 * (np.eye(3) - np.outer(axis, axis)))
            inertia += ms * (d @ d * np.eye(3) - np.outer(d, d))
        masses[i], inertias[i], com[i] = m, inertia + 1e-6 * np.eye(3), c
    return masses, inertias, com


# =========================================================================== estimators
class Estimator:
    """The base of the three estimators (module docstring): a frame's labelled 2-D blobs to 3-D
    blobs, the track's status and start-up, the face check, re-acquisition and the output. A
    subclass gives the pose: ``_initialise``, ``_step``, ``_estimate`` and ``_predict``."""

    kind = ""

    def __init__(self, body: BodyModel, cameras: Iterable[Camera] | Mapping[str, Camera], config=None):
        self.body = body
        cams = list(cameras.values()) if isinstance(cameras, Mapping) else list(cameras)
        self.cameras = {c.name: c for c in cams}
        self.cfg = load_skeleton_config(config).for_cameras(len(self.cameras))
        self.kin = BodyKinematics(body)
        self.labels = set(self.kin.blob_labels)
        self._centroid_local = self.kin.body_centroid_local()
        f = self.cfg.fit
        #: soft floor contact of the body fits (baseline frames, initialisation), or None
        terms = [GroundContact.from_body(body, f.ground_sigma_m, f.floor_z_m)] if f.ground_sigma_m > 0 else []
        if f.upright_sigma_m > 0:
            terms.append(UprightSegment.from_body(body, f.upright_sigma_m))
        #: the upright head (``fit.upright_head_sigma_m``; off for a body model without a 'head' link and
        #: joint), also in the kinematic filters' outlier fit
        has_head = "head" in body.link_names and "head" in body.joint_names
        self._upright_head = (UprightSegment.link_axis(body, f.upright_head_sigma_m, "head", "head")
                              if f.upright_head_sigma_m > 0 and has_head else None)
        if self._upright_head is not None:
            terms.append(self._upright_head)
        #: soft floor contact, upright trunk and head of the body fits, or None
        self._ground = None if not terms else terms[0] if len(terms) == 1 else BodyTerms(terms)
        self._reach = self._arm_reach()
        sided = {lab[2:] for lab in body.blob_labels if lab[:2] == "l_" and "r_" + lab[2:] in body.blob_labels}
        for name, parts in (("fit.mirror_groups", {p for g in f.mirror_groups for p in g}),
                            ("tracking.facing_turn_groups", {p for g in self.cfg.tracking.facing_turn_groups
                                                             for p in g}),
                            ("measurement.view_association", set(self.cfg.measurement.view_association)),
                            ("fit.overlap_parts", set(f.overlap_parts))):
            unknown = sorted(parts - sided)
            if unknown:
                raise InputError(f"skeleton config: field '{name}' names part '{unknown[0]}', which has "
                                 f"no l_/r_ blob pair (pairs: {', '.join(sorted(sided))})")
        t = self.cfg.tracking
        if t.facing_check_frames > 0 and t.facing_label not in self.labels:
            raise InputError(f"skeleton config: field 'tracking.facing_label' names '{t.facing_label}', which "
                             f"carries no blob (blobs: {', '.join(body.blob_labels)}); "
                             "tracking.facing_check_frames: 0 turns the face check off")
        unknown = sorted(set(f.predict_velocity_links) - set(body.link_names))
        if unknown:
            raise InputError(f"skeleton config: field 'fit.predict_velocity_links' names unknown link '{unknown[0]}'")
        #: (n_dof,) bool: the dofs whose velocity the baseline's prediction extrapolates (``fit.predict_velocity_*``);
        #: the root's rotation vector is not differenced (it wraps at pi)
        self._velocity_dofs = np.ones(body.n_dof, bool)
        if f.predict_velocity_links:
            self._velocity_dofs[:] = False
            for name in f.predict_velocity_links:
                self._velocity_dofs[body.dof_slice(name)] = True
        self._velocity_dofs[3:6] = False
        unknown = sorted(set(t.reacquire_labels) - self.labels)
        if unknown:
            raise InputError(f"skeleton config: field 'tracking.reacquire_labels' names '{unknown[0]}', which "
                             f"carries no blob (blobs: {', '.join(body.blob_labels)})")
        #: re-acquired part -> (its shoulder: the origin of the top link of its chain below the nearest
        #: ancestor with a blob, the chain's length down to the part's blob centre, m)
        self._reacquire_chain = {lab: self._chain_below_blob(lab) for lab in t.reacquire_labels}
        for field_name, names in (("tracking.reach_gate_labels", t.reach_gate_labels),
                                  ("measurement.min_view_labels", self.cfg.measurement.min_view_labels),
                                  ("measurement.hidden_labels", self.cfg.measurement.hidden_labels)):
            unknown = sorted(set(names) - self.labels)
            if unknown:
                raise InputError(f"skeleton config: field '{field_name}' names '{unknown[0]}', which "
                                 f"is not a blob label of the body model ({sorted(self.labels)})")
        #: gated part -> (top link, reach m) as ``_reacquire_chain``: the re-acquired parts' chains, then
        #: ``tracking.reach_gate_labels``' through their blob-carrying parent
        self._gate_chain = dict(self._reacquire_chain)
        for lab in t.reach_gate_labels:
            self._gate_chain.setdefault(lab, self._chain_below_blob(lab, through_parent_blob=True))
        self._track_key, self._track_frames = -1, 0  # (initialisations, tracked frames since): _count_track_frame
        #: (pose, its capsules) and {label: its chain's link names}: :meth:`_pose_capsules`, :meth:`_hidden_capsules`
        self._hidden_pose: tuple[np.ndarray, list[Capsule]] | None = None
        self._hidden_chain: dict[str, set[str]] = {}
        #: {camera: [parts]} whose l_/r_ labels the last frame's view association exchanged
        self.view_swaps: dict[str, list[str]] = {}
        #: the last view association: (its input {camera: [Blob2D]}, its output), for _associate
        self._association: tuple[dict, dict] | None = None
        #: the last triangulation: (its input {camera: [Blob2D]}, its output, the labels it triangulated
        #: without the priors), for KinematicEstimator._triangulate_labelled
        self._triangulation: tuple[dict, dict, set] | None = None
        self.overlap_drops: dict[str, list[str]] = {}  # {camera: [parts left out there]} of the last frame
        pr = self.cfg.prior
        unknown = sorted(set(pr.rest_sigma_by_link) - set(body.link_names))
        if unknown:
            raise InputError(
                f"skeleton config: field 'prior.rest_sigma_by_link' names unknown link '{unknown[0]}'"
            )
        #: (L,) rest-prior sigma per link, rad; (n_dof,) per dof
        self.rest_sigma_link = np.array(
            [float(pr.rest_sigma_by_link.get(n, pr.rest_sigma_rad)) for n in body.link_names]
        )
        self.rest_sigma_dof = np.concatenate(
            [np.full(lk.n_dof, self.rest_sigma_link[i]) for i, lk in enumerate(body.links)]
        )
        #: tracks started so far (start-up, relocalisation, re-seed, face turn: each ``_initialise``;
        #: never reset, so that a reset followed by a new track still counts as a change)
        self.initialisations = 0
        self.reset()

    # -- state ---------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything (back to STATUS_INITIALIZING)."""
        self.theta: np.ndarray | None = None
        self.stamp_ns: int | None = None
        self.status = STATUS_INITIALIZING
        self.missed = 0
        self.quality = 0.0
        self.last_observed: dict[str, Blob3D] = {}
        self.timings_ms: dict[str, float] = {}  # per-stage ms of the last update
        self._start_verification()
        self._verify_left = 0
        #: frames at which the face check turned the body round (stamps, ns)
        self.facing_flips: list[int] = []
        #: parts re-acquired from unlabelled skin blobs in the last update (see :meth:`_reacquire`)
        self.reacquired: list[str] = []
        self._reseeded_at: int | None = None  # stamp of the last re-seed (:meth:`reseed`)
        self._edges = None  # the edge statistics given to the current update (:meth:`_edge_goals`)

    def _arm_reach(self) -> float:
        """Largest head-blob to hand-blob distance of the body model, m (fully stretched
        arm: head blob to shoulder plus the bone chain down to the hand blob)."""
        kin = self.kin
        if "head" not in kin.blob_index:
            return 1.0
        p, R = kin.poses(kin.rest)
        head = kin.blob_points(p, R)[kin.blob_index["head"]]
        reach = 0.0
        for hand in ("l_hand", "r_hand"):
            if hand in kin.blob_index:
                shoulder, length = self._chain_below_blob(hand)
                reach = max(reach, length + float(np.linalg.norm(p[shoulder] - head)))
        return reach if reach > 0 else 1.0

    def _chain_below_blob(self, label: str, through_parent_blob: bool = False) -> tuple[int, float]:
        """(top link, length m) of ``label``'s chain: the links from the blob's own up to, not
        including, the nearest ancestor that carries a blob (for a hand: hand, forearm, upper arm
        below the torso); the length runs from the top link's origin (the shoulder) through the
        bones to the blob centre. ``through_parent_blob``: the chain also takes in the parent link when
        it carries a blob (for a shin: shin and thigh below the pelvis, from the hip)."""
        kin, body = self.kin, self.body
        i = int(kin.blob_links[kin.blob_index[label]])
        length = float(np.linalg.norm(kin.blob_local[kin.blob_index[label]]))
        carriers = set(int(k) for k in kin.blob_links)
        if through_parent_blob and body.links[i].parent is not None:
            carriers.discard(int(kin.parent[i]))
        while body.links[i].parent is not None and int(kin.parent[i]) not in carriers:
            length += float(np.linalg.norm(body.links[i].offset))
            i = int(kin.parent[i])
        return i, length

    def _edge_goals(self) -> LinkGoals | None:
        """This frame's edge statistics (given to :meth:`update`) as soft link goals for a body fit
        (``fit.edge_sigma_px``, ``fit.edge_min_found``); None without edges."""
        f = self.cfg.fit
        return None if self._edges is None else LinkGoals.from_edges(self._edges, f.edge_sigma_px, f.edge_min_found)

    def _count_track_frame(self) -> None:
        """Count this tracked frame: ``_track_frames`` is 0 on the first one after an initialisation
        (``initialisations`` changed), then 1, 2, ... (read by :meth:`_gate_reach` and
        :meth:`_view_outlier_threshold`)."""
        if self._track_key != self.initialisations:
            self._track_key, self._track_frames = self.initialisations, 0
        else:
            self._track_frames += 1

    def _gate_reach(self, obs: dict[str, Blob3D]) -> None:
        """Drop (in place) the 3-D blobs of ``tracking.reacquire_labels`` seen in two or more views
        that lie farther than ``reach_gate_margin`` times the part's reach from its shoulder in the
        current pose (a one-view blob's depth is the prior's, so its distance says little; gating
        those too left the self-occlusion scene's hands off longer: seeds 1-6, 115 -> 122 frames
        over 150 mm). ``tracking.reach_gate_labels`` likewise, from the hip (:meth:`_chain_below_blob`
        through the parent's blob), from the ``reach_gate_after_frames``-th frame of a track on: a
        shin's label on the other leg or the trunk in two or three views drags the leg with it
        (default scene seed 1, from frame ~52: a right shin 0.5-1.2 m off, the ankle 1.5 m)."""
        t = self.cfg.tracking
        margin = t.reach_gate_margin
        if margin <= 0:
            return
        p, _ = self.kin.poses(self.theta)
        for lab, (top, reach) in self._gate_chain.items():
            if lab not in self._reacquire_chain and self._track_frames < t.reach_gate_after_frames:
                continue
            if (lab in obs and len(obs[lab].cameras) >= 2
                    and float(np.linalg.norm(obs[lab].mean - p[top])) > margin * reach):
                del obs[lab]

    def _reacquire(self, blobs_by_camera, obs: dict[str, Blob3D]) -> list[str]:
        """Lost parts found again (ALGORITHMS.md §1: the 2-D trackers follow the 3-D priors, so a
        part whose prior has left it, e.g. a hand that rose faster than the prediction, is not
        found by them again). A part of ``tracking.reacquire_labels`` without a 3-D blob seen in two
        or more views this frame takes the best 3-D point where the views' unlabelled skin blobs
        (label 'skin': the blob trackers report them while a skin label finds nothing,
        ``lost_skin_blobs``) meet (:func:`match_skin_blobs`), among the points farther than
        ``reacquire_separation_m`` from every other observed 3-D blob of the skin colour (the head,
        the other hand)
        and within ``reacquire_reach_margin`` times the part's reach of its shoulder in the current
        pose. The nearest point to the shoulder goes first; parts take distinct points. Adds the
        found blobs to ``obs`` (in place) and returns their labels."""
        t = self.cfg.tracking
        lost = [lab for lab in t.reacquire_labels if lab not in obs or len(obs[lab].cameras) < 2]
        if not lost:
            return []
        skin = {c: [b for b in bl if b.label == SKIN] for c, bl in blobs_by_camera.items()}
        if sum(1 for bl in skin.values() if bl) < 2:
            return []
        points = match_skin_blobs(skin, self.cameras)
        # only a skin-coloured part can own a skin blob: the pelvis' or a thigh's blob beside a hand
        # behind the back does not keep the hand from being found there
        others = [b.mean for lab, b in obs.items() if lab not in lost and self._skin_coloured(lab)]
        points = [p for p in points
                  if all(np.linalg.norm(p[0] - m) > t.reacquire_separation_m for m in others)]
        p, _ = self.kin.poses(self.theta)
        pairs = []
        for lab in lost:
            top, reach = self._reacquire_chain[lab]
            for k, pt in enumerate(points):
                d = float(np.linalg.norm(pt[0] - p[top]))
                if d <= t.reacquire_reach_margin * reach:
                    pairs.append((d, lab, k))
        found, used = [], set()
        for _, lab, k in sorted(pairs):
            if lab in found or k in used:
                continue
            obs[lab] = dataclasses.replace(points[k][3], label=lab)
            found.append(lab)
            used.add(k)
        return found

    def _skin_coloured(self, label: str) -> bool:
        """Whether the blob ``label`` has the skin colour class (the head, the hands)."""
        blob = self.body.link(label).blob
        return blob is not None and blob.colour == SKIN

    # -- measurements ----------------------------------------------------------
    def measurement_cov(self, blob: Blob3D) -> np.ndarray:
        """R (3, 3) m² of a triangulated blob: cov_scale · Blob3D.cov + floor² I."""
        m = self.cfg.measurement
        cov = np.asarray(blob.cov, float).reshape(3, 3)
        return m.cov_scale * 0.5 * (cov + cov.T) + m.floor_m**2 * np.eye(3)

    def _check_cameras(self, blobs_by_camera: Mapping[str, Sequence[Blob2D]]) -> None:
        for name in blobs_by_camera:
            if name not in self.cameras:
                raise InputError(
                    f"skeleton: blobs from unknown camera '{name}' (known: {', '.join(self.cameras)})"
                )

    def _triangulate(self, blobs_by_camera, priors: Mapping[str, Blob3D] | None) -> dict[str, Blob3D]:
        labelled = {c: [b for b in bl if b.label in self.labels] for c, bl in blobs_by_camera.items()}
        m = self.cfg.measurement
        labelled = self._screen_views(labelled)  # before the association
        if m.view_association:
            labelled, self.view_swaps = self._associate(labelled)
        labelled = self._drop_small_views(labelled)
        obs = self._triangulate_labelled(labelled, priors)
        obs = {k: v for k, v in obs.items() if k in self.labels}
        if (priors and self.cfg.measurement.hidden_no_view_sigma_m > 0 and self.status == STATUS_TRACKING
                and len(obs) >= self.cfg.tracking.min_blobs):
            # (only beside enough real blobs: a pseudo-measurement never keeps a track alive or starts one)
            obs.update(self._hidden_observations(labelled, priors, obs))
        return obs

    def _drop_small_views(self, labelled: dict[str, list[Blob2D]]) -> dict[str, list[Blob2D]]:
        """{camera: 2-D blobs} without the head's and hands' slivers (``measurement.min_view_fraction``,
        ``min_view_labels``; :func:`artrack.triangulation.drop_slivers`)."""
        m = self.cfg.measurement
        return drop_slivers(labelled, self.cameras, m.min_view_labels, m.min_view_fraction, m.min_view_ray_angle_deg)

    def _triangulate_labelled(self, labelled: dict[str, list[Blob2D]],
                              priors: Mapping[str, Blob3D] | None) -> dict[str, Blob3D]:
        """:func:`triangulate_blobs` of the associated blobs; remembered with its input and the labels
        that did not need ``priors`` (for :class:`KinematicEstimator`, as :meth:`_associate`)."""
        obs, prior_free = self._triangulation_of(labelled, priors)
        self._triangulation = (labelled, obs, prior_free)
        return obs

    def _triangulation_of(self, labelled: dict[str, list[Blob2D]],
                          priors: Mapping[str, Blob3D] | None) -> tuple[dict[str, Blob3D], set[str]]:
        """(:func:`triangulate_blobs` of ``labelled``, the labels it triangulated without ``priors``)."""
        prior_free: set[str] = set()
        m = self.cfg.measurement
        if priors and m.hidden_labels:
            priors = self._hidden_priors(labelled, priors)
        obs = triangulate_blobs(labelled, self.cameras, priors, view_outlier_chi2=self._view_outlier_threshold(),
                                prior_free=prior_free, small_blob_fraction=m.small_blob_fraction)
        return obs, prior_free

    def _pose_capsules(self) -> list[Capsule]:
        """The current pose's shapes as capsules (computed once per pose)."""
        if self._hidden_pose is None or not np.array_equal(self._hidden_pose[0], self.theta):
            p0, p1, radius, link, _ = self.body.capsules(self.theta)
            names = self.body.link_names
            self._hidden_pose = (np.array(self.theta, float), [Capsule(names[int(k)], a, b, float(r))
                                              for a, b, r, k in zip(p0, p1, radius, link, strict=True)])
        return self._hidden_pose[1]

    def _hidden_capsules(self, label: str) -> list[Capsule]:
        """:meth:`_pose_capsules` without those of ``label``'s chain (:meth:`_chain_below_blob`): the
        occluders of :mod:`artrack.hidden` (a drifted forearm must not explain its own hand away)."""
        if label not in self._hidden_chain:
            top, _ = self._chain_below_blob(label)
            i = int(self.kin.blob_links[self.kin.blob_index[label]])
            chain = {self.body.link_names[i]}
            while i != top:  # top is an ancestor of the blob's link
                i = int(self.kin.parent[i])
                chain.add(self.body.link_names[i])
            self._hidden_chain[label] = chain
        chain = self._hidden_chain[label]
        return [c for c in self._pose_capsules() if c.label not in chain]

    def _hide(self, label: str, prior: Blob3D, silent: list[str], ray=None) -> np.ndarray | None:
        """:func:`artrack.hidden.hide` for ``label``'s prior, with those of the cameras ``silent`` (their
        trackers found no blob of it) that looked for it: where the prior is VISIBLE by the projection's
        test (the trackers suppress a label whose prior is OCCLUDED or OFF_IMAGE, so their silence
        says nothing), and the reach of its chain from the current pose."""
        m = self.cfg.measurement
        every = [c for c in self._pose_capsules() if c.label != label]
        mean = np.asarray(prior.mean, float).reshape(1, 3)
        looked = [self.cameras[c] for c in silent
                  if visible_points(self.cameras[c], mean, label, every,
                                    inset_px=-off_image_margin_px(self.cameras[c]))[0]]
        if not looked:
            return None
        top, reach = self._chain_below_blob(label)
        p, _ = self.kin.poses(self.theta)
        return hide(label, prior.mean, prior.cov, looked, self._hidden_capsules(label),
                    ray=ray, reach=(p[top], reach), sigmas=m.hidden_sigmas,
                    miss_probability=m.hidden_miss_probability, inset_px=m.hidden_inset_px)

    def _hidden_priors(self, labelled: dict[str, list[Blob2D]], priors: Mapping[str, Blob3D]) -> Mapping[str, Blob3D]:
        """``priors`` with those of the ``measurement.hidden_labels`` that one view found moved along its
        ray to the likeliest depth given that the other views did not find them
        (:func:`artrack.hidden.hide`): the depth a one-view 3-D blob takes from its prior is then one
        the silent views allow."""
        out = None
        for lab in self.cfg.measurement.hidden_labels:
            views = [c for c, bl in labelled.items() if any(b.label == lab for b in bl)]
            if len(views) != 1 or lab not in priors or self.theta is None:
                continue
            blob = next(b for b in labelled[views[0]] if b.label == lab)
            if not all_finite(blob.mean):
                continue
            origin, d = self.cameras[views[0]].rays(np.asarray(blob.mean, float).reshape(1, 2))
            silent = [c for c in self.cameras if c != views[0]]
            x = self._hide(lab, priors[lab], silent, ray=(origin, d[0]))
            if x is not None:
                out = dict(priors) if out is None else out
                out[lab] = dataclasses.replace(priors[lab], mean=x)
        return priors if out is None else out

    def _hidden_observations(self, labelled: dict[str, list[Blob2D]], priors: Mapping[str, Blob3D],
                             obs: Mapping[str, Blob3D]) -> dict[str, Blob3D]:
        """Pseudo-measurements (no cameras) of the ``measurement.hidden_labels`` that no view found, where
        their prediction would have been seen by views that looked: the likeliest point given that
        those views did not find them (:func:`artrack.hidden.hide`), to ``hidden_no_view_sigma_m``."""
        m = self.cfg.measurement
        out = {}
        for lab in m.hidden_labels:
            if lab in obs or lab not in priors or self.theta is None:
                continue
            if any(b.label == lab for bl in labelled.values() for b in bl):
                continue  # found, but not triangulated
            x = self._hide(lab, priors[lab], list(self.cameras))
            if x is not None:
                # measurement_cov(blob) = cov_scale · cov + floor²: the sigma asked for
                var = max(m.hidden_no_view_sigma_m**2 - m.floor_m**2, 0.0) / max(m.cov_scale, 1e-12)
                out[lab] = Blob3D(lab, x, var * np.eye(3), ())
        return out

    def _view_outlier_threshold(self) -> float:
        """This frame's ``measurement.view_outlier_chi2``: 0 (off) until ``view_outlier_after_frames``
        frames of the track have been counted (:meth:`_count_track_frame`; none before the first
        after its initialisation); a new track's labels come from a start-up pose that is often wrong, and
        views that agree may then agree on the wrong thing."""
        m = self.cfg.measurement
        age = self._track_frames + 1 if self.theta is not None and self._track_key == self.initialisations else 0
        return m.view_outlier_chi2 if age >= m.view_outlier_after_frames else 0.0

    def _triangulation_priors(self, stamp_ns: int) -> dict[str, Blob3D] | None:
        return None

    def _associate(self, labelled: dict[str, list[Blob2D]]) -> tuple[dict[str, list[Blob2D]], dict[str, list[str]]]:
        """:func:`associate_views` of this frame's labelled blobs (``measurement.view_association``);
        remembered with its input (the blob objects themselves), so that an estimator run beside
        this one on the very same blobs (:class:`KinematicEstimator`'s raw tracker) reuses it."""
        m = self.cfg.measurement
        out = associate_views(labelled, self.cameras, m.view_association, m.view_association_margin_chi2)
        self._association = (labelled, out)
        return out

    def _screen_views(self, labelled: dict[str, list[Blob2D]]) -> dict[str, list[Blob2D]]:
        """The labelled 2-D blobs per camera that go on to the view association and the
        triangulation (all of them here; the baseline leaves overlapping leg pairs out)."""
        return labelled

    # -- update ----------------------------------------------------------------
    def update(self, stamp_ns: int, blobs_by_camera: Mapping[str, Sequence[Blob2D]], edges=None) -> BodyEstimate:
        """Estimate at stamp_ns from the 2-D blobs of all cameras ({camera name: [Blob2D]}) and,
        optionally, the combined edge statistics of this frame
        (:class:`artrack.edge_fusion.LinkEdgeStatistics`; soft constraints on the links,
        ALGORITHMS.md §2 "Fusion", in the baseline's body fit and in the kinematic skeleton's
        orientation fit, ``kinematic.orientation_from_fit``; the dynamic estimator ignores them)."""
        stamp_ns = int(stamp_ns)
        self._edges = edges
        self.reacquired = []
        self._check_cameras(blobs_by_camera)
        if self.stamp_ns is not None and stamp_ns < self.stamp_ns:
            self.reset()  # time went backwards (a bag looped): start again
        t0 = time.perf_counter()
        priors = self._triangulation_priors(stamp_ns) if self.theta is not None else None
        obs = self._triangulate(blobs_by_camera, priors)
        self.timings_ms = {"triangulation": 1e3 * (time.perf_counter() - t0)}
        cfg = self.cfg.tracking
        if self.theta is None or self.status == STATUS_LOST:
            theta0 = None
            if self.theta is not None and not cfg.relocalise_from_blobs:
                pass  # lost: wait for a re-seed
            elif len(obs) >= cfg.min_blobs:
                theta0 = self._init_from_labelled(obs)
            elif self._has_startup_blobs(blobs_by_camera):
                theta0 = self._init_from_startup(blobs_by_camera)
            if theta0 is not None:
                self._initialise(stamp_ns, theta0, obs)
                self._start_verification()
                self.status, self.missed = STATUS_TRACKING, 0
                self.stamp_ns = stamp_ns
                self.quality = n_seen(obs) / max(len(self.labels), 1)
                self.last_observed = obs
                return self._estimate(stamp_ns)
            if self.theta is None:
                self.stamp_ns = stamp_ns
                return BodyEstimate.empty(self.body.joint_names, stamp_ns, STATUS_INITIALIZING)
        if self._reseeded_at == stamp_ns and not obs:
            # Re-seeded for this very frame, whose blobs are the 2-D trackers' start-up classes (they had
            # no priors yet): the other estimator's body is this frame's estimate. Fitting to those
            # blobs (skin taken for hands, nothing on the trunk) bends it away before the priors come.
            self.last_observed = obs
            return self._estimate(stamp_ns)
        if self.status == STATUS_TRACKING:
            self._count_track_frame()
            self._gate_reach(obs)
            self.reacquired = self._reacquire(blobs_by_camera, obs)
        t1 = time.perf_counter()
        self._step(stamp_ns, obs)  # may add its own stages to timings_ms
        stages = sum(v for k, v in self.timings_ms.items() if k != "triangulation")
        self.timings_ms["pose"] = 1e3 * (time.perf_counter() - t1) - stages
        self.missed = self.missed + 1 if self._n_used(obs) < cfg.min_blobs else 0
        if self.missed >= cfg.lost_after_frames:
            self.status = STATUS_LOST
        elif self.status != STATUS_LOST:
            self.status = STATUS_TRACKING
        self.stamp_ns = stamp_ns
        self.quality = n_seen(obs) / max(len(self.labels), 1)
        self.last_observed = obs
        if self._verify_left > 0 and len(obs) >= cfg.min_blobs:
            self._verify_facing(stamp_ns, obs)
        if self.status == STATUS_TRACKING and cfg.facing_check_frames > 0:  # from the first frame, beside it
            self._check_facing(stamp_ns, blobs_by_camera, obs)
        return self._estimate(stamp_ns)

    def check_reseed_joints(self, joints: np.ndarray) -> np.ndarray:
        """``joints`` as a (J, 3) float array for :meth:`reseed`; InputError if they are not J finite points."""
        joints = np.asarray(joints, dtype=float)
        if joints.shape != (len(self.body.joint_names), 3) or not np.all(np.isfinite(joints)):
            raise InputError(f"skeleton: reseed joints must be {len(self.body.joint_names)} finite 3-D points, "
                             f"got shape {joints.shape}")
        return joints

    def reseed(self, stamp_ns: int, joints: np.ndarray, sigma_m: float = 0.05,
               limb_sigma_m: float | None = None) -> bool:
        """Re-initialise from another estimator's body when this one is lost or has not started
        (ALGORITHMS.md §4: the loose-limbed body "hands its poses to the skeleton"): the body model
        fitted to the 15 output joints (``joints`` (J, 3) world m, order ``body.joint_names``,
        isotropic ``sigma_m``; the elbows, wrists, knees and ankles at ``limb_sigma_m``, by default
        ``tracking.reseed_limb_sigma_m``) from the rest pose at four headings. Returns whether it
        was taken (False while tracking). InputError for a wrong shape or non-finite joints."""
        joints = self.check_reseed_joints(joints)
        if self.theta is not None and self.status != STATUS_LOST:
            return False
        self._reseeded_at = int(stamp_ns)
        limb = self.cfg.tracking.reseed_limb_sigma_m if limb_sigma_m is None else float(limb_sigma_m)
        sigmas = np.full(len(self.body.joint_names), sigma_m)
        sigmas[limb_joint_indices(self.body.joint_names)] = limb
        targets = [PointTarget(int(k), pt, y, np.eye(3) / sigma**2)
                   for k, pt, y, sigma in zip(self.body.joint_links, self.body.joint_points, joints, sigmas,
                                              strict=True)]
        theta = self._fit_four_headings(targets, joints.mean(axis=0),
                                        self.body.joint_positions(self.kin.rest).mean(axis=0))
        # never ahead of frames still to come (update() would take that for time going backwards)
        stamp_ns = int(stamp_ns) if self.stamp_ns is None else min(int(stamp_ns), self.stamp_ns)
        self._initialise(stamp_ns, theta, {})
        self._start_verification()
        self.status, self.missed, self.stamp_ns = STATUS_TRACKING, 0, stamp_ns
        return True

    # -- facing verification ----------------------------------------------------
    def _start_verification(self) -> None:
        self._verify_left = self.cfg.tracking.verify_frames
        self._reset_verification_sums()
        self._facing: list[float] = []  # the face check's cosines, newest last (a new track starts afresh)
        self._facing_ways: list[np.ndarray] = []  # ... and the facing directions they came from

    def _reset_verification_sums(self) -> None:
        """The verification's summed fit costs and the hypotheses' last fits, back to none."""
        self._verify_n = 0
        self._cost_current = self._cost_flipped = 0.0
        self._flip_theta: np.ndarray | None = None
        groups = self.cfg.tracking.verify_swap_groups
        # per tracking.verify_swap_groups group: the (current, exchanged) fit costs of each frame that
        # observed one of its parts, the newest last
        self._cost_swapped: list[list[tuple[float, float]]] = [[] for _ in groups]
        self._swap_theta: list[np.ndarray | None] = [None] * len(groups)

    def _mirrored(self, obs: Mapping[str, Blob3D], keep: Iterable[str] = ()) -> dict[str, Blob3D]:
        """The blobs with their left and right labels exchanged (l_ <-> r_; others kept, and those of
        the parts in ``keep``, named without the side prefix)."""
        keep = set(keep)
        return self._exchanged(obs, lambda part: part not in keep)

    def _exchanged(self, obs: Mapping[str, Blob3D], exchange: Callable[[str], bool]) -> dict[str, Blob3D]:
        """The blobs with the left and right labels (l_ <-> r_) of the parts for which ``exchange(part)``
        (the part named without the side prefix) is true exchanged; every other label kept."""
        out = {}
        for lab, blob in obs.items():
            m = mirror_label(lab) if exchange(lab[2:]) else lab
            if m in self.labels:
                out[m] = dataclasses.replace(blob, label=m)
        return out

    def _check_facing(self, stamp_ns: int, blobs_by_camera, obs: Mapping[str, Blob3D]) -> None:
        """The face check while tracking (:func:`facing_agreement` of the ``tracking.facing_label``
        blob at the estimated pose): when the mean of the last ``tracking.facing_check_frames``
        cosines is below ``tracking.facing_flip_cosine`` (or that of the last
        ``tracking.facing_quick_frames`` below ``tracking.facing_quick_cosine``), the body faces backwards with its
        left/right labels swapped to match; it is turned round as in the verification (the rest
        pose fitted to the blobs with their labels exchanged; those of a ``tracking.facing_turn_groups``
        group kept where its left parts already lie left of its right ones), to the heading the sizes point to
        (the mean of those frames' :func:`facing_direction`; heading + π if they cancel). A
        heading off sideways (cosine near 0) is left to the fit: turning it round would not help."""
        t = self.cfg.tracking
        link = int(self.kin.blob_links[self.kin.blob_index[t.facing_label]])
        blobs = {name: b for name, bl in blobs_by_camera.items() for b in bl if b.label == t.facing_label}
        pose = self.body.forward_kinematics(self.theta)[link]
        direction = facing_direction(blobs, self.cameras, pose[:3, 3], t.facing_min_size_ratio)
        if direction is None:
            return
        self._facing = (self._facing + [float(forward_xy(pose) @ direction)])[-t.facing_check_frames:]
        self._facing_ways = (self._facing_ways + [direction])[-t.facing_check_frames:]
        n = len(self._facing)
        if n >= t.facing_check_frames and np.mean(self._facing) < t.facing_flip_cosine:
            ways = self._facing_ways
        elif 0 < t.facing_quick_frames <= n and np.mean(self._facing[-t.facing_quick_frames:]) < t.facing_quick_cosine:
            ways = self._facing_ways[-t.facing_quick_frames:]
        else:
            return
        way = np.mean(ways, axis=0)
        yaw = (math.atan2(way[1], way[0]) if np.linalg.norm(way) > 0.1
               else root_heading(exp_so3(self.theta[3:6])) + math.pi)
        # Each turn group's labels are kept where, as labelled, its left parts lie left of its right
        # ones at the heading turned to (a lone part: on its own side of the root), as the
        # start-up orders its hands; exchanged otherwise, as every other sided label is.
        left = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        keep = set()
        for group in t.facing_turn_groups:
            vote = 0.0
            for part in group:
                lb, rb = obs.get("l_" + part), obs.get("r_" + part)
                if lb is not None and rb is not None:
                    vote += float((lb.mean - rb.mean) @ left)
                elif lb is not None or rb is not None:
                    sign, blob = (1.0, lb) if lb is not None else (-1.0, rb)
                    vote += sign * float((blob.mean - self.theta[0:3]) @ left)
            if vote > 0.0:
                keep |= set(group)
        mirrored = self._mirrored(obs, keep)
        theta_f, _ = self._init_fit(self._blob_targets(mirrored), self._rest_at(self.theta[0:3], yaw))
        self._initialise(stamp_ns, theta_f, mirrored)
        self.last_observed = mirrored
        self._facing, self._facing_ways = [], []
        self._verify_left = 0  # the face settled it; the verification's sums were of the other heading
        self.facing_flips.append(int(stamp_ns))

    def _verify_facing(self, stamp_ns: int, obs: Mapping[str, Blob3D]) -> None:
        """Right after initialisation the heading may be off by π with left and right
        swapped (a symmetric pose looks the same). For ``tracking.verify_frames`` frames
        the labelled blobs are also fitted under the mirrored hypothesis (labels l_ <-> r_,
        heading + π); joint limits (knees and elbows bend one way) make the wrong one
        costlier. If the accumulated cost of the mirrored fit falls below
        ``flip_cost_ratio`` times the current one, the tracker re-initialises mirrored.

        A start can also get one group's sides wrong at the right heading: a lone hand raised in
        front of the chest is put on the side of the body axis it lies on (rotation scene seed 10:
        the right hand, 5 cm left of the axis, started as the left hand; the other hand, once found,
        became the right one, and the arms stayed crossed, both hands 0.4-0.7 m off). So each
        ``tracking.verify_swap_groups`` group's labels are exchanged (heading kept) and fitted as
        well, by the same rule: accumulated cost below ``flip_cost_ratio`` times the current one
        re-initialises with them exchanged (seed 10: ratio 0.24-0.29 from the fourth frame on; the
        right starts of default seeds 3 and 7, line seed 1, rotation seed 3 and distractor seed 3:
        0.97 at the lowest single frame, 1.9-3.6 at the tenth percentile). The ratio is also taken
        over the group's last ``tracking.verify_swap_recent_frames`` observed frames alone, the lower
        one deciding: frames before the evidence fit either labelling alike (rotation seed 19: nine
        frames at 0.9-1.0, then 0.3-0.5, the sums below 0.5 only 16 frames after the start)."""
        f, t = self.cfg.fit, self.cfg.tracking
        mirrored = self._mirrored(obs)
        targets, targets_m = self._blob_targets(obs), self._blob_targets(mirrored)
        _, cost_c, _ = fit_pose(
            self.body, self.theta, targets, self.kin.rest, self.rest_sigma_dof, None, 1.0, f.max_nfev,
            tolerance=f.tolerance,
        )
        swaps = []
        for g, group in enumerate(t.verify_swap_groups):
            if not any(lab[2:] in group for lab in obs):
                continue  # none of the group's parts is observed: exchanging changes nothing
            exchanged = self._exchanged(obs, lambda part, group=group: part in group)
            start = self.theta if self._swap_theta[g] is None else self._swap_theta[g]
            theta_s, cost_s, _ = fit_pose(
                self.body, start, self._blob_targets(exchanged), self.kin.rest, self.rest_sigma_dof, None,
                1.0, f.max_nfev, tolerance=f.tolerance,
            )
            self._swap_theta[g] = theta_s
            costs = self._cost_swapped[g]
            costs.append((cost_c, cost_s))
            ratio = sum(c[1] for c in costs) / max(sum(c[0] for c in costs), 1e-12)
            n = t.verify_swap_recent_frames
            if 0 < n <= len(costs):
                c_n, s_n = np.sum(costs[-n:], axis=0)
                ratio = min(ratio, s_n / max(c_n, 1e-12))
            swaps.append((ratio, theta_s, exchanged))
        if self._flip_theta is None:
            yaw = root_heading(exp_so3(self.theta[3:6])) + math.pi
            theta_f, cost_f = self._init_fit(targets_m, self._rest_at(self.theta[0:3], yaw))
        else:
            theta_f, cost_f, _ = fit_pose(
                self.body,
                self._flip_theta,
                targets_m,
                self.kin.rest,
                self.rest_sigma_dof,
                None,
                1.0,
                f.max_nfev,
                tolerance=f.tolerance,
            )
        self._flip_theta = theta_f
        self._cost_current += cost_c
        self._cost_flipped += cost_f
        self._verify_n += 1
        self._verify_left -= 1
        if self._verify_n >= 3 and self._cost_flipped < t.flip_cost_ratio * self._cost_current:
            self._initialise(stamp_ns, theta_f, mirrored)
            self.last_observed = mirrored
            self._verify_left = 0
            self._facing, self._facing_ways = [], []  # the face check's cosines were of the other heading
            return
        if self._verify_n >= 3 and swaps:
            ratio, theta_s, exchanged = min(swaps, key=lambda x: x[0])
            if ratio < t.flip_cost_ratio:
                self._initialise(stamp_ns, theta_s, exchanged)
                self.last_observed = exchanged
                self._reset_verification_sums()  # the sums were of the other labels: verify the rest afresh

    def predict(self, stamp_ns: int) -> BodyEstimate:
        """Prediction for stamp_ns (normally the next frame); ``.blobs`` feed feedback projection.

        While LOST the prediction carries no blobs, so that the 2-D trackers fall back to
        their start-up classes and the body can be found again."""
        if self.theta is None:
            return BodyEstimate.empty(self.body.joint_names, stamp_ns, self.status)
        out = self._predict(int(stamp_ns))
        if self.status == STATUS_LOST:
            out.blobs = []
        return out

    def _n_used(self, obs: Mapping[str, Blob3D]) -> int:
        """Measurements the last step actually used (a frame with fewer counts as unseen); the
        pseudo-measurements of parts no view found (:meth:`_hidden_observations`) do not count."""
        return n_seen(obs)

    # -- initialisation ----------------------------------------------------------
    @staticmethod
    def _has_startup_blobs(blobs_by_camera) -> bool:
        return any(b.label == SKIN for bl in blobs_by_camera.values() for b in bl)

    def _one_view_ray(self, blob: Blob3D) -> tuple[np.ndarray, np.ndarray] | None:
        """(camera centre, unit direction to the blob) when ``blob`` was seen by one view only and
        ``measurement.one_view_depth_sigma_m`` > 0 (its depth is then the prior's), else None."""
        if self.cfg.measurement.one_view_depth_sigma_m <= 0 or len(blob.cameras) != 1:
            return None
        cam = self.cameras.get(blob.cameras[0])
        if cam is None:
            return None
        d = np.asarray(blob.mean, float) - cam.center
        n = float(np.linalg.norm(d))
        return (cam.center, d / n) if n > 0 else None

    def _one_view_cov(self, cov: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """A one-view blob's measurement covariance: ``cov``'s marginal across the ray of unit
        ``direction`` (the prior's depth along it dropped) plus ``one_view_depth_sigma_m``² along it."""
        along = np.outer(direction, direction)
        across = np.eye(3) - along
        return across @ cov @ across + along * self.cfg.measurement.one_view_depth_sigma_m**2

    def _blob_targets(self, obs: Mapping[str, Blob3D]) -> list[PointTarget]:
        out = []
        for lab, blob in obs.items():
            k = self.kin.blob_index[lab]
            cov = self.measurement_cov(blob)
            ray = self._one_view_ray(blob)
            if ray is not None:  # one view: the depth along its ray is the prior's
                cov = self._one_view_cov(cov, ray[1])
            out.append(PointTarget(int(self.kin.blob_links[k]), self.kin.blob_local[k], blob.mean,
                                   np.linalg.inv(cov)))
        return out

    def _rest_at(self, position: np.ndarray, yaw: float) -> np.ndarray:
        theta = self.kin.rest.copy()
        theta[0:3] = position
        theta[3:6] = [0.0, 0.0, yaw]
        return theta

    def _init_fit(self, targets: list[PointTarget], theta0: np.ndarray) -> tuple[np.ndarray, float]:
        f = self.cfg.fit
        theta, cost, _ = fit_pose(
            self.body,
            theta0,
            targets,
            self.kin.rest,
            self.rest_sigma_dof,
            None,
            1.0,
            max_nfev=max(f.max_nfev, 60),
            ground=self._ground,
            tolerance=f.tolerance,
        )
        return theta, cost

    def _init_from_labelled(self, obs: Mapping[str, Blob3D]) -> np.ndarray | None:
        """Multi-start fit of the rest pose (four headings) to labelled 3-D blobs."""
        rest_p, rest_R = self.kin.poses(self.kin.rest)
        rest_centre = np.mean(
            self.kin.blob_points(rest_p, rest_R)[[self.kin.blob_index[k] for k in obs]], axis=0
        )
        centre = np.mean([b.mean for b in obs.values()], axis=0)
        return self._fit_four_headings(self._blob_targets(obs), centre, rest_centre)

    def _fit_four_headings(self, targets: list[PointTarget], centre: np.ndarray, rest_centre: np.ndarray
                           ) -> np.ndarray:
        """The best of four fits of the rest pose to ``targets``, turned to each heading (0, 90, 180,
        270 deg) with the rest-pose point ``rest_centre`` (world m) placed at ``centre``."""
        rest_root = self.kin.rest[0:3]
        best = None
        for yaw in np.arange(4) * (np.pi / 2):
            Rz = exp_so3(np.array([0.0, 0.0, yaw]))
            root = centre - Rz @ (rest_centre - rest_root)
            theta, cost = self._init_fit(targets, self._rest_at(root, yaw))
            if best is None or cost < best[1]:
                best = (theta, cost)
        return best[0]

    def _init_from_startup(self, blobs_by_camera) -> np.ndarray | None:
        """Start-up from ``foreground`` + ``skin`` blobs (module docstring)."""
        s = self.cfg.startup
        fg = {c: [b for b in bl if b.label == FOREGROUND] for c, bl in blobs_by_camera.items()}
        centre_blob = triangulate_blobs(fg, self.cameras,
                                        small_blob_fraction=self.cfg.measurement.small_blob_fraction).get(FOREGROUND)
        skin = {}
        for c, bl in blobs_by_camera.items():
            sk = sorted((b for b in bl if b.label == SKIN), key=lambda b: -b.pixel_count)
            skin[c] = sk[: s.max_skin_blobs_per_camera]
        points = match_skin_blobs(
            skin, self.cameras, 6, s.match_gate_sigma, s.match_gate_px, s.missing_view_penalty_px, s.max_skin_size_m,
            s.share_taken_views, s.min_hand_separation_m, s.min_skin_size_m,
        )
        centre = None if centre_blob is None else centre_blob.mean
        rest_p, rest_R = self.kin.poses(self.kin.rest)
        # One view (one camera sees the person): no ray meets another, depth comes from the floor.
        fg_views = [c for c, bl in fg.items() if bl]
        one_view = (s.one_view_depth_sigma_m > 0 and centre is None and len(fg_views) == 1
                    and sum(1 for sk in skin.values() if sk) <= 1)
        if one_view:
            cam = self.cameras[fg_views[0]]
            start = one_view_start_points(
                cam, max(fg[cam.name], key=lambda b: b.pixel_count), skin.get(cam.name, []),
                float((rest_p[0] + rest_R[0] @ self._centroid_local)[2]), s.max_skin_blobs_per_camera,
            )
            if start is None:
                return None
            centre, points = start

        def held(x: np.ndarray, info: np.ndarray, sigma_across_m: float) -> np.ndarray:
            """A start-up target's information: ``info``, or with one view held to x's ray only."""
            if not one_view:
                return info
            return ray_information(x - cam.center, sigma_across_m, s.one_view_depth_sigma_m)

        if s.start_radius_m > 0:
            # Several people in view: start on the one standing within start_radius_m of start_xy
            # (skin points elsewhere belong to others; a foreground centre elsewhere mixes people).
            xy = np.asarray(s.start_xy, float).reshape(2)
            points = [p for p in points if np.linalg.norm(p[0][:2] - xy) <= s.start_radius_m]
            if centre is not None and np.linalg.norm(centre[:2] - xy) > s.start_radius_m:
                centre = None
        grouped = s.person_gap_m > 0 and len(points) > 1
        if grouped:
            points = nearest_person(points, np.asarray(s.start_xy, float).reshape(2), s.person_gap_m)
        if not points:
            return None
        # The face is the highest skin point; hands are the best-scoring others within
        # arm's reach of it (skin-coloured clutter elsewhere is ignored).
        face = max((p[0] for p in points), key=lambda x: x[2])
        if grouped and centre is not None and np.linalg.norm(centre[:2] - face[:2]) > s.person_gap_m:
            centre = None  # the foreground's centre mixes the people
        # A hand seen in fewer views than min_hand_views (of the cameras with skin blobs) is more
        # often a skin-coloured ghost of the seeding period that two views happen to agree on.
        need = min(s.min_hand_views, sum(1 for sk in skin.values() if sk))
        hands = [
            p[0]
            for p in points
            if p[0] is not face and np.linalg.norm(p[0] - face) <= s.reach_margin * self._reach
            and len(p[2]) >= need
        ][:2]
        yaw_face = None
        if s.facing_from_sizes and not one_view:
            yaw_face = self._startup_face_heading(face, skin)
        if yaw_face is None and centre is not None and not one_view:  # (one view: the face's offset in depth is unseen)
            off = (face - centre)[:2]
            if np.linalg.norm(off) > s.min_facing_offset_m:
                yaw_face = math.atan2(off[1], off[0])
        yaws = [] if yaw_face is None else [yaw_face]
        if len(hands) == 2:
            lat = (hands[1] - hands[0])[:2]
            if np.linalg.norm(lat) > s.min_hand_separation_m:
                y1 = math.atan2(-lat[0], lat[1])
                yaws += [y1, y1 + math.pi]
        if not yaws:
            yaws = list(np.arange(4) * (np.pi / 2))
        head_k = self.kin.blob_index.get("head")
        info_skin = np.eye(3) / s.skin_sigma_m**2
        best = None
        for yaw in yaws:
            fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
            left = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
            Rz = exp_so3(np.array([0.0, 0.0, yaw]))
            targets = []
            head_target = face - s.face_offset_m * fwd
            if head_k is not None:
                hl = int(self.kin.blob_links[head_k])
                info_face = held(face, np.diag([1 / s.skin_sigma_m**2, 1 / s.skin_sigma_m**2,
                                                1 / s.face_sigma_z_m**2]), s.skin_sigma_m)
                targets.append(PointTarget(hl, self.kin.blob_local[head_k], head_target, info_face))
                head_rest = self.kin.blob_points(rest_p, rest_R)[head_k]
                root = head_target - Rz @ (head_rest - rest_p[0])
            else:
                root = np.array([face[0], face[1], rest_p[0][2]])
            axis = centre if centre is not None else head_target
            ordered = sorted(hands, key=lambda x: -float((x - axis) @ left))  # left-most first
            for name, x in zip(("l_hand", "r_hand"), ordered, strict=False):
                if len(ordered) == 1:
                    name = "l_hand" if float((x - axis) @ left) > 0 else "r_hand"
                k = self.kin.blob_index.get(name)
                if k is not None:
                    targets.append(PointTarget(int(self.kin.blob_links[k]), self.kin.blob_local[k], x,
                                               held(x, info_skin, s.skin_sigma_m)))
            if centre is not None:
                info_c = held(centre, np.diag(
                    [1 / s.centroid_sigma_xy_m**2, 1 / s.centroid_sigma_xy_m**2, 1 / s.centroid_sigma_z_m**2]
                ), s.centroid_sigma_xy_m)
                targets.append(PointTarget(0, self._centroid_local, centre, info_c))
            if s.standing_height_sigma_m > 0:  # standing on the floor (z = 0): pelvis near its rest height
                info_h = np.diag([0.0, 0.0, 1.0 / s.standing_height_sigma_m**2])
                targets.append(PointTarget(0, np.zeros(3), self.kin.rest[0:3], info_h))
            if s.heading_sigma_rad > 0:
                # Held near this candidate's heading: a point 1 m ahead of the root, sideways sigma
                # heading_sigma_rad x 1 m. Without it a fit to a face, a hand and the centroid turns
                # the body freely (synthetic default scene: fits started at the right heading ended
                # 80-130 deg away), and the candidates stop being candidates.
                info_y = np.outer(left, left) / s.heading_sigma_rad**2
                targets.append(PointTarget(0, np.array([1.0, 0.0, 0.0]), root + fwd, info_y))
            theta, cost = self._init_fit(targets, self._rest_at(root, yaw))
            if yaw_face is not None:
                yaw_fit = root_heading(exp_so3(theta[3:6]))
                cost += s.facing_weight * (1.0 - math.cos(yaw_fit - yaw_face))
            if best is None or cost < best[1]:
                best = (theta, cost)
        return best[0]

    def _startup_face_heading(self, face: np.ndarray, skin: Mapping[str, Sequence[Blob2D]]) -> float | None:
        """The start-up heading (rad) the face's blob sizes point to (:func:`facing_direction`; the face
        check's cue, ``tracking.facing_min_size_ratio``): in each camera the skin blob nearest the
        projection of the start-up face point ``face`` (world m) within the match gate, None when fewer
        than three views have one or the sizes say nothing. On the synthetic scenes' first tracked
        frame it lay within 7-39 deg of the true heading (default scene, seeds 1-26; 2-3 deg in the rotation
        scene), while starts from the face's offset from the foreground centroid (a few cm) and the line
        between the hands (wrong when one is raised forward, as in the rotation scene) were off by up to
        159 deg (ALGORITHMS.md §1, automatic start-up)."""
        s = self.cfg.startup
        blobs = {}
        for name, bl in skin.items():
            if not bl or name not in self.cameras:
                continue
            uv, depth = self.cameras[name].project(face[None])
            if depth[0] <= 0:
                continue
            k = nearest_in_gate(bl, uv[0], s.match_gate_sigma, s.match_gate_px)
            if k is not None:
                blobs[name] = bl[k]
        way = facing_direction(blobs, self.cameras, face, self.cfg.tracking.facing_min_size_ratio)
        return None if way is None else math.atan2(way[1], way[0])

    # -- output ----------------------------------------------------------------
    def _blob_list(
        self, theta: np.ndarray, state_cov: np.ndarray, means: np.ndarray | None = None
    ) -> list[Blob3D]:
        """Blob3D per blob label: means (B, 3) (default: FK of theta) and cov = shape + state_cov
        (B, 3, 3) (or state_cov only, see measurement.blob_cov)."""
        shape_mean, shape_cov = self.body.blob_gaussians(theta)
        means = shape_mean if means is None else means
        add_shape = self.cfg.measurement.blob_cov == "shape+state"
        out = []
        for k, lab in enumerate(self.kin.blob_labels):
            cov = state_cov[k] + (shape_cov[k] if add_shape else 0.0)
            cams = self.last_observed[lab].cameras if lab in self.last_observed else ()
            out.append(Blob3D(lab, np.asarray(means[k], float).copy(), 0.5 * (cov + cov.T), cams))
        return out

    def _links(self, theta, velocity, angular_velocity, cov) -> list[LinkEstimate]:
        p, R = self.kin.poses(theta)
        return [
            LinkEstimate(
                lk.name,
                p[i],
                R[i],
                np.asarray(velocity[i], float).copy(),
                np.asarray(angular_velocity[i], float).copy(),
                np.asarray(cov[i], float).copy(),
            )
            for i, lk in enumerate(self.body.links)
        ]

    # -- kind-specific -----------------------------------------------------------
    def _initialise(self, stamp_ns: int, theta: np.ndarray, obs: Mapping[str, Blob3D]) -> None:
        raise NotImplementedError

    def _step(self, stamp_ns: int, obs: Mapping[str, Blob3D]) -> None:
        raise NotImplementedError

    def _estimate(self, stamp_ns: int) -> BodyEstimate:
        raise NotImplementedError

    def _predict(self, stamp_ns: int) -> BodyEstimate:
        raise NotImplementedError


def n_seen(obs: Mapping[str, Blob3D]) -> int:
    """The 3-D blobs of ``obs`` that some view found (not the pseudo-measurements, which have no cameras)."""
    return sum(1 for blob in obs.values() if blob.cameras)
