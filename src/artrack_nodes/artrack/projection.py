"""Feedback projection: predicted 3-D blobs -> 2-D blob priors per camera.

ALGORITHMS.md §1, "Inverse observation model": for a link with predicted 3-D
mean ``x`` and covariance ``Σ₃`` the prior in a camera is the projected mean and
the first-order projected covariance ``Σ₂ = J_π Σ₃ J_πᵀ``, where ``J_π`` (2x3) is
the Jacobian of the *full* camera model (pinhole + lens distortion,
:meth:`artrack.cameras.Camera.project_jacobian`) at ``x``; the paper's cruder
form divides the orthogonal xy covariance by (1 + z/f)².

Confidence. The paper weights each prior by the filter's confidence, measured
by the norm of the predicted error covariance ``‖P_{t|t-1}‖``. Here

    confidence = exp(-‖P‖_F / s)          (s = ``confidence_scale``, m²)

which is 1 for a certain prediction, 1/e when ‖P‖_F = s, and -> 0 as the
prediction becomes vague. P is the predicted *position* covariance of the blob's
link (``LinkEstimate.cov[:3, :3]``) when a BodyEstimate is given and has that
link; otherwise (plain Blob3D list) the Blob3D covariance itself. It is computed
in 3-D, so it is the same in every camera (a far camera does not make the
prediction more trustworthy). The default s = 0.01 m² gives 0.5 for an isotropic
σ ≈ 6.3 cm. The projected Gaussian itself always uses the Blob3D covariance
(the blob's predicted extent).

Visibility (codes of :mod:`artrack.types`), checked in this order:

* BEHIND_CAMERA — depth <= ``min_depth``; mean and cov are NaN, confidence 0;
* OFF_IMAGE — projected mean outside the image by more than ``margin`` px
  (default 5 % of the larger image side), or the point lies so far outside the
  field of view that the distortion polynomial would fold it back into the
  image; confidence 0 (mean and cov still given);
* OCCLUDED — the segment from the camera centre towards the blob mean passes
  through a capsule of another link (not the blob's own label); the segment
  stops short of the mean by ``occlusion_margin`` and, for every blob but those
  of ``centre_occlusion_labels`` (the hands), by the blob's extent along it,
  ``s·σ`` with σ² = dᵀ Σ₃ d (d the unit line of sight, s =
  ``occlusion_surface_sigma``) when that is more: what must be hidden is the
  blob's near surface, not its centre, which for the trunk's and legs' blobs
  lies inside the body (tested to its centre, the pelvis was hidden by the tops
  of its own thighs' capsules in 58 % of the view-frames of a walk, and its
  pixels went to the thighs). A hand is small and its centre is its surface; its
  predicted covariance also grows while it is unobserved, which would let a
  hidden hand's label take its neighbours' pixels. Confidence kept (the 2-D
  tracker decides what an occluded prior is worth). Capsules come from
  ``occluders`` or, given a BodyEstimate and the BodyModel, from the predicted
  link poses and the model's shapes (:func:`occluders_from_body`);
* VISIBLE otherwise.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .cameras import Camera
from .types import BEHIND_CAMERA, OCCLUDED, OFF_IMAGE, VISIBLE, Blob3D, BodyEstimate, LinkEstimate, Prior2D

__all__ = [
    "Capsule",
    "confidence_from_covariance",
    "occluded",
    "occluders_from_body",
    "off_image_margin_px",
    "project_gaussian",
    "project_priors",
    "visible_points",
]

#: Default ``confidence_scale`` s in exp(-‖Σ₃‖_F / s), m².
DEFAULT_CONFIDENCE_SCALE = 0.01
#: Default ``occlusion_surface_sigma``: a blob's line of sight stops this many of its standard
#: deviations along it short of its mean (module docstring, OCCLUDED; 0: at ``occlusion_margin``)
DEFAULT_OCCLUSION_SURFACE_SIGMA = 2.0
#: Default ``centre_occlusion_labels``: the blobs whose line of sight runs to their mean (less
#: ``occlusion_margin``) whatever their extent
DEFAULT_CENTRE_OCCLUSION_LABELS = ("l_hand", "r_hand")


@dataclass
class Capsule:
    """A capsule of the predicted body (world frame, m): the set of points within
    ``radius`` of the segment p0-p1 (a sphere when p0 == p1). ``label`` is the
    link it belongs to; a blob is never occluded by a capsule of its own label."""

    label: str
    p0: np.ndarray
    p1: np.ndarray
    radius: float


def project_gaussian(
    camera: Camera, mean: np.ndarray, cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """First-order projection of a 3-D Gaussian into a camera image.

    mean: (3,) m, world frame; cov: (3, 3) m². Returns mean2: (2,) px (the projected
    mean, with distortion), cov2: (2, 2) px² = J Σ₃ Jᵀ with J = d(uv)/d(X_world) at the
    mean, and depth: optical-frame z of the mean, m (<= 0: behind the camera, where the
    projection is meaningless).
    """
    mean = np.asarray(mean, dtype=float).reshape(3)
    cov = np.asarray(cov, dtype=float).reshape(3, 3)
    uv, cov2 = _project_gaussians(camera, mean[None], cov[None])
    depth = float(camera.R[2] @ mean + camera.t[2])
    return uv[0], cov2[0], depth


def _project_gaussians(camera: Camera, means: np.ndarray, covs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`project_gaussian` for N Gaussians (means (N, 3), covs (N, 3, 3)) in one projection
    call: (uv (N, 2) px, cov2 (N, 2, 2) px²)."""
    uv, J = camera.project_jacobian(means)
    cov2 = J @ covs @ np.swapaxes(J, 1, 2)
    return uv, 0.5 * (cov2 + np.swapaxes(cov2, 1, 2))


