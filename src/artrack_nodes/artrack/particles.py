"""Particle filter over joint angles with spatial motion priors and a held stick
(ALGORITHMS.md §3, after Hauberg & Pedersen).

State per particle: the active joint angles θ (d,) of a :class:`PoseManifold`
(torso, head, arms by default; root, legs and wrists stay at the base pose)
and one stick position γ ∈ [0, 1] per hand. Each frame: systematic
resampling, a draw from the prior, weights from the point-cloud likelihood
(eq. (9), :class:`~artrack.pointcloud.SkinModel`), estimate = weighted mean.

Priors (``ParticleConfig.prior``):

``gp``       eq. (1): θ_t ~ N(θ_{t−1}, σ_θ² I) clipped into Θ.
``proj``     eq. (3): x ~ N(F(θ_{t−1}), σ_x² I) in R^{3P}, projected onto M (eq. (4)).
``stick3d``  eq. (8): γ_t ~ N(γ_{t−1}, σ_γ²) on [0, 1] (eq. (7)); hand means
             stick(γ_t) = γ a + (1 − γ) b (eq. (5)), other end points their current
             position; hands drawn with σ_hand, others with σ_x; projected onto M in
             the Σ⁻¹ metric (hand points weighted σ_x / σ_hand).
``stick2d``  §3.1: as stick3d, but each hand's mean is its current position
             projected onto the viewing ray through the image point γ a_uv + (1 − γ) b_uv
             (an image cannot tell the ends apart: they are ordered to fit the current
             hands and γ).
``kkb``      eq. (6): θ drawn from ``gp`` until both hands lie within T_E of
             stick(γ), at most ``kkb_max_rejections`` rejections (then the last
             draw is kept: that particle ignores the stick); the share of capped
             particles is reported.

Without a stick (none received for the frame) the stick priors fall back to
``proj``. Deterministic for a given seed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .body_model import BodyModel
from .cameras import Camera
from .pointcloud import SkinModel
from .pose_manifold import DEFAULT_ACTIVE_LINKS, DEFAULT_POINT_LINKS, PoseManifold
from .types import BodyEstimate, LinkEstimate

__all__ = [
    "PRIORS",
    "ParticleConfig",
    "ParticleFilter",
    "Stick2D",
    "Stick3D",
    "StepStats",
    "gamma_on_stick",
    "stick_point",
]

PRIORS = ("gp", "proj", "stick3d", "stick2d", "kkb")


@dataclass
class Stick3D:
    """A known stick, end points a, b (3,) world, m (eq. (5): stick(γ) = γ a + (1 − γ) b)."""

    a: np.ndarray
    b: np.ndarray


@dataclass
class Stick2D:
    """The stick's image in ``camera``: end points a_uv, b_uv (2,) px (a_uv is the image of a)."""

    a_uv: np.ndarray
    b_uv: np.ndarray
    camera: Camera


def stick_point(a: np.ndarray, b: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Eq. (5): γ a + (1 − γ) b, (..., D) for γ (...,) and end points a, b (D,)."""
    g = np.asarray(gamma, float)[..., None]
    return g * np.asarray(a, float) + (1.0 - g) * np.asarray(b, float)


def gamma_on_stick(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> np.ndarray:
    """γ (...,) in [0, 1] of the stick points nearest to points (..., 3)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = a - b
    g = np.sum((np.asarray(points, float) - b) * ab, axis=-1) / max(float(ab @ ab), 1e-12)
    return np.clip(g, 0.0, 1.0)


@dataclass
class ParticleConfig:
    """Tunables of the §3 tracker (config/particle_tracker.yaml mirrors them). Units: m, rad."""

    n_particles: int = 500
    prior: str = "stick3d"            # gp | proj | stick3d | stick2d | kkb
    sigma_angle: float = 0.06         # rad per frame, p_gp / p_kkb
    sigma_point: float = 0.025        # m per frame, end points (spatial priors)
    sigma_hand: float = 0.001         # m, hands about their stick mean (stick priors)
    sigma_gamma: float = 0.01         # per frame, γ diffusion (eq. (7))
    kkb_threshold: float = 0.02       # m, T_E of eq. (6)
    kkb_max_rejections: int = 5000
    likelihood_sigma: float = 0.03    # m, σ of eq. (9) (0.02: weights collapse onto 1-8 particles; see README)
    likelihood_tau: float = 0.08      # m, truncation distance (τ = tau² in eq. (9))
    n_points: int = 400               # points used per frame (random subset)
    static_explained: float = 0.01    # m, points this close to the static body (legs, pelvis) are dropped
    projection_iterations: int = 8
    projection_reg: float = 0.05      # m/rad, pull to the start in the projection (see PoseManifold.project)
    active_links: tuple[str, ...] = DEFAULT_ACTIVE_LINKS
    point_links: tuple[str, ...] = DEFAULT_POINT_LINKS
    seed: int = 0

    def check(self) -> None:
        """Raise ValueError naming the bad field."""
        if self.prior not in PRIORS:
            raise ValueError(f"prior: unknown prior {self.prior!r} (expected one of {', '.join(PRIORS)})")
        for name in ("n_particles", "n_points", "kkb_max_rejections", "projection_iterations"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)}")
        for name in ("sigma_angle", "sigma_point", "sigma_hand", "likelihood_sigma", "likelihood_tau",
                     "kkb_threshold"):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: must be positive, got {v}")


