"""Bottom-up part detectors ("shouters") of the loose-limbed body (ALGORITHMS.md §4 Inference, Q_t(X_i)).

A simple detector that does the job of the paper's multi-view appearance
detectors: (1) search along camera rays through foreground pixels for 3-D
points that are foreground in every view (a sampled visual hull); (2) put
the centre of a part's tapered cylinder at such points, with random axis
directions and twists, and score every candidate with the part's multi-view
silhouette/edge likelihood (the appearance model: a projected template of the
part); (3) keep the best few, distinct candidates. The proposal Q is a
Gaussian kernel mixture around them; the twist about the cylinder axis is
unobservable, so its kernel variance is large. Detectors run for the head,
the upper and lower arms and the lower legs, as in the paper, and also for the
torso (the largest, most reliable part; without it the first iterations had
no anchor); they do not tell left from right (both sides get the same
candidates). Candidates are weighted by their likelihood (tempered by
``score_temperature``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .body_parts import MIRROR, PART_NAMES, PartGeometry
from .loose_limbed import KernelMixture
from .part_likelihood import PartLikelihood, ViewEvidence, sample_maps

#: parts with a detector (both sides share one)
SHOUTED_PARTS = ("torso", "head", "l_upper_arm", "l_forearm", "l_shin")


@dataclass
class ShouterConfig:
    """Search sizes and proposal widths."""

    n_rays: int = 400             #: foreground pixels per reference view
    n_depths: int = 48            #: depths sampled along each ray
    depth_range: tuple[float, float] = (1.0, 8.0)  #: m from the camera
    fg_min: float = 0.5           #: a hull point is foreground ≥ this in every view
    n_centres: int = 150          #: hull points tried as part centres
    n_orientations: int = 12      #: axis directions per centre
    n_keep: int = 8               #: candidates proposed per part
    n_refine: int = 40            #: best candidates refined by local search
    refine_rounds: int = 3        #: rounds of local search (8 perturbations each, shrinking)
    nms_distance: float = 0.08    #: m, candidates closer than this (centres) are merged
    sd_pos: float = 0.03          #: proposal kernel sd, m
    sd_rot: float = 0.15          #: proposal kernel sd about the axis-normal directions, rad
    sd_twist: float = 1.5         #: proposal kernel sd about the cylinder axis, rad
    score_temperature: float = 2.0  #: candidate weights ∝ exp(log-likelihood / this)
    upright_parts: tuple[str, ...] = ("torso", "head")  #: parts searched with their axis near world up
    upright_max_angle: float = 0.8  #: rad, the cone about +z for those parts


def hull_points(views: Sequence[ViewEvidence], rng: np.random.Generator, config: ShouterConfig | None = None
                ) -> np.ndarray:
    """(M, 3) world points that are foreground in every view, found along rays of foreground pixels."""
    cfg = config or ShouterConfig()
    found = []
    for ref in views:
        ys, xs = np.nonzero(ref.fg >= cfg.fg_min)
        if len(xs) == 0:
            return np.zeros((0, 3))
        pick = rng.choice(len(xs), size=min(cfg.n_rays, len(xs)), replace=False)
        uv = np.stack([xs[pick], ys[pick]], axis=1).astype(float)
        origin, dirs = ref.camera.rays(uv)
        depth = rng.uniform(*cfg.depth_range, size=(len(uv), cfg.n_depths))
        pts = (origin + dirs[:, None, :] * depth[:, :, None]).reshape(-1, 3)
        ok = np.ones(len(pts), bool)
        for v in views:
            if v is ref:
                continue
            fg, _ = sample_maps(v, pts)
            ok &= fg >= cfg.fg_min
        found.append(pts[ok])
    return np.concatenate(found) if found else np.zeros((0, 3))


def _random_axes(n: int, rng: np.random.Generator, max_angle: float = np.pi) -> np.ndarray:
    """n unit vectors uniform on the sphere cap within max_angle of +z."""
    z = rng.uniform(np.cos(max_angle), 1.0, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _align(axis_part: np.ndarray, axis_world: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) taking the part-frame axis (3,) to the world axes (N, 3), then twisting about it."""
    a = axis_part / np.linalg.norm(axis_part)
    c = np.cross(a, axis_world)
    s = np.linalg.norm(c, axis=1)
    ang = np.arctan2(s, axis_world @ a)
    fallback = np.cross(a, [1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.cross(a, [0.0, 1.0, 0.0])
    c = np.where(s[:, None] > 1e-9, c / np.maximum(s, 1e-12)[:, None], fallback / np.linalg.norm(fallback))
    align = Rotation.from_rotvec(c * ang[:, None])
    return (align * Rotation.from_rotvec(np.outer(twist, a))).as_quat()


class Shouter:
    """Detects candidate part poses in one frame's evidence (see module docstring)."""

    def __init__(self, geometry: PartGeometry, likelihood: PartLikelihood, config: ShouterConfig | None = None,
                 seed: int = 0):
        self.geometry = geometry
        self.likelihood = likelihood
        self.config = config or ShouterConfig()
        self.rng = np.random.default_rng(seed)

    def candidates(self, part: int, views: Sequence[ViewEvidence], hull: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Best distinct poses of part ``part``: pos (C, 3), quat (C, 4), log-likelihood (C,)."""
        cfg = self.config
        g = self.geometry
        if len(hull) == 0:
            return np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0)
        rng = self.rng
        centres = hull[rng.choice(len(hull), size=min(cfg.n_centres, len(hull)), replace=False)]
        n = len(centres) * cfg.n_orientations
        upright = g.names[part] in cfg.upright_parts
        axes = _random_axes(n, rng, cfg.upright_max_angle if upright else np.pi)
        quat = _align(g.axis[part], axes, rng.uniform(-np.pi, np.pi, n))
        mid = 0.5 * (g.start[part] + g.end[part])
        pos = np.repeat(centres, cfg.n_orientations, axis=0) - mid * axes
        ll = self.likelihood.log_likelihood(part, pos, quat, views)
        top = np.argsort(-ll)[:cfg.n_refine]
        pos, quat, ll = pos[top], quat[top], ll[top]
        for r in range(cfg.refine_rounds):  # local search about the best candidates
            k = 8
            sp, sr = 0.04 * 0.6**r, 0.3 * 0.6**r
            pp = np.repeat(pos, k, axis=0) + rng.standard_normal((len(pos) * k, 3)) * sp
            qq = (Rotation.from_quat(np.repeat(quat, k, axis=0))
                  * Rotation.from_rotvec(rng.standard_normal((len(pos) * k, 3)) * sr)).as_quat()
            lp = self.likelihood.log_likelihood(part, pp, qq, views).reshape(len(pos), k)
            best = np.argmax(lp, axis=1)
            lbest = lp[np.arange(len(pos)), best]
            better = lbest > ll
            sel = (np.arange(len(pos)) * k + best)[better]
            pos[better], quat[better], ll[better] = pp[sel], qq[sel], lbest[better]
        axes = Rotation.from_quat(quat).apply(g.axis[part])
        order = np.argsort(-ll)
        keep: list[int] = []
        mids = pos + mid * axes
        for k in order:
            if all(np.linalg.norm(mids[k] - mids[j]) > cfg.nms_distance for j in keep):
                keep.append(int(k))
            if len(keep) == cfg.n_keep:
                break
        keep_a = np.array(keep, int)
        return pos[keep_a], quat[keep_a], ll[keep_a]

    def proposal(self, pos: np.ndarray, quat: np.ndarray, part: int, score: np.ndarray | None = None
                 ) -> KernelMixture:
        """Q: kernels about candidate poses (large variance about the cylinder axis), weighted by score."""
        cfg = self.config
        a = np.abs(self.geometry.axis[part])
        rot_var = np.where(a > 0.5, cfg.sd_twist**2, cfg.sd_rot**2)
        var = np.tile(np.concatenate([[cfg.sd_pos**2] * 3, rot_var]), (len(pos), 1))
        logw = np.zeros(len(pos)) if score is None else (score - score.max()) / cfg.score_temperature
        logw -= np.log(np.exp(logw).sum())
        return KernelMixture(logw, pos.copy(), quat.copy(), var)

    def shout(self, views: Sequence[ViewEvidence]) -> dict[int, KernelMixture]:
        """Proposals for every shouted part (and its mirror) in one frame; {} if nothing is foreground."""
        hull = hull_points(views, self.rng, self.config)
        out: dict[int, KernelMixture] = {}
        for name in SHOUTED_PARTS:
            part = PART_NAMES.index(name)
            pos, quat, ll = self.candidates(part, views, hull)
            if len(pos) == 0:
                continue
            q = self.proposal(pos, quat, part, ll)
            out[part] = q
            if name in MIRROR:
                out[PART_NAMES.index(MIRROR[name])] = q
        return out
