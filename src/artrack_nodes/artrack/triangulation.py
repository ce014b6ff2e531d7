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
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from .cameras import Camera
from .errors import InputError
from .types import Blob2D, Blob3D

__all__ = [
    "midpoint",
    "triangulate_blob",
    "triangulate_blobs",
]

#: Smallest eigenvalue of Σ (I - d dᵀ) below which the rays are taken as parallel
#: (two rays at angle θ give about sin²θ / 2; 1e-6 is θ ≈ 0.08°).
_MIN_RAY_SPREAD = 1e-6


def _information_2d(cov: np.ndarray) -> np.ndarray:
    """Inverse of a 2-D covariance (px²) with eigenvalues floored at 1e-9 of the largest
    (and 1e-12 px²), so that a degenerate blob does not make the system singular."""
    cov = np.asarray(cov, dtype=float).reshape(2, 2)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.maximum(w, max(1e-9 * float(np.max(np.abs(w))), 1e-12))
    return (V / w) @ V.T


def midpoint(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares point nearest to N rays (world frame).

    origins: (N, 3) m; directions: (N, 3) unit. Returns the point (3,) m and the
    smallest eigenvalue of Σ (I - d dᵀ) (a ray-spread measure; ~0 for parallel rays).
    """
    origins = np.asarray(origins, dtype=float).reshape(-1, 3)
    directions = np.asarray(directions, dtype=float).reshape(-1, 3)
    proj = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]  # (N, 3, 3)
    A = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, origins)
    spread = float(np.linalg.eigvalsh(A)[0])
    if spread < _MIN_RAY_SPREAD:
        return np.linalg.lstsq(A, b, rcond=None)[0], spread
    return np.linalg.solve(A, b), spread


def _gauss_newton(
    X: np.ndarray,
    cams: Sequence[Camera],
    uvs: np.ndarray,
    infos: np.ndarray,
    prior_mean: np.ndarray | None,
    prior_info: np.ndarray | None,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton on the weighted reprojection error (+ optional Gaussian prior).

    X: (3,) start; uvs: (V, 2) px; infos: (V, 2, 2) px⁻². Returns X (3,) and the
    information matrix H (3, 3) at X.
    """

    def linearise(Xc: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        H = np.zeros((3, 3))
        g = np.zeros(3)
        cost = 0.0
        for cam, uv, W in zip(cams, uvs, infos, strict=True):
            pred, J = cam.project_jacobian(Xc[None])
            r = uv - pred[0]
            JtW = J[0].T @ W
            H += JtW @ J[0]
            g += JtW @ r
            cost += float(r @ W @ r)
        if prior_info is not None:
            dp = prior_mean - Xc
            H += prior_info
            g += prior_info @ dp
            cost += float(dp @ prior_info @ dp)
        return H, g, cost

    def in_front(Xc: np.ndarray) -> bool:
        return all(float(c.R[2] @ Xc + c.t[2]) > 0.0 for c in cams)

    H, g, cost = linearise(X)
    for _ in range(iterations):
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        # Halve the step until the cost does not increase and the point stays in front.
        lam = 1.0
        accepted = False
        for _ in range(8):
            Xn = X + lam * step
            if in_front(Xn):
                Hn, gn, cn = linearise(Xn)
                if cn <= cost * (1.0 + 1e-12) + 1e-12:
                    X, H, g, cost = Xn, Hn, gn, cn
                    accepted = True
                    break
            lam *= 0.5
        if not accepted or float(np.linalg.norm(lam * step)) < 1e-10:
            break
    return X, H


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
    obs = [
        (cam, b)
        for cam, b in observations
        if np.all(np.isfinite(np.asarray(b.mean, float))) and np.all(np.isfinite(np.asarray(b.cov, float)))
    ]
    label = obs[0][1].label if obs else (prior.label if prior is not None else "")
    if not obs:
        return None
    prior_mean = prior_info = None
    if prior is not None:
        prior_mean = np.asarray(prior.mean, dtype=float).reshape(3)
        pc = np.asarray(prior.cov, dtype=float).reshape(3, 3)
        prior_info = np.linalg.inv(0.5 * (pc + pc.T))

    origins = np.empty((len(obs), 3))
    dirs = np.empty((len(obs), 3))
    for i, (cam, b) in enumerate(obs):
        o, d = cam.rays(np.asarray(b.mean, float).reshape(1, 2))
        origins[i], dirs[i] = o, d[0]

    X0 = None
    if len(obs) >= 2:
        X0, spread = midpoint(origins, dirs)
        if spread >= _MIN_RAY_SPREAD:
            keep = [i for i, (cam, _) in enumerate(obs) if float(cam.R[2] @ X0 + cam.t[2]) > 0.0]
            if len(keep) < len(obs):
                obs = [obs[i] for i in keep]
                origins, dirs = origins[keep], dirs[keep]
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

    cams = [c for c, _ in obs]
    uvs = np.array([np.asarray(b.mean, float).reshape(2) for _, b in obs])
    infos = np.array([_information_2d(b.cov) for _, b in obs])
    X, H = _gauss_newton(
        X0,
        cams,
        uvs,
        infos,
        prior_mean if use_prior else None,
        prior_info if use_prior else None,
        iterations,
    )
    try:
        cov = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    cov = 0.5 * (cov + cov.T)
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(cov))):
        return None
    return Blob3D(label, X, cov, tuple(c.name for c in cams))


def triangulate_blobs(
    blobs_by_camera: Mapping[str, Iterable[Blob2D]],
    cameras: Mapping[str, Camera] | Iterable[Camera],
    priors: Mapping[str, Blob3D] | None = None,
    iterations: int = 5,
    fuse_prior: bool = False,
) -> dict[str, Blob3D]:
    """Triangulate every label seen in the cameras.

    blobs_by_camera: {camera name: 2-D blobs of that camera}; cameras: {name: Camera}
    (or a list); priors: {label: predicted Blob3D} used for single-view labels (see
    ``triangulate_blob``). If a camera reports a label twice, the blob with the most
    pixels is used. Returns {label: Blob3D} for the labels that could be
    triangulated, in order of first appearance. Raises InputError for a camera name
    that is not among ``cameras``.
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
    out: dict[str, Blob3D] = {}
    for label, views in by_label.items():
        prior = priors.get(label) if priors else None
        obs = [(cams[name], b) for name, b in views.items()]
        blob = triangulate_blob(obs, prior, iterations=iterations, fuse_prior=fuse_prior)
        if blob is not None:
            out[label] = blob
    return out
