"""Edge measurements, their Jacobian and robust per-component motion statistics.

ALGORITHMS.md §2 "Measurements" and "Robust statistics by re-weighting" (paper §3,
eqs. 7-10):

* from each visible contour sample a 1-D search along the image normal finds the
  nearest intensity edge; its signed distance ``m`` (pixels, positive along the
  normal) is the measurement (:func:`normal_search`);
* row k of ``J`` (N, 6) is the normal component of the image motion of sample k
  under each generator ``G_j`` of the component's motion (closed form,
  :func:`jacobian_rows`), so that to first order ``m ~= J xi``;
* ``C = J^T J`` and ``xi_hat = C^-1 J^T m`` (eq. 7), the statistics
  ``p(xi) ∝ exp(-(xi - xi_hat)^T C (xi - xi_hat))`` (eq. 9) handed to the
  kinematic propagation (:mod:`artrack.propagation`);
* robustness: each residual and its row of J are scaled by ``w(m) = 1/(c + |m|)``
  and the solve is iterated (:func:`motion_statistics`).

Frames: the motion ``xi = (v, w)`` is in the component's frame (``E_t = E_{t-1} exp(xi)``,
see :mod:`artrack.lie`); image points are pixels of an OpenCV optical camera.
"""

from __future__ import annotations

import cv2
import numpy as np

from artrack.lie import GeometryError, inverse_se3, skew

__all__ = ["ColourCone", "body_like", "fit_colour_cone", "jacobian_rows", "motion_statistics", "normal_search",
           "robust_weights"]


class ColourCone:
    """Appearance of one surface under shading: colours ``b ≈ s u`` (a ray in colour space).

    u (C,) unit axis; s_lo, s_hi: brightness range along the axis; perp_max: largest distance from the
    axis (grey levels). Shading (darker towards a silhouette, a renderer's rings, real Lambertian fall-off)
    changes ``s`` only, a different material changes the chromaticity (``perp``) or leaves the range —
    the "brightness / chromaticity distortion" model of background subtraction. Used for edge polarity
    (:func:`normal_search` ``colour_model``): an outline edge has the surface's colour on its inner side
    and something else on its outer side.
    """

    __slots__ = ("perp_max", "s_hi", "s_lo", "u")

    def __init__(self, u: np.ndarray, s_lo: float, s_hi: float, perp_max: float):
        self.u = np.asarray(u, dtype=float)
        self.s_lo, self.s_hi, self.perp_max = float(s_lo), float(s_hi), float(perp_max)

    def __repr__(self) -> str:
        return (f"ColourCone(u={np.round(self.u, 3)}, s=[{self.s_lo:.1f}, {self.s_hi:.1f}], "
                f"perp_max={self.perp_max:.1f})")


def fit_colour_cone(colours: np.ndarray, margin: float = 10.0, low: float = 5.0, high: float = 95.0
                    ) -> ColourCone | None:
    """:class:`ColourCone` of colour samples (N, C) (or (N,) grey): axis = principal direction of the
    uncentred second moment, brightness range = [low, high] percentiles of ``s`` widened by ``margin``,
    ``perp_max`` = the ``high`` percentile of the distance from the axis plus ``margin``. None if N < 8."""
    X = np.asarray(colours, dtype=float)
    X = X.reshape(len(X), -1)
    X = X[np.all(np.isfinite(X), axis=1)]
    if len(X) < 8:
        return None
    _, vec = np.linalg.eigh(X.T @ X)
    u = vec[:, -1] * (1.0 if vec[:, -1].sum() >= 0 else -1.0)
    s = X @ u
    perp = np.linalg.norm(X - s[:, None] * u[None, :], axis=1)
    lo, hi = np.percentile(s, [low, high])
    return ColourCone(u, lo - margin, hi + margin, float(np.percentile(perp, high)) + margin)


def body_like(colours: np.ndarray, u: np.ndarray, s_lo: np.ndarray, s_hi: np.ndarray,
              perp_max: np.ndarray) -> np.ndarray:
    """(N, S) bool: colours (N, S, C) lie in the per-row cones (u (N, C), s_lo, s_hi, perp_max (N,))."""
    s = np.einsum("nsc,nc->ns", colours, u)
    perp = np.linalg.norm(colours - s[..., None] * u[:, None, :], axis=-1)
    return (perp <= perp_max[:, None]) & (s >= s_lo[:, None]) & (s <= s_hi[:, None])


