"""Per-part image likelihood of the loose-limbed body (ALGORITHMS.md §4 Likelihoods).

Evidence per camera: a foreground map ``fg`` in [0, 1] (difference to a
background image, soft-thresholded and blurred) and an edge map ``edge`` in
[0, 1] (Sobel magnitude, normalised, blurred, kept near the foreground). A
part pose X is scored by its projected tapered cylinder: points on the axis
and across it (offsets u·r, |u| ≤ 0.5, along the direction perpendicular to
both the axis and the viewing ray) should be foreground, points on the two
outlines (u = ±1) should lie on edges, and points just outside
(u = ±``outside``) should be background (this separates a limb from the
silhouette of the torso behind it); for the torso, points at the shoulders'
width along its own y axis should be foreground just below its distal end
and background just above it (without them the torso slides down the
equally wide column of the legs, and its twist is unobservable). Views are independent given the part:

    log φ(X) = − Σ_views [ w_fg · mean_in (1 − fg)² + w_edge · mean_outline (1 − edge)²
                           + w_bg · mean_out fg² + w_cap · (mean_above fg² + mean_shoulders (1 − fg)²) ]

(the squared-residual form of Deutscher's silhouette/edge cost). The same
function scores the annealed kinematic-tree filter (through all 10 parts).
Vectorised over poses: one projection call per view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from .body_parts import PartGeometry, cylinder_points
from .cameras import Camera


@dataclass
class LikelihoodConfig:
    """Parameters of the evidence maps and the part likelihood."""

    fg_low: float = 12.0       #: grey levels (max over B, G, R) of |image − background| where fg starts
    fg_high: float = 35.0      #: ... and where fg = 1
    blur_sigma_px: float = 1.5  #: Gaussian blur of both maps, px
    edge_norm_percentile: float = 99.0  #: edge magnitude at this percentile maps to 1
    edge_fg_dilate_px: int = 5  #: edges are kept within this distance of the foreground
    w_fg: float = 6.0           #: weight of the silhouette term per view
    w_edge: float = 3.0         #: weight of the edge term per view
    w_bg: float = 2.0           #: weight of the outside term per view (points just outside should be background)
    outside: float = 1.8        #: offset of the outside points (× radius)
    cap_parts: tuple[str, ...] = ("torso",)  #: parts whose shoulders are scored (see module docstring)
    cap_offset: float = 0.08    #: m above / below the distal end of the shoulder test points
    w_cap: float = 3.0          #: weight of that term per view
    n_axial: int = 6            #: samples along the cylinder axis
    interior: tuple[float, ...] = (-0.5, 0.0, 0.5)  #: offsets across the cylinder (× radius)


@dataclass
class ViewEvidence:
    """Evidence maps of one camera: fg, edge (H, W) float32 in [0, 1]."""

    camera: Camera
    fg: np.ndarray
    edge: np.ndarray


def view_evidence(camera: Camera, image_bgr: np.ndarray, background_bgr: np.ndarray,
                  config: LikelihoodConfig | None = None) -> ViewEvidence:
    """Foreground and edge maps of one image given the (empty-room) background image, both (H, W, 3) uint8."""
    cfg = config or LikelihoodConfig()
    diff = cv2.absdiff(image_bgr, background_bgr).max(axis=2).astype(np.float32)
    fg = np.clip((diff - cfg.fg_low) / (cfg.fg_high - cfg.fg_low), 0.0, 1.0)
    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
    mag = cv2.magnitude(cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3))
    near = cv2.dilate((fg > 0.5).astype(np.uint8), np.ones((2 * cfg.edge_fg_dilate_px + 1,) * 2, np.uint8))
    mag *= near
    scale = float(np.percentile(mag[near > 0], cfg.edge_norm_percentile)) if near.any() else 1.0
    edge = np.clip(mag / max(scale, 1e-6), 0.0, 1.0)
    if cfg.blur_sigma_px > 0:
        fg = cv2.GaussianBlur(fg, (0, 0), cfg.blur_sigma_px)
        edge = cv2.GaussianBlur(edge, (0, 0), cfg.blur_sigma_px)
    return ViewEvidence(camera, fg.astype(np.float32), edge.astype(np.float32))


def frame_evidence(cameras: Sequence[Camera], images: dict[str, np.ndarray], backgrounds: dict[str, np.ndarray],
                   config: LikelihoodConfig | None = None) -> list[ViewEvidence]:
    """view_evidence for every camera (images and backgrounds keyed by camera name)."""
    return [view_evidence(c, images[c.name], backgrounds[c.name], config) for c in cameras]


def sample_maps(view: ViewEvidence, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(fg, edge) values (N,) at world points (N, 3), nearest pixel; 0 outside the image or behind the camera."""
    uv, depth = view.camera.project(points)
    h, w = view.fg.shape
    # far off or behind the camera (masked below): keep the integer cast defined
    uv = np.clip(np.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0), -1.0, float(max(h, w)))
    iu = np.rint(uv[:, 0]).astype(np.int64)
    iv = np.rint(uv[:, 1]).astype(np.int64)
    ok = (depth > 0.05) & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    fg = np.zeros(len(points), np.float32)
    ed = np.zeros(len(points), np.float32)
    fg[ok] = view.fg[iv[ok], iu[ok]]
    ed[ok] = view.edge[iv[ok], iu[ok]]
    return fg, ed


