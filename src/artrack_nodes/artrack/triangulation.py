"""3-D blobs from the 2-D blobs of all cameras.

ALGORITHMS.md §1, "3-D blobs": 2-D blob means and covariances from two or more
calibrated views are combined into a 3-D mean and covariance per tracked part,
weighted by the 2-D covariances.

Method (per label). Each view i contributes the measurement ``u_i = π_i(X) + n_i``,
``n_i ~ N(0, Σ_i)`` with π_i the full camera model (pinhole + distortion) and Σ_i
the 2-D blob covariance. Starting from the least-squares midpoint of the viewing
rays, a few Gauss–Newton steps minimise ``Σ_i (u_i - π_i(X))ᵀ Σ_i⁻¹ (u_i - π_i(X))``;
the returned covariance is the inverse information ``(Σ_i J_iᵀ Σ_i⁻¹ J_i)⁻¹`` at the
solution (J_i = dπ_i/dX, 2x3).

The blob's shape in 3-D (:func:`blob_extent`): its 2-D covariances are projections of the
part's 3-D second moments S, ``C_i ≈ J_i S J_iᵀ`` (ALGORITHMS.md §1, "Inverse observation
model", read backwards); three or more views determine S by linear least squares (two do not:
with d_1, d_2 their viewing rays, S + c (d_1 d_2ᵀ + d_2 d_1ᵀ) projects alike in both). A torso's
widest horizontal axis is the shoulder line, whose heading the blob means cannot give.

Left/right association across views (:func:`associate_views`): look-alike pairs (the trouser
legs) can carry their l_/r_ labels the wrong way round in some views only; of the ways of
exchanging the pair per view, the one whose rays meet best (lowest weighted reprojection error)
is taken before triangulating, so that no 3-D blob mixes both parts.

Views that disagree (``view_outlier_chi2``, :func:`_drop_outlier_views`): a 2-D tracker whose
label has moved onto something else in one view (a hand's class on a bare knee) drags the 3-D blob
between the two. With three or more views such a view shows as the one whose removal lowers the
weighted reprojection error most; it is left out while that drop exceeds the threshold.

One view constrains only the ray (rank-2 information). Then a prior Blob3D
(e.g. the skeleton's prediction) is required and fused as one more Gaussian in
information form, so the depth along the ray comes from the prior; without a
prior the blob is not triangulated (None). With two or more views the prior is
not used (unless ``fuse_prior=True``) so that the result stays a measurement
independent of the prediction; note that a single-view result *does* reuse the
prior along the ray, which a downstream Kalman update should not count again.

Caveat: a Blob2D covariance describes the blob's spatial extent in the image,
not the uncertainty of its mean; using it as measurement noise weights views
sensibly (large/far blobs count less) but the absolute 3-D covariance is then
of the order of the blob's 3-D extent divided by sqrt(number of views).

Small blobs (``small_blob_fraction``): by its extent alone a blob of a few pixels would count
most, although it is the least reliable view: a part mostly hidden (a hand behind the hip seen
as a 7-pixel sliver) or a label holding on to a few stray pixels, whose mean is biased and whose
extent is small because the part is cut. Each view's information is multiplied by
``n / (n + n₀)``, n the blob's pixel count and n₀ = ``small_blob_fraction`` × the camera's image
area (a blob of n₀ pixels counts half; one of many pixels as its extent says).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from .cameras import Camera
from .errors import InputError
from .types import Blob2D, Blob3D, all_finite

__all__ = [
    "associate_views",
    "blob_extent",
    "drop_slivers",
    "midpoint",
    "midpoints",
    "triangulate_blob",
    "triangulate_blobs",
]

#: Most views whose left/right labels :func:`associate_views` exchanges jointly (2^(k-1) hypotheses).
MAX_ASSOCIATION_VIEWS = 6

#: Smallest eigenvalue of Σ (I - d dᵀ) below which the rays are taken as parallel
#: (two rays at angle θ give about sin²θ / 2; 1e-6 is θ ≈ 0.08°).
_MIN_RAY_SPREAD = 1e-6


def _information_2d(covs: np.ndarray) -> np.ndarray:
    """Inverses (n, 2, 2) of 2-D covariances (n, 2, 2) px², each with its eigenvalues floored at
    1e-9 of its largest (and 1e-12 px²), so that a degenerate blob does not make the system
    singular. All at once: one batched eigendecomposition."""
    covs = np.asarray(covs, dtype=float).reshape(-1, 2, 2)
    w, V = np.linalg.eigh(0.5 * (covs + covs.swapaxes(1, 2)))
    w = np.maximum(w, np.maximum(1e-9 * np.max(np.abs(w), axis=1), 1e-12)[:, None])
    return (V / w[:, None, :]) @ V.swapaxes(1, 2)


def midpoint(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares point nearest to N rays (world frame).

    origins: (N, 3) m; directions: (N, 3) unit. Returns the point (3,) m and the
    smallest eigenvalue of Σ (I - d dᵀ) (a ray-spread measure; ~0 for parallel rays).
    """
    X, spread = midpoints(np.asarray(origins, dtype=float).reshape(1, -1, 3),
                          np.asarray(directions, dtype=float).reshape(1, -1, 3))
    return X[0], float(spread[0])


