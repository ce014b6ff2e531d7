"""Quadric models, their image conics and visible contour samples — ALGORITHMS.md §2 "Model".

A component is built from quadric surfaces ``X^T Q X = 0`` (``X`` homogeneous, in
the component frame; ``X^T Q X < 0`` is the inside), each clipped by a second
quadric: a surface point is kept only where ``X^T Q_clip X <= 0``.

Seen through ``E`` (component -> camera), the quadric in camera coordinates is
``Q' = E^-T Q E^-1 = [[A, b], [b^T, c]]`` (paper eq. 2-3) and its outline in the
*normalised* camera is the conic ``C = A c - b b^T`` (eq. 4): a normalised image
point ``d = (x, y, 1)`` lies on it when ``d^T C d = 0``. ``C`` is unchanged when
``Q`` is negated, and ``d^T C d <= 0`` exactly when the ray through ``d`` meets the
quadric, so the gradient of ``d^T C d`` points *out of* the silhouette. In pixels
``C_px = K^-T C K^-1``.

Sample points are laid along the conic at equal image spacing (the paper maps a
unit circle to C with ``dtheta = dp / (dp/dtheta)``; here the conic is sampled
densely in a parameter and resampled by arc length, which is the same thing) and
kept only if visible: the point of tangency is in front of the camera, inside the
clipping quadric, and not hidden by another (clipped) quadric along its ray.

Conics handled: ellipses, hyperbolae (quadrics partly behind the camera),
parabolae, and degenerate line pairs (cylinders and cones always image to a line
pair). Shapes are stated in every docstring; camera frames are OpenCV optical
frames (x right, y down, z forward), pixels have (0, 0) at the centre of the
top-left pixel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from artrack.lie import GeometryError, inverse_se3

__all__ = [
    "ClippedQuadric",
    "ContourSamples",
    "cone",
    "cylinder",
    "ellipsoid",
    "image_conic",
    "quadric_in_camera",
    "quadric_value",
    "ray_quadric_depths",
    "sample_contour",
    "sample_contours",
    "slab",
    "sphere",
    "tangent_points",
    "transform_quadric",
    "visibility_mask",
]


# --------------------------------------------------------------------------- constructors


def ellipsoid(radii: Sequence[float], center: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Axis-aligned ellipsoid ``sum_k ((X_k - c_k) / r_k)^2 = 1`` in the component frame -> Q (4, 4)."""
    r = np.asarray(radii, dtype=float)
    if r.shape != (3,) or np.any(r <= 0):
        raise GeometryError(f"ellipsoid: radii must be 3 positive numbers, got {radii!r}")
    Q = np.diag(np.r_[1.0 / r**2, -1.0])
    return transform_quadric(Q, _translation(center))


