"""Start-up and facing cues of the 3-D estimators (ALGORITHMS.md §1, automatic start-up).

Skin blobs matched across views into the face and hands (:func:`match_skin_blobs`), grouped
into people (:func:`nearest_person`); one camera's start points (:func:`one_view_start_points`);
the facing that the face's blob sizes tell (:func:`facing_direction`, :func:`facing_agreement`),
which the face check during tracking uses as well. The rules are described in
``artrack.estimator``, where the estimators apply them.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.cluster.hierarchy import fcluster, linkage

from .cameras import Camera
from .triangulation import midpoint, triangulate_blob
from .types import Blob2D, Blob3D


def root_heading(R_root: np.ndarray) -> float:
    """Yaw (rad) of the root's forward (+x) axis projected on the floor."""
    return math.atan2(float(R_root[1, 0]), float(R_root[0, 0]))


def forward_xy(world_from_link: np.ndarray) -> np.ndarray:
    """The horizontal unit direction (2,) of a link's forward (+x) axis, world xy."""
    x = world_from_link[:2, 0]
    return x / max(float(np.linalg.norm(x)), 1e-9)


def facing_direction(blobs: Mapping[str, Blob2D], cameras: Mapping[str, Camera], origin: np.ndarray,
                     min_size_ratio: float = 2.0) -> np.ndarray | None:
    """The horizontal way a part faces by its 2-D blob sizes (the face check of ``tracking.facing_*``):
    a unit (2,) world xy vector. ``blobs``: camera -> that part's Blob2D; each view's size at 1 m is
    its pixel count x the squared distance from the camera centre to ``origin`` (the link origin,
    world m), and the sizes are fitted as ``a + c · u_k`` (u_k: the horizontal unit direction from
    the link to camera k, least squares): c is the way the larger blobs lie.

    The head's skin-coloured blob is the face in the views it looks at and only the neck in the
    views behind it (the hair covers the rest): about 4x larger at 1 m (synthetic seeds 1, 12:
    correlation with the cosine of each camera's bearing from the true facing 0.79, 0.85). Pixel
    counts must be real ones (shrinking with the squared distance). None with fewer than three
    views, views in a line, or the largest size less than ``min_size_ratio`` times the smallest
    (alike from every side)."""
    origin = np.asarray(origin, float)
    size, rows = [], []
    for name, blob in blobs.items():
        to_camera = np.asarray(cameras[name].center, float) - origin
        horizontal = float(np.linalg.norm(to_camera[:2]))
        if horizontal < 1e-6:
            continue
        size.append(blob.pixel_count * float(to_camera @ to_camera))
        rows.append([1.0, *(to_camera[:2] / horizontal)])
    if len(size) < 3 or max(size) < min_size_ratio * max(min(size), 1e-12):
        return None
    A = np.array(rows)
    if np.linalg.matrix_rank(A, tol=1e-3) < 3:
        return None
    c = np.linalg.lstsq(A, np.asarray(size) / np.mean(size), rcond=None)[0][1:]
    norm = float(np.linalg.norm(c))
    return None if norm < 1e-9 else c / norm


def facing_agreement(blobs: Mapping[str, Blob2D], cameras: Mapping[str, Camera],
                     world_from_link: np.ndarray, min_size_ratio: float = 2.0) -> float | None:
    """Whether a part's 2-D blob sizes say it faces the way it is posed: the cosine of the
    horizontal angle between the link's forward (+x) axis and :func:`facing_direction`
    (``world_from_link``: (4, 4) the link's pose). A body tracked facing backwards, with every
    left/right label swapped to match, explains the blobs' positions as well as the right one,
    but not the head's sizes: about -1 there; a heading off sideways gives about 0. None when
    the sizes say nothing (see :func:`facing_direction`)."""
    direction = facing_direction(blobs, cameras, world_from_link[:3, 3], min_size_ratio)
    return None if direction is None else float(forward_xy(world_from_link) @ direction)