def midpoints(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`midpoint` of P bundles of N rays each, at once: origins and directions (P, N, 3).
    Returns the points (P, 3) m and the ray spreads (P,)."""
    proj = np.eye(3) - directions[..., :, None] * directions[..., None, :]  # (P, N, 3, 3)
    A = proj.sum(axis=1)
    b = np.einsum("pnij,pnj->pi", proj, origins)
    spread = np.linalg.eigvalsh(A)[:, 0]
    X = np.empty(b.shape)
    ok = spread >= _MIN_RAY_SPREAD
    if ok.any():
        X[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    for p in np.flatnonzero(~ok):
        X[p] = np.linalg.lstsq(A[p], b[p], rcond=None)[0]
    return X, spread


def _gauss_newton(
    X: np.ndarray,
    cams: Sequence[Camera],
    uvs: np.ndarray,
    infos: np.ndarray,
    prior_mean: np.ndarray,
    prior_info: np.ndarray,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton on the weighted reprojection error (+ optional Gaussian prior), for B
    independent points at once (one projection call per camera and step, not per point).

    X: (B, 3) starts; cams: the C cameras; uvs: (B, C, 2) px; infos: (B, C, 2, 2) px⁻², zero
    where camera c does not see point b; prior_mean (B, 3) m and prior_info (B, 3, 3) m⁻², zero
    for no prior. Each point halves its own step until its cost does not increase and it stays
    in front of its cameras, and stops on its own. Returns X (B, 3), the information
    matrices H (B, 3, 3) at X and the costs (B,) there (weighted squared reprojection error
    plus prior term).
    """
    X = np.array(X, dtype=float).reshape(-1, 3)
    n = X.shape[0]
    seen = np.any(infos != 0.0, axis=(2, 3))  # (B, C)

    def linearise(Xc: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r = np.zeros((len(sel), len(cams), 2))
        J = np.zeros((len(sel), len(cams), 2, 3))
        for c, cam in enumerate(cams):
            rows = np.flatnonzero(seen[sel, c])
            if len(rows):
                pred, Jc = cam.project_jacobian(Xc[rows])
                r[rows, c] = uvs[sel[rows], c] - pred
                J[rows, c] = Jc
        W = infos[sel]
        JtW = np.einsum("bcki,bckl->bcil", J, W)
        dp = prior_mean[sel] - Xc
        P = prior_info[sel]
        H = np.einsum("bcil,bclj->bij", JtW, J) + P
        g = np.einsum("bcil,bcl->bi", JtW, r) + np.einsum("bij,bj->bi", P, dp)
        cost = np.einsum("bck,bckl,bcl->b", r, W, r) + np.einsum("bi,bij,bj->b", dp, P, dp)
        return H, g, cost

    def in_front(Xc: np.ndarray, sel: np.ndarray) -> np.ndarray:
        depth = np.stack([Xc @ cam.R[2] + cam.t[2] for cam in cams], axis=1)
        return np.all((depth > 0.0) | ~seen[sel], axis=1)

    H, g, cost = linearise(X, np.arange(n))
    active = np.ones(n, bool)
    for _ in range(iterations):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        step = np.zeros((n, 3))
        try:  # all 3x3 solves at once ...
            step[idx] = np.linalg.solve(H[idx], g[idx][..., None])[..., 0]
        except np.linalg.LinAlgError:  # ... unless one is singular: it stops only its own point
            for b in idx:
                try:
                    step[b] = np.linalg.solve(H[b], g[b])
                except np.linalg.LinAlgError:
                    active[b] = False
        idx = np.flatnonzero(active)
        lam = np.ones(n)
        accepted = np.zeros(n, bool)
        pending = idx
        for _ in range(8):
            if not len(pending):
                break
            Xn = X[pending] + lam[pending, None] * step[pending]
            front = in_front(Xn, pending)
            if front.any():
                sel = pending[front]
                Hn, gn, cn = linearise(Xn[front], sel)
                ok = cn <= cost[sel] * (1.0 + 1e-12) + 1e-12
                good = sel[ok]
                X[good], H[good], g[good], cost[good] = Xn[front][ok], Hn[ok], gn[ok], cn[ok]
                accepted[good] = True
            pending = pending[~accepted[pending]]
            lam[pending] *= 0.5
        moved = np.linalg.norm(lam[:, None] * step, axis=1)
        active &= accepted & (moved >= 1e-10)
    return X, H, cost


class _Problem(NamedTuple):
    """One label's triangulation, ready for :func:`_gauss_newton`."""

    label: str
    cameras: list[Camera]
    uvs: np.ndarray  # (k, 2) px, the blob means in those cameras
    infos: np.ndarray  # (k, 2, 2) px⁻²
    start: np.ndarray  # (3,) m
    prior_mean: np.ndarray | None  # (3,) m, when the prior is fused
    prior_info: np.ndarray | None  # (3, 3) m⁻²


def _finite(b: Blob2D) -> bool:
    return all_finite(b.mean, b.cov)


def _set_up(
    obs: list[tuple[Camera, Blob2D]],
    dirs: np.ndarray,
    infos: np.ndarray,
    prior: Blob3D | None,
    fuse_prior: bool,
) -> _Problem | None:
    """The Gauss–Newton problem of one blob (see :func:`triangulate_blob`): drop the views whose
    ray midpoint lies behind them, start at the midpoint (one usable direction: on the ray,
    nearest the prior). obs: finite observations; dirs: (k, 3) their viewing rays; infos: (k, 2, 2)
    their 2-D information (:func:`_information_2d`)."""
    label = obs[0][1].label if obs else (prior.label if prior is not None else "")
    if not obs:
        return None
    prior_mean = prior_info = None
    if prior is not None:
        prior_mean = np.asarray(prior.mean, dtype=float).reshape(3)
        pc = np.asarray(prior.cov, dtype=float).reshape(3, 3)
        prior_info = np.linalg.inv(0.5 * (pc + pc.T))
    origins = np.array([cam.center for cam, _ in obs])

    X0 = None
    if len(obs) >= 2:
        X0, spread = midpoint(origins, dirs)
        if spread >= _MIN_RAY_SPREAD:
            keep = [i for i, (cam, _) in enumerate(obs) if float(cam.R[2] @ X0 + cam.t[2]) > 0.0]
            if len(keep) < len(obs):
                obs = [obs[i] for i in keep]
                origins, dirs, infos = origins[keep], dirs[keep], infos[keep]
                X0, spread = midpoint(origins, dirs) if len(obs) >= 2 else (None, 0.0)
        if X0 is not None and spread < _MIN_RAY_SPREAD:
            X0 = None
    if not obs:
        return None
    use_prior = X0 is None or fuse_prior
    if X0 is None:
        # Only one usable direction: the prior must supply the depth.
        if prior is None:
            return None
        # Start on the (first) ray, at the point nearest to the prior mean.
        s = max(float(dirs[0] @ (prior_mean - origins[0])), 1e-3)
        X0 = origins[0] + s * dirs[0]
    uvs = np.array([np.asarray(b.mean, float).reshape(2) for _, b in obs])
    return _Problem(label, [c for c, _ in obs], uvs, infos, X0,
                    prior_mean if use_prior else None, prior_info if use_prior else None)


def _run(problems: list[_Problem], iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the problems' Gauss–Newton steps together (:func:`_gauss_newton`): X (n, 3), H (n, 3, 3),
    cost (n,)."""
    cams: dict[str, Camera] = {}
    for problem in problems:
        for c in problem.cameras:
            cams.setdefault(c.name, c)
    col = {name: i for i, name in enumerate(cams)}
    n, nc = len(problems), len(cams)
    X0 = np.zeros((n, 3))
    uvs = np.zeros((n, nc, 2))
    infos = np.zeros((n, nc, 2, 2))
    prior_mean = np.zeros((n, 3))
    prior_info = np.zeros((n, 3, 3))
    for b, pb in enumerate(problems):
        cols = [col[c.name] for c in pb.cameras]
        uvs[b, cols], infos[b, cols], X0[b] = pb.uvs, pb.infos, pb.start
        if pb.prior_mean is not None:
            prior_mean[b], prior_info[b] = pb.prior_mean, pb.prior_info
    return _gauss_newton(X0, list(cams.values()), uvs, infos, prior_mean, prior_info, iterations)


def _solve(problems: list[_Problem], iterations: int, view_outlier_chi2: float = 0.0) -> list[Blob3D | None]:
    """:func:`_run`, each result turned into a Blob3D (None where the information matrix is
    singular or not finite); with ``view_outlier_chi2`` > 0 after :func:`_drop_outlier_views`."""
    X, H, cost = _run(problems, iterations)
    if view_outlier_chi2 > 0:
        problems = list(problems)
        _drop_outlier_views(problems, X, H, cost, iterations, view_outlier_chi2)
    out: list[Blob3D | None] = []
    for b, pb in enumerate(problems):
        try:
            cov = np.linalg.inv(H[b])
        except np.linalg.LinAlgError:
            out.append(None)
            continue
        cov = 0.5 * (cov + cov.T)
        if not (np.all(np.isfinite(X[b])) and np.all(np.isfinite(cov))):
            out.append(None)
            continue
        out.append(Blob3D(pb.label, X[b].copy(), cov, tuple(c.name for c in pb.cameras)))
    return out


def _drop_outlier_views(problems: list[_Problem], X: np.ndarray, H: np.ndarray, cost: np.ndarray,
                        iterations: int, max_chi2: float) -> None:
    """Leave out the views that disagree with the others (in place: ``problems`` and the results
    X, H, cost of :func:`_run`). A blob seen in three or more views whose weighted reprojection
    error is above ``max_chi2`` is solved again without each of its views in turn (all at once,
    from its solution); the view whose removal lowers the error most goes if it lowers it by more
    than ``max_chi2``, and the test repeats while three or more views remain. A 2-D tracker whose
    label sits on the wrong thing in one view (a hand's class on a knee) otherwise drags the 3-D
    blob between the two (this project's addition to ALGORITHMS.md §1, "3-D blobs")."""
    while True:
        tests = [b for b, pb in enumerate(problems) if len(pb.cameras) >= 3 and cost[b] > max_chi2]
        if not tests:
            return
        subsets, owners = [], []
        for b in tests:
            pb = problems[b]
            for v in range(len(pb.cameras)):
                keep = [i for i in range(len(pb.cameras)) if i != v]
                subsets.append(pb._replace(cameras=[pb.cameras[i] for i in keep], uvs=pb.uvs[keep],
                                           infos=pb.infos[keep], start=X[b]))
                owners.append(b)
        Xs, Hs, cs = _run(subsets, iterations)
        changed = False
        for b in tests:
            rows = [j for j, o in enumerate(owners) if o == b]
            j = min(rows, key=lambda r: cs[r])
            if cost[b] - cs[j] > max_chi2:
                problems[b], X[b], H[b], cost[b] = subsets[j], Xs[j], Hs[j], cs[j]
                changed = True
        if not changed:
            return


def triangulate_blob(
    observations: Sequence[tuple[Camera, Blob2D]],
    prior: Blob3D | None = None,
    iterations: int = 5,
    fuse_prior: bool = False,
) -> Blob3D | None:
    """Covariance-weighted triangulation of one blob seen by several cameras.

    observations: (camera, 2-D blob) pairs, blob mean (2,) px and cov (2, 2) px² in
    that camera's (distorted) image. prior: optional Blob3D (world, mean (3,) m, cov
    (3, 3) m²), required when only one view is usable; fused also with several
    views when ``fuse_prior``. iterations: Gauss–Newton steps (from the ray midpoint).

    Returns a Blob3D in the world frame (mean (3,) m, cov (3, 3) m², ``cameras`` the
    contributing camera names, label of the 2-D blobs or of the prior), or None when
    there is no usable view, or a single view (or only parallel rays) and no prior.
    Views whose ray midpoint lies behind them are dropped.
    """
    obs = [(cam, b) for cam, b in observations if _finite(b)]
    dirs = np.array([cam.rays(np.asarray(b.mean, float).reshape(1, 2))[1][0] for cam, b in obs]).reshape(-1, 3)
    infos = _information_2d(np.array([b.cov for _, b in obs]))
    problem = _set_up(obs, dirs, infos, prior, fuse_prior)
    return None if problem is None else _solve([problem], iterations)[0]


def triangulate_blobs(
    blobs_by_camera: Mapping[str, Iterable[Blob2D]],
    cameras: Mapping[str, Camera] | Iterable[Camera],
    priors: Mapping[str, Blob3D] | None = None,
    iterations: int = 5,
    fuse_prior: bool = False,
    view_outlier_chi2: float = 0.0,
    prior_free: set[str] | None = None,
    small_blob_fraction: float = 0.0,
) -> dict[str, Blob3D]:
    """Triangulate every label seen in the cameras (as :func:`triangulate_blob` per label, with
    one undistortion per camera and the labels' Gauss–Newton steps run together).

    blobs_by_camera: {camera name: 2-D blobs of that camera}; cameras: {name: Camera}
    (or a list); priors: {label: predicted Blob3D} used for single-view labels (see
    ``triangulate_blob``). If a camera reports a label twice, the blob with the most
    pixels is used. Returns {label: Blob3D} for the labels that could be
    triangulated, in order of first appearance. Raises InputError for a camera name
    that is not among ``cameras``. ``prior_free``, when given, receives the labels whose
    triangulation did not use ``priors`` (their rays met): the same with any other priors.
    ``small_blob_fraction`` > 0: each view's information is multiplied by n / (n + n₀), n the
    blob's pixel count, n₀ this times the camera's width × height (module docstring).
    """
    cams = dict(cameras) if isinstance(cameras, Mapping) else {c.name: c for c in cameras}
    by_label: dict[str, dict[str, Blob2D]] = {}
    for cam_name, blobs in blobs_by_camera.items():
        if cam_name not in cams:
            raise InputError(f"triangulate_blobs: blobs from unknown camera '{cam_name}'")
        for b in blobs:
            views = by_label.setdefault(b.label, {})
            old = views.get(cam_name)
            if old is None or b.pixel_count > old.pixel_count:
                views[cam_name] = b
    # Viewing rays: one undistortion per camera for all its (finite) blobs; their 2-D information at once.
    ray: dict[tuple[str, str], np.ndarray] = {}
    for name in cams:
        keys = [(label, name) for label, views in by_label.items() if name in views and _finite(views[name])]
        if keys:
            uv = np.array([np.asarray(by_label[label][name].mean, float).reshape(2) for label, _ in keys])
            dirs = cams[name].rays(uv)[1]
            ray.update(zip(keys, dirs, strict=True))
    infos = _information_2d(np.array([by_label[label][name].cov for label, name in ray]))
    if small_blob_fraction > 0 and len(infos):
        n = np.array([by_label[label][name].pixel_count for label, name in ray], float)
        n0 = np.array([small_blob_fraction * cams[name].width * cams[name].height for _, name in ray])
        infos = infos * (n / (n + n0))[:, None, None]
    info = dict(zip(ray, infos, strict=True))
    problems: list[_Problem] = []
    for label, views in by_label.items():
        obs = [(cams[name], b) for name, b in views.items() if (label, name) in ray]
        dirs = np.array([ray[(label, c.name)] for c, _ in obs]).reshape(-1, 3)
        infos = np.array([info[(label, c.name)] for c, _ in obs]).reshape(-1, 2, 2)
        problem = _set_up(obs, dirs, infos, priors.get(label) if priors else None, fuse_prior)
        if problem is not None:
            problems.append(problem)
            if prior_free is not None and problem.prior_mean is None:
                prior_free.add(label)
    if not problems:
        return {}
    return {blob.label: blob for blob in _solve(problems, iterations, view_outlier_chi2) if blob is not None}


def drop_overlapping_pairs(
    blobs_by_camera: Mapping[str, Sequence[Blob2D]],
    parts: Iterable[str],
    max_chi2: float,
) -> tuple[dict[str, list[Blob2D]], dict[str, list[str]]]:
    """Leave a symmetric part pair out of the views where its two blobs overlap.

    Where two look-alike parts (trouser legs) overlap in a view, their pixels are shared out by
    the priors alone: the two blobs are pulled towards each other and say nothing about which
    part is which. Triangulated, they drag both 3-D blobs to the middle, so the legs lose their
    motion as they pass and come out of the crossing exchanged. For each part p of ``parts``, in
    every view that sees both ``l_p`` and ``r_p``, the pair is dropped when the squared
    Mahalanobis distance between their means under the sum of their covariances is below
    ``max_chi2``; the other views and the body fit's priors carry the pair through (this
    project's addition to the 3-D blobs of ALGORITHMS.md §1).

    Returns (blobs_by_camera without the dropped blobs; {camera: [parts dropped there]}).
    """
    out = {c: list(bl) for c, bl in blobs_by_camera.items()}
    dropped: dict[str, list[str]] = {}
    if max_chi2 <= 0:
        return out, dropped
    for name in sorted(out):
        by_label = {b.label: b for b in out[name] if _finite(b)}
        drop = set()
        for part in parts:
            left, right = by_label.get("l_" + part), by_label.get("r_" + part)
            if left is None or right is None:
                continue
            d = np.asarray(left.mean, float).reshape(2) - np.asarray(right.mean, float).reshape(2)
            S = np.asarray(left.cov, float).reshape(2, 2) + np.asarray(right.cov, float).reshape(2, 2)
            if float(d @ np.linalg.solve(S, d)) < max_chi2:
                drop |= {left.label, right.label}
                dropped.setdefault(name, []).append(part)
        if drop:
            out[name] = [b for b in out[name] if b.label not in drop]
    return out, dropped


def drop_slivers(
    blobs_by_camera: Mapping[str, Sequence[Blob2D]],
    cameras: Mapping[str, Camera],
    labels: Iterable[str],
    min_fraction: float,
    min_ray_angle_deg: float = 0.0,
) -> dict[str, list[Blob2D]]:
    """Leave a sliver of a part out of the views where two or more other views see it whole.

    A blob of one of ``labels`` with fewer pixels than ``min_fraction`` × its camera's image area
    is a part mostly hidden in that view, or its label holding on to stray pixels (another
    person's hand): its mean is the least reliable, yet its extent is so small that even weighted
    by ``small_blob_fraction`` (:func:`triangulate_blobs`) it counts about twice as much as a whole
    hand elsewhere, and on the wrong thing it pulls the 3-D blob, and with it the next priors,
    along its ray. It is dropped where two or more other views see the part with at least that
    many pixels; with fewer it is kept (a ray still helps). ``min_ray_angle_deg`` > 0: those views
    must also fix the point, two of their rays (through the blobs' means) meeting at least that
    far from parallel and from anti-parallel; two cameras facing each other see along nearly one
    line, their depth is barely measured, and a wrong label in one of them (the other hand, close
    by in its image) then puts the 3-D blob far off along it while the slivers would have caught
    it. This project's addition to the 3-D blobs of ALGORITHMS.md §1; ``min_fraction`` <= 0:
    nothing is dropped.

    Returns blobs_by_camera without the slivers.
    """
    out = {c: list(bl) for c, bl in blobs_by_camera.items()}
    applies = set(labels)
    if min_fraction <= 0 or not applies:
        return out
    least = {c: min_fraction * cameras[c].width * cameras[c].height for c in out}
    whole: dict[str, list[tuple[str, Blob2D]]] = {}  # label -> (camera, blob) of the views that see it whole
    for c, blobs in out.items():
        for label, b in {b.label: b for b in blobs if b.label in applies and b.pixel_count >= least[c]}.items():
            whole.setdefault(label, []).append((c, b))
    max_cos = np.cos(np.radians(min_ray_angle_deg))
    fixed = set()  # labels whose whole views fix the point
    for label, views in whole.items():
        if len(views) < 2:
            continue
        if min_ray_angle_deg > 0:
            d = np.array([cameras[c].rays(np.asarray(b.mean, float).reshape(1, 2))[1][0]
                          for c, b in views if _finite(b)]).reshape(-1, 3)
            if not np.any(np.abs(d @ d.T)[np.triu_indices(len(d), 1)] <= max_cos):
                continue
        fixed.add(label)
    return {c: [b for b in blobs if b.label not in applies or b.pixel_count >= least[c]
                or b.label not in fixed] for c, blobs in out.items()}


def associate_views(
    blobs_by_camera: Mapping[str, Sequence[Blob2D]],
    cameras: Mapping[str, Camera],
    parts: Iterable[str],
    margin_chi2: float,
    iterations: int = 2,
) -> tuple[dict[str, list[Blob2D]], dict[str, list[str]]]:
    """Left/right association of a symmetric part pair across views, before triangulation.

    A 2-D tracker can hold the l_ and r_ labels of two look-alike parts (trouser legs) the
    wrong way round in one view and the right way in the others; triangulated as labelled,
    each 3-D blob then mixes both legs. For each part p of ``parts``, the views that see both
    ``l_p`` and ``r_p`` (finite) are tested: every way of exchanging the pair's labels in a
    subset of them (the first view fixed: exchanging all views is the global left/right
    question, which the body fit answers) is triangulated, and the one with the lowest summed
    weighted reprojection error (:func:`_gauss_newton`'s cost, both labels) is taken if it
    beats the labels as given by more than ``margin_chi2``. The geometry, not the prior, decides:
    the consistent association is the one whose rays meet. More than
    :data:`MAX_ASSOCIATION_VIEWS` such views: not tested.

    Returns (blobs_by_camera with the exchanged labels; {camera: [parts exchanged there]}).
    """
    cams = dict(cameras)
    out = {c: list(bl) for c, bl in blobs_by_camera.items()}
    tests = []  # per part: (part, its views [(camera, left index, right index)], hypotheses, first problem)
    problems: list[_Problem] = []
    for part in parts:
        left, right = "l_" + part, "r_" + part
        views = []
        for name in sorted(out):
            idx = {b.label: i for i, b in enumerate(out[name]) if b.label in (left, right) and _finite(b)}
            if len(idx) == 2 and name in cams:
                views.append((name, idx[left], idx[right]))
        k = len(views)
        if not 2 <= k <= MAX_ASSOCIATION_VIEWS:
            continue
        ray, uv = {}, {}  # per (camera, blob index): viewing ray, mean
        for name, *idx in views:
            keys = [(name, i) for i in idx]
            uv.update((key, np.asarray(out[name][key[1]].mean, float).reshape(2)) for key in keys)
            ray.update(zip(keys, cams[name].rays(np.array([uv[key] for key in keys]))[1], strict=True))
        info = dict(zip(ray, _information_2d(np.array([out[name][i].cov for name, i in ray])), strict=True))
        used = [cams[name] for name, *_ in views]
        centres = np.array([c.center for c in used])
        # every hypothesis' two bundles (the left label's blobs, then the right's) at once
        flips, bundles = [], []
        for h in range(2 ** (k - 1)):  # bit v-1 of h: exchange the pair in view v (view 0 fixed)
            flip = [v > 0 and bool(h >> (v - 1) & 1) for v in range(k)]
            flips.append(flip)
            for own, other in ((1, 2), (2, 1)):
                bundles.append([(view[0], view[other] if f else view[own])
                                for view, f in zip(views, flip, strict=True)])
        X0s, spreads = midpoints(np.broadcast_to(centres, (len(bundles), k, 3)),
                                 np.array([[ray[key] for key in keys] for keys in bundles]))
        depth = X0s @ np.array([c.R[2] for c in used]).T + np.array([c.t[2] for c in used])  # (2H, k)
        meet = (spreads >= _MIN_RAY_SPREAD) & np.all(depth > 0.0, axis=1)
        first, hypotheses = len(problems), []
        for h, flip in enumerate(flips):
            if meet[2 * h] and meet[2 * h + 1]:  # both rays' bundles meet in front of their cameras
                problems.extend(_Problem(f"{part}:{h}", used, np.array([uv[key] for key in bundles[j]]),
                                         np.array([info[key] for key in bundles[j]]), X0s[j], None, None)
                                for j in (2 * h, 2 * h + 1))
                hypotheses.append(flip)
        if len(hypotheses) < 2 or any(hypotheses[0]):  # the labels as given must be among them
            del problems[first:]
            continue
        tests.append((part, views, hypotheses, first))
    swapped: dict[str, list[str]] = {}
    if not tests:
        return out, swapped
    _, _, cost = _run(problems, iterations)
    for part, views, hypotheses, first in tests:
        total = cost[first:first + 2 * len(hypotheses)].reshape(-1, 2).sum(axis=1)
        best = int(np.argmin(total))
        if best == 0 or total[0] - total[best] <= margin_chi2:
            continue
        for (name, i_left, i_right), f in zip(views, hypotheses[best], strict=True):
            if f:
                bl = out[name]
                bl[i_left], bl[i_right] = (replace(bl[i_left], label="r_" + part),
                                           replace(bl[i_right], label="l_" + part))
                swapped.setdefault(name, []).append(part)
    return out, swapped


def blob_extent(observations: Sequence[tuple[Camera, Blob2D]], point: np.ndarray) -> np.ndarray | None:
    """The 3-D second moments S (3, 3) m² of a blob at ``point`` (3,) m (world) whose projections
    best match its 2-D covariances: ``Σ_i ‖(J_i S J_iᵀ − C_i) / tr C_i‖²`` minimised over symmetric
    S (linear least squares; J_i = dπ_i/dX at the point, so each view's relative shape counts, near
    or far), eigenvalues clipped at 0. None with fewer than three finite views in front of the point
    (two leave one direction of S undetermined, see the module docstring)."""
    X = np.asarray(point, dtype=float).reshape(3)
    rows, rhs = [], []
    for cam, blob in observations:
        C = np.asarray(blob.cov, dtype=float).reshape(2, 2)
        if not _finite(blob) or float(cam.R[2] @ X + cam.t[2]) <= 0.0:
            continue
        w = 1.0 / max(float(np.trace(C)), 1e-9)
        J = cam.project_jacobian(X[None])[1][0]
        for a, c in ((0, 0), (1, 1), (0, 1)):
            # C[a, c] = Σ_pq J[a, p] J[c, q] S[p, q], unknowns S00 S11 S22 S01 S02 S12
            rows.append(w * np.array([J[a, 0] * J[c, 0], J[a, 1] * J[c, 1], J[a, 2] * J[c, 2],
                                      J[a, 0] * J[c, 1] + J[a, 1] * J[c, 0],
                                      J[a, 0] * J[c, 2] + J[a, 2] * J[c, 0],
                                      J[a, 1] * J[c, 2] + J[a, 2] * J[c, 1]]))
            rhs.append(w * C[a, c])
    if len(rows) < 9:
        return None
    x = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    S = np.array([[x[0], x[3], x[4]], [x[3], x[1], x[5]], [x[4], x[5], x[2]]])
    vals, vecs = np.linalg.eigh(S)
    return (vecs * np.maximum(vals, 0.0)) @ vecs.T
