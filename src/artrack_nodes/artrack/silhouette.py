"""Checks of a tracked body on real video without ground truth (issue 5, "Checks").

* ``reference_foreground``: a foreground mask per view and frame that does not come from
  the tracker. The tracker's own background is causal (seeded from the first frames,
  artrack/blobs.py); this reference uses the whole clip instead: the clip is cut into
  blocks of ``block`` frames, each block's per-pixel temporal median is a background
  candidate, and a pixel of frame t is foreground when it differs (max over B, G, R)
  by more than ``threshold`` grey levels from *every* candidate whose block centre is at
  least ``min_gap`` frames away from t. Blocks far in time show the room where the
  person stands at t (they moved since), and taking the minimum over several of them
  removes the ghosts a single median keeps where the person spent most of the clip.
  Weak points: a body part that stays in one place for the whole clip is missing
  from the mask, and so is any part whose colour matches the room (dark shorts on the
  black treadmill) within ``threshold``.
* ``iou``: intersection over union of two masks.
* ``tolerant_overlap``: how the IoU's two failures split at a small tolerance: the share of the
  model's pixels within ``tol_px`` of the reference, and of the reference's within ``tol_px`` of
  the model. At the working resolution a limb is ~10 px wide and the calibration's residual is
  2-4 px (/work/shared/DATA.md: 8-17 px at full size), so the strict IoU punishes offsets that these
  shares forgive; ``shifted_iou`` gives the scale of it: the IoU of a mask with itself moved by a
  few pixels.
* ``BodySilhouette``: the body model's shapes (config/body_model.yaml capsules and
  ellipsoids, the same geometry `artrack synth` renders) placed at an estimate's link
  poses and rasterised in each camera.
* ``joints_inside``: whether projected joints fall inside a dilated mask.
* ``joint_speeds``: per-joint speed between consecutive frames, m/s.
* ``colour_marker``: a distinctly coloured object (e.g. the Pose2Sim man's cyan cap) found in
  every view by its HSV range and triangulated: an independent 3-D point on the person, to
  check that the tracked head stays with that person and to prove a calibration by reprojection.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from .body_model import BodyModel
from .cameras import Camera
from .synth import Renderer
from .triangulation import midpoint
from .types import BodyEstimate

__all__ = ["BodySilhouette", "colour_marker", "iou", "joint_speeds", "joints_inside", "marker_centre",
           "reference_foreground", "shifted_iou", "tolerant_overlap", "triangulate_point"]


def reference_foreground(
    frames: Sequence[Mapping[str, np.ndarray]],
    *,
    block: int = 20,
    min_gap: int = 30,
    threshold: float = 25.0,
    open_px: int = 3,
    stride: int = 2,
) -> list[dict[str, np.ndarray]]:
    """Foreground masks (H, W) bool per frame and camera from the whole clip (module docstring).

    frames: per frame {camera: (H, W, 3) uint8 BGR}; block: frames per background candidate
    (every ``stride``-th frame enters its median); min_gap: a candidate is used for frame t
    only if its block centre is at least this many frames from t (if none is, the farthest
    one); threshold: grey levels; open_px: morphological opening (removes speckle), px.
    """
    n = len(frames)
    if n == 0:
        return []
    starts = list(range(0, n, block))
    centres = np.array([min(s + block, n) / 2 + s / 2 for s in starts])
    names = list(frames[0])
    medians = {name: [np.median(np.stack([frames[i][name] for i in range(s, min(s + block, n), stride)]),
                                axis=0).astype(np.int16) for s in starts] for name in names}
    kernel = np.ones((open_px, open_px), np.uint8) if open_px > 1 else None
    out = []
    for t, images in enumerate(frames):
        gaps = np.abs(centres - t)
        use = np.flatnonzero(gaps >= min_gap)
        if use.size == 0:
            use = np.array([int(np.argmax(gaps))])
        masks = {}
        for name in names:
            img = images[name].astype(np.int16)
            diff = np.min([np.abs(img - medians[name][k]).max(axis=2) for k in use], axis=0)
            m = (diff > threshold).astype(np.uint8)
            if kernel is not None:
                m = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel)
            masks[name] = m.astype(bool)
        out.append(masks)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1.0 when both are empty)."""
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def _within(mask: np.ndarray, tol_px: int) -> np.ndarray:
    """Pixels within ``tol_px`` (Euclidean disc) of a True pixel of ``mask``."""
    if tol_px <= 0:
        return mask
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * tol_px + 1,) * 2)
    return cv2.dilate(mask.astype(np.uint8), k).astype(bool)


def tolerant_overlap(model: np.ndarray, reference: np.ndarray, tol_px: int) -> tuple[float, float]:
    """(share of ``model``'s pixels within ``tol_px`` of ``reference``, share of ``reference``'s pixels
    within ``tol_px`` of ``model``); an empty mask's share is 1.0 (nothing of it misses)."""
    nm, nr = np.count_nonzero(model), np.count_nonzero(reference)
    on = np.count_nonzero(model & _within(reference, tol_px)) / nm if nm else 1.0
    covered = np.count_nonzero(reference & _within(model, tol_px)) / nr if nr else 1.0
    return float(on), float(covered)


