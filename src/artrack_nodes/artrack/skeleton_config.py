"""Tunables of the 3-D body estimators (config/skeleton.yaml; ALGORITHMS.md §1).

One dataclass per section of the file (``measurement``, ``tracking``, ``prior``, ``fit``,
``kinematic``, ``dynamic``, ``startup``), gathered in :class:`SkeletonConfig`, and
:func:`load_skeleton_config`, which checks every field and names a bad one in one line. What the
fields do is described where they act: the estimators (``artrack.estimator``,
``artrack.baseline_estimator``, ``artrack.kalman_skeleton``), ``artrack.body_fit`` (the body fit) and
``artrack.startup`` (start-up and facing cues).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .config import require_bool
from .errors import InputError

FOREGROUND = "foreground"
SKIN = "skin"
KINDS = ("baseline", "kinematic", "dynamic")  # make_estimator's estimators


@dataclass
class MeasurementConfig:
    """How 3-D blobs become measurements (see config/skeleton.yaml)."""

    cov_scale: float = 0.05
    floor_m: float = 0.005
    gate_chi2: float = 16.27
    blob_cov: str = "shape+state"
    view_association: list = field(default_factory=lambda: ["thigh", "shin"])
    view_association_margin_chi2: float = 4.0
    #: a 3-D blob of three or more views whose weighted reprojection error is above this is solved again
    #: without the view that disagrees (:func:`artrack.triangulation._drop_outlier_views`; 0 = off) ...
    view_outlier_chi2: float = 4.0
    #: ... once a track is this many frames old
    #: (:meth:`artrack.estimator.Estimator._view_outlier_threshold`; 0 = always)
    view_outlier_after_frames: int = 40
    #: a view's blob of n pixels counts n / (n + n₀) in the triangulation, n₀ = this × the image
    #: area (:func:`artrack.triangulation.triangulate_blobs`; 0 = by its extent alone)
    small_blob_fraction: float = 3.90625e-4
    #: a view's 2-D blob of ``min_view_labels`` with fewer pixels than this × the camera's image area (a
    #: sliver) is left out of the triangulation where two or more views see the part with more pixels
    #: (0 = off; :meth:`artrack.estimator.Estimator._drop_small_views`)
    min_view_fraction: float = 1.953125e-4
    #: the blob labels ``min_view_fraction`` applies to
    min_view_labels: list = field(default_factory=lambda: ["head", "l_hand", "r_hand"])
    #: the views that see a part whole drop its slivers only if two of their rays meet at least this
    #: far (degrees) from parallel and from anti-parallel (:func:`artrack.triangulation.drop_slivers`; 0: any two)
    min_view_ray_angle_deg: float = 45.0
    #: a 3-D blob seen by one view only takes its depth along that view's ray from the prior it was
    #: triangulated with (the prediction); the body fits count it across the ray only, and this sigma
    #: (m) along it (:meth:`artrack.estimator.Estimator._blob_targets`); 0 = as triangulated (the prediction's depth)
    one_view_depth_sigma_m: float = 0.0
    #: negative evidence (:mod:`artrack.hidden`): a part of these labels found by one view only takes
    #: its prior's depth along that ray where the views that looked for it and did not find it would
    #: not have seen it (:meth:`artrack.estimator.Estimator._hidden_priors`; [] = off)
    hidden_labels: list = field(default_factory=lambda: ["l_hand", "r_hand"])
    #: ... searched over the prediction's ± this many standard deviations
    hidden_sigmas: float = 3.0
    #: ... the probability that a view's tracker misses a part in its sight: the price of each view that
    #: would have seen a point (:func:`artrack.hidden.hide`; 0.01: one view fewer beats any 3-sigma move)
    hidden_miss_probability: float = 0.01
    #: ... a point nearer the image border than this (px) counts as not seen by that view
    hidden_inset_px: float = 0.0
    #: a part of ``hidden_labels`` that no view found is measured, to this sigma (m), at the likeliest
    #: point given that the views which looked did not find it
    #: (:meth:`artrack.estimator.Estimator._hidden_observations`;
    #: 0 = off; only beside ``tracking.min_blobs`` real 3-D blobs, and never counted as seen)
    hidden_no_view_sigma_m: float = 0.1


@dataclass
class TrackingConfig:
    """Status logic."""

    min_blobs: int = 3
    lost_after_frames: int = 15
    #: a LOST estimator re-initialises from its own blobs (False: only ``reseed`` restarts it, e.g. from
    #: the loose_limbed node; the first start still uses the blobs)
    relocalise_from_blobs: bool = True
    #: a re-seed (:meth:`artrack.estimator.Estimator.reseed`) from another estimator's body holds its elbows, wrists,
    #: knees and ankles only this loosely, m (its trunk and head at the re-seed's sigma): the
    #: loose-limbed body's limbs are its weakest part, and the rest pose and the blobs do better
    reseed_limb_sigma_m: float = 1.0
    verify_frames: int = 20
    flip_cost_ratio: float = 0.5
    #: parts (no side prefix) whose left/right labels the verification also exchanges alone, heading
    #: kept, and switches to by the same ``flip_cost_ratio`` rule; [] = none
    verify_swap_groups: list = field(default_factory=lambda: [["hand"]])
    #: ... judged also on the group's last this many observed frames alone (0 = on the sums since the
    #: start only): frames before the evidence, which fit either labelling alike, no longer hold it off
    verify_swap_recent_frames: int = 3
    #: the face check (:func:`artrack.startup.facing_agreement`): over this many frames while tracking (0 = off) ...
    facing_check_frames: int = 15
    #: ... a mean cosine below this between the estimated facing and the way the ``facing_label``
    #: blob's sizes point turns the body round (heading + π, left <-> right)
    facing_flip_cosine: float = -0.7
    #: ... or, sooner, a mean below ``facing_quick_cosine`` over the last this many frames (0 = only the
    #: full window): a body started facing backwards is turned after a few frames, not fifteen
    facing_quick_frames: int = 5
    facing_quick_cosine: float = -0.85
    #: ... counted only in frames whose largest size is at least this many times the smallest
    facing_min_size_ratio: float = 2.0
    #: the blob whose size shows the facing: the head's skin is the face from the front, the neck
    #: from behind (the hair covers the rest)
    facing_label: str = "head"
    #: parts (no side prefix) whose left/right exchange at the face check's turn is decided by their
    #: sides: a group is kept as labelled where its left parts lie left of its right ones at the heading
    #: turned to (a heading that drifted round while the group's own labels stayed right), exchanged
    #: otherwise; other sided parts are always exchanged; [] = every label exchanged
    facing_turn_groups: list = field(default_factory=lambda: [["hand"]])
    #: parts re-acquired when lost (:meth:`artrack.estimator.Estimator._reacquire`): a part of these without a 3-D blob
    #: seen in two or more views takes the point where the views' unlabelled skin blobs meet ...
    reacquire_labels: list = field(default_factory=lambda: ["l_hand", "r_hand"])
    #: ... if that point lies farther than this from every other observed 3-D blob, m ...
    reacquire_separation_m: float = 0.15
    #: ... and within this many times the part's reach (the bone chain from its shoulder) of its shoulder
    reacquire_reach_margin: float = 1.1
    #: a re-acquired part's own dofs are fitted from the arm as it is and also with its hinges half
    #: bent (:meth:`artrack.baseline_estimator.BaselineEstimator._reach_for`); False: from the arm as it is only
    reacquire_bent_start: bool = True
    #: a 3-D blob of ``reacquire_labels`` triangulated (two or more views) farther than this many times the part's reach
    #: from its shoulder in the current pose is not used (the hand's label sits on something else:
    #: another person's face), and the part may be re-acquired; 0 = never
    reach_gate_margin: float = 1.3
    #: further parts gated so (not re-acquired), their reach measured from the joint above their blob-carrying
    #: parent (a shin from its hip, through the thigh, whose same-coloured label may be as wrong as its own) ...
    reach_gate_labels: list = field(default_factory=lambda: ["l_shin", "r_shin"])
    #: ... from this many frames after a track starts (the start-up pose's legs are the rest pose's)
    reach_gate_after_frames: int = 10


def _default_rest_sigmas() -> dict[str, float]:
    return {"torso": 0.3, "head": 0.5, "l_hand": 0.3, "r_hand": 0.3, "l_foot": 0.3, "r_foot": 0.3}


@dataclass
class PriorConfig:
    """Rest-pose prior on the joint dofs, shared by all estimators."""

    rest_sigma_rad: float = 1.0
    rest_sigma_by_link: dict = field(default_factory=_default_rest_sigmas)


@dataclass
class FitConfig:
    """Bounded least-squares pose fit (baseline, initialisation)."""

    previous_sigma_rad: float = 2.0
    max_nfev: int = 40
    tolerance: float = 1e-3
    predict_velocity_sigma: float = 1.0
    #: the baseline's prediction extrapolates the joint dofs and the root's position by this times
    #: dt times their smoothed velocity (0: zero velocity, the pose at t)
    predict_velocity_gain: float = 0.5
    #: exponential-smoothing weight of the newest frame difference in that velocity
    predict_velocity_smoothing: float = 0.5
    #: links whose dofs are extrapolated ([] = all joints and the root's position)
    predict_velocity_links: list = field(default_factory=list)
    robust_scale: float = 3.0
    edge_sigma_px: float = 1.0
    edge_min_found: int = 8
    ground_sigma_m: float = 0.0
    #: soft upright trunk (:class:`artrack.body_fit.UprightSegment`): sigma of the thorax' horizontal
    #: offset from the pelvis, m; 0 = off
    upright_sigma_m: float = 0.0
    #: soft upright head (:meth:`artrack.body_fit.UprightSegment.link_axis`): sigma of the head
    #: joint's horizontal offset from the neck pivot (the head link's origin), beyond the rest pose's, m; 0 = off
    upright_head_sigma_m: float = 0.03
    floor_z_m: float = 0.0
    axis_label: str = "torso"
    axis_sigma_rad: float = 0.35
    axis_min_ratio: float = 1.3
    mirror_groups: list = field(default_factory=lambda: [["thigh", "shin"], ["shin"]])
    mirror_screen_ratio: float = 1.5
    #: the screen itself runs only when the cost of its start (the labelled fit's legs exchanged, no
    #: fit) is below this times the labelled fit's cost (a large value: always)
    mirror_prescreen_ratio: float = 10.0
    #: the screen is abandoned when after ``mirror_screen_abandon_after`` iterations its cost is
    #: still above ``mirror_screen_abandon_ratio`` times the labelled fit's (0 iterations: never)
    mirror_screen_abandon_after: int = 6
    mirror_screen_abandon_ratio: float = 3.0
    #: l_/r_ parts left out of a view's triangulation where their two 2-D blobs overlap there
    #: (squared Mahalanobis distance between the means under the summed covariances below
    #: ``overlap_chi2``; :func:`artrack.triangulation.drop_overlapping_pairs`); [] = off
    overlap_parts: list = field(default_factory=lambda: ["thigh", "shin"])
    overlap_chi2: float = 4.0


@dataclass
class KinematicConfig:
    """Kalman filters + kinematic constraint solver."""

    blob_jerk: float = 200.0
    link_jerk: float = 200.0
    init_position_sigma_m: float = 0.1
    init_velocity_sigma: float = 0.5
    init_acceleration_sigma: float = 3.0
    writeback_sigma_m: float = 0.01
    alpha: float = 1.0
    link_goal_weight: float = 0.02
    rest_weight: float = 4.0
    previous_sigma_rad: float = 0.08
    limit_sigma_rad: float = 0.02
    gravity_weight: float = 2.0
    coast_velocity_decay: float = 0.8
    coast_acceleration_decay: float = 0.3
    max_iterations: int = 8
    predict_iterations: int = 3
    angular_velocity_smoothing: float = 0.5
    robust_scale: float = 3.0
    outlier_fit_scale: float = 1.5
    #: the largest factor on a blob filter's process noise in a frame where the frame's robust body fit
    #: explains its blob (weight factor at most 2) but the filter's prediction does not (normalised
    #: innovation squared d²/3 above 1): a manoeuvre, not an outlier (1 = off; config/skeleton.yaml)
    maneuver_max_scale: float = 10.0
    orientation_from_fit: bool = True
    fit_source: str = "baseline"
    warmup_frames: int = 40
    follow_raw_track: bool = True


@dataclass
class DynamicConfig:
    """Full dynamics (masses, springs, damping)."""

    substeps: int = 4
    spring_scale: float = 1.0
    spring_stiffness_max: float = 20000.0
    linear_damping: float = 2.0
    angular_damping: float = 8.0
    rest_stiffness: float = 0.5
    limit_stiffness: float = 50.0
    gravity_weight: float = 2.0
    predict_velocity_sigma: float = 0.5
    outlier_fit_scale: float = 0.0
    #: stiffness-proportional (Rayleigh) damping of the springs, s (0 = none; ConstraintSolver.step_dynamic)
    stiffness_damping_s: float = 0.01
    #: with kinematic.fit_source 'baseline': the observation springs pull toward the raw tracker's
    #: robust body fit of the frame (its blob centres, one consistent body) instead of the triangulated
    #: blobs, and the raw tracker owns the track's life cycle, as for the kinematic estimator
    follow_fit: bool = True
    #: torsional springs toward the raw tracker's link orientations (with follow_fit), N m/rad (0 = none)
    fit_orientation_stiffness: float = 150.0


@dataclass
class StartupConfig:
    """Initialisation from the start-up classes ``foreground`` and ``skin``."""

    face_offset_m: float = 0.06
    min_facing_offset_m: float = 0.02
    min_hand_separation_m: float = 0.15
    match_gate_sigma: float = 3.0
    match_gate_px: float = 4.0
    missing_view_penalty_px: float = 10.0
    max_skin_blobs_per_camera: int = 5
    skin_sigma_m: float = 0.03
    face_sigma_z_m: float = 0.08
    standing_height_sigma_m: float = 0.08
    centroid_sigma_xy_m: float = 0.10
    centroid_sigma_z_m: float = 0.30
    facing_weight: float = 20.0
    reach_margin: float = 1.15
    start_xy: tuple = (0.0, 0.0)
    start_radius_m: float = 0.0
    heading_sigma_rad: float = 0.35
    min_hand_views: int = 3
    #: a start-up skin blob larger than this (m, the side of its area's square at the matched point's
    #: depth, :func:`artrack.startup.blob_size_m`) sees the point but does not locate it
    #: (:func:`artrack.startup.match_skin_blobs`); 0 = off
    max_skin_size_m: float = 0.32
    #: a start-up skin point none of whose locating blobs is at least this large (m, as
    #: ``max_skin_size_m``) is a speck, neither the face nor a hand (:func:`artrack.startup.match_skin_blobs`
    #: ``min_size_m``); 0 = off
    min_skin_size_m: float = 0.07
    #: a start-up skin point whose extension to a further view took a blob that a better point other
    #: than the face, at least ``min_hand_separation_m`` away horizontally, already took (two hands
    #: merged there) is kept, that view seeing it without locating it (:func:`artrack.startup.match_skin_blobs`
    #: ``share_taken_views``); False = such a point is dropped
    share_taken_views: bool = True
    #: skin points farther apart than this horizontally (single linkage) are different people; with
    #: several, start-up starts on the fullest group (up to three points) whose highest point (the
    #: face) is nearest ``start_xy`` (:func:`artrack.startup.nearest_person`); 0 = off
    person_gap_m: float = 1.0
    #: one view sees the person (one camera): start-up points placed at the depth where the foreground
    #: centroid's ray comes down to the rest pose's centroid height, held to their rays, and to this
    #: sigma (m) along them (:func:`artrack.startup.one_view_start_points`); 0 = no start-up from one view
    one_view_depth_sigma_m: float = 0.3
    #: the start-up heading is read from the face's 2-D blob sizes
    #: (:func:`artrack.startup.facing_direction`, the face check's cue: face in front, neck behind)
    #: when they say something, else from the face's offset from the foreground centroid; False =
    #: always the offset
    facing_from_sizes: bool = True


@dataclass
class SkeletonConfig:
    """All tunables of the 3-D estimators, one section each (config/skeleton.yaml)."""

    measurement: MeasurementConfig = field(default_factory=MeasurementConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    kinematic: KinematicConfig = field(default_factory=KinematicConfig)
    dynamic: DynamicConfig = field(default_factory=DynamicConfig)
    startup: StartupConfig = field(default_factory=StartupConfig)
    #: {section: {field: value}} that replace the values above when the estimator has at most
    #: ``few_cameras_max`` cameras (parts seen by one view constrain only their ray: ray-shaped
    #: measurements, floor contact, upright trunk); config/skeleton.yaml ``few_cameras`` (a file's
    #: fields are merged into these; ``max_cameras: 0`` turns them off)
    few_cameras: dict = field(default_factory=lambda: {
        "measurement": {"one_view_depth_sigma_m": 0.1},
        "fit": {"ground_sigma_m": 0.005, "upright_sigma_m": 0.15},
    })
    #: ``few_cameras.max_cameras`` in the file
    few_cameras_max: int = 2

    def for_cameras(self, n_cameras: int) -> SkeletonConfig:
        """This configuration for an estimator with ``n_cameras`` cameras (``few_cameras`` applied
        for at most ``few_cameras_max``)."""
        if n_cameras > self.few_cameras_max or not self.few_cameras:
            return self
        merged = dataclasses.asdict(self)
        merged.pop("few_cameras_max")
        merged["few_cameras"] = {"max_cameras": self.few_cameras_max, **self.few_cameras}
        for section, values in self.few_cameras.items():
            merged[section].update(values)
        return load_skeleton_config(merged)


def load_skeleton_config(config: SkeletonConfig | Mapping[str, Any] | None = None) -> SkeletonConfig:
    """SkeletonConfig from None (defaults), a SkeletonConfig, or a mapping of sections
    (the parsed config/skeleton.yaml). Unknown sections / keys raise InputError."""
    if config is None:
        return SkeletonConfig()
    if isinstance(config, SkeletonConfig):
        return config
    if not isinstance(config, Mapping):
        raise InputError(f"skeleton config: expected a mapping of sections, got {type(config).__name__}")
    out = SkeletonConfig()
    sections = {f.name: f for f in dataclasses.fields(SkeletonConfig) if f.name != "few_cameras_max"}
    for name, values in config.items():
        if name not in sections:
            raise InputError(f"skeleton config: unknown section '{name}' (known: {', '.join(sections)})")
        if values is None:
            continue
        if not isinstance(values, Mapping):
            raise InputError(f"skeleton config: section '{name}' must be a mapping")
        if name == "few_cameras":
            values = dict(values)
            max_cameras = values.pop("max_cameras", out.few_cameras_max)
            if isinstance(max_cameras, bool) or not isinstance(max_cameras, int) or max_cameras < 0:
                raise InputError(f"skeleton config: field 'few_cameras.max_cameras' must be an integer >= 0 "
                                 f"(got {max_cameras!r})")
            if "few_cameras" in values:
                raise InputError("skeleton config: section 'few_cameras' cannot hold 'few_cameras'")
            load_skeleton_config(values)  # the same checks, on the overrides alone
            for section, fields in values.items():  # (fields not given keep their default overrides)
                out.few_cameras.setdefault(section, {}).update(fields or {})
            out.few_cameras_max = max_cameras
            continue
        current = getattr(out, name)
        known = {f.name: f for f in dataclasses.fields(current)}
        for key, value in values.items():
            if key not in known:
                raise InputError(
                    f"skeleton config: unknown field '{name}.{key}' (known: {', '.join(sorted(known))})"
                )
            default = getattr(current, key)
            if isinstance(default, bool):
                require_bool(value, f"skeleton config: field '{name}.{key}'")
            if isinstance(default, list) and not isinstance(value, (list, tuple)):
                # (list('l_hand') would be its letters)
                raise InputError(f"skeleton config: field '{name}.{key}' must be a list, got {type(value).__name__}")
            try:
                value = type(default)(value)
            except (TypeError, ValueError):
                raise InputError(
                    f"skeleton config: field '{name}.{key}' must be {type(default).__name__}"
                ) from None
            setattr(current, key, value)
    xy = out.startup.start_xy
    if len(xy) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in xy):
        raise InputError("skeleton config: field 'startup.start_xy' must be two finite numbers (x, y), m")
    non_negative = (("fit.ground_sigma_m", out.fit.ground_sigma_m),
                    ("fit.upright_sigma_m", out.fit.upright_sigma_m),
                    ("fit.mirror_screen_ratio", out.fit.mirror_screen_ratio),
                    ("fit.mirror_prescreen_ratio", out.fit.mirror_prescreen_ratio),
                    ("startup.start_radius_m", out.startup.start_radius_m),
                    ("startup.person_gap_m", out.startup.person_gap_m),
                    ("startup.one_view_depth_sigma_m", out.startup.one_view_depth_sigma_m),
                    ("measurement.one_view_depth_sigma_m", out.measurement.one_view_depth_sigma_m),
                    ("measurement.hidden_sigmas", out.measurement.hidden_sigmas),
                    ("measurement.hidden_inset_px", out.measurement.hidden_inset_px),
                    ("measurement.hidden_no_view_sigma_m", out.measurement.hidden_no_view_sigma_m),
                    ("tracking.reach_gate_margin", out.tracking.reach_gate_margin))
    for name, value in non_negative:
        if value < 0:
            raise InputError(f"skeleton config: field '{name}' must be >= 0 (got {value!r})")
    if out.fit.max_nfev < 1:
        raise InputError(f"skeleton config: field 'fit.max_nfev' must be >= 1 (got {out.fit.max_nfev!r})")
    if out.fit.mirror_screen_abandon_after < 0:
        raise InputError("skeleton config: field 'fit.mirror_screen_abandon_after' must be >= 0 "
                         f"(got {out.fit.mirror_screen_abandon_after!r})")
    if out.fit.mirror_screen_abandon_ratio < out.fit.mirror_screen_ratio:
        raise InputError("skeleton config: field 'fit.mirror_screen_abandon_ratio' must be >= "
                         f"fit.mirror_screen_ratio (got {out.fit.mirror_screen_abandon_ratio!r}): it would "
                         "abandon screens that pass")
    if not 1e-12 <= out.fit.tolerance < 1.0:
        raise InputError(f"skeleton config: field 'fit.tolerance' must be in [1e-12, 1) (got {out.fit.tolerance!r})")
    for name, groups in (("fit.mirror_groups", out.fit.mirror_groups),
                         ("tracking.facing_turn_groups", out.tracking.facing_turn_groups),
                         ("tracking.verify_swap_groups", out.tracking.verify_swap_groups)):
        if not all(isinstance(g, (list, tuple)) and g and all(isinstance(p, str) and p for p in g) for g in groups):
            raise InputError(f"skeleton config: field '{name}' must be a list of lists of part names "
                             "(without the side prefix, e.g. [[thigh, shin], [shin]])")
    if not all(isinstance(p, str) and p for p in out.measurement.view_association):
        raise InputError("skeleton config: field 'measurement.view_association' must be a list of part names "
                         "(without the side prefix, e.g. [thigh, shin])")
    if out.measurement.view_association_margin_chi2 < 0:
        raise InputError("skeleton config: field 'measurement.view_association_margin_chi2' must be >= 0")
    if not out.measurement.view_outlier_chi2 >= 0:
        raise InputError("skeleton config: field 'measurement.view_outlier_chi2' must be >= 0 (0 = off)")
    if not isinstance(out.tracking.verify_swap_recent_frames, int) or out.tracking.verify_swap_recent_frames < 0:
        raise InputError("skeleton config: field 'tracking.verify_swap_recent_frames' must be an integer >= 0 "
                         f"(0 = off; got {out.tracking.verify_swap_recent_frames!r})")
    if not isinstance(out.measurement.view_outlier_after_frames, int) or out.measurement.view_outlier_after_frames < 0:
        raise InputError("skeleton config: field 'measurement.view_outlier_after_frames' must be an integer >= 0")
    if not out.measurement.min_view_fraction >= 0:
        raise InputError("skeleton config: field 'measurement.min_view_fraction' must be >= 0 (0 = off)")
    if not 0.0 < out.measurement.hidden_miss_probability < 1.0:
        raise InputError("skeleton config: field 'measurement.hidden_miss_probability' must be in (0, 1) "
                         f"(got {out.measurement.hidden_miss_probability!r})")
    if not 0.0 <= out.measurement.min_view_ray_angle_deg <= 90.0:
        raise InputError("skeleton config: field 'measurement.min_view_ray_angle_deg' must be in [0, 90] degrees")
    if not isinstance(out.measurement.min_view_labels, list) or not all(
            isinstance(p, str) and p for p in out.measurement.min_view_labels):
        raise InputError("skeleton config: field 'measurement.min_view_labels' must be a list of blob labels")
    if not out.measurement.small_blob_fraction >= 0:
        raise InputError("skeleton config: field 'measurement.small_blob_fraction' must be >= 0 (0 = off)")
    parts = out.fit.overlap_parts
    if not isinstance(parts, list) or not all(isinstance(p, str) and p for p in parts):
        raise InputError("skeleton config: field 'fit.overlap_parts' must be a list of part names "
                         "(e.g. [thigh, shin])")
    if not out.fit.overlap_chi2 >= 0:
        raise InputError("skeleton config: field 'fit.overlap_chi2' must be >= 0")
    if out.measurement.blob_cov not in ("shape+state", "state"):
        raise InputError("skeleton config: field 'measurement.blob_cov' must be 'shape+state' or 'state'")
    if out.tracking.facing_check_frames < 0:
        raise InputError("skeleton config: field 'tracking.facing_check_frames' must be >= 0 (0 = off)")
    if not out.tracking.reseed_limb_sigma_m > 0:
        raise InputError("skeleton config: field 'tracking.reseed_limb_sigma_m' must be > 0")
    if out.tracking.facing_quick_frames < 0:
        raise InputError("skeleton config: field 'tracking.facing_quick_frames' must be >= 0 (0 = off)")
    if not -1.0 <= out.tracking.facing_quick_cosine <= 1.0:
        raise InputError("skeleton config: field 'tracking.facing_quick_cosine' must be in [-1, 1]")
    if not -1.0 <= out.tracking.facing_flip_cosine <= 1.0:
        raise InputError("skeleton config: field 'tracking.facing_flip_cosine' must be in [-1, 1]")
    if out.fit.predict_velocity_gain < 0 or not 0.0 < out.fit.predict_velocity_smoothing <= 1.0:
        raise InputError("skeleton config: field 'fit.predict_velocity_gain' must be >= 0 and "
                         "'fit.predict_velocity_smoothing' in (0, 1]")
    if out.tracking.reacquire_separation_m < 0 or out.tracking.reacquire_reach_margin < 0:
        raise InputError("skeleton config: fields 'tracking.reacquire_separation_m' and "
                         "'tracking.reacquire_reach_margin' must be >= 0")
    if not all(isinstance(p, str) and p for p in out.tracking.reacquire_labels):
        raise InputError("skeleton config: field 'tracking.reacquire_labels' must be a list of blob labels "
                         "(e.g. [l_hand, r_hand]; [] = off)")
    if not isinstance(out.tracking.reach_gate_labels, list) or not all(
            isinstance(p, str) and p for p in out.tracking.reach_gate_labels):
        raise InputError("skeleton config: field 'tracking.reach_gate_labels' must be a list of blob labels "
                         "(e.g. [l_shin, r_shin]; [] = off)")
    if not isinstance(out.tracking.reach_gate_after_frames, int) or out.tracking.reach_gate_after_frames < 0:
        raise InputError("skeleton config: field 'tracking.reach_gate_after_frames' must be an integer >= 0")
    if not out.tracking.facing_min_size_ratio >= 1.0:
        raise InputError("skeleton config: field 'tracking.facing_min_size_ratio' must be >= 1")
    return out