def normal_search(
    gray_image: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    max_dist_px: float,
    *,
    threshold: float = 8.0,
    step_px: float = 1.0,
    blur_sigma: float = 0.0,
    gradients: tuple[np.ndarray, np.ndarray] | None = None,
    select: str = "nearest",
    colour_image: np.ndarray | None = None,
    colour_model: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    side_px: float = 1.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance to the nearest intensity edge along each normal (paper §3, Fig. 2).

    gray_image: (H, W) single-channel image (any dtype; used as float32 intensity), or (H, W, C)
    with C <= 4 channels (e.g. BGR): then ``|dI/dn|`` is the root-sum-square over the channels of
    each channel's directional derivative (a colour edge).
    points: (N, 2) pixel positions (x, y); normals: (N, 2) image directions (normalised here).
    max_dist_px: search half-length; samples are taken at ``k * step_px`` for
    ``|k * step_px| <= max_dist_px``, read from the Sobel gradient images by bilinear interpolation
    (``cv2.remap``; outside the image the gradient is 0, so borders never make edges).
    An edge is a local maximum of ``|dI/dn|`` (the gradient's component along the normal, intensity
    units per pixel, 3x3 Sobel scaled by 1/8) of at least ``threshold``; the one nearest the point
    wins (ties: the stronger), refined to sub-pixel by a parabola through the three samples around
    the maximum. The two end samples cannot be maxima, so the usable range is
    ``max_dist_px - step_px``. ``gradients`` = precomputed (gx, gy) float32 images (as from
    :func:`cv2.Sobel`, (H, W) or (H, W, C)) to share between many searches of the same image.
    select: ``'nearest'`` (the paper's rule, above) or ``'strongest'`` (the largest qualifying
    maximum within the range; ties: the nearer) — more robust when a weak texture or shading
    edge lies between the prediction and the true outline.

    Returns ``distance`` (N,) signed along the normal, pixels (NaN where nothing was found), and
    ``found`` (N,) bool. A missing edge is never reported as a zero distance.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    nrm = np.asarray(normals, dtype=float).reshape(-1, 2)
    if pts.shape != nrm.shape:
        raise GeometryError(f"normal_search: points {pts.shape} and normals {nrm.shape} differ in shape")
    n = len(pts)
    distance = np.full(n, np.nan)
    found = np.zeros(n, dtype=bool)
    if n == 0:
        return distance, found
    nlen = np.linalg.norm(nrm, axis=1)
    ok = nlen > 0
    nrm = nrm / np.where(ok, nlen, 1.0)[:, None]
    if gradients is None:
        img = np.asarray(gray_image)
        if img.ndim != 2 and not (img.ndim == 3 and 1 <= img.shape[2] <= 4):
            raise GeometryError(f"normal_search: image must be (H, W) or (H, W, C<=4), got shape {img.shape}")
        img = img.astype(np.float32)
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
    else:
        gx, gy = gradients
    if select not in ("nearest", "strongest"):
        raise GeometryError(f"normal_search: select must be 'nearest' or 'strongest', got {select!r}")
    kmax = int(np.floor(max_dist_px / step_px + 1e-9))
    if kmax < 2:
        raise GeometryError(
            f"normal_search: max_dist_px={max_dist_px} must be at least 2 * step_px={step_px}"
        )
    offs = np.arange(-kmax, kmax + 1) * step_px  # (S,)
    sx = (pts[:, None, 0] + offs[None, :] * nrm[:, None, 0]).astype(np.float32)
    sy = (pts[:, None, 1] + offs[None, :] * nrm[:, None, 1]).astype(np.float32)
    border = cv2.BORDER_CONSTANT
    gxs = cv2.remap(gx, sx, sy, cv2.INTER_LINEAR, borderMode=border, borderValue=0.0).astype(float)
    gys = cv2.remap(gy, sx, sy, cv2.INTER_LINEAR, borderMode=border, borderValue=0.0).astype(float)
    if gxs.ndim == 3:  # colour: root-sum-square of the channels' directional derivatives
        g = np.sqrt(np.sum((gxs * nrm[:, None, 0, None] + gys * nrm[:, None, 1, None]) ** 2, axis=-1))
    else:
        g = np.abs(gxs * nrm[:, None, 0] + gys * nrm[:, None, 1])  # (N, S)
    mid = g[:, 1:-1]
    peak = (mid >= g[:, :-2]) & (mid > g[:, 2:]) & (mid >= threshold)
    peak &= ok[:, None]
    if colour_model is not None and colour_image is not None:
        has, u, s_lo, s_hi, pmax = colour_model
        has = np.asarray(has, dtype=bool)
        if has.any():
            cimg = np.asarray(colour_image, dtype=np.float32)
            inner = offs[1:-1]
            rows_m = np.flatnonzero(has)
            pm, nm = pts[rows_m], nrm[rows_m]

            def colours_at(shift: float) -> np.ndarray:
                cx = (pm[:, None, 0] + (inner[None, :] + shift) * nm[:, None, 0]).astype(np.float32)
                cy = (pm[:, None, 1] + (inner[None, :] + shift) * nm[:, None, 1]).astype(np.float32)
                c = cv2.remap(cimg, cx, cy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(float)
                return c.reshape(len(rows_m), len(inner), -1)

            args = (np.asarray(u, float)[rows_m].reshape(len(rows_m), -1), np.asarray(s_lo, float)[rows_m],
                    np.asarray(s_hi, float)[rows_m], np.asarray(pmax, float)[rows_m])
            polar = body_like(colours_at(-side_px), *args) & ~body_like(colours_at(side_px), *args)
            peak[rows_m] &= polar
    # nearest peak to the centre; among equal distances the stronger one
    if select == "nearest":
        dist_rank = np.abs(offs[1:-1])[None, :] - 1e-9 * mid / (mid.max() + 1.0)
    else:
        dist_rank = -mid + 1e-9 * np.abs(offs[1:-1])[None, :]
    score = np.where(peak, dist_rank, np.inf)
    k = np.argmin(score, axis=1)
    found = np.isfinite(score[np.arange(n), k])
    rows = np.flatnonzero(found)
    kk = k[rows] + 1  # index in g
    a, b, c = g[rows, kk - 1], g[rows, kk], g[rows, kk + 1]
    den = a - 2.0 * b + c
    delta = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    distance[rows] = offs[kk] + np.clip(delta, -0.5, 0.5) * step_px
    return distance, found


def jacobian_rows(
    points_3d_in_camera: np.ndarray,
    normals: np.ndarray,
    K: np.ndarray,
    E_cam_from_component: np.ndarray,
) -> np.ndarray:
    """Closed-form measurement Jacobian (N, 6): ``d m_k / d xi_j`` (pixels per unit of ``xi``).

    points_3d_in_camera: (N, 3) sample points (m, camera frame, z > 0) rigidly attached to the
    component; normals: (N, 2) unit image normals along which ``m`` is measured; K: (3, 3);
    E_cam_from_component: (4, 4). A point with component coordinates ``P = E^-1 X`` moved by
    ``exp(xi)`` in the component frame has camera velocity ``dX/dxi = R [I | -skew(P)]``
    (``E G_j E^-1 X``), and its pixel velocity is ``K[:2, :2] @ [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]``
    times that; the row is the normal component. For a point on an occluding contour this is
    exact to first order too (the contour generator slides only along the surface tangent).
    """
    X = np.asarray(points_3d_in_camera, dtype=float).reshape(-1, 3)
    n = np.asarray(normals, dtype=float).reshape(-1, 2)
    K = np.asarray(K, dtype=float)
    E = np.asarray(E_cam_from_component, dtype=float)
    R = E[:3, :3]
    P = X @ inverse_se3(E)[:3, :3].T + inverse_se3(E)[:3, 3]  # component frame
    dX = np.empty((len(X), 3, 6))
    dX[:, :, :3] = R
    dX[:, :, 3:] = -R @ skew(P)
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    Jp = np.zeros((len(X), 2, 3))
    Jp[:, 0, 0] = 1.0 / z
    Jp[:, 1, 1] = 1.0 / z
    Jp[:, 0, 2] = -x / z**2
    Jp[:, 1, 2] = -y / z**2
    Juv = K[:2, :2] @ Jp  # (N, 2, 3) pixels per metre in the camera frame
    nJ = np.einsum("ni,nij->nj", n, Juv)  # (N, 3)
    return np.einsum("nj,njk->nk", nJ, dX)


def robust_weights(m: np.ndarray, c_robust: float) -> np.ndarray:
    """Re-weighting ``w(m) = c / (c + |m|)``: the paper's ``1/(c + |m|)`` scaled so that ``w(0) = 1``.

    The constant factor ``c`` changes neither ``xi_hat`` nor the relative weights of components
    sharing the same ``c``; it keeps ``C`` in the units of ``J^T J`` (pixels^-2 per unit of ``xi``^2).
    """
    if c_robust <= 0:
        raise GeometryError(f"robust_weights: c_robust must be positive, got {c_robust!r}")
    return c_robust / (c_robust + np.abs(m))


def motion_statistics(
    J: np.ndarray,
    m: np.ndarray,
    c_robust: float = 2.0,
    iterations: int = 3,
    *,
    valid: np.ndarray | None = None,
    rcond: float = 1e-10,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-component motion estimate and information matrix (paper eqs. 7, 9 and §3.2).

    J: (N, 6) Jacobian rows; m: (N,) signed edge distances (pixels); rows with ``valid`` False
    or a non-finite ``m`` (edge not found) are left out. Rows from several cameras and several
    quadrics of one component may simply be stacked: the motion is in the component's frame,
    shared by every view.
    iterations: number of re-weighted solves. 0 gives plain least squares (``C = J^T J``,
    ``xi_hat = C^-1 J^T m``); each iteration scales every residual ``r = m - J xi_hat`` (the raw ``m``
    in the first, i.e. ``xi_hat = 0`` — the paper's one iteration per frame) *and* its row of J by
    ``w(r) = c/(c + |r|)`` (:func:`robust_weights`) and solves again: ``C = (WJ)^T (WJ)``,
    ``xi_hat = C^-1 (WJ)^T (W m)``. Scaling rows and residuals by ``w`` (as the paper's §3.2 text
    says) puts ``w^2`` in the normal equations, a redescending influence ``m/(c+|m|)^2``; the
    paper's eq. 10 would correspond to scaling by ``sqrt(w)`` (Laplacian tails).
    rcond: relative singular-value cut-off; a rank-deficient ``C`` (a single quadric has only 5
    observable d.o.f., a cylinder's outline 4) gives the minimum-norm ``xi_hat`` (no motion along
    unobserved directions); the propagation regularises ``C`` before inverting it.

    Returns ``xi_hat`` (6,) in the component frame and ``C`` (6, 6).
    """
    J = np.asarray(J, dtype=float).reshape(-1, 6)
    m = np.asarray(m, dtype=float).reshape(-1)
    if len(J) != len(m):
        raise GeometryError(f"motion_statistics: J has {len(J)} rows but m has {len(m)} entries")
    use = np.isfinite(m) & np.all(np.isfinite(J), axis=1)
    if valid is not None:
        use &= np.asarray(valid, dtype=bool).reshape(-1)
    J, m = J[use], m[use]
    if len(m) == 0:
        return np.zeros(6), np.zeros((6, 6))
    if iterations < 0:
        raise GeometryError(f"motion_statistics: iterations must be >= 0, got {iterations}")
    xi = np.zeros(6)
    Jw, mw = J, m
    for _ in range(iterations):
        w = robust_weights(m - J @ xi, c_robust)
        Jw, mw = J * w[:, None], m * w
        xi = np.linalg.lstsq(Jw, mw, rcond=rcond)[0]
    if iterations == 0:
        xi = np.linalg.lstsq(J, m, rcond=rcond)[0]
    return xi, Jw.T @ Jw
