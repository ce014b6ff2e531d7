"""The raw baseline estimator: per-frame triangulation and a bounded least-squares body fit
(ALGORITHMS.md §1). The shared frame (start-up, gates, the track's life cycle) is
``estimator.Estimator``'s.

``'baseline'`` — the "raw feature tracker" of the paper's Table 1, an honest
baseline: each frame the labelled 2-D blobs are triangulated
(``triangulation.triangulate_blobs``) and the body model's theta is fitted to
the 3-D blobs by bounded least squares (``scipy.optimize.least_squares``,
bounds = joint limits), residuals whitened by the measurement covariances,
plus weak rest-pose and previous-pose regularisers on the joint dofs so that
unobserved dofs (elbow swivel, feet) stay sane. No temporal filtering beyond
that warm start / weak previous-pose term. ``predict`` returns the last
estimate moved on by ``fit.predict_velocity_gain`` times its smoothed joint and
root-position velocities (0: the zero-velocity model; the root's rotation is held)
with covariance inflated by (σ_v Δt)²: a constant-velocity prediction damped by
half, since the per-frame fits' velocities are noisy (gain 1 overshoots).
Optional floor contact (``fit.ground_sigma_m`` > 0, :class:`GroundContact`, also in
the initial fits): a person standing or walking on the floor keeps the lower of the
body's lowest rest points (the ankles) at its rest height above z = ``fit.floor_z_m``
and neither below it — legs whose blobs are missing or mislabelled are not pulled up.
Upright head (``fit.upright_head_sigma_m``, :meth:`UprightSegment.link_axis`, also in the
initial fits and the kinematic filters' outlier fit): the head's blob (the face) sits a few
cm from the neck pivot and barely observes its pitch, so the head is held near upright.
Heading cue from the torso's shape (``fit.axis_*``, baseline): the
3-D second moments that explain the torso's 2-D blob covariances in three or more views
(``triangulation.blob_extent``) have their widest horizontal axis along the shoulders;
two points on the torso's lateral axis are pulled across onto that line, the nearer of its
two directions (heading mod π; the blob means of torso and head hardly constrain it).
Left/right data association (``fit.mirror_groups``, baseline): the two trouser legs share
one colour class, so where they pass each other the 2-D labels follow the priors and swap;
each frame the body is fitted again with the l_/r_ blobs of each group exchanged (default:
the whole legs, then the shins alone, which cross below the knees) and the fit of lowest
(robust) cost wins. The exchanged fit is screened by the group's own dofs alone
(``fit_pose(free_dofs=...)``, the rest held at the labelled fit: for the shins alone the
knees, so only a crossing that the present hips explain earns the full fit; blobs on links
below the group's, a model's feet, move with it in the screen) and fitted in
full only when the screen comes within ``fit.mirror_screen_ratio`` of the labelled cost; the
screen itself is skipped when its start costs more than
``fit.mirror_prescreen_ratio`` times the labelled fit, and abandoned when after
``fit.mirror_screen_abandon_after`` iterations it is still above ``fit.mirror_screen_abandon_ratio``
times (speed only: of the benches' 30 seeds, one run changed). Before that, per view
(``measurement.view_association``, all estimators): a pair labelled the wrong way round in some
views but not others is put back by the rays that meet (``triangulation.associate_views``); and
before that (baseline), a pair whose two 2-D blobs overlap in a view is left out of that view
(``fit.overlap_parts``, ``triangulation.drop_overlapping_pairs``): their pixels are shared out
by the priors alone, so the two blobs pull each other to the middle and the legs lose their
motion as they pass.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from .body_fit import PointTarget, exchange_sides, fit_pose, mirror_label
from .body_model import BodyModel
from .constraints import log_so3
from .estimator import Estimator
from .triangulation import blob_extent, drop_overlapping_pairs
from .types import Blob2D, Blob3D, BodyEstimate

__all__ = ["BaselineEstimator"]


#: half length (m) of the lever along the axis link's lateral axis on which the horizontal-axis
#: cue acts (the cue's sigma in m is this times ``fit.axis_sigma_rad``)
_AXIS_LEVER_M = 0.15
#: floor (m, 1 sigma) of the narrower horizontal extent in the ``fit.axis_min_ratio`` test
_AXIS_FLOOR_M = 0.03


def _pose_jacobians(body: BodyModel, theta: np.ndarray, h: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """d(link pose)/dθ: (L, 6, n) [position; rotation vector (world)] and d(blob centre)/dθ (B, 3, n)."""
    n = body.n_dof
    batch = np.vstack([theta[None], theta[None] + h * np.eye(n)])
    T = body.forward_kinematics(batch)
    dp = (T[1:, :, :3, 3] - T[0, :, :3, 3]) / h  # (n, L, 3)
    rel = T[1:, :, :3, :3] @ np.swapaxes(T[0, :, :3, :3], -1, -2)[None]
    dr = log_so3(rel) / h  # (n, L, 3)
    Jl = np.concatenate([dp, dr], axis=2).transpose(1, 2, 0)
    bc = body.blob_centres(batch)
    Jb = ((bc[1:] - bc[0]) / h).transpose(1, 2, 0)
    return Jl, Jb


class BaselineEstimator(Estimator):
    """Per-frame triangulation + bounded least-squares body fit (module docstring)."""

    kind = "baseline"

    def reset(self) -> None:
        """As :meth:`Estimator.reset`, with the frame's axis cue and the dof velocities."""
        super().reset()
        self._axis: tuple[np.ndarray, np.ndarray] | None = None  # this frame's horizontal-axis cue
        self._dof_velocity: np.ndarray | None = None  # smoothed d theta / dt (joint dofs, root position)

    def _screen_views(self, labelled: dict[str, list[Blob2D]]) -> dict[str, list[Blob2D]]:
        """``fit.overlap_parts``: a pair whose two blobs overlap in a view is left out of it."""
        f = self.cfg.fit
        if not f.overlap_parts:
            return labelled
        labelled, self.overlap_drops = drop_overlapping_pairs(labelled, f.overlap_parts, f.overlap_chi2)
        return labelled

    def _triangulate(self, blobs_by_camera, priors: Mapping[str, Blob3D] | None) -> dict[str, Blob3D]:
        """As the base class, and this frame's torso-shape heading cue (``fit.axis_*``) from the
        axis label's 2-D blobs in the views that triangulated it."""
        obs = super()._triangulate(blobs_by_camera, priors)
        self._axis = None
        f = self.cfg.fit
        blob = obs.get(f.axis_label)
        if f.axis_sigma_rad > 0 and blob is not None:
            views = [(self.cameras[c], b) for c, bl in blobs_by_camera.items() for b in bl
                     if b.label == f.axis_label and c in blob.cameras]
            self._axis = self._horizontal_axis(blob, blob_extent(views, blob.mean))
        return obs

    def _horizontal_axis(self, blob: Blob3D, extent: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """(centre (3,), unit horizontal axis (3,)) of the widest horizontal extent of the
        ``fit.axis_label`` blob, or None when its horizontal extent is too round to tell
        (axes ratio below ``fit.axis_min_ratio``)."""
        if extent is None:
            return None
        vals, vecs = np.linalg.eigh(extent[:2, :2])
        if vals[1] <= 0 or vals[1] < self.cfg.fit.axis_min_ratio**2 * max(vals[0], _AXIS_FLOOR_M**2):
            return None
        return np.asarray(blob.mean, float), np.array([vecs[0, 1], vecs[1, 1], 0.0])

    def _axis_targets(self, link_rotations: np.ndarray) -> list[PointTarget]:
        """The heading cue of the axis blob's shape (``fit.axis_*``; see :func:`blob_extent`): two
        points ±_AXIS_LEVER_M along the link's lateral (y) axis through its blob centre are pulled,
        across the observed widest horizontal axis only, onto that axis (sigma ``axis_sigma_rad``
        as an angle). The axis has no direction; it takes the one nearer the link's lateral axis in
        ``link_rotations`` (L, 3, 3) world_from_link (the current pose), so it turns the heading
        towards the nearer of the two alignments, never by π."""
        if self._axis is None:
            return []
        centre, axis = self._axis
        f = self.cfg.fit
        k = self.kin.blob_index[f.axis_label]
        link = int(self.kin.blob_links[k])
        lateral = link_rotations[link][:, 1]
        if float(axis @ lateral) < 0.0:
            axis = -axis
        across = np.array([-axis[1], axis[0], 0.0])
        info = np.outer(across, across) / (2.0 * (_AXIS_LEVER_M * f.axis_sigma_rad) ** 2)
        lever = np.array([0.0, _AXIS_LEVER_M, 0.0])
        local = self.kin.blob_local[k]
        return [PointTarget(link, local + sign * lever, centre + sign * _AXIS_LEVER_M * axis, info)
                for sign in (1.0, -1.0)]

    def _initialise(self, stamp_ns, theta, obs):
        self.initialisations += 1
        self._dof_velocity = None
        self._set_pose(theta, np.eye(self.body.n_dof) * 1e-2, None, 0.0)

    def _set_pose(self, theta, cov_theta, previous_links, dt):
        f = self.cfg.fit
        if previous_links is not None and dt > 0:  # self.theta: the pose set last
            v = np.where(self._velocity_dofs, (theta - self.theta) / dt, 0.0)
            a = f.predict_velocity_smoothing
            self._dof_velocity = v if self._dof_velocity is None else a * v + (1.0 - a) * self._dof_velocity
        self.theta = theta
        self.cov_theta = cov_theta
        Jl, Jb = _pose_jacobians(self.body, theta)
        self.link_cov = Jl @ cov_theta @ np.swapaxes(Jl, 1, 2)
        self.blob_cov = Jb @ cov_theta @ np.swapaxes(Jb, 1, 2)
        p, R = self.kin.poses(theta)
        L = self.kin.n_links
        self.velocity, self.angular_velocity = np.zeros((L, 3)), np.zeros((L, 3))
        if previous_links is not None and dt > 0:
            p0, R0 = previous_links
            self.velocity = (p - p0) / dt
            self.angular_velocity = log_so3(R @ np.swapaxes(R0, 1, 2)) / dt
        self.poses = (p, R)

    def _triangulation_priors(self, stamp_ns):
        # the prediction's blobs (_predict) without the rest of its BodyEstimate
        theta, q = self._predicted_pose(stamp_ns)
        return {b.label: b for b in self._blob_list(theta, self.blob_cov + q * np.eye(3))}

    def _mirror_hypotheses(self, obs: Mapping[str, Blob3D]) -> list[tuple[dict[str, Blob3D], np.ndarray, set]]:
        """This frame's blobs with the left and right blobs of each ``fit.mirror_groups`` group
        exchanged (groups whose parts are not seen on both sides are skipped): the other
        data associations of the legs, which the body fit tests against the labelled one.
        Each comes with the dofs that move the exchanged blobs' links and no other observed
        blob's link (the hips and knees for the whole legs, the knees for the shins alone), and
        the exchanged labels."""
        out = []
        for group in self.cfg.fit.mirror_groups:
            swapped = {side + part for part in group if "l_" + part in obs and "r_" + part in obs
                       for side in ("l_", "r_")}
            if swapped:  # each label takes its mirror's blob (the labels keep obs' order)
                source = {k: obs[mirror_label(k)] if k in swapped else obs[k] for k in obs}
                free = self._own_dofs(swapped, obs, carry_below=True)
                out.append(({k: dataclasses.replace(b, label=k) for k, b in source.items()}, free, swapped))
        return out

    def _own_dofs(self, labels, obs: Mapping[str, Blob3D], carry_below: bool = False) -> np.ndarray:
        """The dofs that move the links of the blobs ``labels`` and no other observed blob's link
        (nor the root): for the legs the hips and knees, for a hand its shoulder, elbow and wrist.
        carry_below: other blobs on links below ``labels``' links may move too (a model's foot
        blobs, carried by the knees: for a fit whose cost counts their residuals as well)."""
        moves = self.body.dof_moves_link
        link = {k: int(self.kin.blob_links[self.kin.blob_index[k]]) for k in set(obs) | set(labels)}
        own = moves[[link[k] for k in labels]].any(axis=0)
        others = [link[k] for k in obs if k not in labels]
        if carry_below:  # (the links at or below one of labels' links)
            tops = [link[k] for k in labels]
            others = [i for i in others if not self.body.link_carried_by[i, tops].any()]
        return np.flatnonzero(own & ~moves[others + [0]].any(axis=0))

    def _reach_for(self, labels, obs: Mapping[str, Blob3D], theta: np.ndarray) -> np.ndarray:
        """``theta`` with the parts ``labels`` (just re-acquired, :meth:`_reacquire`) moved onto their
        new blobs by their own dofs alone (plain least squares, the rest of the body held): from the
        old pose, far off, the robust fit would take the new blob for an outlier. Fitted from the arm
        as it is and again (``tracking.reacquire_bent_start``) with its hinges (the elbow; dof names
        ending '.hinge') half bent, the lower cost kept: from a straight arm, the elbow on its limit,
        the fit cannot bend it toward a blob nearer the shoulder (the first-order step points off the
        limit)."""
        f = self.cfg.fit
        free = self._own_dofs(labels, obs)
        if not free.size:
            return theta
        targets = self._blob_targets({k: obs[k] for k in labels})
        hinges = free[[self.body.dof_names[i].endswith(".hinge") for i in free]]
        starts = [theta]
        if hinges.size and self.cfg.tracking.reacquire_bent_start:
            bent = theta.copy()
            bent[hinges] = 0.5 * (self.body.lower[hinges] + self.body.upper[hinges])
            starts.append(bent)
        best, best_cost = theta, np.inf
        for start in starts:
            fitted, cost, _ = fit_pose(self.body, start, targets, self.kin.rest, self.rest_sigma_dof, theta,
                                       f.previous_sigma_rad, f.max_nfev, 0.0, tolerance=f.tolerance, free_dofs=free)
            if cost < best_cost:
                best, best_cost = fitted, cost
        return best

    def _step(self, stamp_ns, obs):
        f = self.cfg.fit
        dt = (stamp_ns - self.stamp_ns) * 1e-9
        targets = self._blob_targets(obs)
        axis = self._axis_targets(self.poses[1]) if targets else []
        targets += axis
        goals = self._edge_goals()
        if not targets and (goals is None or not len(goals.links)):
            # Nothing observed: the pose coasts (a fit to the priors alone leaves the root free to wander).
            self._set_pose(self.theta, self.cov_theta, self.poses, dt)
            return
        start = self._reach_for(self.reacquired, obs, self.theta) if self.reacquired else self.theta
        theta, cost, cov = fit_pose(
            self.body,
            start,
            targets,
            self.kin.rest,
            self.rest_sigma_dof,
            self.theta,
            f.previous_sigma_rad,
            f.max_nfev,
            f.robust_scale,
            goals,
            self._ground,
            tolerance=f.tolerance,
        )
        for mirrored, free, swapped in self._mirror_hypotheses(obs):
            # Screen first: the exchanged blobs refitted by their own dofs alone (hips and knees;
            # the knees for the shins alone), the rest of the body held at the labelled fit, from
            # that fit's legs mirrored across the body's sagittal plane (left in the right's pose
            # and back). Its cost bounds the full mirrored fit's from above, so only a screen near
            # the labelled cost earns the full fit.
            targets_m = self._blob_targets(mirrored) + axis
            prior = (self.kin.rest, self.rest_sigma_dof, self.theta, f.previous_sigma_rad)
            rest = (f.robust_scale, goals, self._ground)
            theta_m, cost_m = exchange_sides(self.body, theta, swapped), 0.0
            if free.size:  # (no dof of their own: straight to the full fit)
                _, cost_m, _ = fit_pose(self.body, theta_m, targets_m, *prior, f.max_nfev, *rest, evaluate_only=True)
                if cost_m >= f.mirror_prescreen_ratio * cost:
                    continue  # hopeless from the start: no screen
                abandon = ((f.mirror_screen_abandon_after, f.mirror_screen_abandon_ratio * cost)
                           if f.mirror_screen_abandon_after > 0 else None)
                theta_m, cost_m, _ = fit_pose(self.body, theta_m, targets_m, *prior, f.max_nfev, *rest,
                                              tolerance=f.tolerance, free_dofs=free, abandon=abandon)
            if cost_m < f.mirror_screen_ratio * cost:
                theta_m, cost_m, cov_m = fit_pose(self.body, theta_m, targets_m, *prior, f.max_nfev, *rest,
                                                  tolerance=f.tolerance)
                if cost_m < cost:
                    theta, cost, cov = theta_m, cost_m, cov_m
        self._set_pose(theta, cov, self.poses, dt)

    def _estimate(self, stamp_ns):
        return BodyEstimate(
            int(stamp_ns),
            list(self.body.joint_names),
            self.body.joint_positions(self.theta),
            self._links(self.theta, self.velocity, self.angular_velocity, self.link_cov),
            self._blob_list(self.theta, self.blob_cov),
            self.status,
            float(self.quality),
        )

    def _predicted_pose(self, stamp_ns) -> tuple[np.ndarray, float]:
        """(theta, q): the pose predicted for stamp_ns (the last one moved on by the smoothed dof
        velocities, ``fit.predict_velocity_gain``) and the variance q (m²) its links and blobs gain
        (``fit.predict_velocity_sigma``)."""
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        q = (self.cfg.fit.predict_velocity_sigma * dt) ** 2
        theta = self.theta
        gain = self.cfg.fit.predict_velocity_gain
        if gain > 0 and self._dof_velocity is not None:
            theta = np.clip(theta + gain * dt * self._dof_velocity, self.body.lower, self.body.upper)
        return theta, q

    def _predict(self, stamp_ns):
        theta, q = self._predicted_pose(stamp_ns)
        L = self.kin.n_links
        link_cov = self.link_cov.copy()
        link_cov[:, :3, :3] += q * np.eye(3)
        zeros = np.zeros((L, 3))
        return BodyEstimate(
            int(stamp_ns),
            list(self.body.joint_names),
            self.body.joint_positions(theta),
            self._links(theta, zeros, zeros, link_cov),
            self._blob_list(theta, self.blob_cov + q * np.eye(3)),
            self.status,
            float(self.quality),
        )