def same_blobs(a: Mapping[str, Sequence[Blob2D]], b: Mapping[str, Sequence[Blob2D]]) -> bool:
    """Whether {camera: [Blob2D]} a and b hold the very same blob objects, camera by camera, in order."""
    return a.keys() == b.keys() and all(
        len(a[c]) == len(bl) and all(x is y for x, y in zip(a[c], bl, strict=True)) for c, bl in b.items())


def _in_gate(blob: Blob2D, uv: np.ndarray, gate_sigma: float, gate_px: float) -> tuple[bool, float]:
    r = np.asarray(uv, float) - np.asarray(blob.mean, float)
    d_px = float(np.linalg.norm(r))
    try:
        d2 = float(r @ np.linalg.solve(np.asarray(blob.cov, float).reshape(2, 2), r))
    except np.linalg.LinAlgError:
        d2 = np.inf
    return (d2 <= gate_sigma**2 or d_px <= gate_px), d_px


def nearest_in_gate(blobs: Sequence[Blob2D], uv: np.ndarray, gate_sigma: float, gate_px: float) -> int | None:
    """Index of the blob nearest (px) to ``uv`` among those whose gate (:func:`_in_gate`) holds it, or None."""
    best, best_d = None, np.inf
    for k, blob in enumerate(blobs):
        inside, d = _in_gate(blob, uv, gate_sigma, gate_px)
        if inside and d < best_d:
            best, best_d = k, d
    return best


def nearest_person(points: list, xy: np.ndarray, gap_m: float) -> list:
    """The start-up skin points (:func:`match_skin_blobs` tuples, point first) of the person nearest
    ``xy`` (2,) m: the points are grouped by single linkage on their horizontal distances (groups
    farther apart than ``gap_m`` are different people); of the groups with the most points (up to
    three: a face and two hands; a lone point is more often a ghost), the one whose highest point
    (the face) lies nearest ``xy`` horizontally is returned, in the input order."""
    if len(points) < 2:
        return points
    xy_all = np.array([p[0][:2] for p in points], float)
    group = fcluster(linkage(xy_all, "single"), gap_m, criterion="distance")
    groups = {g: np.flatnonzero(group == g) for g in set(group.tolist())}
    if len(groups) == 1:
        return points

    def rank(members: np.ndarray) -> tuple[int, float]:
        top = max(members, key=lambda i: points[i][0][2])
        return -min(len(members), 3), float(np.linalg.norm(xy_all[top] - xy))

    best = min(groups, key=lambda g: rank(groups[g]))
    return [p for p, g in zip(points, group, strict=True) if g == best]


def blob_size_m(camera: Camera, blob: Blob2D, depth_m: float) -> float:
    """The physical size (m) a 2-D blob implies at ``depth_m`` (m, along the camera's axis): the side of
    the square of its area, as a uniform ellipse of its covariance (area 4π √det C px²), times the
    pinhole scale depth / f."""
    det = max(float(np.linalg.det(np.asarray(blob.cov, float).reshape(2, 2))), 0.0)
    f = math.sqrt(float(camera.K[0, 0]) * float(camera.K[1, 1]))
    return math.sqrt(4.0 * math.pi * math.sqrt(det)) * float(depth_m) / f


