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
equally wide column of the legs, and its twist is unobservable). The head
also carries an appearance term, the face: a silhouette cannot tell a person
facing the camera from one turned away (the whole body mirrored, left and right
swapped, fits the same outline), but the face is skin and the back of the head
is hair. A ring of points around the head at ``face_height`` is sampled; each
one facing the camera should be skin (``skin`` map: the blob tracker's default
skin colour model, ``colour_model.skin_model``) where it is in front (within
``face_half_angle`` of the head's forward axis) and not skin where it is behind.
Views are independent given the part:

    log φ(X) = − Σ_views [ w_fg · mean_in (1 − fg)² + w_edge · mean_outline (1 − edge)²
                           + w_bg · mean_out fg² + w_cap · (mean_above fg² + mean_shoulders (1 − fg)²)
                           + w_face · mean_ring (skin − front)² ]

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

from .blob_config import BlobTrackerConfig
from .body_parts import PartGeometry, cylinder_points
from .cameras import Camera
from .colour_model import colour_features, skin_model


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
    face_parts: tuple[str, ...] = ("head",)  #: parts scored by the face term (module docstring; () = none)
    w_face: float = 3.0          #: weight of the face term per view
    face_height: float = 0.13    #: m along the head's axis from its origin: the ring of face points
    face_ring: int = 12          #: points on that ring (on the cylinder's surface, × radius)
    face_half_angle: float = 1.0  #: rad from the forward (+x) axis: the face; behind (beyond π − this): hair
    skin_blur_sigma_px: float = 1.0  #: Gaussian blur of the skin map, px


@dataclass
class ViewEvidence:
    """Evidence maps of one camera: fg, edge and skin (H, W) float32 in [0, 1] (skin: None = no
    colour evidence, the face term is then left out)."""

    camera: Camera
    fg: np.ndarray
    edge: np.ndarray
    skin: np.ndarray | None = None


def view_evidence(camera: Camera, image_bgr: np.ndarray, background_bgr: np.ndarray,
                  config: LikelihoodConfig | None = None) -> ViewEvidence:
    """Foreground, edge and (with a face term) skin maps of one image given the (empty-room) background
    image, both (H, W, 3) uint8."""
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
    skin = None
    if cfg.face_parts and cfg.w_face > 0:
        skin = skin_map(image_bgr, cfg.skin_blur_sigma_px)
    return ViewEvidence(camera, fg.astype(np.float32), edge.astype(np.float32), skin)


def skin_map(image_bgr: np.ndarray, blur_sigma_px: float = 0.0) -> np.ndarray:
    """(H, W) float32 in [0, 1]: exp(−½ d²) of every pixel's colour distance d to the default skin model
    (``colour_model.skin_model``; 0 where darker than its minimum intensity), optionally blurred."""
    cfg = BlobTrackerConfig()
    d2 = skin_model(cfg).distance2(colour_features(image_bgr).reshape(-1, 3), cfg).reshape(image_bgr.shape[:2])
    skin = np.exp(-0.5 * np.minimum(d2, 50.0)).astype(np.float32)
    if blur_sigma_px > 0:
        skin = cv2.GaussianBlur(skin, (0, 0), blur_sigma_px)
    return skin


def frame_evidence(cameras: Sequence[Camera], images: dict[str, np.ndarray], backgrounds: dict[str, np.ndarray],
                   config: LikelihoodConfig | None = None) -> list[ViewEvidence]:
    """view_evidence for every camera (images and backgrounds keyed by camera name)."""
    return [view_evidence(c, images[c.name], backgrounds[c.name], config) for c in cameras]


def _pixels(view: ViewEvidence, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixel (row, column) (N,) of world points (N, 3) and whether it is in the image and in front."""
    uv, depth = view.camera.project(points)
    h, w = view.fg.shape
    # far off or behind the camera (masked below): keep the integer cast defined
    uv = np.clip(np.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0), -1.0, float(max(h, w)))
    iu = np.rint(uv[:, 0]).astype(np.int64)
    iv = np.rint(uv[:, 1]).astype(np.int64)
    ok = (depth > 0.05) & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    return iv, iu, ok


def sample_maps(view: ViewEvidence, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(fg, edge) values (N,) at world points (N, 3), nearest pixel; 0 outside the image or behind the camera."""
    iv, iu, ok = _pixels(view, points)
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
        face = None
        if self.geometry.names[part] in cfg.face_parts and cfg.w_face > 0:
            face = self._face_ring(part, pos, np.asarray(quat, float).reshape(-1, 4))
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
            if face is not None and view.skin is not None:
                total -= cfg.w_face * self._face_cost(view, *face)
        return total

    def _face_ring(self, part: int, pos: np.ndarray, quat: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The face ring of part poses (N): points (N, K, 3) world, outward normals (N, K, 3) and the
        expected skin (K,) (1 in front, 0 behind, NaN on the sides: not scored)."""
        cfg, g = self.config, self.geometry
        phi = np.linspace(-np.pi, np.pi, cfg.face_ring, endpoint=False)
        local_n = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)  # part frame, head x = forward
        s = (cfg.face_height - g.start[part]) / max(g.end[part] - g.start[part], 1e-9)
        radius = g.r_start[part] + np.clip(s, 0.0, 1.0) * (g.r_end[part] - g.r_start[part])
        R = Rotation.from_quat(quat).as_matrix()
        normals = np.einsum("nab,kb->nka", R, local_n)
        centre = pos + cfg.face_height * np.einsum("nab,b->na", R, g.axis[part])
        points = centre[:, None, :] + radius * normals
        expected = np.full(len(phi), np.nan)
        expected[np.abs(phi) <= cfg.face_half_angle] = 1.0
        expected[np.abs(phi) >= np.pi - cfg.face_half_angle] = 0.0
        return points, normals, expected

    @staticmethod
    def _face_cost(view: ViewEvidence, points: np.ndarray, normals: np.ndarray, expected: np.ndarray
                   ) -> np.ndarray:
        """(N,) mean (skin − expected)² over the face-ring points that face the camera and are scored."""
        n, k = points.shape[:2]
        iv, iu, ok = _pixels(view, points.reshape(-1, 3))
        skin = np.zeros(n * k, np.float32)
        skin[ok] = view.skin[iv[ok], iu[ok]]
        facing = np.einsum("nka,nka->nk", normals, view.camera.center - points) > 0
        use = facing & np.isfinite(expected)[None, :] & ok.reshape(n, k)
        r2 = np.where(use, (skin.reshape(n, k) - np.nan_to_num(expected)[None, :]) ** 2, 0.0)
        return r2.sum(axis=1) / np.maximum(use.sum(axis=1), 1)

    def log_likelihood_parts(self, pos: np.ndarray, quat: np.ndarray, views: Sequence[ViewEvidence]) -> np.ndarray:
        """(N, P) log φ of every part for whole-body poses pos (N, P, 3), quat (N, P, 4)."""
        return np.stack([self.log_likelihood(p, pos[:, p], quat[:, p], views)
                         for p in range(self.geometry.n_parts)], axis=1)
