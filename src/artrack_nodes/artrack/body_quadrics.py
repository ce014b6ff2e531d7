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
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from artrack.body_model import BodyModel, Shape
from artrack.lie import inverse_se3
from artrack.quadrics import ClippedQuadric, cylinder, ellipsoid, sample_contour, slab, sphere, transform_quadric

__all__ = ["BodyQuadric", "BodySamples", "body_quadrics", "sample_body", "shape_quadrics"]


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
    alpha = np.einsum("mi,pij,mj->mp", d, A, d)
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
        inside = np.einsum("ki,kij,kj->k", X, clip_cam[p], X) <= 0.0
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
    """
    E = np.asarray(cam_from_link, dtype=float)
    n = len(quadrics)
    Einv = inverse_se3(E)
    # every primitive in camera coordinates, Q' = E^-T Q E^-1 (eq. 2); no clip = always inside (zeros)
    Q_cam = np.empty((n, 4, 4))
    clip_cam = np.zeros((n, 4, 4))
    for k, bq in enumerate(quadrics):
        Ti = Einv[bq.link]
        Q_cam[k] = Ti.T @ bq.quadric.surface @ Ti
        if bq.quadric.clip is not None:
            clip_cam[k] = Ti.T @ bq.quadric.clip @ Ti
    wanted = None if links is None else set(int(i) for i in links)
    parts = []
    for k, bq in enumerate(quadrics):
        if wanted is not None and bq.link not in wanted:
            continue
        s = sample_contour(bq.quadric, E[bq.link], K, image_size, spacing_px, margin_px=margin_px)
        if len(s):
            parts.append((s, bq.link, k))
    if not parts:
        z2, z3, zi = np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, dtype=int)
        return BodySamples(z2, z2.copy(), z3, zi, zi.copy())
    uv = np.vstack([s.uv for s, _, _ in parts])
    nrm = np.vstack([s.normals for s, _, _ in parts])
    P = np.vstack([s.points_cam for s, _, _ in parts])
    link = np.concatenate([np.full(len(s), li) for s, li, _ in parts])
    prim = np.concatenate([np.full(len(s), k) for s, _, k in parts])
    if occlusion and n > 1:
        keep = ~_occluded(P, prim, Q_cam, clip_cam)
        uv, nrm, P, link, prim = uv[keep], nrm[keep], P[keep], link[keep], prim[keep]
    return BodySamples(uv, nrm, P, link, prim)