def sphere(radius: float, center: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Sphere of ``radius`` (m) about ``center`` (3,) in the component frame -> Q (4, 4)."""
    if radius <= 0:
        raise GeometryError(f"sphere: radius must be positive, got {radius!r}")
    return ellipsoid((radius, radius, radius), center)


def cylinder(radius: float) -> np.ndarray:
    """Infinite circular cylinder ``x^2 + y^2 = r^2`` about the component's z axis -> Q (4, 4).

    Clip it with :func:`slab` to get a finite one; place it elsewhere with :func:`transform_quadric`.
    """
    if radius <= 0:
        raise GeometryError(f"cylinder: radius must be positive, got {radius!r}")
    return np.diag([1.0, 1.0, 0.0, -(radius**2)])


def cone(slope: float, apex_z: float = 0.0) -> np.ndarray:
    """Double circular cone ``x^2 + y^2 = (slope (z - apex_z))^2`` about the z axis -> Q (4, 4).

    ``slope`` is radius gained per metre along z (tan of the half angle). Clip with
    :func:`slab` to keep one truncated nappe (a truncated cone, e.g. a limb).
    """
    if slope <= 0:
        raise GeometryError(f"cone: slope must be positive, got {slope!r}")
    Q = np.diag([1.0, 1.0, -(slope**2), 0.0])
    return transform_quadric(Q, _translation((0.0, 0.0, apex_z)))


def slab(z_min: float, z_max: float) -> np.ndarray:
    """Clipping quadric ``(z - z_min)(z - z_max) <= 0``: the slab ``z_min <= z <= z_max`` -> Q (4, 4)."""
    if not z_max > z_min:
        raise GeometryError(f"slab: need z_max > z_min, got {z_min!r}, {z_max!r}")
    Q = np.zeros((4, 4))
    Q[2, 2] = 1.0
    Q[2, 3] = Q[3, 2] = -0.5 * (z_min + z_max)
    Q[3, 3] = z_min * z_max
    return Q


def transform_quadric(Q: np.ndarray, T_to_from: np.ndarray) -> np.ndarray:
    """Express quadric ``Q`` (4, 4), given in frame *from*, in frame *to*: ``T^-T Q T^-1``.

    ``T_to_from`` (4, 4) maps *from* coordinates to *to* coordinates (e.g. ``E_cam_from_component``).
    """
    Ti = inverse_se3(T_to_from)
    return Ti.T @ np.asarray(Q, dtype=float) @ Ti


def quadric_value(Q: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``X^T Q X`` for points ``X (..., 3)`` (made homogeneous) -> ``(...)``; negative inside."""
    X = np.asarray(X, dtype=float)
    Xh = np.concatenate([X, np.ones(X.shape[:-1] + (1,))], axis=-1)
    return np.einsum("...i,ij,...j->...", Xh, Q, Xh)


def _translation(t: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


@dataclass(frozen=True)
class ClippedQuadric:
    """One model primitive: ``surface`` Q (4, 4) clipped by ``clip`` (4, 4) or None (component frame)."""

    surface: np.ndarray
    clip: np.ndarray | None = None


@dataclass(frozen=True)
class ContourSamples:
    """Visible contour samples of one clipped quadric in one camera.

    uv: (N, 2) pixel positions on the image conic; normals: (N, 2) unit image normals pointing out
    of the silhouette; points_cam: (N, 3) the 3-D points of tangency in the camera frame (m), i.e. the
    surface points whose image is ``uv``.
    """

    uv: np.ndarray
    normals: np.ndarray
    points_cam: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


# --------------------------------------------------------------------------- conics


def quadric_in_camera(Q: np.ndarray, E_cam_from_component: np.ndarray) -> np.ndarray:
    """``Q' = E^-T Q E^-1`` (4, 4): the quadric in camera coordinates (paper eq. 2)."""
    return transform_quadric(Q, E_cam_from_component)


def image_conic(Q: np.ndarray, E_cam_from_component: np.ndarray, K: np.ndarray | None = None) -> np.ndarray:
    """Image conic (3, 3) of quadric ``Q`` (4, 4, component frame) seen through ``E`` (component -> camera).

    ``C = A c - b b^T`` from ``Q' = [[A, b], [b^T, c]]`` (paper eq. 4), in normalised camera
    coordinates when ``K`` is None, else in pixels: ``K^-T C K^-1`` (``K`` (3, 3) intrinsics).
    Points ``x~`` on the outline satisfy ``x~^T C x~ = 0``; ``< 0`` inside the silhouette.
    """
    Qc = quadric_in_camera(Q, E_cam_from_component)
    A, b, c = Qc[:3, :3], Qc[:3, 3], Qc[3, 3]
    C = A * c - np.outer(b, b)
    if K is not None:
        Ki = np.linalg.inv(np.asarray(K, dtype=float))
        C = Ki.T @ C @ Ki
    return 0.5 * (C + C.T)


def ray_quadric_depths(Q_cam: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Depths ``lam`` (N, 2) where rays ``lam * d`` from the camera centre meet ``Q_cam`` (4, 4, camera).

    ``directions`` (N, 3) need not be unit (with ``d = (x, y, 1)`` the depth is z). Solves
    ``lam^2 d^T A d + 2 lam b^T d + c = 0``; sorted ascending, NaN where there is no real root.
    """
    d = np.asarray(directions, dtype=float)
    A, b, c = Q_cam[:3, :3], Q_cam[:3, 3], Q_cam[3, 3]
    alpha = np.einsum("ni,ij,nj->n", d, A, d)
    beta = d @ b
    out = np.full((len(d), 2), np.nan)
    scale = np.abs(alpha) + np.abs(beta) + abs(c) + 1e-300
    lin = np.abs(alpha) <= 1e-12 * scale
    disc = beta**2 - alpha * c
    quad = ~lin & (disc >= 0)
    sq = np.sqrt(np.where(quad, disc, 0.0))
    # numerically stable roots: q = -(beta + sign(beta) sqrt(disc)); roots q/alpha and c/q
    q = -(beta + np.where(beta >= 0, 1.0, -1.0) * sq)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(quad, q / np.where(alpha == 0, 1.0, alpha), np.nan)
        r2 = np.where(quad & (q != 0), c / np.where(q == 0, 1.0, q), r1)
        lin_ok = lin & (np.abs(beta) > 1e-300)
        rl = np.where(lin_ok, -c / np.where(lin_ok, 2.0 * beta, 1.0), np.nan)
    out[:, 0] = np.where(lin, rl, np.minimum(r1, r2))
    out[:, 1] = np.where(lin, np.nan, np.maximum(r1, r2))
    return out


def tangent_points(Q_cam: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Points of tangency (N, 3) in the camera frame for rays ``rays`` (N, 3) through outline points.

    On the outline the two roots of :func:`ray_quadric_depths` coincide: ``lam = -b^T d / d^T A d``;
    NaN where ``d^T A d`` vanishes (ray along an asymptotic direction).
    """
    d = np.asarray(rays, dtype=float)
    A, b = Q_cam[:3, :3], Q_cam[:3, 3]
    alpha = np.einsum("ni,ij,nj->n", d, A, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.where(np.abs(alpha) > 1e-15, -(d @ b) / np.where(alpha == 0, 1.0, alpha), np.nan)
    return lam[:, None] * d


def visibility_mask(
    points_cam: np.ndarray,
    clip_cam: np.ndarray | None = None,
    occluders_cam: Sequence[ClippedQuadric] = (),
    *,
    min_depth: float = 1e-6,
    rel_tol: float = 1e-6,
) -> np.ndarray:
    """Visibility (N,) bool of surface points ``points_cam`` (N, 3) in the camera frame.

    Visible = finite, depth ``z > min_depth`` (in front of the camera), inside ``clip_cam`` (4, 4, camera
    frame, or None), and no quadric of ``occluders_cam`` (each a :class:`ClippedQuadric` already in
    *camera* coordinates) is hit by the ray from the camera centre at a depth below
    ``(1 - rel_tol)`` times the point's depth, at a hit point inside that occluder's clip. The
    quadric the points lie on may be included among the occluders (self-occlusion of non-convex
    surfaces): its own tangent double root is excluded by ``rel_tol``.
    """
    P = np.asarray(points_cam, dtype=float)
    vis = np.all(np.isfinite(P), axis=1)
    P = np.where(vis[:, None], P, 1.0)
    vis &= P[:, 2] > min_depth
    if clip_cam is not None:
        vis &= quadric_value(clip_cam, P) <= 1e-9 * max(1.0, float(np.abs(clip_cam).max()))
    if not occluders_cam:
        return vis
    depth = np.where(vis, P[:, 2], 1.0)
    d = P / depth[:, None]
    for occ in occluders_cam:
        lam = ray_quadric_depths(occ.surface, d)
        for k in range(2):
            lk = lam[:, k]
            ok = np.isfinite(lk) & (lk > min_depth) & (lk < depth * (1.0 - rel_tol))
            if occ.clip is not None and np.any(ok):
                hit = d * np.where(ok, lk, 0.0)[:, None]
                ok &= quadric_value(occ.clip, hit) <= 0.0
            vis &= ~ok
    return vis


# --------------------------------------------------------------------------- conic sampling


def _line_pair(C: np.ndarray) -> list[np.ndarray]:
    """Split a degenerate (rank-2) conic into its two real lines (3,), or [] if they are complex."""
    B = np.stack([np.cross(C[:, 1], C[:, 2]), np.cross(C[:, 2], C[:, 0]), np.cross(C[:, 0], C[:, 1])])
    B = 0.5 * (B + B.T)  # adjugate of the symmetric C; equals -p p^T for real lines meeting at p
    i = int(np.argmax(np.abs(np.diag(B))))
    if B[i, i] >= 0:  # -p p^T with p the intersection point: needs a non-positive diagonal
        return []
    p = B[:, i] / np.sqrt(-B[i, i])
    px = np.array([[0.0, p[2], -p[1]], [-p[2], 0.0, p[0]], [p[1], -p[0], 0.0]])
    M = C + px
    r, c = np.unravel_index(int(np.argmax(np.abs(M))), M.shape)
    lines = [M[r, :].copy(), M[:, c].copy()]
    return [
        ln / np.linalg.norm(ln[:2]) for ln in lines if np.linalg.norm(ln[:2]) > 1e-12 * np.linalg.norm(ln)
    ]


def _clip_line(line: np.ndarray, box: tuple[float, float, float, float]) -> np.ndarray | None:
    """Segment (2, 2) of the line ``a x + b y + c = 0`` inside box (x0, y0, x1, y1), or None."""
    a, b, c = line
    x0, y0, x1, y1 = box
    p0 = -c * np.array([a, b]) / (a * a + b * b)  # foot of the perpendicular from the origin
    t = np.array([-b, a]) / np.hypot(a, b)
    lo, hi = -np.inf, np.inf
    for k, (lo_k, hi_k) in enumerate(((x0, x1), (y0, y1))):
        if abs(t[k]) < 1e-15:
            if not lo_k <= p0[k] <= hi_k:
                return None
            continue
        s0, s1 = sorted(((lo_k - p0[k]) / t[k], (hi_k - p0[k]) / t[k]))
        lo, hi = max(lo, s0), min(hi, s1)
    if not hi > lo:
        return None
    return np.stack([p0 + lo * t, p0 + hi * t])


def _conic_curves(
    C: np.ndarray, box: tuple[float, float, float, float], step: float
) -> list[tuple[np.ndarray, bool]]:
    """Dense polylines (M, 2) on a non-degenerate conic ``C`` (pixels), with a closed flag."""
    A2, b2, c2 = C[:2, :2], C[:2, 2], C[2, 2]
    lam, U = np.linalg.eigh(A2)
    big = float(np.max(np.abs(lam)))
    x0, y0, x1, y1 = box
    corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]])
    if np.min(np.abs(lam)) <= 1e-10 * big:  # parabola: in the eigenframe lam_k t^2 + 2 beta . s + c = 0
        k = int(np.argmax(np.abs(lam)))
        j = 1 - k
        beta = U.T @ b2
        if abs(beta[j]) < 1e-15 * max(1.0, np.abs(beta).max()):
            return []
        span = np.linalg.norm(corners, axis=1).max() * 2.0 + 10.0
        tt = np.linspace(-span, span, 4001)
        ss = -(lam[k] * tt * tt + 2.0 * beta[k] * tt + c2) / (2.0 * beta[j])
        S = np.zeros((len(tt), 2))
        S[:, k], S[:, j] = tt, ss
        return [(S @ U.T, False)]
    center = -np.linalg.solve(A2, b2)
    f0 = c2 + b2 @ center  # conic value at the centre
    g = -f0
    rmax = np.linalg.norm(corners - center, axis=1).max() + 10.0
    curves: list[tuple[np.ndarray, bool]] = []
    if lam[0] * lam[1] > 0:  # ellipse
        if g / lam[0] <= 0:
            return []
        ax = np.sqrt(g / lam)
        n = int(min(2_000_000, max(256, 2.0 * np.pi * ax.max() / max(step, 1e-6))))
        th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
        S = np.stack([ax[0] * np.cos(th), ax[1] * np.sin(th)], axis=1)
        curves.append((center + S @ U.T, True))
        return curves
    # hyperbola: lam[0] < 0 < lam[1] (eigh sorts ascending); lam0 s0^2 + lam1 s1^2 = g
    if abs(g) < 1e-300:
        return []
    main = 1 if g > 0 else 0  # the axis the branches cross
    a_main = np.sqrt(g / lam[main])
    a_other = np.sqrt(-g / lam[1 - main])
    # parameter u = sinh(tau): s_other = a_other u, s_main = +-a_main sqrt(1 + u^2); the image speed
    # |dS/du| <= hypot(a_main, a_other) =: h, and |S| <= rmax needs |u| <= rmax / h
    umax = 1.01 * rmax / np.hypot(a_main, a_other)
    n = int(min(2_000_000, max(512, 2.0 * umax * np.hypot(a_main, a_other) / max(step, 1e-6))))
    u = np.linspace(-umax, umax, n)
    for sgn in (1.0, -1.0):
        S = np.zeros((n, 2))
        S[:, main] = sgn * a_main * np.sqrt(1.0 + u * u)
        S[:, 1 - main] = a_other * u
        curves.append((center + S @ U.T, False))
    return curves


def _resample(
    poly: np.ndarray, closed: bool, box: tuple[float, float, float, float], spacing: float
) -> np.ndarray:
    """Points at arc-length ``spacing`` along the parts of ``poly`` (M, 2) inside ``box``."""
    x0, y0, x1, y1 = box
    inside = (poly[:, 0] >= x0) & (poly[:, 0] <= x1) & (poly[:, 1] >= y0) & (poly[:, 1] <= y1)
    if not inside.any():
        return np.zeros((0, 2))
    if closed:
        if inside.all():
            poly = np.vstack([poly, poly[:1]])
            runs = [poly]
            return _arc_samples(runs, spacing)
        shift = int(np.argmin(inside))  # start the loop at an outside point
        poly, inside = np.roll(poly, -shift, axis=0), np.roll(inside, -shift)
    edges = np.flatnonzero(np.diff(np.r_[0, inside.astype(np.int8), 0]))
    runs = [poly[s:e] for s, e in zip(edges[::2], edges[1::2]) if e - s >= 2]
    return _arc_samples(runs, spacing)


def _arc_samples(runs: list[np.ndarray], spacing: float) -> np.ndarray:
    out = []
    for run in runs:
        seg = np.linalg.norm(np.diff(run, axis=0), axis=1)
        s = np.r_[0.0, np.cumsum(seg)]
        if s[-1] <= 0:
            continue
        n = int(np.floor(s[-1] / spacing))
        targets = (np.arange(n + 1) + 0.5 * (s[-1] / spacing - n)) * spacing  # centred in the run
        targets = targets[targets <= s[-1]]
        out.append(np.stack([np.interp(targets, s, run[:, 0]), np.interp(targets, s, run[:, 1])], axis=1))
    return np.vstack(out) if out else np.zeros((0, 2))


def _conic_points(C: np.ndarray, box: tuple[float, float, float, float], spacing: float) -> np.ndarray:
    """Points (N, 2) on the pixel conic ``C`` (3, 3) inside ``box``, evenly spaced by ``spacing`` px."""
    Cn = C / np.abs(C).max()
    sv = np.linalg.svd(Cn, compute_uv=False)
    if sv[2] <= 1e-10 * sv[0]:  # degenerate: a line pair (cylinders, cones) or a double line
        pts = []
        for line in _line_pair(Cn):
            seg = _clip_line(line, box)
            if seg is not None:
                pts.append(_arc_samples([seg], spacing))
        return np.vstack(pts) if pts else np.zeros((0, 2))
    fine = spacing / 8.0
    pts = [_resample(poly, closed, box, spacing) for poly, closed in _conic_curves(Cn, box, fine)]
    if not pts:
        return np.zeros((0, 2))
    uv = np.vstack(pts)
    for _ in range(2):  # Newton steps along the gradient put the chord-interpolated points back on the conic
        uvh = np.c_[uv, np.ones(len(uv))]
        f = np.einsum("ni,ij,nj->n", uvh, Cn, uvh)
        g = 2.0 * (uvh @ Cn)[:, :2]
        gg = np.einsum("ni,ni->n", g, g)
        uv = uv - np.where(gg > 0, f / np.where(gg > 0, gg, 1.0), 0.0)[:, None] * g
    return uv


def sample_contour(
    quadric: ClippedQuadric | np.ndarray,
    E_cam_from_component: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    spacing_px: float = 5.0,
    occluders: Sequence[tuple[ClippedQuadric, np.ndarray]] = (),
    *,
    margin_px: float = 0.0,
) -> ContourSamples:
    """Visible outline samples of one clipped quadric in one camera (ALGORITHMS.md §2 "Model").

    quadric: :class:`ClippedQuadric` (or a bare Q (4, 4), unclipped) in the component frame.
    E_cam_from_component: (4, 4). K: (3, 3) intrinsics. image_size: (width, height) px; samples are
    kept within ``[-margin, w - 1 + margin] x [-margin, h - 1 + margin]``.
    spacing_px: image distance between consecutive samples along the conic.
    occluders: (clipped quadric, its E_cam_from_component) pairs that may hide this one — other
    components, other quadrics of the same component; the sampled quadric itself may be included.
    Returns the visible samples (:class:`ContourSamples`): pixel positions, outward unit image
    normals (gradient of ``x~^T C x~``), and the 3-D points of tangency in the camera frame.
    """
    prim = quadric if isinstance(quadric, ClippedQuadric) else ClippedQuadric(np.asarray(quadric, float))
    K = np.asarray(K, dtype=float)
    E = np.asarray(E_cam_from_component, dtype=float)
    w, h = image_size
    box = (-margin_px, -margin_px, w - 1 + margin_px, h - 1 + margin_px)
    C = image_conic(prim.surface, E, K)
    uv = _conic_points(C, box, float(spacing_px))
    empty = ContourSamples(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)))
    if len(uv) == 0:
        return empty
    uvh = np.c_[uv, np.ones(len(uv))]
    grad = (uvh @ C)[:, :2]
    gnorm = np.linalg.norm(grad, axis=1)
    keep = gnorm > 1e-12 * np.abs(C).max()
    normals = grad / np.where(keep, gnorm, 1.0)[:, None]
    rays = uvh @ np.linalg.inv(K).T
    Q_cam = quadric_in_camera(prim.surface, E)
    P = tangent_points(Q_cam, rays)
    clip_cam = None if prim.clip is None else quadric_in_camera(prim.clip, E)
    occ_cam = [
        ClippedQuadric(
            quadric_in_camera(o.surface, Eo), None if o.clip is None else quadric_in_camera(o.clip, Eo)
        )
        for o, Eo in occluders
    ]
    keep &= visibility_mask(P, clip_cam, occ_cam)
    if not keep.any():
        return empty
    return ContourSamples(uv[keep], normals[keep], P[keep])


