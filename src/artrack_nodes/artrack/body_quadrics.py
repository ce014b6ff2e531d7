"""The body model as clipped quadrics, and its visible outline in a camera — ALGORITHMS.md §2 "Model".

Every shape of every body-model link (``config/body_model.yaml``) becomes one or more
:class:`artrack.quadrics.ClippedQuadric` in the *link* frame:

* ellipsoid (centre, semi-axes along the link axes) -> one ellipsoid, unclipped;
* sphere -> one sphere, unclipped;
* capsule (segment ``p0 -> p1``, radius r) -> a cylinder of radius r about the segment clipped
  by the slab between the end points, plus two spheres of radius r at the ends, each clipped to
  its outer half (the slab ``[-r, 0]`` beyond ``p0``, ``[L, L + r]`` beyond ``p1`` along the
  axis). The union is exactly the capsule. A zero-length capsule is a sphere.

:func:`sample_body` lays contour samples on every primitive's image conic (paper eq. 4,
:func:`artrack.quadrics.sample_contour`, clip test included) and then removes samples hidden
by any other primitive of the body (same or other link) with one batched ray / quadric test
(the same test as :func:`artrack.quadrics.visibility_mask`, vectorised over all samples and
all occluders at once). Images are pinhole (``K`` only): undistort the image first, or map
the 3-D tangent points through the full camera model.

:func:`visible_surface_gaussian` gives a link's blob feature (ALGORITHMS.md §1, "blob classes as
Gaussians") from the same primitives: the mean and covariance of the part of the link's surface, in
the blob's colour, that cameras around the body see (hidden surface removed with the same ray test).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from artrack.body_model import BodyModel, Shape
from artrack.lie import inverse_se3
from artrack.quadrics import ClippedQuadric, cylinder, ellipsoid, sample_contours, slab, sphere, transform_quadric

__all__ = ["BodyQuadric", "BodySamples", "body_quadrics", "sample_body", "sample_body_views", "shape_quadrics",
           "visible_surface_gaussian"]


@dataclass(frozen=True)
class BodyQuadric:
    """One clipped quadric of the body: ``link`` index, ``shape`` index in that link, ``part``
    ('ellipsoid', 'sphere', 'cylinder', 'cap0', 'cap1') and the quadric (link frame)."""

    link: int
    shape: int
    part: str
    quadric: ClippedQuadric


@dataclass(frozen=True)
class BodySamples:
    """Visible outline samples of the whole body in one camera (pinhole pixels of ``K``).

    uv (M, 2) px; normals (M, 2) unit, pointing out of the primitive's silhouette;
    points_cam (M, 3) tangent points in the camera frame (m); link (M,) and prim (M,) indices
    (into ``body.links`` and the :func:`body_quadrics` list).
    """

    uv: np.ndarray
    normals: np.ndarray
    points_cam: np.ndarray
    link: np.ndarray
    prim: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


def _frame_along(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """(4, 4) link_from_capsule: origin at p0, z axis along p1 - p0 (any x, y)."""
    z = (p1 - p0) / np.linalg.norm(p1 - p0)
    helper = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = p0
    return T


def shape_quadrics(shape: Shape) -> list[tuple[str, ClippedQuadric]]:
    """(part name, clipped quadric in the link frame) list of one body-model shape (module docstring)."""
    if shape.kind == "ellipsoid":
        return [("ellipsoid", ClippedQuadric(ellipsoid(shape.radii, shape.centre)))]
    if shape.kind == "sphere":
        return [("sphere", ClippedQuadric(sphere(shape.radius, shape.centre)))]
    if shape.kind != "capsule":
        raise ValueError(f"shape_quadrics: unknown shape kind {shape.kind!r}")
    p0, p1, r = np.asarray(shape.p0, float), np.asarray(shape.p1, float), float(shape.radius)
    length = float(np.linalg.norm(p1 - p0))
    if length < 1e-9:
        return [("sphere", ClippedQuadric(sphere(r, p0)))]
    T = _frame_along(p0, p1)  # link_from_capsule

    def in_link(Q: np.ndarray) -> np.ndarray:
        return transform_quadric(Q, T)

    return [
        ("cylinder", ClippedQuadric(in_link(cylinder(r)), in_link(slab(0.0, length)))),
        ("cap0", ClippedQuadric(in_link(sphere(r)), in_link(slab(-r, 0.0)))),
        ("cap1", ClippedQuadric(in_link(sphere(r, (0.0, 0.0, length))), in_link(slab(length, length + r)))),
    ]


def body_quadrics(body: BodyModel) -> list[BodyQuadric]:
    """All clipped quadrics of ``body``, link by link (link frames)."""
    out = []
    for li, lk in enumerate(body.links):
        for si, sh in enumerate(lk.shapes):
            out.extend(BodyQuadric(li, si, part, q) for part, q in shape_quadrics(sh))
    return out


def _occluded(points: np.ndarray, own: np.ndarray, Q_cam: np.ndarray, clip_cam: np.ndarray,
              min_depth: float = 1e-6, rel_tol: float = 1e-6) -> np.ndarray:
    """(M,) bool: the ray to each point (M, 3) hits another primitive (Q_cam, clip_cam (P, 4, 4)) in front.

    ``own`` (M,) is each point's own primitive index (never its own occluder).
    """
    depth = points[:, 2]
    d = points / depth[:, None]  # rays with z = 1, so ray depth = z
    A, b, c = Q_cam[:, :3, :3], Q_cam[:, :3, 3], Q_cam[:, 3, 3]
    alpha = (d[:, :, None] * d[:, None, :]).reshape(-1, 9) @ A.reshape(-1, 9).T  # d^T A_p d (M, P)
    beta = d @ b.T
    disc = beta**2 - alpha * c[None, :]
    real = (disc >= 0) & (np.abs(alpha) > 1e-15)
    sq = np.sqrt(np.where(real, disc, 0.0))
    a_safe = np.where(real, alpha, 1.0)
    hidden = np.zeros(len(points), dtype=bool)
    for sgn in (-1.0, 1.0):
        lam = (-beta + sgn * sq) / a_safe
        ok = real & (lam > min_depth) & (lam < depth[:, None] * (1.0 - rel_tol))
        ok[np.arange(len(points)), own] = False
        if not ok.any():
            continue
        m, p = np.nonzero(ok)
        X = np.c_[d[m] * lam[m, p][:, None], np.ones(len(m))]
        inside = np.einsum("ki,ki->k", (X[:, :, None] * X[:, None, :]).reshape(-1, 16),
                           clip_cam.reshape(-1, 16)[p]) <= 0.0
        hidden[m[inside]] = True
    return hidden


def sample_body(
    quadrics: Sequence[BodyQuadric],
    cam_from_link: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    spacing_px: float = 5.0,
    *,
    margin_px: float = 0.0,
    occlusion: bool = True,
    links: Sequence[int] | None = None,
) -> BodySamples:
    """Visible outline samples of the body in one camera (ALGORITHMS.md §2 "Model").

    quadrics: from :func:`body_quadrics`; cam_from_link: (L, 4, 4) pose of every link in the
    camera (``cam_from_world @ world_from_link``); K (3, 3); image_size (width, height) px;
    spacing_px: image spacing of samples along each conic. occlusion: drop samples hidden by any
    other primitive of the body. links: only sample primitives of these links (all still occlude).
    Equal to :func:`artrack.quadrics.sample_contour` per primitive followed by the occlusion test;
    computed for all primitives at once (:func:`sample_body_views`).
    """
    return sample_body_views(quadrics, np.asarray(cam_from_link, dtype=float)[None], np.asarray(K, float)[None],
                             [image_size], spacing_px, margin_px=margin_px, occlusion=occlusion, links=links)[0]


def _prims_in_cameras(quadrics: Sequence[BodyQuadric], cam_from_link: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every primitive in every camera, ``Q' = E^-T Q E^-1`` (eq. 2): surfaces and clips (V, P, 4, 4);
    no clip = always inside (zeros)."""
    Ti = inverse_se3(cam_from_link)[:, [bq.link for bq in quadrics]]  # (V, P, 4, 4)
    TiT = np.swapaxes(Ti, -1, -2)
    surf = np.stack([bq.quadric.surface for bq in quadrics])
    clip = np.stack([np.zeros((4, 4)) if bq.quadric.clip is None else bq.quadric.clip for bq in quadrics])
    return TiT @ surf @ Ti, TiT @ clip @ Ti