def confidence_from_covariance(cov: np.ndarray, scale: float = DEFAULT_CONFIDENCE_SCALE) -> float:
    """exp(-‖Σ‖_F / scale) in [0, 1]: the paper's ‖P_{t|t-1}‖ confidence (module docstring)."""
    norm = float(np.linalg.norm(np.asarray(cov, dtype=float)))
    if not np.isfinite(norm):
        return 0.0
    return float(np.exp(-norm / float(scale)))


def _segment_distances(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> np.ndarray:
    """Distances between segments a0-a1 and b0-b1, all (..., 3) and broadcast together -> (...).

    Closest points of two segments (Ericson, Real-Time Collision Detection, 5.1.9),
    vectorised (e.g. N lines of sight (N, 1, 3) against M capsule axes (1, M, 3) -> (N, M)).
    """
    a0, a1, b0, b1 = np.broadcast_arrays(*(np.asarray(x, float) for x in (a0, a1, b0, b1)))
    d1 = a1 - a0
    d2 = b1 - b0
    r = a0 - b0
    eps = 1e-12

    def dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.einsum("...i,...i->...", x, y)

    a, e, f, c, b = dot(d1, d1), dot(d2, d2), dot(d2, r), dot(r, d1), dot(d2, d1)
    a_ok, e_ok = a > eps, e > eps
    a_safe, e_safe = np.where(a_ok, a, 1.0), np.where(e_ok, e, 1.0)
    denom = a * e - b * b
    ok = denom > eps * a * np.maximum(e, eps)  # not parallel
    s = np.clip(np.where(ok, (b * f - c * e) / np.where(ok, denom, 1.0), 0.0), 0.0, 1.0)
    t = np.where(e_ok, (b * s + f) / e_safe, 0.0)
    s = np.where(t < 0.0, np.clip(-c / a_safe, 0.0, 1.0), s)
    s = np.where(t > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s)
    t = np.clip(t, 0.0, 1.0)
    # degenerate second segment (a point): t = 0, s from projecting it on the first
    s = np.where(e_ok, s, np.clip(-c / a_safe, 0.0, 1.0))
    # degenerate first segment (a point): s = 0, t from projecting it on the second
    t = np.where(a_ok, t, np.where(e_ok, np.clip(f / e_safe, 0.0, 1.0), 0.0))
    s = np.where(a_ok, s, 0.0)
    p = a0 + s[..., None] * d1
    q = b0 + t[..., None] * d2
    return np.linalg.norm(p - q, axis=-1)


def _as_capsules(occluders: Iterable) -> list[Capsule]:
    out = []
    for o in occluders:
        if isinstance(o, Capsule):
            out.append(o)
        else:
            label, p0, p1, radius = o
            out.append(Capsule(str(label), np.asarray(p0, float), np.asarray(p1, float), float(radius)))
    return out


def occluded(
    camera_center: np.ndarray,
    point: np.ndarray,
    label: str,
    capsules: Sequence[Capsule],
    occlusion_margin: float = 0.05,
) -> bool:
    """True if a capsule whose label differs from ``label`` intersects the line of sight
    from camera_center to ``point`` (world, m), shortened by ``occlusion_margin`` m at the
    point's end (so that a neighbouring link touching the blob near its joint does not
    count). Capsules beyond the point never occlude it."""
    return bool(_occluded_many(camera_center, np.asarray(point, float).reshape(1, 3), [label],
                               capsules, occlusion_margin)[0])


def _occluded_many(camera_center: np.ndarray, points: np.ndarray, labels: Sequence[str],
                   capsules: Sequence[Capsule], occlusion_margin: float | np.ndarray) -> np.ndarray:
    """:func:`occluded` for N points (N, 3) with their labels at once -> (N,) bool; occlusion_margin:
    one for all points or (N,) one per point."""
    points = np.asarray(points, float).reshape(-1, 3)
    if not capsules or not len(points):
        return np.zeros(len(points), bool)
    margin = np.broadcast_to(np.asarray(occlusion_margin, float), (len(points),))
    C = np.asarray(camera_center, float).reshape(3)
    v = points - C
    dist = np.linalg.norm(v, axis=1)
    near = dist <= margin
    end = points - v / np.where(near, 1.0, dist)[:, None] * margin[:, None]
    p0 = np.array([c.p0 for c in capsules], dtype=float).reshape(-1, 3)
    p1 = np.array([c.p1 for c in capsules], dtype=float).reshape(-1, 3)
    radii = np.array([c.radius for c in capsules], dtype=float)
    other = np.array([[c.label != lab for c in capsules] for lab in labels], bool).reshape(len(points), -1)
    hit = (_segment_distances(C, end[:, None], p0[None], p1[None]) < radii) & other
    return hit.any(axis=1) & ~near


def off_image_margin_px(camera: Camera) -> float:
    """The default OFF_IMAGE tolerance of :func:`project_priors`: 5 % of the camera's larger image side, px."""
    return 0.05 * max(camera.width, camera.height)


def visible_points(camera: Camera, points: np.ndarray, label: str, capsules: Sequence[Capsule],
                   occlusion_margin: float = 0.05, inset_px: float = 0.0, min_depth: float = 1e-3) -> np.ndarray:
    """(N,) bool: which world points (N, 3) m a part ``label`` placed there would show in ``camera``:
    in front of it (depth > ``min_depth``), projected inside the image shrunk by ``inset_px`` on
    each side (and not folded back by the distortion, as OFF_IMAGE), and not OCCLUDED by a
    capsule of another label (:func:`occluded`, to ``occlusion_margin`` short of the point)."""
    points = np.asarray(points, float).reshape(-1, 3)
    out = np.zeros(len(points), bool)
    x_cam = points @ camera.R.T + camera.t
    front = np.flatnonzero(x_cam[:, 2] > min_depth)
    if not len(front):
        return out
    r2 = (x_cam[front, 0] ** 2 + x_cam[front, 1] ** 2) / x_cam[front, 2] ** 2
    uv, _ = camera.project(points[front])
    inside = front[(r2 <= _fov_radius2(camera)) & camera.in_image(uv, margin=-float(inset_px))]
    out[inside] = ~_occluded_many(camera.center, points[inside], [label] * len(inside), capsules, occlusion_margin)
    return out


def occluders_from_body(body, links: Iterable[LinkEstimate]) -> list[Capsule]:
    """World capsules of the body's shapes at the given link poses.

    body: a BodyModel (uses ``body.links[i].name`` and ``.shapes``, each with
    ``as_capsule()`` -> (p0, p1, radius) in the link frame); links: LinkEstimate
    (position (3,) m = link-frame origin, rotation (3, 3) world_from_link). Links
    without an estimate contribute nothing. Capsule labels are link names.
    """
    poses = {lk.name: lk for lk in links}
    out = []
    for link in body.links:
        est = poses.get(link.name)
        if est is None:
            continue
        R = np.asarray(est.rotation, dtype=float).reshape(3, 3)
        p = np.asarray(est.position, dtype=float).reshape(3)
        for shape in link.shapes:
            a, b, r = shape.as_capsule()
            out.append(Capsule(link.name, R @ a + p, R @ b + p, float(r)))
    return out


def _fov_radius2(camera: Camera) -> float:
    """Squared radius, in undistorted normalised coordinates, beyond which a point is
    certainly outside the image: 1.5² x that of the farthest image corner."""
    w, h = camera.width, camera.height
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    xy = camera.normalized_from_pixel(corners)
    return float(2.25 * np.max(np.sum(xy**2, axis=1)))


def project_priors(
    blobs3d: Sequence[Blob3D] | BodyEstimate,
    cameras: Mapping[str, Camera] | Iterable[Camera],
    stamp_ns: int | None = None,
    occluders: Iterable[Capsule | tuple] | None = None,
    confidence_scale: float = DEFAULT_CONFIDENCE_SCALE,
    margin: float | None = None,
    occlusion_margin: float = 0.05,
    min_depth: float = 1e-3,
    body=None,
    occlusion_surface_sigma: float = DEFAULT_OCCLUSION_SURFACE_SIGMA,
    centre_occlusion_labels: Iterable[str] = DEFAULT_CENTRE_OCCLUSION_LABELS,
) -> dict[str, list[Prior2D]]:
    """Project predicted 3-D blobs into every camera as 2-D priors.

    blobs3d: the predicted blobs (world frame, mean (3,) m, cov (3, 3) m²), or a
    BodyEstimate (its ``.blobs``; its ``stamp_ns`` when ``stamp_ns`` is None; its
    links' position covariances for the confidence).
    cameras: dict name -> Camera or a list of cameras. stamp_ns: the frame the
    priors predict (int ns). occluders: capsules of the predicted body, as
    :class:`Capsule` or tuples (label, p0 (3,), p1 (3,), radius) in world m.
    confidence_scale: s in exp(-‖P‖_F / s), m². margin: OFF_IMAGE tolerance, px
    (default 5 % of the larger image side). occlusion_margin: m (see ``occluded``), the
    least distance by which a blob's line of sight stops short of its mean;
    occlusion_surface_sigma: it stops short by this many of the blob's standard deviations
    along it when that is more, except for the blobs of ``centre_occlusion_labels``
    (module docstring, OCCLUDED).
    min_depth: m, nearer points are BEHIND_CAMERA. body: BodyModel; with a
    BodyEstimate and no ``occluders``, the occluders are its shapes at the
    predicted link poses.

    ``project_priors(prediction, cameras, body)`` (the ARCHITECTURE.md form) is
    accepted too: a third positional argument that is not an integer is the body.

    Returns {camera name: [Prior2D per blob, in input order]}, every blob in every
    camera, each with its visibility code (module docstring).
    """
    if stamp_ns is not None and not isinstance(stamp_ns, int | np.integer):
        body, stamp_ns = stamp_ns, None
    link_cov: dict[str, np.ndarray] = {}
    if isinstance(blobs3d, BodyEstimate):
        if stamp_ns is None:
            stamp_ns = blobs3d.stamp_ns
        link_cov = {lk.name: np.asarray(lk.cov, dtype=float)[:3, :3] for lk in blobs3d.links}
        if occluders is None and body is not None:
            occluders = occluders_from_body(body, blobs3d.links)
        blobs3d = blobs3d.blobs
    stamp_ns = int(stamp_ns or 0)
    cams = list(cameras.values()) if isinstance(cameras, Mapping) else list(cameras)
    capsules = _as_capsules(occluders) if occluders is not None else []

    blobs3d = list(blobs3d)
    labels = [blob.label for blob in blobs3d]
    centre_only = set(centre_occlusion_labels)
    extended = np.array([lab not in centre_only for lab in labels], bool)
    means3 = np.array([np.asarray(b.mean, dtype=float).reshape(3) for b in blobs3d]).reshape(-1, 3)
    covs3 = np.array([np.asarray(b.cov, dtype=float).reshape(3, 3) for b in blobs3d]).reshape(-1, 3, 3)
    confs = [confidence_from_covariance(link_cov.get(b.label, covs3[k]), confidence_scale)
             for k, b in enumerate(blobs3d)]
    out: dict[str, list[Prior2D]] = {}
    for cam in cams:
        m = off_image_margin_px(cam) if margin is None else float(margin)
        r2_max = _fov_radius2(cam)
        # all blobs of this camera at once: projection with the first-order covariance, the
        # field-of-view and image tests, and the lines of sight against the capsules
        x_cam = means3 @ cam.R.T + cam.t
        front = np.flatnonzero(x_cam[:, 2] > min_depth)
        uv, cov2 = _project_gaussians(cam, means3[front], covs3[front])
        r2 = (x_cam[front, 0] ** 2 + x_cam[front, 1] ** 2) / x_cam[front, 2] ** 2
        inside = (r2 <= r2_max) & cam.in_image(uv, margin=m)
        occ = np.zeros(len(front), bool)
        seen = front[inside]
        stop = np.full(len(seen), float(occlusion_margin))  # how far short of each mean its line of sight stops
        surface = extended[seen]  # the blobs tested against their near surface
        ext = seen[surface]
        if occlusion_surface_sigma > 0 and len(ext):
            d = means3[ext] - cam.center
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
            sigma = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", d, covs3[ext], d), 0.0))
            stop[surface] = np.maximum(occlusion_margin, occlusion_surface_sigma * sigma)
        occ[inside] = _occluded_many(cam.center, means3[seen], [labels[k] for k in seen], capsules, stop)
        priors = [Prior2D(lab, np.full(2, np.nan), np.full((2, 2), np.nan), 0.0, BEHIND_CAMERA, stamp_ns)
                  for lab in labels]
        for j, k in enumerate(front):
            if not inside[j]:
                priors[k] = Prior2D(labels[k], uv[j].copy(), cov2[j].copy(), 0.0, OFF_IMAGE, stamp_ns)
            else:
                priors[k] = Prior2D(labels[k], uv[j].copy(), cov2[j].copy(), confs[k], OCCLUDED if occ[j] else VISIBLE,
                                    stamp_ns)
        out[cam.name] = priors
    return out