def shifted_iou(mask: np.ndarray, shift_px: int) -> float:
    """IoU of a mask with itself moved ``shift_px`` to the right (what a pose or calibration offset of
    that size costs a perfect silhouette)."""
    moved = np.zeros_like(mask)
    if shift_px < mask.shape[1]:
        moved[:, shift_px:] = mask[:, :mask.shape[1] - shift_px]
    return iou(mask, moved)


class BodySilhouette:
    """The body model's shapes at an estimate's link poses, rasterised per camera."""

    def __init__(self, body: BodyModel, cameras: Sequence[Camera]):
        self.body = body
        self.cameras = list(cameras)
        self.renderer = Renderer(body, self.cameras)
        self._index = {name: i for i, name in enumerate(body.link_names)}

    def masks(self, estimate: BodyEstimate) -> dict[str, np.ndarray] | None:
        """{camera: (H, W) bool} for the estimate, or None if it has no (complete) link poses."""
        if len(estimate.links) != len(self.body.links):
            return None
        T = np.tile(np.eye(4), (len(self.body.links), 1, 1))
        for link in estimate.links:
            i = self._index.get(link.name)
            if i is None:
                return None
            T[i, :3, :3] = link.rotation
            T[i, :3, 3] = link.position
        if not np.all(np.isfinite(T)):
            return None
        return {c.name: m for c, m in zip(self.cameras, self.renderer.silhouettes(T), strict=True)}


def joints_inside(camera: Camera, joints: np.ndarray, mask_dilated: np.ndarray) -> np.ndarray:
    """(J,) bool: joint (J, 3) world, m, projects in front of the camera inside ``mask_dilated``
    (H, W) bool. NaN joints, joints behind the camera or outside the image count as outside."""
    J = np.asarray(joints, dtype=float).reshape(-1, 3)
    inside = np.zeros(J.shape[0], bool)
    finite = np.all(np.isfinite(J), axis=1)
    if not finite.any():
        return inside
    uv, depth = camera.project(J[finite])
    px = np.round(uv).astype(np.int64)
    h, w = mask_dilated.shape
    ok = (depth > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    hit = np.zeros(len(px), bool)
    hit[ok] = mask_dilated[px[ok, 1], px[ok, 0]]
    inside[np.flatnonzero(finite)] = hit
    return inside


def joint_speeds(stamps_ns: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(T-1, J) speed of each joint between consecutive frames, m/s (NaN where either is NaN).

    stamps_ns: (T,) int ns, increasing; joints: (T, J, 3) world, m."""
    t = np.asarray(stamps_ns, dtype=np.int64)
    J = np.asarray(joints, dtype=float)
    if len(t) < 2:
        return np.zeros((0, J.shape[1] if J.ndim == 3 else 0))
    dt = np.diff(t).astype(float) * 1e-9
    return np.linalg.norm(np.diff(J, axis=0), axis=2) / dt[:, None]


def marker_centre(image_bgr: np.ndarray, hsv_low: Sequence[int], hsv_high: Sequence[int]) -> np.ndarray | None:
    """(2,) pixel centroid of the largest connected region with HSV (OpenCV: H 0..180) in
    [hsv_low, hsv_high], or None if there is none."""
    hsv = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, tuple(int(v) for v in hsv_low), tuple(int(v) for v in hsv_high))
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask)
    if n < 2:
        return None
    return centroids[1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))]


def triangulate_point(cameras: Sequence[Camera], uv: Mapping[str, np.ndarray]) -> tuple[np.ndarray, dict[str, float]]:
    """One point seen at pixels ``uv`` {camera: (2,)} by two or more of ``cameras``: (3,) world
    point, m (midpoint of the viewing rays, lens distortion removed), and each view's
    reprojection error, px."""
    used = [c for c in cameras if c.name in uv]
    origins, directions = [], []
    for c in used:
        o, d = c.rays(np.asarray(uv[c.name], dtype=float)[None])
        origins.append(o)
        directions.append(d[0])
    X, _ = midpoint(np.array(origins), np.array(directions))
    return X, {c.name: float(np.linalg.norm(c.project(X[None])[0][0] - uv[c.name])) for c in used}


def colour_marker(cameras: Sequence[Camera], images: Mapping[str, np.ndarray], hsv_low: Sequence[int],
                  hsv_high: Sequence[int]) -> tuple[np.ndarray | None, dict[str, float]]:
    """The marker (``marker_centre`` in each view) triangulated from the views that see it:
    (3,) world point, m (None with fewer than two views), and those views' reprojection errors, px."""
    seen = {}
    for c in cameras:
        uv = marker_centre(images[c.name], hsv_low, hsv_high)
        if uv is not None:
            seen[c.name] = uv
    if len(seen) < 2:
        return None, {}
    return triangulate_point(cameras, seen)