# --------------------------------------------------------------------------- batched sampling


def pixel_conics(Q_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel image conics (n, 3, 3) of quadrics ``Q_cam`` (n, 4, 4) already in camera coordinates.

    :func:`image_conic` batched: ``C = A c - b b^T`` (paper eq. 4), ``K^-T C K^-1`` with ``K`` (n, 3, 3)
    the intrinsics of each quadric's camera, symmetrised.
    """
    A, b, c = Q_cam[:, :3, :3], Q_cam[:, :3, 3], Q_cam[:, 3, 3]
    C = A * c[:, None, None] - b[:, :, None] * b[:, None, :]
    Ki = np.linalg.inv(K)
    C = np.swapaxes(Ki, 1, 2) @ C @ Ki
    return 0.5 * (C + np.swapaxes(C, 1, 2))


def _line_pairs(Cn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_line_pair` batched over degenerate conics ``Cn`` (m, 3, 3).

    Returns lines (2m, 3) (line 0 then line 1 of each conic, interleaved), their conic index (2m,)
    and a validity mask (2m,) (complex pair, or a line without a finite direction).
    """
    m = len(Cn)
    c0, c1, c2 = Cn[:, :, 0], Cn[:, :, 1], Cn[:, :, 2]
    B = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=1)
    B = 0.5 * (B + np.swapaxes(B, 1, 2))
    diag = np.diagonal(B, axis1=1, axis2=2)
    i = np.argmax(np.abs(diag), axis=1)
    r = np.arange(m)
    Bii = diag[r, i]
    real = Bii < 0
    p = B[r, :, i] / np.sqrt(np.where(real, -Bii, 1.0))[:, None]
    px = np.zeros((m, 3, 3))
    px[:, 0, 1], px[:, 0, 2] = p[:, 2], -p[:, 1]
    px[:, 1, 0], px[:, 1, 2] = -p[:, 2], p[:, 0]
    px[:, 2, 0], px[:, 2, 1] = p[:, 1], -p[:, 0]
    M = Cn + px
    flat = np.argmax(np.abs(M).reshape(m, 9), axis=1)
    rr, cc = flat // 3, flat % 3
    lines = np.empty((m, 2, 3))
    lines[:, 0] = M[r, rr, :]
    lines[:, 1] = M[r, :, cc]
    lines = lines.reshape(2 * m, 3)
    n2 = np.linalg.norm(lines[:, :2], axis=1)
    ok = np.repeat(real, 2) & (n2 > 1e-12 * np.linalg.norm(lines, axis=1))
    lines = lines / np.where(ok, n2, 1.0)[:, None]
    return lines, np.repeat(r, 2), ok