class PartLikelihood:
    """log φ_part(X) over all views for the parts of ``geometry`` (see module docstring)."""

    def __init__(self, geometry: PartGeometry, config: LikelihoodConfig | None = None):
        self.geometry = geometry
        self.config = config or LikelihoodConfig()

    def log_likelihood(self, part: int, pos: np.ndarray, quat: np.ndarray,
                       views: Sequence[ViewEvidence]) -> np.ndarray:
        """(N,) log φ of part index ``part`` at poses pos (N, 3), quat (N, 4) given the views' evidence."""
        cfg = self.config
        pos = np.asarray(pos, float).reshape(-1, 3)
        n = len(pos)
        if n == 0:
            return np.zeros(0)
        centres, radii, axis_w = cylinder_points(self.geometry, part, pos, np.asarray(quat, float).reshape(-1, 4),
                                                 cfg.n_axial)
        section = self.geometry.section[part]
        Rm = None
        if not np.allclose(section, 1.0):
            Rm = Rotation.from_quat(np.asarray(quat, float).reshape(-1, 4)).as_matrix()
        cap = None
        if self.geometry.names[part] in cfg.cap_parts:  # (N, 2 above/below, 2 sides, 3) world
            g = self.geometry
            width = float(g.r_end[part] * g.section[part][1])
            local = np.array([[[0.0, s * width, g.end[part] + h] for s in (1.0, -1.0)]
                              for h in (cfg.cap_offset, -cfg.cap_offset)])
            Rq = Rotation.from_quat(np.asarray(quat, float).reshape(-1, 4)).as_matrix()
            cap = pos[:, None, None, :] + np.einsum("nab,hsb->nhsa", Rq, local)
        inner = np.asarray(cfg.interior, float)
        offs = np.concatenate([inner, [-1.0, 1.0, -cfg.outside, cfg.outside]])
        n_in = len(inner)
        total = np.zeros(n)
        for view in views:
            ray = centres - view.camera.center  # (N, K, 3)
            perp = np.cross(axis_w[:, None, :], ray)
            perp /= np.linalg.norm(perp, axis=-1, keepdims=True) + 1e-12
            half = np.broadcast_to(radii[None, :], perp.shape[:2])
            if Rm is not None:  # elliptic section: half-width = support function along perp
                local = np.einsum("nab,nka->nkb", Rm, perp)
                half = half * np.hypot(section[0] * local[..., 0], section[1] * local[..., 1])
            pts = centres[:, :, None, :] + (offs[None, None, :, None] * half[:, :, None, None]
                                            * perp[:, :, None, :])  # (N, K, U, 3)
            fg, ed = sample_maps(view, pts.reshape(-1, 3))
            fg = fg.reshape(n, -1, len(offs))
            ed = ed.reshape(n, -1, len(offs))
            s_fg = np.mean((1.0 - fg[:, :, :n_in]) ** 2, axis=(1, 2))
            s_ed = np.mean((1.0 - ed[:, :, n_in:n_in + 2]) ** 2, axis=(1, 2))
            s_bg = np.mean(fg[:, :, n_in + 2:] ** 2, axis=(1, 2))
            total -= cfg.w_fg * s_fg + cfg.w_edge * s_ed + cfg.w_bg * s_bg
            if cap is not None:  # shoulders: foreground at the shoulder line, background just above it
                fgc, _ = sample_maps(view, cap.reshape(-1, 3))
                fgc = fgc.reshape(n, 2, 2)
                total -= cfg.w_cap * (np.mean(fgc[:, 0] ** 2, axis=1) + np.mean((1.0 - fgc[:, 1]) ** 2, axis=1))
        return total

    def log_likelihood_parts(self, pos: np.ndarray, quat: np.ndarray, views: Sequence[ViewEvidence]) -> np.ndarray:
        """(N, P) log φ of every part for whole-body poses pos (N, P, 3), quat (N, P, 4)."""
        return np.stack([self.log_likelihood(p, pos[:, p], quat[:, p], views)
                         for p in range(self.geometry.n_parts)], axis=1)