def match_skin_blobs(
    skin_by_camera: Mapping[str, Sequence[Blob2D]],
    cameras: Mapping[str, Camera],
    max_points: int = 3,
    gate_sigma: float = 3.0,
    gate_px: float = 4.0,
    missing_view_penalty_px: float = 10.0,
    max_size_m: float = 0.0,
    share_taken_views: bool = False,
    share_min_separation_m: float = 0.0,
    min_size_m: float = 0.0,
) -> list[tuple[np.ndarray, float, tuple[str, ...], Blob3D]]:
    """Match unlabelled skin blobs across views into at most ``max_points`` 3-D points.

    Every pair of blobs from two cameras whose rays meet (midpoint in front of both,
    reprojecting inside both blobs: Mahalanobis ≤ gate_sigma in the blob's 2-D
    covariance, or ≤ gate_px) seeds a candidate, which is extended by the gated
    nearest blob of every other camera and triangulated; its score is the mean
    reprojection error (px) plus ``missing_view_penalty_px`` per camera with skin
    blobs that it does not see. Candidates are taken greedily by score, never
    sharing a 2-D blob. ``max_size_m`` > 0: a blob larger than this at the point
    (:func:`blob_size_m`; a hand merged in that view with a ghost of the background or
    another skin region) sees the point but does not locate it: it counts among the
    point's views, not in its triangulation, and cannot seed a pair. ``share_taken_views``:
    a candidate whose extension took a blob that a better point has already taken (two hands
    merged in that view) is not dropped: that view sees it without locating it, and it is
    triangulated again from its other blobs if at least two remain; but not when that better
    point is the highest so far (the face): a ghost of the start position near the head lined up
    with the face's blobs (synthetic default scene, seed 21), nor when the two points are less than
    ``share_min_separation_m`` apart horizontally (the other hand stands beside a hand; a skin
    point stacked above it is more often its forearm or a ghost: self-occlusion seed 44). An
    oversized view only sees its point: its blob is taken by nobody (rotation scene seed 4: the
    face-and-neck blob of the view behind a hand raised before the face was oversized at the hand,
    and the hand, taken first, took it from the face, which was dropped).
    ``min_size_m`` > 0: a candidate whose locating blobs are all smaller than this at the point is a
    speck (a few skin-coloured pixels, e.g. through the hair on the crown: line scene seed 1, 5-8 px
    in three views, 0.18 m above the face), not a face or a hand: it is not taken. Returns [(X (3,)
    world m, score px, the names of the cameras that see it, the triangulated Blob3D
    (label 'skin'; its cameras those that locate it))], best first.
    """
    names = sorted(c for c, bl in skin_by_camera.items() if len(bl) and c in cameras)
    if len(names) < 2:
        return []

    def oversized_at(c: str, k: int, depth_m: float) -> bool:
        return max_size_m > 0 and blob_size_m(cameras[c], skin_by_camera[c][k], depth_m) > max_size_m

    rays = {}
    for c in names:
        uv = np.array([np.asarray(b.mean, float) for b in skin_by_camera[c]]).reshape(-1, 2)
        o, d = cameras[c].rays(uv)
        rays[c] = (o, d)
    cands: dict[frozenset, tuple[np.ndarray, float, tuple[str, ...], Blob3D]] = {}
    for ci, cj in itertools.combinations(names, 2):
        for a in range(len(skin_by_camera[ci])):
            for b in range(len(skin_by_camera[cj])):
                X, spread = midpoint(
                    np.stack([rays[ci][0], rays[cj][0]]), np.stack([rays[ci][1][a], rays[cj][1][b]])
                )
                if spread < 1e-6:
                    continue
                members = {ci: a, cj: b}
                ok = True
                for c, k in members.items():
                    uv, depth = cameras[c].project(X[None])
                    if (depth[0] <= 0 or not _in_gate(skin_by_camera[c][k], uv[0], gate_sigma, gate_px)[0]
                            or oversized_at(c, k, depth[0])):
                        ok = False
                        break
                if not ok:
                    continue
                oversized: dict[str, int] = {}
                for ck in names:
                    if ck in members:
                        continue
                    uv, depth = cameras[ck].project(X[None])
                    if depth[0] <= 0:
                        continue
                    best = nearest_in_gate(skin_by_camera[ck], uv[0], gate_sigma, gate_px)
                    if best is None:
                        continue
                    if oversized_at(ck, best, depth[0]):
                        oversized[ck] = best
                    else:
                        members[ck] = best
                key = frozenset(members.items()) | frozenset(oversized.items())
                if key in cands:
                    continue
                blob = triangulate_blob(
                    [(cameras[c], skin_by_camera[c][k]) for c, k in sorted(members.items())]
                )
                if blob is None:
                    continue
                errs, largest = [], 0.0
                for c, k in members.items():
                    uv, depth = cameras[c].project(blob.mean[None])
                    errs.append(float(np.linalg.norm(uv[0] - np.asarray(skin_by_camera[c][k].mean, float))))
                    if min_size_m > 0:
                        largest = max(largest, blob_size_m(cameras[c], skin_by_camera[c][k], float(depth[0])))
                if min_size_m > 0 and largest < min_size_m:
                    continue  # a speck
                seen = len(members) + len(oversized)
                score = float(np.mean(errs)) + missing_view_penalty_px * (len(names) - seen)
                cands[key] = (blob.mean, score, tuple(sorted([*members, *oversized])), blob, members)
    out = []
    owner: dict = {}  # a taken 2-D blob -> the index in ``out`` of the point that took it
    for X, score, cams, blob, members in sorted(cands.values(), key=lambda v: v[1]):
        taken = [m for m in members.items() if m in owner]  # an oversized view only sees: it takes nothing
        if taken:
            # Shared only with points below the highest one so far (the face: see the docstring).
            highest = max(range(len(out)), key=lambda i: float(out[i][0][2]))
            free = {c: k for c, k in members.items() if (c, k) not in owner}
            if not share_taken_views or len(free) < 2 or any(owner[m] == highest for m in taken):
                continue
            blob = triangulate_blob([(cameras[c], skin_by_camera[c][k]) for c, k in sorted(free.items())])
            if blob is None or any(np.linalg.norm(blob.mean[:2] - out[owner[m]][0][:2]) < share_min_separation_m
                                   for m in taken):
                continue
            X = blob.mean
        owner.update(dict.fromkeys((m for m in members.items() if m not in owner), len(out)))
        out.append((X, score, cams, blob))
        if len(out) >= max_points:
            break
    return out