def _clip_lines(lines: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_clip_line` batched: lines (m, 3), boxes (m, 4) -> segments (m, 2, 2) and a validity mask (m,)."""
    a, b, c = lines[:, 0], lines[:, 1], lines[:, 2]
    p0 = -c[:, None] * lines[:, :2] / (a * a + b * b)[:, None]
    t = np.stack([-b, a], axis=1) / np.hypot(a, b)[:, None]
    lo = np.full(len(lines), -np.inf)
    hi = np.full(len(lines), np.inf)
    ok = np.ones(len(lines), dtype=bool)
    for k in range(2):
        lo_k, hi_k = boxes[:, k], boxes[:, k + 2]
        flat = np.abs(t[:, k]) < 1e-15
        ok &= ~flat | ((lo_k <= p0[:, k]) & (p0[:, k] <= hi_k))
        tk = np.where(flat, 1.0, t[:, k])
        sa, sb = (lo_k - p0[:, k]) / tk, (hi_k - p0[:, k]) / tk
        lo = np.where(flat, lo, np.maximum(lo, np.minimum(sa, sb)))
        hi = np.where(flat, hi, np.minimum(hi, np.maximum(sa, sb)))
    ok &= hi > lo
    seg = np.stack([p0 + np.where(ok, lo, 0.0)[:, None] * t, p0 + np.where(ok, hi, 0.0)[:, None] * t], axis=1)
    return seg, ok


def _segment_ids(lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(segment index, index within the segment) of every element of consecutive segments ``lengths`` (k,)."""
    total = int(lengths.sum())
    seg = np.repeat(np.arange(len(lengths)), lengths)
    start = np.cumsum(lengths) - lengths
    return seg, np.arange(total) - start[seg]


def _curve_runs(points: np.ndarray, lengths: np.ndarray, closed: np.ndarray, boxes: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_resample`'s runs, batched over curves.

    points (N, 2): the dense polylines one after the other, ``lengths`` (k,) points each (> 0), ``closed``
    (k,) bool, ``boxes`` (k, 4). Returns the run polylines one after the other (T, 2), each run's length
    (R,) and curve index (R,): the maximal parts of each curve inside its box with >= 2 points, in
    curve order (a closed curve entirely inside is one run closed by repeating its first point; a
    closed curve partly inside starts at its first outside point).
    """
    start = np.cumsum(lengths) - lengths
    cid = np.repeat(np.arange(len(lengths)), lengths)
    bx = boxes[cid]
    inside = (points[:, 0] >= bx[:, 0]) & (points[:, 0] <= bx[:, 2]) & (points[:, 1] >= bx[:, 1]) \
        & (points[:, 1] <= bx[:, 3])
    n_in = np.add.reduceat(inside.astype(np.int64), start)
    whole = closed & (n_in == lengths)  # closed and entirely inside: the curve closed by its first point
    j = np.arange(len(points)) - start[cid]
    first_out = np.minimum.reduceat(np.where(inside, lengths[cid], j), start)
    shift = np.where(closed & ~whole, first_out, 0)
    olen = np.where(n_in > 0, lengths + whole, 0)
    ocid, oj = _segment_ids(olen)
    order = start[ocid] + (oj + shift[ocid]) % lengths[ocid]
    ins = inside[order]
    first = oj == 0
    last = oj == olen[ocid] - 1
    prev_in = np.r_[False, ins[:-1]] & ~first
    next_in = np.r_[ins[1:], False] & ~last
    rs = np.flatnonzero(ins & ~prev_in)
    re = np.flatnonzero(ins & ~next_in) + 1
    rlen = re - rs
    good = rlen >= 2
    rs, rlen = rs[good], rlen[good]
    rid, rj = _segment_ids(rlen)
    return points[order[rs[rid] + rj]], rlen, ocid[rs]


def _arc_samples_batch(runs: np.ndarray, lengths: np.ndarray, spacing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_arc_samples` batched: runs (T, 2) one after the other, ``lengths`` (R,) points each (>= 2),
    ``spacing`` (R,) px per run.

    Returns samples (S, 2) and their run index (S,), run by run in order.
    """
    if len(lengths) == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=int)
    start = np.cumsum(lengths) - lengths
    end = start + lengths - 1  # last point of each run
    dx, dy = np.diff(runs[:, 0]), np.diff(runs[:, 1])
    seg = np.sqrt(dx * dx + dy * dy)
    seg[end[:-1]] = 1.0  # a gap between consecutive runs keeps the cumulative length increasing
    G = np.r_[0.0, np.cumsum(seg)]
    L = G[end] - G[start]
    n = np.where(L > 0, np.floor(L / spacing), -1.0)
    rid, k = _segment_ids((n + 1).astype(np.int64))
    sp = spacing[rid]
    t = (k + 0.5 * (L[rid] / sp - n[rid])) * sp
    keep = t <= L[rid]
    rid, t = rid[keep], t[keep]
    g0 = G[start[rid]]
    pos = np.searchsorted(G, t + g0, side="right") - 1
    pos = np.clip(pos, start[rid], end[rid] - 1)
    s0 = G[pos] - g0
    ds = G[pos + 1] - G[pos]
    dp = runs[pos + 1] - runs[pos]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where((ds > 0)[:, None], dp / np.where(ds > 0, ds, 1.0)[:, None] * (t - s0)[:, None] + runs[pos],
                       runs[pos + 1])
    return out, rid