@dataclass
class StepStats:
    """Diagnostics of one filter step: prior used, effective sample size, seconds (CPU) for the
    prior and the likelihood, p_kkb's share of particles that hit the rejection cap and mean
    rejections, the mean hand-to-stick distance over particles (m, NaN without a 3-D stick)."""

    prior: str
    ess: float
    prior_s: float
    likelihood_s: float
    n_points: int
    kkb_capped_share: float = float("nan")
    kkb_mean_rejections: float = float("nan")
    hand_stick_distance: float = float("nan")
    extra: dict = field(default_factory=dict)


class ParticleFilter:
    """The §3 tracker. body: body model; theta0: (n_dof,) initial full pose (also the base pose
    of the inactive dofs); gamma0: (2,) initial stick positions of the left / right hand."""

    def __init__(self, body: BodyModel, theta0: np.ndarray, config: ParticleConfig | None = None,
                 gamma0: np.ndarray | None = None):
        self.config = ParticleConfig() if config is None else config
        self.config.check()
        self.body = body
        self.manifold = PoseManifold(body, theta0, self.config.active_links, self.config.point_links)
        moving = [i for i in range(len(body.links)) if self._moves(i)]
        self.skin = SkinModel(body, moving)
        n = self.config.n_particles
        self.rng = np.random.default_rng(self.config.seed)
        self.theta = np.repeat(self.manifold.active(theta0)[None], n, axis=0)
        g0 = np.full(2, 0.5) if gamma0 is None else np.asarray(gamma0, float).reshape(2)
        self.gamma = np.repeat(g0[None], n, axis=0)
        self.log_w = np.zeros(n)
        self._point_sigma = np.full(self.manifold.P, self.config.sigma_point)
        self._warm_up()

    def _warm_up(self) -> None:
        """Evaluate the likelihood once on dummy points (no random numbers drawn). The first
        evaluation of the (particles x capsules x points) arrays otherwise pays for fresh memory
        pages (~0.5 s; the allocator then reuses its heap), so every frame costs the same."""
        full = self.manifold.full_theta(self.theta)
        z = np.linspace(-1.0, 1.0, 3 * self.config.n_points).reshape(-1, 3) + full[0, :3]
        eye = full[0, :3] + np.array([3.0, 0.0, 0.0])
        self.skin.log_likelihood(full, z, eye, self.config.likelihood_sigma, self.config.likelihood_tau**2)

    def _moves(self, link: int) -> bool:
        j = link
        active = set(self.manifold.active_links)
        while j >= 0:
            if j in active:
                return True
            j = int(self.body.parent_index[j])
        return False

    # ------------------------------------------------------------------ filter step
    def step(self, points_world: np.ndarray, camera_center: np.ndarray,
             stick: Stick3D | Stick2D | None = None) -> tuple[np.ndarray, StepStats]:
        """One frame: resample, predict with the configured prior, weigh by the points.

        points_world: (K, 3) world points (already cropped to the person's workspace);
        camera_center: (3,) world position of the depth camera; stick: this frame's stick.
        Returns (estimate: full pose (n_dof,), StepStats).
        """
        cfg = self.config
        if isinstance(stick, Stick2D):
            stick = self._orient(stick)
        self._resample()
        prior = cfg.prior
        if prior in ("stick3d", "kkb") and not isinstance(stick, Stick3D):
            prior = "proj" if prior == "stick3d" else "gp"
        if prior == "stick2d" and not isinstance(stick, Stick2D):
            prior = "proj"
        t0 = time.process_time()
        stats_extra: dict = {}
        if prior == "gp":
            self.theta = self._gp(self.theta)
        elif prior == "kkb":
            stats_extra = self._kkb(stick)
        else:
            self._spatial(prior, stick)
        t1 = time.process_time()
        z = self._select_points(points_world, camera_center)
        full = self.manifold.full_theta(self.theta)
        static = self.skin.static_sq_distance(full[0], z, camera_center)
        ll = self.skin.log_likelihood(full, z, camera_center, cfg.likelihood_sigma, cfg.likelihood_tau**2, static)
        self.log_w = ll - ll.max()
        t2 = time.process_time()
        w = self.weights
        est = self.manifold.full_theta(w @ self.theta)
        hand_d = float("nan")
        if isinstance(stick, Stick3D):
            hands = self.manifold.hands(self.theta)
            hand_d = float(np.mean([_point_segment_distance(hands[:, h], stick.a, stick.b) for h in (0, 1)]))
        stats = StepStats(prior=prior, ess=float(1.0 / np.sum(w * w)), prior_s=t1 - t0, likelihood_s=t2 - t1,
                          n_points=len(z), hand_stick_distance=hand_d,
                          kkb_capped_share=stats_extra.get("capped_share", float("nan")),
                          kkb_mean_rejections=stats_extra.get("mean_rejections", float("nan")))
        return est, stats

    def _orient(self, stick: Stick2D) -> Stick2D:
        """The stick image with its ends ordered so that γ means what it meant so far: of the two
        orders, the one whose points stick(γ) lie nearer to the current hands' projections."""
        hands = self.manifold.hands(self.weights @ self.theta)[0]           # (2, 3)
        uv, _ = stick.camera.project(hands)
        g = self.estimate_gamma()
        keep = np.linalg.norm(stick_point(stick.a_uv, stick.b_uv, g) - uv, axis=1).sum()
        swap = np.linalg.norm(stick_point(stick.b_uv, stick.a_uv, g) - uv, axis=1).sum()
        return stick if keep <= swap else Stick2D(stick.b_uv, stick.a_uv, stick.camera)

    def body_estimate(self, theta: np.ndarray, stamp_ns: int) -> BodyEstimate:
        """The estimate as the skeleton node publishes it: joints, link poses, blobs (world frame);
        quality = effective sample size / number of particles."""
        T = self.body.forward_kinematics(theta)
        links = [LinkEstimate(name=lk.name, position=T[i, :3, 3].copy(), rotation=T[i, :3, :3].copy())
                 for i, lk in enumerate(self.body.links)]
        w = self.weights
        return BodyEstimate(stamp_ns=int(stamp_ns), joint_names=list(self.body.joint_names),
                            joints=self.body.joint_positions(theta, T), links=links, blobs=self.body.blobs3d(theta),
                            quality=float(1.0 / np.sum(w * w) / len(w)))

    @property
    def weights(self) -> np.ndarray:
        """(n,) normalised particle weights."""
        w = np.exp(self.log_w - self.log_w.max())
        return w / w.sum()

    def estimate_gamma(self) -> np.ndarray:
        """(2,) weighted mean stick positions of the hands."""
        return self.weights @ self.gamma

    def _resample(self) -> None:
        """Systematic resampling by the current weights (a no-op on equal weights)."""
        n = len(self.theta)
        w = self.weights
        if np.allclose(w, 1.0 / n):
            return
        pos = (self.rng.random() + np.arange(n)) / n
        idx = np.minimum(np.searchsorted(np.cumsum(w), pos), n - 1)
        self.theta = self.theta[idx]
        self.gamma = self.gamma[idx]
        self.log_w = np.zeros(n)

    def _select_points(self, points_world: np.ndarray, camera_center: np.ndarray) -> np.ndarray:
        """Drop points the static body explains (within static_explained) and keep a random subset."""
        z = np.asarray(points_world, float).reshape(-1, 3)
        z = z[np.all(np.isfinite(z), axis=1)]
        if len(z) and self.config.static_explained > 0:
            base = self.manifold.base_theta
            d2 = self.skin.static_sq_distance(base, z, camera_center)
            z = z[d2 > self.config.static_explained**2]
        if len(z) > self.config.n_points:
            z = z[self.rng.choice(len(z), self.config.n_points, replace=False)]
        return z

    # ------------------------------------------------------------------ priors
    def _gp(self, theta: np.ndarray) -> np.ndarray:
        """Eq. (1), clipped into Θ."""
        return self.manifold.clip(theta + self.config.sigma_angle * self.rng.standard_normal(theta.shape))

    def _diffuse_gamma(self) -> None:
        """Eq. (7): γ_t ~ N(γ_{t−1}, σ_γ²) restricted to [0, 1] (redrawn outside, then clipped)."""
        g = self.gamma + self.config.sigma_gamma * self.rng.standard_normal(self.gamma.shape)
        for _ in range(10):
            bad = (g < 0) | (g > 1)
            if not bad.any():
                break
            g[bad] = self.gamma[bad] + self.config.sigma_gamma * self.rng.standard_normal(int(bad.sum()))
        self.gamma = np.clip(g, 0.0, 1.0)

    def _spatial(self, prior: str, stick: Stick3D | Stick2D | None) -> None:
        """Eqs. (3), (8) and §3.1: sample end points, project onto M."""
        cfg = self.config
        M = self.manifold
        mean = M.end_points(self.theta)                                   # (n, P, 3)
        sigma = self._point_sigma.copy()
        if prior in ("stick3d", "stick2d"):
            self._diffuse_gamma()
            hp = M.hand_points
            if prior == "stick3d":
                mean[:, hp] = stick_point(stick.a, stick.b, self.gamma)
            else:
                uv = stick_point(stick.a_uv, stick.b_uv, self.gamma)      # (n, 2, 2)
                origin, rays = stick.camera.rays(uv.reshape(-1, 2))
                rays = rays.reshape(-1, 2, 3)
                cur = mean[:, hp] - origin
                mean[:, hp] = origin + np.sum(cur * rays, axis=-1, keepdims=True) * rays
            sigma[hp] = cfg.sigma_hand
        x = mean + sigma[None, :, None] * self.rng.standard_normal(mean.shape)
        weights = cfg.sigma_point / sigma
        self.theta, _ = M.project(x, self.theta, weights, reg=cfg.projection_reg,
                                  max_iter=cfg.projection_iterations)

    def _kkb(self, stick: Stick3D) -> dict:
        """Eq. (6): rejection sampling from p_gp until both hands are within T_E of stick(γ)."""
        cfg = self.config
        M = self.manifold
        self._diffuse_gamma()
        target = stick_point(stick.a, stick.b, self.gamma)                 # (n, 2, 3)
        n = len(self.theta)
        out = self.theta.copy()
        rejections = np.zeros(n, int)
        accepted = np.zeros(n, bool)
        remaining = np.arange(n)
        cap = cfg.kkb_max_rejections
        while len(remaining):
            budget = cap - rejections[remaining]                           # draws left before the cap
            B = int(min(budget.min(), max(8, 20000 // len(remaining))))
            prev = self.theta[remaining]
            cand = M.clip(prev[:, None, :] + cfg.sigma_angle * self.rng.standard_normal((len(remaining), B, M.d)))
            hands = M.hands(cand.reshape(-1, M.d)).reshape(len(remaining), B, 2, 3)
            ok = np.all(np.linalg.norm(hands - target[remaining][:, None], axis=-1) < cfg.kkb_threshold, axis=-1)
            got = ok.any(axis=1)
            first = np.argmax(ok, axis=1)
            k = np.where(got, first, B - 1)
            out[remaining] = cand[np.arange(len(remaining)), k]
            rejections[remaining] += np.where(got, first, B)
            accepted[remaining[got]] = True
            remaining = remaining[~got & (rejections[remaining] < cap)]
        self.theta = out
        capped = ~accepted                   # the last (rejected) draw is kept: the stick is ignored
        return {"capped_share": float(capped.mean()), "mean_rejections": float(rejections.mean())}


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) distance of points p (n, 3) to the segment a-b."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)
