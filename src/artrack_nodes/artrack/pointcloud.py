"""Dense 3-D points: the half-capsule skin likelihood, the marker error, and a depth camera
rendering the body model (ALGORITHMS.md §3 "Likelihood" and "Error measure").

Skin: every body shape as a capsule (:meth:`BodyModel.capsules`; ellipsoids
become capsules), of which only the half facing the camera is kept. For a
point z with unit direction v towards the camera, ρ the offset from the
capsule axis and a its component towards the camera: in front (ρ·v ≥ 0) the
distance is |‖ρ‖ − r|; behind, the distance to the rim of the half capsule,
sqrt(a² + (‖ρ_⊥‖ − r)²). The likelihood (eq. (9)) is
log p(Z | θ) = −Σ_k min(D²(θ, z_k), τ) / (2σ²), computed for all particles
with matrix products only (no (N, S, K, 3) tensors).

Depth camera: each pixel's ray is cast against the body's true shapes
(ellipsoids, capsules, spheres), a held stick (a thin capsule) and the room
(floor, walls), then noised like a stereo / structured-light sensor
(σ_z = k·z²), with random dropouts and missing pixels at depth edges.
Points travel in the camera's optical frame (x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .body_model import BodyModel
from .cameras import Camera

__all__ = [
    "ARM_LINKS",
    "DepthNoise",
    "SkinModel",
    "arm_markers",
    "camera_from_world_points",
    "crop_box",
    "half_capsule_sq_distance",
    "marker_error",
    "points_from_depth",
    "raycast_depth",
    "render_depth",
    "skin_distance",
    "workspace_box",
    "world_from_camera_points",
]

ARM_LINKS = ("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm")


# ---------------------------------------------------------------------- distances
def half_capsule_sq_distance(points: np.ndarray, view: np.ndarray, p0: np.ndarray, p1: np.ndarray,
                             radius: np.ndarray) -> np.ndarray:
    """Squared distance (N, S, K) of points z (K, 3) to the camera-facing half of capsules.

    view: (K, 3) unit vectors from each point towards the camera; p0, p1: (N, S, 3)
    axis end points (world, m); radius: (S,) m. Zero-length capsules are spheres.
    """
    z = np.asarray(points, float)
    v = np.asarray(view, float)
    N, S = p0.shape[:2]
    u = p1 - p0
    L = np.linalg.norm(u, axis=-1)                                      # (N, S)
    uh = u / np.maximum(L, 1e-12)[..., None]
    P0 = p0.reshape(-1, 3)
    U = uh.reshape(-1, 3)
    du = (U @ z.T).reshape(N, S, -1) - np.sum(p0 * uh, axis=-1)[..., None]   # (z - p0)·u
    dd = (np.sum(z * z, axis=1)[None, None, :] - 2.0 * (P0 @ z.T).reshape(N, S, -1)
          + np.sum(p0 * p0, axis=-1)[..., None])                         # |z - p0|²
    dv = np.sum(z * v, axis=1)[None, None, :] - (P0 @ v.T).reshape(N, S, -1)  # (z - p0)·v
    vu = (U @ v.T).reshape(N, S, -1)                                     # v·u
    t = np.clip(du, 0.0, L[..., None])
    rho2 = np.maximum(dd - 2.0 * t * du + t * t, 0.0)
    a_num = dv - t * vu                                                  # ρ·v
    rho = np.sqrt(rho2)
    r = np.asarray(radius, float)[None, :, None]
    front = (rho - r) ** 2
    a = a_num / np.sqrt(np.maximum(1.0 - vu * vu, 1e-6))
    b = np.sqrt(np.maximum(rho2 - a * a, 0.0))
    back = a * a + (b - r) ** 2
    return np.where(a_num >= 0.0, front, back)


def skin_distance(points: np.ndarray, p0: np.ndarray, p1: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Unsigned distance (..., M) of points (M, 3) to the surface of the union of full capsules
    p0, p1 (..., S, 3), radius (S,): |min_s (dist(z, segment_s) − r_s)|."""
    z = np.asarray(points, float)
    u = p1 - p0
    L2 = np.maximum(np.sum(u * u, axis=-1), 1e-18)
    d = z[..., None, :, :] - p0[..., :, None, :]                        # (..., S, M, 3)
    t = np.clip(np.sum(d * u[..., :, None, :], axis=-1) / L2[..., None], 0.0, 1.0)
    foot = p0[..., :, None, :] + t[..., None] * u[..., :, None, :]
    dist = np.linalg.norm(z[..., None, :, :] - foot, axis=-1) - np.asarray(radius)[:, None]
    return np.abs(dist.min(axis=-2))


