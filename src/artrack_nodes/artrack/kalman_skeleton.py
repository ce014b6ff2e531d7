"""The dynamic skeleton: Kalman filters as goals of the virtual-work constraint solver
(ALGORITHMS.md §1, paper §2.1 and §2.3), kinematic or with full dynamics. The shared frame
(start-up, gates, the track's life cycle) is ``estimator.Estimator``'s; the raw tracker run
beside the filters is ``baseline_estimator.BaselineEstimator``.

``'kinematic'`` — the paper's cheap variant (§2.3, "15 % CPU"): one
constant-acceleration Kalman filter per blob (paper Eq. 7; ``kalman.py``)
and per link origin; the filtered blob positions are *goals* for the
virtual-work constraint solver (``constraints.py``), springs of stiffness
``α P⁻¹`` (the filters' inverse covariance; paper: ``Q_o = α Σ⁻¹ (y − x)``),
over free rigid links held together by hard ball / hinge constraints.
Soft priors fill the unobserved links: rest pose (relative orientation to the
parent), previous / predicted orientation, joint limits (springs toward the
clipped pose), a weak "gravity" on limbs without blobs, and weak goals from
the link-origin filters. The solver iterates to a globally consistent pose,
which is written back into the filters ("the results then become the new
state estimates"). Before the filters' update every blob is classified against
one consistent body: the body model fitted robustly to the frame's blobs (as
the baseline); a blob far from that fit gets its R inflated by a Cauchy weight
(``kinematic.outlier_fit_scale``), since each filter alone judges its blob only
against its own prediction and would follow a consistently mislabelled blob.
Conversely, a blob that fit explains but its filter's prediction does not is a manoeuvre (a
hand that starts to wave): the filter's process noise is scaled by the normalised innovation,
at most ``kinematic.maneuver_max_scale`` times (adaptive process noise), so that the filter
follows the limb rather than the soft innovation gate (``kinematic.robust_scale``) taking the
motion for an outlier and the filter falling behind. That fit is also the links' orientation
measurement (``kinematic.orientation_from_fit``):
the blob filters measure positions only, and a torso whose blobs sit on its axis
(pelvis, torso, head) leaves its heading to the springs; the solver's orientation
springs then pull each link to the fit's rotation instead of its extrapolated
previous one, and the fit follows its own track from frame to frame (started from
its last result, not from the solver's pose), so that a heading the solver lets
drift does not carry the measurement with it. With edges on, the edge statistics
enter that fit as soft link constraints, as in the baseline (ALGORITHMS.md §2 "Fusion").
With ``kinematic.fit_source: baseline`` (default) that fit is the raw tracker's: a
baseline estimator runs beside the filters on the same 2-D blobs (``self.raw``), so the
legs' left/right association, the torso-shape cue, the floor contact, the re-acquired
hands and its face check all shape the outlier test and the orientation goals. Track
initiation: for the first ``kinematic.warmup_frames`` frames after the filters are
(re)initialised, while their velocities and accelerations are still unknown, the raw
tracker's estimate and prediction are the output (and so the 2-D priors); then the
filters take over. The raw tracker also owns the track's life cycle
(``kinematic.follow_raw_track``): when it starts a new track (start-up, relocalisation, a
re-seed, its face check or verification turning the body round) the filters restart at its
pose and warm up again, and they run no face checks of their own. ``predict`` runs the
filters forward and solves the constraints for the predicted goals; its blobs carry the
prediction covariance from ``P_prior``.

``'dynamic'`` — full dynamics (paper §2.1): links with masses and inertias,
observations as damped springs, ``q̈ = W (Q + Jᵀλ)`` integrated in
sub-steps by ``ConstraintSolver.step_dynamic``; the prediction integrates the
same system forward without new observations. As the kinematic estimator, it runs the raw
tracker beside it (``dynamic.follow_fit``, ``kinematic.fit_source: baseline``): the springs pull
toward that tracker's robust fit of the frame (its blob centres, and torsional springs toward
its link orientations, ``dynamic.fit_orientation_stiffness``), which owns the track's life
cycle and is the output while the dynamics warm up (``kinematic.warmup_frames``). Springs on
the raw triangulated blobs instead (``follow_fit: false``, the form before stop 47) let a
mislabelled blob fling light links about, and the loop diverged (metres within seconds).
Stiffness-proportional damping (``dynamic.stiffness_damping_s``) damps the fast modes of light
links on stiff springs (a hand's spin about its own axis) that damping per unit mass leaves ringing.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.linalg import null_space

from .baseline_estimator import BaselineEstimator
from .body_fit import fit_pose
from .constraints import (
    Force,
    OrientationGoal,
    PointGoal,
    assemble,
    exp_so3,
    log_so3,
    orientation_goals,
    pack_terms,
    soft_energy_terms,
)
from .errors import InputError
from .estimator import Estimator, n_seen
from .kalman import ConstantAccelerationKF
from .lie import skew
from .startup import same_blobs
from .types import STATUS_TRACKING, Blob3D, BodyEstimate

__all__ = ["DynamicEstimator", "KinematicEstimator"]


class KinematicEstimator(Estimator):
    """Kalman filters as goals of the kinematic constraint solver (module docstring).

    State: ``theta`` / link poses ``p``, ``R``; ``blob_kf`` (B blob centres) and
    ``link_kf`` (L link origins), constant-acceleration filters; ``omega`` (L, 3)
    smoothed angular velocities, rad/s. Diagnostics of the last update:
    ``iterations`` (solver) and ``n_accepted`` (blobs passing the innovation gate).
    """

    kind = "kinematic"

    def __init__(self, body, cameras, config=None):
        #: the raw tracker run beside the filters (``kinematic.fit_source: baseline``), or None
        self.raw: BaselineEstimator | None = None
        super().__init__(body, cameras, config)
        source = self.cfg.kinematic.fit_source
        if source not in ("baseline", "own"):
            raise InputError(f"skeleton config: field 'kinematic.fit_source' is '{source}', expected baseline or own")
        if self.kind == "kinematic" and source == "baseline":
            self.raw = BaselineEstimator(body, cameras, config)
        self.solver = self.kin.solver()
        no_blob = np.ones(self.kin.n_links, bool)
        no_blob[self.kin.blob_links] = False
        no_blob[0] = True
        self.goal_links = np.flatnonzero(no_blob)  # links pulled toward their predicted origin
        limbs = no_blob.copy()
        limbs[0] = False
        self.gravity_links = np.flatnonzero(limbs)

    # -- the raw tracker beside the filters (kinematic.fit_source: baseline) -----------
    def reset(self) -> None:
        """As :meth:`Estimator.reset`, the filters' count and the raw tracker too."""
        super().reset()
        self._filter_frames = 0  # filter updates since the last (re)initialisation
        #: stamps (ns) at which the filters were re-initialised at the raw tracker's new track
        self.raw_restarts: list[int] = []
        if self.raw is not None:
            self.raw.reset()
        # the raw tracker's track count seen last (_follow_raw_track)
        self._raw_initialisations = self.raw.initialisations if self.raw is not None else 0

    def update(self, stamp_ns, blobs_by_camera, edges=None):
        """As :meth:`Estimator.update`, with the raw tracker (``self.raw``) updated first on the
        same blobs: its frame fit is the filters' outlier test and orientation goal, and while
        the filters warm up (``kinematic.warmup_frames``) its estimate is the output."""
        if self.raw is None:
            return super().update(stamp_ns, blobs_by_camera, edges)
        t0 = time.perf_counter()
        raw = self.raw.update(stamp_ns, blobs_by_camera, edges)
        raw_ms = 1e3 * (time.perf_counter() - t0)
        if self._follow_raw_track(int(stamp_ns)):
            # restarted at the raw tracker's pose of this frame: its blobs are already in it (as a
            # track's first frame, no filter update on them)
            self.timings_ms, self.quality, self.last_observed = {}, self.raw.quality, self.raw.last_observed
            out = self._estimate(int(stamp_ns))
        else:
            out = super().update(stamp_ns, blobs_by_camera, edges)
        # the raw tracker's update (its own triangulation included) is this estimator's outlier fit
        self.timings_ms["outlier_fit"] = self.timings_ms.get("outlier_fit", 0.0) + raw_ms
        return raw if self._raw_leads() else out

    def predict(self, stamp_ns):
        """The filters' prediction, or the raw tracker's while it leads (:meth:`update`), so that the
        2-D priors come from the same body as the output."""
        return self.raw.predict(stamp_ns) if self._raw_leads() else super().predict(stamp_ns)

    def reseed(self, stamp_ns, joints, sigma_m=0.05, limb_sigma_m=None):
        """As :meth:`Estimator.reseed`, the raw tracker re-seeded first."""
        if self.raw is not None:
            self.raw.reseed(stamp_ns, joints, sigma_m, limb_sigma_m)
        return super().reseed(stamp_ns, joints, sigma_m, limb_sigma_m)

    def _follow_raw_track(self, stamp_ns: int) -> bool:
        """The raw tracker owns the track's life cycle (``kinematic.follow_raw_track``): when it has
        started a new track since the last frame (start-up, relocalisation, re-seed, its face check
        or verification turning the body round), or tracks while the filters do not, the filters
        are re-initialised at its pose, as after a re-seed, and warm up again. Without this the
        filters keep a body the raw tracker has just found wrong (a mirrored start, a hand on the
        other side) and, once they lead, output it. Returns whether they were re-initialised."""
        started = self.raw.initialisations != self._raw_initialisations
        self._raw_initialisations = self.raw.initialisations
        if not self._raw_owns_track():
            return False
        if not started and self.theta is not None and self.status == STATUS_TRACKING:
            return False
        if self.stamp_ns is not None and stamp_ns < self.stamp_ns:
            return False  # time went backwards: update() resets and starts again
        self._initialise(stamp_ns, self.raw.theta, self.raw.last_observed)
        self._start_verification()
        self._verify_left = 0  # the raw tracker's checks decide the heading (_check_facing)
        self.status, self.missed, self.stamp_ns = STATUS_TRACKING, 0, stamp_ns
        self.raw_restarts.append(stamp_ns)
        return True

    def _check_facing(self, stamp_ns, blobs_by_camera, obs):
        """The face check (:meth:`Estimator._check_facing`), left to the raw tracker while it
        tracks and ``kinematic.follow_raw_track`` is on (its turns re-initialise the filters)."""
        if not self._raw_owns_track():
            super()._check_facing(stamp_ns, blobs_by_camera, obs)

    def _verify_facing(self, stamp_ns, obs):
        """The mirrored-start verification, left to the raw tracker as :meth:`_check_facing`."""
        if not self._raw_owns_track():
            super()._verify_facing(stamp_ns, obs)

    def _raw_tracking(self) -> bool:
        return self.raw is not None and self.raw.theta is not None and self.raw.status == STATUS_TRACKING

    def _raw_owns_track(self) -> bool:
        """Whether the raw tracker decides the track's life cycle now (``kinematic.follow_raw_track``
        and it is tracking): :meth:`_follow_raw_track`, :meth:`_check_facing`, :meth:`_verify_facing`."""
        return self.cfg.kinematic.follow_raw_track and self._raw_tracking()

    def _raw_leads(self) -> bool:
        """Whether the raw tracker's estimate is the output: it is tracking, and the filters have
        had fewer than ``kinematic.warmup_frames`` updates since they were (re)initialised."""
        return self._raw_tracking() and self._filter_frames < self.cfg.kinematic.warmup_frames

    def _new_filter(self, positions: np.ndarray, q: float) -> ConstantAccelerationKF:
        k = self.cfg.kinematic
        return ConstantAccelerationKF(
            positions, k.init_position_sigma_m**2, k.init_velocity_sigma**2, k.init_acceleration_sigma**2, q
        )

    def _initialise(self, stamp_ns, theta, obs):
        k = self.cfg.kinematic
        self.initialisations += 1
        self.theta = self.body.clip(theta)
        p, R = self.kin.poses(self.theta)
        self.p, self.R = p, R
        self.blob_kf = self._new_filter(self.kin.blob_points(p, R), k.blob_jerk)
        self.link_kf = self._new_filter(p, k.link_jerk)
        self.omega = np.zeros((self.kin.n_links, 3))
        self.link_cov = np.tile(np.eye(6) * k.init_position_sigma_m**2, (self.kin.n_links, 1, 1))
        self.iterations = 0
        self.n_accepted = n_seen(obs)
        self._fit_theta = None  # the outlier fit's own track (orientation_from_fit)
        self._filter_frames = 0

    # -- goals -------------------------------------------------------------------
    def _soft_terms(self, blob_x, blob_P, link_x, link_P, R_goal):
        """Static soft terms (packed once) and the callable adding the pose-dependent priors."""
        k = self.cfg.kinematic
        terms: list = []
        for b in range(len(self.kin.blob_labels)):
            S = k.alpha * np.linalg.inv(blob_P[b])
            terms.append(PointGoal(int(self.kin.blob_links[b]), self.kin.blob_local[b], blob_x[b], S))
        if k.link_goal_weight > 0:
            for i in self.goal_links:
                S = k.link_goal_weight * np.linalg.inv(link_P[i])
                terms.append(PointGoal(int(i), np.zeros(3), link_x[i], S))
        if k.previous_sigma_rad > 0:
            for i in range(self.kin.n_links):
                terms.append(OrientationGoal(i, R_goal[i], 1.0 / k.previous_sigma_rad**2))
        if k.gravity_weight > 0:
            for i in self.gravity_links:
                f = np.array([0.0, 0.0, -k.gravity_weight * self.kin.masses[i]])
                terms.append(Force(int(i), self.kin.com[i], f))
        static = pack_terms(terms)
        parent = self.kin.parent
        lo, hi = self.body.lower, self.body.upper
        rest_S = k.rest_weight / self.rest_sigma_link**2
        limit_S = 1.0 / k.limit_sigma_rad**2
        rest_links = np.flatnonzero(rest_S[1:] > 0) + 1

        def all_terms(p, R):
            # rest pose relative to the parent, then a joint-limit spring on each link out of its limits
            out = static + orientation_goals(
                rest_links, R[parent[rest_links]] @ self.kin.rest_local[rest_links], rest_S[rest_links]
            )
            theta = self.kin.theta_from_poses(p, R)
            clipped = np.clip(theta, lo, hi)
            # (the root has no joint limit spring)
            outside = np.unique(self.kin.link_of_dof[(clipped != theta) & self.kin.non_root_dofs]).tolist()
            if outside:
                targets = [
                    R[parent[i]] @ self.kin.local_rotation(i, clipped[self.body.links[i].dof_slice]) for i in outside
                ]
                out = out + orientation_goals(outside, np.array(targets), limit_S)
            return out

        return terms, all_terms

    def _solve(self, p0, R0, blob_x, blob_P, link_x, link_P, R_goal, iterations):
        _, terms = self._soft_terms(blob_x, blob_P, link_x, link_P, R_goal)
        res = self.solver.solve_kinematic(p0, R0, terms, max_iterations=iterations, step_tol=1e-4)
        theta = self.body.clip(self.kin.theta_from_poses(res.p, res.R))
        return theta, res, terms

    def _link_covariance(self, p, R, terms) -> np.ndarray:
        """(L, 6, 6) covariance of the link poses: the soft terms' information restricted
        to the constraint manifold, N (Nᵀ H N)⁻¹ Nᵀ with N a null-space basis of J."""
        _, K, _ = soft_energy_terms(self.kin.n_links, p, R, terms(p, R))
        H = np.zeros((6 * self.kin.n_links,) * 2)
        for i in range(self.kin.n_links):
            H[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = K[i] + 1e-6 * np.eye(6)
        J = assemble(self.kin.constraints, p, R, dense=True)[1]
        # N from a complete QR of Jᵀ (independent joint rows: the body's tree), the SVD otherwise
        Q, Rq = np.linalg.qr(J.T, mode="complete")
        d = np.abs(np.diag(Rq))
        N = Q[:, J.shape[0] :] if d.size and d.min() > 1e-10 * d.max() else null_space(J)
        C = N @ np.linalg.solve(N.T @ H @ N, N.T)
        return np.array([C[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(self.kin.n_links)])

    def _triangulation_priors(self, stamp_ns):
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        x, P = self.blob_kf.predicted(dt)
        _, shape_cov = self.body.blob_gaussians(self.theta)
        return {
            lab: Blob3D(lab, x[b, :3], P[b, :3, :3] + shape_cov[b])
            for b, lab in enumerate(self.kin.blob_labels)
        }

    def _associate(self, labelled):
        """As :meth:`Estimator._associate`, reusing the raw tracker's association of this frame
        when it ran on the very same blobs (it did, unless its ``fit.overlap_parts`` screen left a
        pair out): the same function of the same input, computed once."""
        if self.raw is not None and self.raw._association is not None:
            seen, result = self.raw._association
            if same_blobs(seen, labelled):
                self._association = (labelled, result)
                out, swaps = result
                return {c: list(bl) for c, bl in out.items()}, {c: list(p) for c, p in swaps.items()}
        return super()._associate(labelled)

    def _triangulate_labelled(self, labelled, priors):
        """As :meth:`Estimator._triangulate_labelled`; when the raw tracker triangulated the very
        same associated blobs this frame, its results for the labels whose rays met (no prior used)
        are taken as they are, and only the others are triangulated here, with this estimator's
        priors: the same blobs as triangulating all of them again, in the same order (those others to
        the last bits: solved in a smaller batch, the cameras' projections take another BLAS path)."""
        raw = self.raw._triangulation if self.raw is not None else None
        if raw is None or not same_blobs(raw[0], labelled):
            return super()._triangulate_labelled(labelled, priors)
        _, raw_obs, raw_free = raw
        rest = {c: [b for b in bl if b.label not in raw_free] for c, bl in labelled.items()}
        own, own_free = self._triangulation_of(rest, priors) if any(rest.values()) else ({}, set())
        obs = {}
        for lab in dict.fromkeys(b.label for bl in labelled.values() for b in bl):  # first appearance
            source = raw_obs if lab in raw_free else own
            if lab in source:
                obs[lab] = source[lab]
        self._triangulation = (labelled, obs, raw_free | own_free)
        return obs

    def _step(self, stamp_ns, obs):
        k = self.cfg.kinematic
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        B = len(self.kin.blob_labels)
        self._filter_frames += 1
        tk = time.perf_counter()
        self.blob_kf.predict(dt)
        self.link_kf.predict(dt)
        z = np.full((B, 3), np.nan)
        Rm = np.tile(np.eye(3), (B, 1, 1))
        mask = np.zeros(B, bool)
        t0 = time.perf_counter()
        theta_fit, fit_d2 = self._outlier_fit(obs, k.outlier_fit_scale)
        t1 = time.perf_counter()
        fit_centres = (None if theta_fit is None or self.cfg.measurement.one_view_depth_sigma_m <= 0
                       else self.body.blob_centres(theta_fit))  # (only for one-view depths)
        for lab, blob in obs.items():
            b = self.kin.blob_index[lab]
            z[b], Rm[b] = blob.mean, self.measurement_cov(blob)
            ray = self._one_view_ray(blob)
            if ray is not None and fit_centres is not None:
                # One view: its depth along the ray is the filters' own prediction (the prior it was
                # triangulated with), which would feed back on itself and run away; the depth comes
                # from the frame's body fit instead (floor contact, upright trunk), the point of the
                # ray nearest that fit's blob, to measurement.one_view_depth_sigma_m along the ray.
                origin, d = ray
                z[b] = origin + float((fit_centres[b] - origin) @ d) * d
                Rm[b] = self._one_view_cov(Rm[b], d)
                r = z[b] - fit_centres[b]
                fit_d2[lab] = float(r @ np.linalg.solve(Rm[b], r))
            S = self.blob_kf.P_prior[b, :3, :3] + Rm[b]
            nu = z[b] - self.blob_kf.x_prior[b, :3]
            d2 = float(nu @ np.linalg.solve(S, nu))
            if k.maneuver_max_scale > 1.0 and d2 > 3.0 and fit_d2.get(lab, np.inf) <= k.outlier_fit_scale**2:
                # A manoeuvre: the frame's body fit explains the blob, the filter's constant-acceleration
                # prediction does not. Its process noise grows with the normalised innovation (adaptive
                # process noise, Bar-Shalom et al. 2001, §11.2), so the filter follows the limb instead
                # of the soft gate below taking the innovation for an outlier and the filter falling behind.
                scale = min(d2 / 3.0, k.maneuver_max_scale)
                self.blob_kf.inflate_prior(b, scale)
                S = self.blob_kf.P_prior[b, :3, :3] + Rm[b]
                d2 = float(nu @ np.linalg.solve(S, nu))
            mask[b] = d2 <= self.cfg.measurement.gate_chi2
            if lab in fit_d2:
                # Outlier classification against the frame's robust body fit (_outlier_fit):
                # a blob the consistent body does not explain pulls its filter little.
                Rm[b] = Rm[b] * (1.0 + fit_d2[lab] / k.outlier_fit_scale**2)
            if k.robust_scale > 0:
                # Soft gate (Cauchy weight, as the baseline's robust fit): an unlikely innovation
                # pulls less, but never not at all, so a filter that has fallen behind a fast limb
                # is not locked out for good by the hard gate (it would coast away forever).
                Rm[b] = Rm[b] * (1.0 + d2 / k.robust_scale**2)
        # Coasting filters (no accepted measurement) lose their velocity and acceleration gradually.
        used = mask | (np.isfinite(z[:, 0]) & (k.robust_scale > 0))
        x = self.blob_kf.x.copy()
        x[~used, 3:6] *= k.coast_velocity_decay
        x[~used, 6:9] *= k.coast_acceleration_decay
        self.blob_kf.x_prior = self.blob_kf.x = x
        self.blob_kf.update(z, Rm, used)
        self.n_accepted = int(sum(mask[self.kin.blob_index[lab]] for lab, blob in obs.items() if blob.cameras))
        t2 = time.perf_counter()
        R_pred = exp_so3(self.omega * dt) @ self.R
        # the links' orientation springs: toward the frame's robust body fit when it ran, else the
        # constant-angular-velocity prediction
        R_goal = self.kin.poses(theta_fit)[1] if (k.orientation_from_fit and theta_fit is not None) else R_pred
        theta, res, terms = self._solve(
            self.p,
            self.R,
            self.blob_kf.position,
            self.blob_kf.position_cov(),
            self.link_kf.x_prior[:, :3],
            self.link_kf.position_cov(prior=True),
            R_goal,
            k.max_iterations,
        )
        self.iterations = res.iterations
        p, R = self.kin.poses(theta)
        # Write the consistent answer back into the filters (paper §2.3).
        self.blob_kf.project_position(self.kin.blob_points(p, R))
        self.link_kf.update(p, np.eye(3) * k.writeback_sigma_m**2)
        if dt > 0:
            w = log_so3(R @ np.swapaxes(self.R, 1, 2)) / dt
            a = k.angular_velocity_smoothing
            self.omega = (1.0 - a) * self.omega + a * w
        self.theta, self.p, self.R = theta, p, R
        self.link_cov = self._link_covariance(p, R, terms)
        t3 = time.perf_counter()
        self.timings_ms.update(outlier_fit=1e3 * (t1 - t0), kalman=1e3 * (t2 - tk - (t1 - t0)),
                               constraints=1e3 * (t3 - t2))

    def _outlier_fit(self, obs, scale):
        """Outlier classification against one consistent body (ALGORITHMS.md §1, measurement
        step): the body model fitted robustly (Cauchy loss ``fit.robust_scale``, as the baseline)
        to this frame's 3-D blobs, started from the last pose moved by the root filter's
        prediction (``kinematic.orientation_from_fit``: from the fit's own last result, held
        near it); with ``kinematic.fit_source: baseline`` the raw tracker's fit of this frame
        instead, while it tracks. Returns (theta_fit or None, {label: whitened squared residual
        of the blob to that fit})."""
        f = self.cfg.fit
        own_track = self.kind == "kinematic" and self.cfg.kinematic.orientation_from_fit
        if scale <= 0 or len(obs) < self.cfg.tracking.min_blobs:
            if own_track:
                self._fit_theta = None  # the next fit starts again from the solver's pose
            return None, {}
        if self._raw_tracking():  # (kinematic.fit_source: baseline) the raw tracker's fit of this frame
            theta = self.raw.theta
        else:
            theta0, previous = self.theta.copy(), self.theta
            if self.kind == "kinematic":
                theta0[0:3] = self.link_kf.x_prior[0, :3]
            if own_track and self._fit_theta is not None:
                theta0 = previous = self._fit_theta
            theta, _, _ = fit_pose(
                self.body,
                theta0,
                self._blob_targets(obs),
                self.kin.rest,
                self.rest_sigma_dof,
                previous,
                f.previous_sigma_rad,
                f.max_nfev,
                f.robust_scale,
                link_goals=self._edge_goals() if own_track else None,
                ground=self._upright_head,
                tolerance=f.tolerance,
            )
        if own_track:
            self._fit_theta = theta
        centres = self.body.blob_centres(theta)
        d2 = {}
        for lab, blob in obs.items():
            r = blob.mean - centres[self.kin.blob_index[lab]]
            d2[lab] = float(r @ np.linalg.solve(self.measurement_cov(blob), r))
        return theta, d2

    def _n_used(self, obs):
        return self.n_accepted

    def _estimate(self, stamp_ns):
        return BodyEstimate(
            int(stamp_ns),
            list(self.body.joint_names),
            self.body.joint_positions(self.theta),
            self._links(self.theta, self.link_kf.velocity, self.omega, self.link_cov),
            self._blob_list(self.theta, self.blob_kf.position_cov()),
            self.status,
            float(self.quality),
        )

    def _predict(self, stamp_ns):
        k = self.cfg.kinematic
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        xb, Pb = self.blob_kf.predicted(dt)
        xl, Pl = self.link_kf.predicted(dt)
        R_pred = exp_so3(self.omega * dt) @ self.R
        theta, res, _ = self._solve(
            self.p, R_pred, xb[:, :3], Pb[:, :3, :3], xl[:, :3], Pl[:, :3, :3], R_pred, k.predict_iterations
        )
        link_cov = self.link_cov.copy()
        link_cov[:, :3, :3] = Pl[:, :3, :3]
        return BodyEstimate(
            int(stamp_ns),
            list(self.body.joint_names),
            self.body.joint_positions(theta),
            self._links(theta, xl[:, 3:6], self.omega, link_cov),
            self._blob_list(theta, Pb[:, :3, :3]),
            self.status,
            float(self.quality),
        )


class DynamicEstimator(KinematicEstimator):
    """Full dynamics (paper §2.1): free rigid links with masses and inertias (from the
    body model's shapes), observation springs ``Q_o = α Σ⁻¹ (y − x)`` toward the
    triangulated blobs (α = ``dynamic.spring_scale``, stiffness capped at
    ``spring_stiffness_max`` N/m), viscous damping, rest-pose / joint-limit torsional
    springs and weak gravity on unobserved limbs, hard joints through the
    virtual-work constraint force; integrated by ``ConstraintSolver.step_dynamic``
    in ``substeps`` per frame with stiffness-proportional damping ``stiffness_damping_s``. The
    prediction integrates the same system on without observation springs (momentum carries the
    links forward). With ``follow_fit`` (module docstring) the springs' targets are the raw tracker's
    fit of the frame, which also leads the track's life cycle as for :class:`KinematicEstimator`."""

    kind = "dynamic"
    blowups = 0  # integration steps dropped because the solve became non-finite

    def __init__(self, body, cameras, config=None):
        super().__init__(body, cameras, config)
        if self.cfg.dynamic.follow_fit and self.cfg.kinematic.fit_source == "baseline":
            self.raw = BaselineEstimator(body, cameras, config)
            self._raw_initialisations = self.raw.initialisations

    def _initialise(self, stamp_ns, theta, obs):
        super()._initialise(stamp_ns, theta, obs)
        self.nu = np.zeros((self.kin.n_links, 6))
        self.blob_state_cov = np.tile(
            np.eye(3) * self.cfg.kinematic.init_position_sigma_m**2, (len(self.kin.blob_labels), 1, 1)
        )

    def _n_used(self, obs):
        return n_seen(obs)

    def _priors_callable(self, static: list):
        d = self.cfg.dynamic
        parent = self.kin.parent
        lo, hi = self.body.lower, self.body.upper
        rest_S = d.rest_stiffness / self.rest_sigma_link**2
        terms = list(static)
        if d.gravity_weight > 0:
            for i in self.gravity_links:
                terms.append(
                    Force(
                        int(i), self.kin.com[i], np.array([0.0, 0.0, -d.gravity_weight * self.kin.masses[i]])
                    )
                )

        def all_terms(p, R):
            out = list(terms)
            theta = self.kin.theta_from_poses(p, R)
            clipped = np.clip(theta, lo, hi)
            for i, lk in enumerate(self.body.links):
                if i == 0:
                    continue
                Rk = R[parent[i]]
                if rest_S[i] > 0:
                    out.append(OrientationGoal(i, Rk @ self.kin.rest_local[i], rest_S[i]))
                sl = lk.dof_slice
                if np.any(clipped[sl] != theta[sl]):
                    out.append(
                        OrientationGoal(i, Rk @ self.kin.local_rotation(i, clipped[sl]), d.limit_stiffness)
                    )
            return out

        return all_terms

    def _integrate(self, p, R, nu, dt, static):
        d = self.cfg.dynamic
        terms = self._priors_callable(static)
        n = max(int(d.substeps), 1)
        for _ in range(n):
            try:
                res = self.solver.step_dynamic(p, R, nu, dt / n, terms, d.linear_damping, d.angular_damping,
                                               stiffness_damping=d.stiffness_damping_s)
            except np.linalg.LinAlgError:
                res = None
            if res is None or not all(np.all(np.isfinite(a)) for a in (res.p, res.R, res.nu)):
                # numerical blow-up (stiff springs against the sub-step): hold the pose, stop
                # the motion, and let the next frame's observations take over
                self.blowups += 1
                return p, R, np.zeros_like(nu), terms
            p, R, nu = res.p, res.R, res.nu
        return p, R, nu, terms

    def _observation_springs(self, obs) -> list:
        d = self.cfg.dynamic
        _, fit_d2 = self._outlier_fit(obs, d.outlier_fit_scale)
        fit = d.follow_fit and self._raw_tracking()
        centres = R_fit = None
        if fit:  # the raw tracker's link poses: its blob centres and rotations from one forward kinematics
            p_fit, R_fit = self.kin.poses(self.raw.theta)
            centres = self.kin.blob_points(p_fit, R_fit)
        out = []
        for lab, blob in obs.items():
            b = self.kin.blob_index[lab]
            # blobs far from the frame's robust body fit pull less (as in the kinematic tracker)
            inflate = 1.0 + fit_d2.get(lab, 0.0) / max(d.outlier_fit_scale, 1e-9) ** 2
            w, V = np.linalg.eigh(np.linalg.inv(self.measurement_cov(blob) * inflate))
            S = (V * np.minimum(d.spring_scale * w, d.spring_stiffness_max)) @ V.T
            target = centres[b] if fit else blob.mean
            out.append(PointGoal(int(self.kin.blob_links[b]), self.kin.blob_local[b], target, S))
        if fit and d.fit_orientation_stiffness > 0:
            out += [OrientationGoal(i, R_fit[i], d.fit_orientation_stiffness) for i in range(self.kin.n_links)]
        return out

    def _triangulation_priors(self, stamp_ns):
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        p, R = self.kin.poses(self.theta)
        x = self.kin.blob_points(p, R)
        lever = np.einsum("bij,bj->bi", R[self.kin.blob_links], self.kin.blob_local)
        v = self.nu[self.kin.blob_links, :3] + np.cross(self.nu[self.kin.blob_links, 3:], lever)
        _, shape_cov = self.body.blob_gaussians(self.theta)
        return {
            lab: Blob3D(lab, x[b] + v[b] * dt, self.blob_state_cov[b] + shape_cov[b])
            for b, lab in enumerate(self.kin.blob_labels)
        }

    def _step(self, stamp_ns, obs):
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        self._filter_frames += 1  # (the raw tracker leads for kinematic.warmup_frames of them, with follow_fit)
        springs = self._observation_springs(obs)
        if dt > 0:
            p, R, nu, terms = self._integrate(self.p, self.R, self.nu, dt, springs)
        else:
            p, R, nu, terms = self.p, self.R, self.nu, self._priors_callable(springs)
        theta = self.body.clip(self.kin.theta_from_poses(p, R))
        self.theta = theta
        self.p, self.R = self.kin.poses(theta)
        self.nu = nu
        self.omega = nu[:, 3:].copy()
        self.link_cov = self._link_covariance(self.p, self.R, terms)
        # Blob centre covariance from the link covariance (position + lever × rotation).
        lever = np.einsum("bij,bj->bi", self.R[self.kin.blob_links], self.kin.blob_local)
        A = np.concatenate([np.broadcast_to(np.eye(3), (lever.shape[0], 3, 3)), -skew(lever)], axis=2)
        C = self.link_cov[self.kin.blob_links]
        self.blob_state_cov = A @ C @ np.swapaxes(A, 1, 2)

    def _estimate(self, stamp_ns):
        return BodyEstimate(
            int(stamp_ns),
            list(self.body.joint_names),
            self.body.joint_positions(self.theta),
            self._links(self.theta, self.nu[:, :3], self.nu[:, 3:], self.link_cov),
            self._blob_list(self.theta, self.blob_state_cov),
            self.status,
            float(self.quality),
        )

    def _predict(self, stamp_ns):
        d = self.cfg.dynamic
        dt = max((stamp_ns - self.stamp_ns) * 1e-9, 0.0)
        p, R, nu = self.p, self.R, self.nu
        if dt > 0:
            p, R, nu, _ = self._integrate(p, R, nu, dt, [])
        theta = self.body.clip(self.kin.theta_from_poses(p, R))
        q = (d.predict_velocity_sigma * dt) ** 2
        link_cov = self.link_cov.copy()
        link_cov[:, :3, :3] += q * np.eye(3)
        return BodyEstimate(
            int(stamp_ns),
            list(self.body.joint_names),
            self.body.joint_positions(theta),
            self._links(theta, nu[:, :3], nu[:, 3:], link_cov),
            self._blob_list(theta, self.blob_state_cov + q * np.eye(3)),
            self.status,
            float(self.quality),
        )
