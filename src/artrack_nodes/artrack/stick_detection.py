"""A 2-D stick detector: the image of a known, uniformly coloured stick
(ALGORITHMS.md §3.1: p_stick2d needs only the stick's image).

Pixels within an HSV colour box (OpenCV ranges: H 0-180, S and V 0-255) are
cleaned by a morphological opening; a robust line is fitted to them
(``cv2.fitLine``, Huber); the ends are the extreme projections onto the line
of the pixels within ``max_line_distance_px`` of it. The ends are returned
in a fixed order (smaller u first, then smaller v); which end is which on the
real stick is for the tracker to decide (:class:`artrack.particles.ParticleFilter`
orders them to fit its hands).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["StickDetection", "StickDetectorConfig", "detect_stick"]


@dataclass
class StickDetectorConfig:
    """Colour box (HSV, OpenCV ranges) of the stick and acceptance limits (px)."""

    hsv_lower: tuple[int, int, int] = (25, 150, 120)
    hsv_upper: tuple[int, int, int] = (35, 255, 255)
    min_pixels: int = 25
    min_length_px: float = 15.0
    max_line_distance_px: float = 3.0


@dataclass
class StickDetection:
    """Ends a_uv, b_uv (2,) px and the number of stick pixels."""

    a_uv: np.ndarray
    b_uv: np.ndarray
    pixel_count: int


def detect_stick(image_bgr: np.ndarray, config: StickDetectorConfig | None = None) -> StickDetection | None:
    """The stick in a BGR uint8 image (H, W, 3), or None if too few pixels / too short."""
    cfg = StickDetectorConfig() if config is None else config
    hsv = cv2.cvtColor(np.ascontiguousarray(image_bgr, dtype=np.uint8), cv2.COLOR_BGR2HSV)
    mask = cv2.inRange(hsv, np.array(cfg.hsv_lower, np.uint8), np.array(cfg.hsv_upper, np.uint8))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
    v, u = np.nonzero(mask)
    if len(u) < cfg.min_pixels:
        return None
    pts = np.column_stack([u, v]).astype(np.float32)
    vx, vy, x0, y0 = cv2.fitLine(pts, cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
    d = np.array([vx, vy], float)
    rel = pts - np.array([x0, y0], float)
    t = rel @ d
    near = np.abs(rel @ np.array([-d[1], d[0]])) <= cfg.max_line_distance_px
    if near.sum() < cfg.min_pixels:
        return None
    t = t[near]
    ends = np.array([x0, y0], float) + np.outer([t.min(), t.max()], d)
    if np.linalg.norm(ends[1] - ends[0]) < cfg.min_length_px:
        return None
    ends = ends[np.lexsort((ends[:, 1], ends[:, 0]))]
    return StickDetection(ends[0], ends[1], int(near.sum()))