def arm_markers(body: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """Motion-capture style markers on the arms' skin: (link index (M,), points (M, 3) link frame).

    On each arm link: at 1/3 and 2/3 of the bone, on the surface of its capsule
    facing forward (+x) and outward (±y), 4 per link, 16 in all.
    """
    idx, pts = [], []
    for name in ARM_LINKS:
        lk = body.link(name)
        _, _, r = lk.shapes[0].as_capsule()
        side = 1.0 if name.startswith("l_") else -1.0
        for f in (1.0 / 3.0, 2.0 / 3.0):
            for direction in (np.array([1.0, 0.0, 0.0]), np.array([0.0, side, 0.0])):
                idx.append(body.link_index(name))
                pts.append(f * lk.end + r * direction)
    return np.array(idx, int), np.array(pts, float)


def marker_error(body: BodyModel, theta_est: np.ndarray, theta_true: np.ndarray) -> float:
    """Eq. (10) for one frame: mean distance (m) of the true arm markers to the estimated
    capsule skin (all body shapes as capsules). theta_*: (n_dof,)."""
    idx, pts = arm_markers(body)
    T = body.forward_kinematics(np.asarray(theta_true, float))
    markers = body.transform_points(T, idx, pts)
    p0, p1, r, _, _ = body.capsules(np.asarray(theta_est, float))
    return float(skin_distance(markers, p0, p1, r).mean())


# ---------------------------------------------------------------------- likelihood
class SkinModel:
    """The §3 likelihood (eq. (9)) over particles of a pose manifold.

    body: the body model; moving: (L,) bool, links whose pose depends on the
    particle (the others are evaluated once per frame at the base pose).
    """

    def __init__(self, body: BodyModel, moving_links: Sequence[int]):
        self.body = body
        _, _, self.radius, self.cap_link, _ = body.capsules(body.rest_pose())
        moving = np.zeros(len(body.links), bool)
        moving[list(moving_links)] = True
        self.moving = moving[self.cap_link]                               # (S,) per capsule

    def log_likelihood(self, theta_full: np.ndarray, points: np.ndarray, camera_center: np.ndarray,
                       sigma: float, tau: float, static_sq: np.ndarray | None = None) -> np.ndarray:
        """log p(Z | θ) up to a constant, (N,), for full poses θ (N, n_dof) and points Z (K, 3) world.

        sigma: m, point-to-skin noise; tau: m², truncation of the squared distance.
        static_sq: (K,) precomputed squared distances to the static capsules (see
        :meth:`static_sq_distance`), computed from theta_full[0] if None.
        """
        theta_full = np.asarray(theta_full, float).reshape(-1, self.body.n_dof)
        z = np.asarray(points, float).reshape(-1, 3)
        view = np.asarray(camera_center, float) - z
        view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
        if static_sq is None:
            static_sq = self.static_sq_distance(theta_full[0], z, camera_center)
        p0, p1, _, _, _ = self.body.capsules(theta_full)
        m = self.moving
        d2 = half_capsule_sq_distance(z, view, p0[:, m], p1[:, m], self.radius[m]).min(axis=1)
        d2 = np.minimum(np.minimum(d2, static_sq[None, :]), tau)
        return -d2.sum(axis=1) / (2.0 * sigma * sigma)

    def static_sq_distance(self, theta_full: np.ndarray, points: np.ndarray, camera_center: np.ndarray) -> np.ndarray:
        """(K,) squared distance of points (K, 3) to the camera-facing static capsules (inf if none)."""
        z = np.asarray(points, float).reshape(-1, 3)
        s = ~self.moving
        if not s.any():
            return np.full(len(z), np.inf)
        view = np.asarray(camera_center, float) - z
        view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
        p0, p1, _, _, _ = self.body.capsules(np.asarray(theta_full, float).reshape(1, -1))
        return half_capsule_sq_distance(z, view, p0[:, s], p1[:, s], self.radius[s]).min(axis=1)[0]


# ---------------------------------------------------------------------- depth camera
class DepthNoise:
    """Sensor model: sigma_z = k_quadratic·z² (m), a share ``dropout`` of random pixels and
    pixels next to a depth step larger than ``edge_step`` m are missing."""

    def __init__(self, k_quadratic: float = 0.002, dropout: float = 0.05, edge_step: float = 0.08):
        self.k_quadratic = float(k_quadratic)
        self.dropout = float(dropout)
        self.edge_step = float(edge_step)


def _near(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays o + t d (d (R, 3) unit) passing within ``radius`` of ``centre``."""
    w = centre - o
    along = d @ w
    return np.nonzero((w @ w - along * along <= radius * radius) & (along > 0))[0]


def _ray_capsules(o: np.ndarray, d: np.ndarray, p0: np.ndarray, p1: np.ndarray, r: np.ndarray,
                  best: np.ndarray | None = None) -> np.ndarray:
    """Nearest positive ray parameter (R,) of rays o + t d (d (R, 3) unit) with capsules (S, ...)."""
    best = np.full(len(d), np.inf) if best is None else best
    for a, b, rad in zip(p0, p1, r, strict=True):
        u = b - a
        L = float(np.linalg.norm(u))
        idx = _near(o, d, 0.5 * (a + b), 0.5 * L + rad)
        if len(idx) == 0:
            continue
        di = d[idx]
        bi = best[idx]
        for c in (a, b):  # end spheres
            w = o - c
            bb = di @ w
            disc = bb * bb - (w @ w - rad * rad)
            t = -bb - np.sqrt(np.maximum(disc, 0.0))
            bi = np.where((disc >= 0) & (t > 1e-6) & (t < bi), t, bi)
        if L > 1e-9:
            u = u / L
            w = o - a
            du = di @ u
            dp = di - np.outer(du, u)
            wp = w - (w @ u) * u
            A = np.sum(dp * dp, axis=1)
            B = 2.0 * (dp @ wp)
            Cc = wp @ wp - rad * rad
            disc = B * B - 4.0 * A * Cc
            t = (-B - np.sqrt(np.maximum(disc, 0.0))) / np.maximum(2.0 * A, 1e-12)
            s = (w @ u) + t * du
            bi = np.where((disc >= 0) & (t > 1e-6) & (s >= 0) & (s <= L) & (t < bi), t, bi)
        best[idx] = bi
    return best


def _ray_ellipsoids(o: np.ndarray, d: np.ndarray, centres: np.ndarray, axes: np.ndarray,
                    best: np.ndarray | None = None) -> np.ndarray:
    """Nearest positive ray parameter (R,) with ellipsoids: centres (E, 3), axes (E, 3, 3) columns
    = world semi-axes."""
    best = np.full(len(d), np.inf) if best is None else best
    for c, A in zip(centres, axes, strict=True):
        idx = _near(o, d, c, float(np.linalg.norm(A, axis=0).max()))
        if len(idx) == 0:
            continue
        Minv = np.linalg.inv(A)
        oo = Minv @ (o - c)
        dd = d[idx] @ Minv.T
        a = np.sum(dd * dd, axis=1)
        b = dd @ oo
        disc = b * b - a * (oo @ oo - 1.0)
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
        bi = best[idx]
        best[idx] = np.where((disc >= 0) & (t > 1e-6) & (t < bi), t, bi)
    return best


_RAYS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(centre (3,), unit world directions (H*W, 3)) of all pixels, row-major, cached per calibration."""
    key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(), camera.R.tobytes(),
           camera.t.tobytes())
    if key not in _RAYS:
        if len(_RAYS) > 4:
            _RAYS.clear()
        v, u = np.mgrid[0:camera.height, 0:camera.width]
        o, d = camera.rays(np.stack([u.ravel(), v.ravel()], axis=1).astype(float))
        _RAYS[key] = (np.asarray(o, float), d)
    return _RAYS[key]


def raycast_depth(body: BodyModel, theta: np.ndarray | None, camera: Camera,
                  stick: tuple[np.ndarray, np.ndarray] | None = None, stick_radius: float = 0.015,
                  room: tuple[float, float] = (5.5, 3.0)) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free optical-frame depth (H, W) float (m) of the body (true shapes), an optional stick
    (end points a, b world) and the room (walls at ±room[0], ceiling room[1], floor 0), plus a
    label image (H, W) uint8: 0 room, 1 body, 2 stick."""
    from .synth import _geometry  # the renderer's shape tables (same shapes as the RGB images)

    o, d = _pixel_rays(camera)
    # room
    big = 1e9
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = [np.where(d[:, 2] < -1e-9, -o[2] / d[:, 2], big),
              np.where(d[:, 2] > 1e-9, (room[1] - o[2]) / d[:, 2], big),
              np.where(np.abs(d[:, 0]) > 1e-9, (np.sign(d[:, 0]) * room[0] - o[0]) / d[:, 0], big),
              np.where(np.abs(d[:, 1]) > 1e-9, (np.sign(d[:, 1]) * room[0] - o[1]) / d[:, 1], big)]
    t_room = np.min(np.where(np.stack(ts) > 0, np.stack(ts), big), axis=0)
    t_body = np.full(len(d), np.inf)
    if theta is not None:
        g = _geometry(body)
        T = body.forward_kinematics(np.asarray(theta, float))
        p0 = body.transform_points(T, g.cap_link, g.cap_p0)
        p1 = body.transform_points(T, g.cap_link, g.cap_p1)
        ec = body.transform_points(T, g.ell_link, g.ell_centre)
        ea = T[g.ell_link, :3, :3] @ g.ell_axes
        t_body = _ray_ellipsoids(o, d, ec, ea, _ray_capsules(o, d, p0, p1, g.cap_r))
    t_stick = np.full(len(d), np.inf)
    if stick is not None:
        a, b = (np.asarray(x, float) for x in stick)
        t_stick = _ray_capsules(o, d, a[None], b[None], np.array([stick_radius]))
    t_all = np.stack([t_room, t_body, t_stick])
    label = np.argmin(t_all, axis=0)
    t = t_all[label, np.arange(len(d))]
    depth = t * (d @ camera.R[2])  # optical z
    return depth.reshape(camera.height, camera.width), label.reshape(camera.height, camera.width).astype(np.uint8)


def render_depth(body: BodyModel, theta: np.ndarray | None, camera: Camera, rng: np.random.Generator,
                 noise: DepthNoise | None = None, stick: tuple[np.ndarray, np.ndarray] | None = None,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Noisy depth image (H, W) float32 m, NaN where missing, and the label image (see raycast_depth)."""
    noise = DepthNoise() if noise is None else noise
    depth, label = raycast_depth(body, theta, camera, stick)
    z = depth + rng.standard_normal(depth.shape) * noise.k_quadratic * depth**2
    missing = rng.random(depth.shape) < noise.dropout
    if noise.edge_step > 0:
        gx = np.zeros_like(depth)
        gy = np.zeros_like(depth)
        gx[:, 1:] = np.abs(np.diff(depth, axis=1))
        gy[1:, :] = np.abs(np.diff(depth, axis=0))
        edge = (gx > noise.edge_step) | (gy > noise.edge_step)
        edge[:, :-1] |= edge[:, 1:]
        edge[:-1, :] |= edge[1:, :]
        missing |= edge
    z[missing] = np.nan
    return z.astype(np.float32), label


def points_from_depth(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """Optical-frame points (K, 3) float32 (m) of the valid pixels of a depth image (H, W) m,
    through the lens model (the rays of the distorted pixels), row-major pixel order."""
    valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        return np.zeros((0, 3), np.float32)
    _, d = _pixel_rays(camera)
    d_cam = d[valid.ravel()] @ camera.R.T
    z = depth[valid].astype(float)
    return (d_cam * (z / d_cam[:, 2])[:, None]).astype(np.float32)


def world_from_camera_points(camera: Camera, points_cam: np.ndarray) -> np.ndarray:
    """(K, 3) optical-frame points -> world (x_cam = R X + t)."""
    return (np.asarray(points_cam, float) - camera.t) @ camera.R


def camera_from_world_points(camera: Camera, points_world: np.ndarray) -> np.ndarray:
    """(K, 3) world points -> optical frame."""
    return np.asarray(points_world, float) @ camera.R.T + camera.t


def workspace_box(root_xyz: np.ndarray, half_xy: tuple[float, float] = (1.0, 1.2),
                  z_range: tuple[float, float] = (0.05, 2.4)) -> tuple[np.ndarray, np.ndarray]:
    """(lower (3,), upper (3,)) world box around a standing person's root position (m): the
    pass-through filter that keeps the person (and what they hold) and drops floor and walls."""
    r = np.asarray(root_xyz, float)
    return (np.array([r[0] - half_xy[0], r[1] - half_xy[1], z_range[0]]),
            np.array([r[0] + half_xy[0], r[1] + half_xy[1], z_range[1]]))


def crop_box(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The finite points (K, 3) inside the axis-aligned box [lower, upper]."""
    p = np.asarray(points).reshape(-1, 3)
    return p[np.all(np.isfinite(p) & (p >= lower) & (p <= upper), axis=1)]