def sample_body_views(
    quadrics: Sequence[BodyQuadric],
    cam_from_link: np.ndarray,
    K: np.ndarray,
    image_sizes: Sequence[tuple[int, int]],
    spacing_px: float | Sequence[float] = 5.0,
    *,
    margin_px: float = 0.0,
    occlusion: bool = True,
    links: Sequence[int] | None = None,
) -> list[BodySamples]:
    """:func:`sample_body` for several cameras in one batched pass (ALGORITHMS.md §2 "Model").

    cam_from_link: (V, L, 4, 4), one set of link poses per camera; K: (V, 3, 3); image_sizes: V
    (width, height); spacing_px: one for all cameras or (V,) one per camera. All primitives of all
    cameras are sampled together (:func:`artrack.quadrics.sample_contours`), then each camera's
    samples pass the occlusion test.
    Returns one :class:`BodySamples` per camera.
    """
    E = np.asarray(cam_from_link, dtype=float)
    K = np.asarray(K, dtype=float)
    V, n = len(E), len(quadrics)
    Q_cam, clip_cam = _prims_in_cameras(quadrics, E)
    sel = np.ones(n, dtype=bool) if links is None else np.isin([bq.link for bq in quadrics], list(links))
    prim_ids = np.flatnonzero(sel)
    boxes = np.array([(-margin_px, -margin_px, w - 1 + margin_px, h - 1 + margin_px) for w, h in image_sizes],
                     dtype=float)
    cam_of = np.repeat(np.arange(V), len(prim_ids))
    uv, nrm, P, owner = sample_contours(Q_cam[:, prim_ids].reshape(-1, 4, 4), clip_cam[:, prim_ids].reshape(-1, 4, 4),
                                        K[cam_of], boxes[cam_of],
                                        np.broadcast_to(np.asarray(spacing_px, dtype=float), (V,))[cam_of])
    cam = owner // max(len(prim_ids), 1)
    prim = prim_ids[owner % max(len(prim_ids), 1)] if len(prim_ids) else owner
    link_of = np.array([bq.link for bq in quadrics], dtype=int)
    bounds = np.searchsorted(cam, np.arange(V + 1))
    out = []
    for v in range(V):
        a, b = bounds[v], bounds[v + 1]
        u, nr, p, pr = uv[a:b], nrm[a:b], P[a:b], prim[a:b]
        if occlusion and n > 1 and len(u):
            keep = ~_occluded(p, pr, Q_cam[v], clip_cam[v])
            u, nr, p, pr = u[keep], nr[keep], p[keep], pr[keep]
        out.append(BodySamples(u, nr, p, link_of[pr], pr))
    return out


