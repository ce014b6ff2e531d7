"""Negative evidence: where a part that some cameras did not find can be.

ALGORITHMS.md §1 ("Inverse observation model"): the predicted body is projected into every
camera and each prior is marked VISIBLE, OFF_IMAGE or OCCLUDED by the predicted body's shapes.
Read backwards, the same test says where a part is *not*: a camera whose 2-D tracker found no
blob of the part would have seen it at any point that projects inside its image and whose line
of sight no other link blocks. A hand behind the back is seen by one camera or none; its depth
along the one ray, or its whole position, then comes from the prediction alone, which drifts
(self-occlusion scene, seed 5: a hand seen by one camera placed 0.43–0.56 m off, where the
three cameras that did not find it would have seen it).

:func:`hide` searches the prediction's Gaussian (along the one view's ray, or in 3-D when no
view found the part) for the most probable point given that the silent cameras did not find
it: each silent camera that would have seen a point costs -log of the probability that its
tracker misses a part in sight (``miss_probability``), added to the prediction's -log density.
The candidates stay within the part's reach of its chain's top joint and outside every other
part's shape (a hand inside the trunk would hide from every view). The prediction itself
competes: it is kept (None) unless a point seen by fewer of the silent views is more probable.
The occluders are the body's capsules at its current pose, without those
of the part's own chain (a drifted forearm must not explain its own hand away).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .cameras import Camera
from .projection import Capsule, _segment_distances, visible_points

__all__ = ["hide", "RAY_SAMPLES", "GRID_SAMPLES"]

#: Points sampled along a single view's ray, evenly over the prior's ± ``sigmas`` along it.
RAY_SAMPLES = 25
#: Points sampled per axis of the prior's whitened Gaussian when no view found the part (a cube
#: over ± ``sigmas``, kept inside the ball of that radius).
GRID_SAMPLES = 9


def _ray_candidates(origin: np.ndarray, direction: np.ndarray, mean: np.ndarray, cov: np.ndarray,
                    sigmas: float, min_depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reference point (3,): the ray's point nearest ``mean``, candidates (N, 3), their cost: the
    distance along the ray in the prior's standard deviations there)."""
    d = direction / np.linalg.norm(direction)
    s0 = max(float(d @ (mean - origin)), min_depth)
    sigma = float(np.sqrt(max(d @ cov @ d, 1e-12)))
    t = np.linspace(-sigmas, sigmas, RAY_SAMPLES)
    s = s0 + sigma * t
    keep = s > min_depth
    return origin + s0 * d, origin + s[keep, None] * d, np.abs(t[keep])


def _grid_candidates(mean: np.ndarray, cov: np.ndarray, sigmas: float) -> tuple[np.ndarray, np.ndarray]:
    """(candidates (N, 3), their Mahalanobis distance from ``mean`` under ``cov``)."""
    axis = np.linspace(-sigmas, sigmas, GRID_SAMPLES)
    u = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    r = np.linalg.norm(u, axis=1)
    u, r = u[r <= sigmas + 1e-9], r[r <= sigmas + 1e-9]
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    L = V * np.sqrt(np.maximum(w, 1e-12))
    return mean + u @ L.T, r


def _inside_capsules(points: np.ndarray, capsules: Sequence[Capsule]) -> np.ndarray:
    """(N,) bool: which points (N, 3) lie inside one of the capsules (no part can be there)."""
    if not capsules:
        return np.zeros(len(points), bool)
    p0 = np.array([c.p0 for c in capsules], float)[None]
    p1 = np.array([c.p1 for c in capsules], float)[None]
    radius = np.array([c.radius for c in capsules], float)
    dist = _segment_distances(points[:, None], points[:, None], p0, p1)  # a point: a degenerate segment
    return (dist < radius[None]).any(axis=1)


def hide(label: str, mean: np.ndarray, cov: np.ndarray, silent: Sequence[Camera], capsules: Sequence[Capsule], *,
         ray: tuple[np.ndarray, np.ndarray] | None = None, reach: tuple[np.ndarray, float] | None = None,
         sigmas: float = 3.0, miss_probability: float = 0.01, occlusion_margin: float = 0.05,
         inset_px: float = 0.0, min_depth: float = 1e-3) -> np.ndarray | None:
    """The most probable point (3,) m of the part ``label`` predicted at ``mean`` (3,) m with
    covariance ``cov`` (3, 3) m², given that none of the ``silent`` cameras found it; None when that
    is the prediction itself (module docstring).

    Each candidate scores -log of the prediction's density (half its squared Mahalanobis distance)
    plus -log ``miss_probability`` for each silent camera that would have seen it: a tracker misses
    a part in plain sight with that probability. At 0.01 (4.6 a view, more than the 4.5 of a
    candidate 3 sigma off) one view fewer beats any distance within ± 3 sigma.

    ray: (origin (3,), unit direction (3,)) of the one view that found the part: the candidates
    lie on it (and the prediction is taken to the ray's point nearest it); None: no view found
    it, the candidates fill the prior's ± ``sigmas`` ellipsoid.
    reach: (centre (3,), radius m): candidates farther from the centre are not taken. capsules:
    the occluding shapes, inside which no candidate is taken either
    (:func:`artrack.projection.visible_points`, with ``occlusion_margin`` m and ``inset_px``: a
    point closer to the image border than this counts as unseen)."""
    mean = np.asarray(mean, float).reshape(3)
    cov = np.asarray(cov, float).reshape(3, 3)
    if ray is not None:
        ref, points, cost = _ray_candidates(np.asarray(ray[0], float), np.asarray(ray[1], float), mean, cov,
                                            sigmas, min_depth)
    else:
        ref = mean
        points, cost = _grid_candidates(mean, cov, sigmas)
    if reach is not None:
        near = np.linalg.norm(points - np.asarray(reach[0], float), axis=1) <= float(reach[1])
        points, cost = points[near], cost[near]
    if len(points) and capsules:
        outside = ~_inside_capsules(points, [c for c in capsules if c.label != label])
        points, cost = points[outside], cost[outside]
    if not len(points) or not silent or not 0.0 < miss_probability < 1.0:
        return None
    every = np.vstack([ref[None], points])
    seen = np.zeros(len(every), int)
    for cam in silent:
        seen += visible_points(cam, every, label, capsules, occlusion_margin, inset_px, min_depth)
    if seen[0] == 0:
        return None
    # MAP: -log prior (0.5 cost²) - log P(no blob found | the part in sight) for every silent view
    # that would have seen it; the reference (the prediction, cost 0) competes
    score = 0.5 * np.concatenate([[0.0], cost]) ** 2 - seen * np.log(miss_probability)
    best = int(np.argmin(score))
    return points[best - 1].copy() if best > 0 else None