def sample_contours(
    Q_cam: np.ndarray,
    clip_cam: np.ndarray,
    K: np.ndarray,
    boxes: np.ndarray,
    spacing_px: float | np.ndarray = 5.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`sample_contour` (no occluders) for many quadrics at once, in one numpy pass (ALGORITHMS.md §2 "Model").

    Q_cam (n, 4, 4): the quadrics in their camera's coordinates (``E^-T Q E^-1``, eq. 2); clip_cam (n, 4, 4):
    their clipping quadrics in camera coordinates (all zeros: unclipped); K (n, 3, 3): each one's camera
    intrinsics; boxes (n, 4): ``(x0, y0, x1, y1)`` px, the image area to sample (``sample_contour``'s
    ``[-margin, w - 1 + margin] x [-margin, h - 1 + margin]``); spacing_px: image spacing of samples,
    one for all or (n,) one per quadric.

    Returns (uv (M, 2) px, normals (M, 2) unit and outward, points_cam (M, 3) tangent points in the camera
    frame, owner (M,) quadric index), quadric by quadric in input order, each quadric's samples in the
    order :func:`sample_contour` gives them and equal to them up to rounding. Ellipses (every bounded
    quadric in front of the camera) and line pairs (cylinders, cones) are sampled without any per-quadric
    Python loop; hyperbolae and parabolae (quadrics crossing the camera plane) fall back to the per-conic
    curve construction.
    """
    Q_cam = np.asarray(Q_cam, dtype=float)
    clip_cam = np.asarray(clip_cam, dtype=float)
    K = np.asarray(K, dtype=float)
    boxes = np.asarray(boxes, dtype=float)
    n = len(Q_cam)
    spacing = np.broadcast_to(np.asarray(spacing_px, dtype=float), (n,))
    empty = (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, dtype=int))
    if n == 0:
        return empty
    C = pixel_conics(Q_cam, K)
    cmax = np.abs(C).reshape(n, 9).max(axis=1)
    Cn = C / cmax[:, None, None]
    sv = np.linalg.svd(Cn, compute_uv=False)
    degenerate = sv[:, 2] <= 1e-10 * sv[:, 0]
    fine = spacing / 8.0
    # run polylines from every source, with their conic, an ordering key within the conic, and a
    # flag for the Newton refinement (non-degenerate conics only)
    run_pts: list[np.ndarray] = []
    run_len: list[np.ndarray] = []
    run_owner: list[np.ndarray] = []
    run_key: list[np.ndarray] = []
    # line pairs: every clipped line is one 2-point run
    deg = np.flatnonzero(degenerate)
    if len(deg):
        lines, li, ok = _line_pairs(Cn[deg])
        seg, inb = _clip_lines(lines, boxes[deg[li]])
        ok &= inb
        run_pts.append(seg[ok].reshape(-1, 2))
        run_len.append(np.full(int(ok.sum()), 2))
        run_owner.append(deg[li[ok]])
        run_key.append(np.tile([0, 1], len(deg))[ok])
    nd = np.flatnonzero(~degenerate)
    if len(nd):
        A2, b2, c2 = Cn[nd, :2, :2], Cn[nd, :2, 2], Cn[nd, 2, 2]
        lam, U = np.linalg.eigh(A2)
        big = np.abs(lam).max(axis=1)
        ell = (np.abs(lam).min(axis=1) > 1e-10 * big) & (lam[:, 0] * lam[:, 1] > 0)
        curves_pts, curves_len, curves_closed, curves_owner, curves_key = [], [], [], [], []
        e = np.flatnonzero(ell)
        if len(e):
            center = -np.linalg.solve(A2[e], b2[e][:, :, None])[:, :, 0]
            g = -(c2[e] + np.einsum("ni,ni->n", b2[e], center))
            real = g / lam[e, 0] > 0
            e, center, g = e[real], center[real], g[real]
            ax = np.sqrt(g[:, None] / lam[e])
            cnt = np.minimum(2_000_000, np.maximum(256, 2.0 * np.pi * ax.max(axis=1) / np.maximum(fine[nd[e]], 1e-6)))
            cnt = cnt.astype(np.int64)
            # center + S U^T, S = (ax0 cos th, ax1 sin th), th = 2 pi k / cnt (as _conic_curves), x = cx + p cos + q sin
            pq = ax[:, None, :] * U[e]  # (k, 2 [x, y], 2 [cos, sin])
            half = np.sqrt(pq[:, :, 0] ** 2 + pq[:, :, 1] ** 2)  # half extents of the ellipse's bounding box
            bx = boxes[nd[e]]
            tol = 1e-6  # px: far above the rounding of the dense points
            whole = np.all((center - half > bx[:, :2] + tol) & (center + half < bx[:, 2:] - tol), axis=1)
            # a closed curve inside the box is one run closed by its first point (th = 0 again)
            npts = cnt + whole
            eid, j = _segment_ids(npts)
            k = np.where(j == cnt[eid], 0, j)
            th = k * (2.0 * np.pi / cnt[eid])
            cs, sn = np.cos(th), np.sin(th)
            pts = np.empty((len(th), 2))
            for i in range(2):
                pts[:, i] = center[eid, i] + pq[eid, i, 0] * cs + pq[eid, i, 1] * sn
            run_pts.append(pts[whole[eid]])
            run_len.append(npts[whole])
            run_owner.append(nd[e[whole]])
            run_key.append(np.zeros(int(whole.sum()), dtype=int))
            part = ~whole[eid]
            if part.any():
                curves_pts.append(pts[part])
                curves_len.append(cnt[~whole])
                curves_closed.append(np.ones(int((~whole).sum()), dtype=bool))
                curves_owner.append(nd[e[~whole]])
                curves_key.append(np.zeros(int((~whole).sum()), dtype=int))
        for q in nd[~ell]:  # hyperbolae, parabolae: per conic
            for sub, (poly, closed) in enumerate(_conic_curves(Cn[q], tuple(boxes[q]), float(fine[q]))):
                curves_pts.append(poly)
                curves_len.append(np.array([len(poly)]))
                curves_closed.append(np.array([closed]))
                curves_owner.append(np.array([q]))
                curves_key.append(np.array([sub]))
        if curves_pts:
            owner_c = np.concatenate(curves_owner)
            pts, rl, rc = _curve_runs(np.concatenate(curves_pts), np.concatenate(curves_len),
                                      np.concatenate(curves_closed), boxes[owner_c])
            run_pts.append(pts)
            run_len.append(rl)
            run_owner.append(owner_c[rc])
            run_key.append(np.concatenate(curves_key)[rc])
    if not run_pts:
        return empty
    run_of = np.concatenate(run_owner)
    uv, rid = _arc_samples_batch(np.concatenate(run_pts), np.concatenate(run_len), spacing[run_of])
    owner = run_of[rid]
    key = np.concatenate(run_key)[rid]
    order = np.argsort(owner * 8 + key, kind="stable")
    uv, owner = uv[order], owner[order]
    if len(uv) == 0:
        return empty
    newton = ~degenerate[owner]
    if newton.any():
        Cs = Cn[owner[newton]]
        x = uv[newton]
        for _ in range(2):  # as in _conic_points: back onto the conic along the gradient
            xh = np.c_[x, np.ones(len(x))]
            f = np.einsum("ni,nij,nj->n", xh, Cs, xh)
            gr = 2.0 * np.einsum("ni,nij->nj", xh, Cs)[:, :2]
            gg = np.einsum("ni,ni->n", gr, gr)
            x = x - np.where(gg > 0, f / np.where(gg > 0, gg, 1.0), 0.0)[:, None] * gr
        uv[newton] = x
    uvh = np.c_[uv, np.ones(len(uv))]
    grad = np.einsum("ni,nij->nj", uvh, C[owner])[:, :2]
    gnorm = np.linalg.norm(grad, axis=1)
    keep = gnorm > 1e-12 * cmax[owner]
    normals = grad / np.where(keep, gnorm, 1.0)[:, None]
    rays = np.einsum("ni,nji->nj", uvh, np.linalg.inv(K)[owner])
    Qo = Q_cam[owner]
    alpha = np.einsum("ni,ni->n", (rays[:, :, None] * rays[:, None, :]).reshape(-1, 9), Qo[:, :3, :3].reshape(-1, 9))
    with np.errstate(divide="ignore", invalid="ignore"):
        lam_t = np.where(np.abs(alpha) > 1e-15,
                         -np.einsum("ni,ni->n", rays, Qo[:, :3, 3]) / np.where(alpha == 0, 1.0, alpha), np.nan)
    P = lam_t[:, None] * rays
    # visibility_mask without occluders: finite, in front, inside the clip
    fin = np.all(np.isfinite(P), axis=1)
    Pf = np.where(fin[:, None], P, 1.0)
    keep &= fin & (Pf[:, 2] > 1e-6)
    clip_tol = 1e-9 * np.maximum(1.0, np.abs(clip_cam).reshape(n, 16).max(axis=1))
    Xh = np.c_[Pf, np.ones(len(Pf))]
    keep &= np.einsum("ni,ni->n", (Xh[:, :, None] * Xh[:, None, :]).reshape(-1, 16),
                      clip_cam.reshape(n, 16)[owner]) <= clip_tol[owner]
    return uv[keep], normals[keep], P[keep], owner[keep]