# ---------------------------------------------------------------------- blob features from the shapes
def _fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (equal area each, 4 pi / n)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _surface_samples(part: str, shape: Shape, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (N, 3), outward unit normals (N, 3) and area weights (N,) m^2 on one part of a shape
    (link frame); the parts of :func:`shape_quadrics`."""
    u = _fibonacci_sphere(n)
    if part in ("ellipsoid", "sphere"):
        if shape.kind == "ellipsoid":
            centre, radii = np.asarray(shape.centre, float), np.asarray(shape.radii, float)
        else:  # a sphere, or a zero-length capsule
            centre = np.asarray(shape.centre if shape.kind == "sphere" else shape.p0, float)
            radii = np.full(3, float(shape.radius))
        g = u / radii  # the normal of x = c + radii * u is along radii^-1 u; dA = |det| |radii^-1 u| dA_u
        gn = np.linalg.norm(g, axis=1)
        return centre + u * radii, g / gn[:, None], np.prod(radii) * gn * (4.0 * np.pi / n)
    p0, p1, r = np.asarray(shape.p0, float), np.asarray(shape.p1, float), float(shape.radius)
    T = _frame_along(p0, p1)
    R, length = T[:3, :3], float(np.linalg.norm(p1 - p0))
    if part == "cylinder":
        n_phi = 48
        n_len = max(2, n // n_phi)
        phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
        t = (np.arange(n_len) + 0.5) * (length / n_len)
        phi, t = (a.ravel() for a in np.meshgrid(phi, t))
        nrm = np.column_stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)]) @ R.T
        pts = p0 + t[:, None] * R[:, 2] + r * nrm
        return pts, nrm, np.full(len(pts), 2.0 * np.pi * r * length / len(pts))
    outer = u[u[:, 2] <= 0.0] if part == "cap0" else u[u[:, 2] > 0.0]  # capsule frame: z along p0 -> p1
    nrm = outer @ R.T
    end = p0 if part == "cap0" else p1
    return end + r * nrm, nrm, np.full(len(outer), 4.0 * np.pi * r * r / n)


def visible_surface_gaussian(body: BodyModel, link: int, colour: str, *, n_views: int = 16,
                             distance_m: float = 4.0, samples: int = 1200) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3,) and covariance (3, 3), link frame, m, of the visible surface of ``colour`` on link
    ``link``: the Gaussian its 2-D blob measures (ALGORITHMS.md §1: a blob is the mean and covariance
    of its pixels).

    The body stands in its rest pose; ``n_views`` cameras on a horizontal ring of radius
    ``distance_m`` around the root, at the height of the link's shapes, look at it. Every shape
    of the link in ``colour`` is sampled (``samples`` points per part, area-weighted); a sample
    counts in a view when it faces the camera and no other primitive of the body hides it (the
    ray test of :func:`sample_body`), weighted by its projected area (area x cos of the viewing
    angle). So the parts covered by other shapes (hair over the face, the pelvis over the top of
    a thigh, the forearm over the wrist) and the surfaces seen end-on do not count, as in the
    images. Raises ValueError when the link has no visible surface of that colour.
    """
    lk = body.links[link]
    quadrics = body_quadrics(body)
    prim = {(bq.link, bq.shape, bq.part): k for k, bq in enumerate(quadrics)}
    pts, nrm, area, own = [], [], [], []
    for si, sh in enumerate(lk.shapes):
        if sh.colour != colour:
            continue
        for part, _ in shape_quadrics(sh):
            p, n_, a = _surface_samples(part, sh, samples)
            pts.append(p)
            nrm.append(n_)
            area.append(a)
            own.append(np.full(len(p), prim[(link, si, part)]))
    if not pts:
        raise ValueError(f"link '{lk.name}' has no shape of colour '{colour}'")
    p_link, n_link, area, own = (np.concatenate(x) for x in (pts, nrm, area, own))
    world_from_link = body.forward_kinematics(body.rest_pose())
    R, t = world_from_link[link, :3, :3], world_from_link[link, :3, 3]
    p_world, n_world = p_link @ R.T + t, n_link @ R.T
    centre = np.array([*world_from_link[0, :2, 3], p_world[:, 2].mean()])
    weight = np.zeros(len(p_link))
    for phi in np.arange(n_views) * (2.0 * np.pi / n_views):
        forward = -np.array([np.cos(phi), np.sin(phi), 0.0])  # camera z: towards the body, level
        down = np.array([0.0, 0.0, -1.0])  # camera y
        cam_from_world = np.eye(4)
        cam_from_world[:3, :3] = np.vstack([np.cross(down, forward), down, forward])
        position = centre - distance_m * forward
        cam_from_world[:3, 3] = -cam_from_world[:3, :3] @ position
        to_camera = position - p_world
        cos = np.einsum("ij,ij->i", n_world, to_camera) / np.linalg.norm(to_camera, axis=1)
        front = cos > 0.0
        p_cam = p_world[front] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        Q_cam, clip_cam = _prims_in_cameras(quadrics, (cam_from_world @ world_from_link)[None])
        seen = ~_occluded(p_cam, own[front], Q_cam[0], clip_cam[0])
        idx = np.flatnonzero(front)[seen]
        weight[idx] += area[idx] * cos[idx]
    if weight.sum() <= 0.0:
        raise ValueError(f"link '{lk.name}': no surface of colour '{colour}' is visible")
    mean = weight @ p_link / weight.sum()
    d = p_link - mean
    return mean, (weight[:, None] * d).T @ d / weight.sum()