def one_view_start_points(
    camera: Camera,
    foreground: Blob2D,
    skin: Sequence[Blob2D],
    centre_height_m: float,
    max_points: int = 3,
) -> tuple[np.ndarray, list[tuple[np.ndarray, float, tuple[str, ...]]]] | None:
    """Start-up points from a single view, where no ray meets another (ALGORITHMS.md §1, automatic
    start-up; one camera "still constrains the ray"): depth from the floor instead of a second view.

    The person stands on the floor (z = 0, REP 103 z up), so the body's centroid lies at about
    ``centre_height_m`` (the rest pose's): the foreground blob's viewing ray is cut at that height.
    The skin blobs (largest first, at most ``max_points``) are placed on their rays at the centre's
    depth, in the vertical plane through the centre that faces the camera (a hand reaching towards
    or away from the camera is off that plane; the fit's ray-shaped targets leave it free there).

    Returns (centre (3,) world m, [(X (3,), pixel count, (camera name,))], largest first; every point
    lies on its ray, so ``X - camera.center`` is its direction), or None when the centroid's ray does
    not come down to that height in front of the camera (a camera at the centroid's height or below
    it, or one looking up: no floor cue).
    """
    origin, dirs = camera.rays(np.asarray(foreground.mean, float).reshape(1, 2))
    d = dirs[0]
    if abs(d[2]) < 1e-3:
        return None
    t = (centre_height_m - origin[2]) / d[2]
    if t <= 0.3:
        return None
    centre = origin + t * d
    n = centre - origin
    n[2] = 0.0
    n /= np.linalg.norm(n)
    blobs = sorted(skin, key=lambda b: -b.pixel_count)[:max_points]
    points: list[tuple[np.ndarray, float, tuple[str, ...]]] = []
    if blobs:
        _, sd = camera.rays(np.array([np.asarray(b.mean, float) for b in blobs]).reshape(-1, 2))
        for b, ds in zip(blobs, sd, strict=True):
            denom = float(ds @ n)
            if denom <= 1e-3:
                continue
            s = float((centre - origin) @ n) / denom
            points.append((origin + s * ds, float(b.pixel_count), (camera.name,)))
    return centre, points


def ray_information(direction: np.ndarray, sigma_across_m: float, sigma_along_m: float) -> np.ndarray:
    """(3, 3) information of a point known to sigma_across_m off a viewing ray of ``direction``
    (any length) and to sigma_along_m along it (one view's point; depth from a weaker cue)."""
    d = np.asarray(direction, float).reshape(3)
    d = d / np.linalg.norm(d)
    along = np.outer(d, d)
    return (np.eye(3) - along) / sigma_across_m**2 + along / sigma_along_m**2
