"""Edge-based articulated tracking of the body model — ALGORITHMS.md §2 (Drummond & Cipolla, Algorithm 1).

One :meth:`EdgeTracker.step` per video frame, starting from predicted link poses
(world_from_link), repeated ``iterations`` times:

1. *sampling* — contour samples of every link's clipped quadrics in every camera at the
   current pose, visible ones only, all cameras in one batched pass
   (:func:`artrack.body_quadrics.sample_body_views`: conic
   ``C = A c - b b^T``, clip and occlusion tests);
2. *search* — from each sample a 1-D search along the image normal for the nearest
   (or strongest, see config) edge of the image gradient, grey or colour
   (:func:`artrack.edges.normal_search`), giving the signed distance ``m`` (px). With ``polarity``
   an edge must have the quadric's learnt colour inside and not outside
   (:meth:`EdgeTracker.learn_appearance`, :class:`artrack.edges.ColourCone`): without it the
   renderer's inner shading rings stop the search short whenever the body moves outwards, and each
   frame recovers only part of its motion. The outline offset measured at the trusted pose
   (rendered outlines ~0.5 px wide of the model) is subtracted from ``m``;
3. *statistics* — Jacobian rows per sample (normal component of the image motion under the
   six generators, :func:`artrack.edges.jacobian_rows` batched over links), in the *link*
   frame with ``E = cam_from_world @ world_from_link``, so rows of all views are stacked for
   one ``xi`` per link; robust re-weighting ``w = c/(c + |m|)`` gives ``xi_hat_i``, ``C_i``
   (:func:`artrack.edges.motion_statistics`, eqs. 7-10). A zero-motion prior
   ``D = diag(d_t I3, d_r I3)`` (px^2 per m^2 / rad^2: the information of a per-frame motion of
   about ``1/sqrt(d)``) is added as damped least squares, ``C' = C + D``,
   ``xi_hat' = C'^-1 C xi_hat``: links seen by few or no samples and directions no view observes
   (depth in one view, a limb's spin) stay put instead of taking a minimum-norm guess. Links
   with fewer than ``min_found`` edges found, and no measured link below them (small hands and
   feet at low resolution, occluded limbs), are *carried*: they keep their pose relative to
   their parent (a zero-motion prior in their own frame would leave them behind in the world);
4. *propagation* — Algorithm 1 over the kinematic tree (ball / hinge joints of the body
   model), ``E_i <- E_i exp(xi_i)`` and exact coercion of the joints
   (:func:`artrack.propagation.articulated_update`).

Resolution: the pixel lengths of the config (``spacing_px``, ``search_px``, ``polarity_side_px``,
``blur_sigma``) are given for an image ``reference_width_px`` wide and multiplied by
``s = width / reference_width_px`` in each camera (outline rims, shading rings, edge blur and per-frame
motions are ``s`` times wider there); edge distances and Jacobian rows are divided by ``s`` (reference
pixels), so ``c_robust``, the damping and the learnt outline offset keep their meaning at every resolution.

Lens distortion: each image is first resampled to the pinhole camera ``K`` (``cv2.remap``
with maps built once per camera), since quadrics image to conics only without distortion.
Poses are world_from_link (4, 4) as from :meth:`artrack.body_model.BodyModel.forward_kinematics`;
every link frame's origin is its proximal joint. Joint limits are not enforced here.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from artrack.body_model import BodyModel
from artrack.body_quadrics import BodySamples, body_quadrics, sample_body_views
from artrack.cameras import Camera
from artrack.edges import ColourCone, fit_colour_cone, motion_statistics, normal_search, robust_weights
from artrack.lie import inverse_se3, skew
from artrack.propagation import Joint, articulated_update, tree_schedule

__all__ = ["CameraMeasurements", "EdgeTracker", "EdgeTrackerConfig", "STAGES", "body_joints"]

#: Timing stages reported by :meth:`EdgeTracker.step` (ms, summed over iterations).
STAGES = ("gradients", "sampling", "search", "statistics", "propagation")


@dataclass
class EdgeTrackerConfig:
    """Edge tracker parameters; documented field by field in ``config/edge_features.yaml``."""

    spacing_px: float = 4.0
    search_px: float = 10.0
    threshold: float = 6.0
    select: str = "nearest"
    colour: bool = True
    blur_sigma: float = 0.8
    c_robust: float = 2.0
    robust_iterations: int = 1
    iterations: int = 3
    damping_translation: float = 400.0
    damping_rotation: float = 200.0
    min_found: int = 8
    occlusion: bool = True
    undistort: bool = True
    polarity: bool = True
    polarity_side_px: float = 1.5
    appearance_margin: float = 10.0
    learn_offset: bool = True
    reference_width_px: float = 320.0
    eps: float = 1e-9
    warmup_frames: int = 40

    def __post_init__(self) -> None:
        if self.spacing_px <= 0 or self.search_px < 2.0 or self.c_robust <= 0:
            raise ValueError("EdgeTrackerConfig: need spacing_px > 0, search_px >= 2 and c_robust > 0")
        if self.damping_translation < 0 or self.damping_rotation < 0:
            raise ValueError("EdgeTrackerConfig: damping_translation and damping_rotation must be >= 0")
        if self.iterations < 1 or self.robust_iterations < 0:
            raise ValueError("EdgeTrackerConfig: need iterations >= 1 and robust_iterations >= 0")
        if self.polarity_side_px <= 0 or self.appearance_margin < 0:
            raise ValueError("EdgeTrackerConfig: need polarity_side_px > 0 and appearance_margin >= 0")
        if self.warmup_frames < 0:
            raise ValueError("EdgeTrackerConfig: need warmup_frames >= 0")
        if self.reference_width_px < 0:
            raise ValueError("EdgeTrackerConfig: need reference_width_px >= 0 (0: no resolution scaling)")
        if self.select not in ("nearest", "strongest"):
            raise ValueError(f"EdgeTrackerConfig: select must be 'nearest' or 'strongest', got {self.select!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> EdgeTrackerConfig:
        """Build from a mapping (unknown keys are an error; missing ones take the defaults)."""
        data = dict(data or {})
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ValueError(f"EdgeTrackerConfig: unknown field(s) {', '.join(unknown)}")
        kw = {}
        for k, v in data.items():
            default = getattr(cls(), k)
            if isinstance(default, bool) and not isinstance(v, bool):
                # bool("false") is True: a switch must be a YAML true / false
                raise ValueError(f"EdgeTrackerConfig: {k} must be true or false, got {v!r}")
            kw[k] = type(default)(v)
        return cls(**kw)

    @classmethod
    def from_yaml(cls, path: str | Path) -> EdgeTrackerConfig:
        """Read ``config/edge_features.yaml`` (its ``edge_tracker`` mapping, or the top level)."""
        from artrack.config import read_yaml  # one-line InputError naming the file
        from artrack.errors import InputError

        data = read_yaml(path)
        try:
            return cls.from_dict(data.get("edge_tracker", data))
        except (TypeError, ValueError) as exc:
            raise InputError(f"{path}: {exc}") from None

    def as_dict(self) -> dict[str, Any]:
        """Plain dict of every field."""
        return asdict(self)


@dataclass
class CameraMeasurements:
    """The last iteration's edge measurements in one camera (pinhole pixels of ``K``).

    samples: the visible contour samples; distance (M,) signed px (NaN where not found);
    found (M,) bool; weight (M,) final robust weight ``c/(c + |r|)`` (residual ``r`` in reference pixels,
    see ``reference_width_px``; 0 where not found).
    """

    samples: BodySamples
    distance: np.ndarray
    found: np.ndarray
    weight: np.ndarray


def body_joints(body: BodyModel) -> list[Joint | None]:
    """One :class:`Joint` per link (None for the root): ball or hinge at the link origin (its
    proximal joint), hinge axis in the link frame, reference pose ``[I | offset]`` (rest)."""
    out: list[Joint | None] = []
    for i, lk in enumerate(body.links):
        if body.parent_index[i] < 0:
            out.append(None)
            continue
        T0 = np.eye(4)
        T0[:3, 3] = lk.offset
        if lk.joint == "hinge":
            out.append(Joint("hinge", np.zeros(3), lk.axis.copy(), T0))
        else:
            out.append(Joint("ball", np.zeros(3), None, T0))
    return out


def _jacobian_batch(points_cam: np.ndarray, normals: np.ndarray, K: np.ndarray,
                    cam_from_link: np.ndarray) -> np.ndarray:
    """:func:`artrack.edges.jacobian_rows` with one pose per sample: cam_from_link (M, 4, 4) -> (M, 6)."""
    R = cam_from_link[:, :3, :3]
    Ri = np.swapaxes(R, 1, 2)
    P = np.einsum("mij,mj->mi", Ri, points_cam - cam_from_link[:, :3, 3])  # link frame
    dX = np.concatenate([R, -R @ skew(P)], axis=2)  # (M, 3, 6)
    x, y, z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    fx, fy, s = K[0, 0], K[1, 1], K[0, 1]
    # n^T K[:2,:2] [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
    a = normals[:, 0] * fx
    b = normals[:, 0] * s + normals[:, 1] * fy
    nJ = np.stack([a / z, b / z, -(a * x + b * y) / z**2], axis=1)
    return np.einsum("mj,mjk->mk", nJ, dX)


class EdgeTracker:
    """Edge-based articulated tracker (module docstring). Cameras are fixed; images arrive per frame."""

    def __init__(self, body: BodyModel, cameras: Sequence[Camera], config: EdgeTrackerConfig | None = None):
        self.body = body
        self.cameras = list(cameras)
        self.config = config or EdgeTrackerConfig()
        self.quadrics = body_quadrics(body)
        self.joints = body_joints(body)
        self.schedule = tree_schedule(body.parent_index)
        self.n_links = len(body.links)
        self._maps: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
        self.last_measurements: dict[str, CameraMeasurements] = {}
        #: per body quadric, the appearance learnt by :meth:`learn_appearance` (None: not seen)
        self.appearance: list[ColourCone | None] | None = None
        #: signed outline offset (px, along the outward normal) measured at the trusted pose and
        #: subtracted from every edge distance (:meth:`learn_appearance`)
        self.outline_offset_px = 0.0

    # ------------------------------------------------------------------ images
    def _undistort(self, cam: Camera, img: np.ndarray) -> np.ndarray:
        if not self.config.undistort or not np.any(cam.dist != 0):
            return img
        if cam.name not in self._maps:
            self._maps[cam.name] = cv2.initUndistortRectifyMap(
                cam.K, cam.dist, None, cam.K, (cam.width, cam.height), cv2.CV_32FC1)
        m1, m2 = self._maps[cam.name]
        return cv2.remap(img, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def gradients(self, cam: Camera, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sobel (gx, gy) float32 of the undistorted, blurred image (grey (H, W) or colour (H, W, 3))."""
        return self.prepare(cam, image)[:2]

    def prepare(self, cam: Camera, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gx, gy, image) float32: Sobel gradients of the undistorted, blurred image and that image."""
        img = np.asarray(image)
        if img.ndim == 3 and not self.config.colour:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        img = self._undistort(cam, img).astype(np.float32)
        if self.config.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.config.blur_sigma * self.scale(cam))
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1.0 / 8.0)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1.0 / 8.0)
        return gx, gy, img

    # ------------------------------------------------------------------ appearance (edge polarity)
    def learn_appearance(self, images_by_camera: Mapping[str, np.ndarray], link_poses_world: np.ndarray) -> None:
        """Learn every body quadric's colour (:class:`artrack.edges.ColourCone`) from images at a trusted pose.

        Colours are read ``polarity_side_px`` and ``polarity_side_px + 1`` px inside every visible
        contour sample (against its outward normal) in every given view, pooled per quadric (a quadric
        with fewer than 8 colours takes its link's pool). Used by the edge search when ``polarity`` is
        on: an outline edge has the quadric's colour inside and not outside (:func:`artrack.edges.normal_search`).
        Typically called once with the first frame and its (initialised) pose; :meth:`step` calls it on
        its first frame, at the predicted pose, if it was never called.
        """
        cfg = self.config
        E = np.asarray(link_poses_world, dtype=float)
        cols: list[np.ndarray] = []
        prims: list[np.ndarray] = []
        cams = [c for c in self.cameras if c.name in images_by_camera]
        for cam, s in zip(cams, self._sample(cams, E)[1]):
            img = self.prepare(cam, images_by_camera[cam.name])[2]
            for d in (cfg.polarity_side_px * self.scale(cam), (cfg.polarity_side_px + 1.0) * self.scale(cam)):
                p = (s.uv - d * s.normals).astype(np.float32)
                c = cv2.remap(img, p[:, 0:1], p[:, 1:2], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                inside = (p[:, 0] >= 0) & (p[:, 0] <= cam.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= cam.height - 1)
                cols.append(c.reshape(len(p), -1)[inside].astype(float))
                prims.append(s.prim[inside])
        col = np.vstack(cols) if cols else np.zeros((0, 1))
        prim = np.concatenate(prims) if prims else np.zeros(0, dtype=int)
        links = np.array([q.link for q in self.quadrics])
        per_link = {}
        for i in range(self.n_links):  # a link no view sees keeps no colour (no polarity test for it)
            own = col[links[prim] == i] if len(prim) else col[:0]
            per_link[i] = fit_colour_cone(own, cfg.appearance_margin) if len(own) >= 8 else None
        self.appearance = []
        for k, q in enumerate(self.quadrics):
            own = col[prim == k]
            self.appearance.append(fit_colour_cone(own, cfg.appearance_margin) if len(own) >= 8 else per_link[q.link])
        self.outline_offset_px = 0.0
        if cfg.learn_offset:
            # the image outline vs the model's at the trusted pose (edge blur, anti-aliasing, clothing):
            # the median signed distance of the edges found, with the polarity test just learnt
            grads = {c.name: self.prepare(c, images_by_camera[c.name]) for c in self.cameras
                     if c.name in images_by_camera}
            self.measure(grads, E, dict.fromkeys(STAGES, 0.0))
            d = np.concatenate([m.distance[m.found] / self.scale(self._camera(name))
                                for name, m in self.last_measurements.items()] or [np.zeros(0)])
            if len(d) >= 8:
                lim = 0.25 * cfg.search_px
                self.outline_offset_px = float(np.clip(np.median(d), -lim, lim))

    def _colour_model(self, prim: np.ndarray, channels: int):
        """(has, u, s_lo, s_hi, perp_max) arrays for samples of primitives ``prim`` (M,), or None."""
        if not self.config.polarity or self.appearance is None:
            return None
        n = len(self.quadrics)
        has = np.zeros(n, dtype=bool)
        u = np.zeros((n, channels))
        lo, hi, pm = np.zeros(n), np.zeros(n), np.zeros(n)
        for k, cone in enumerate(self.appearance):
            if cone is not None and len(cone.u) == channels:
                has[k], u[k], lo[k], hi[k], pm[k] = True, cone.u, cone.s_lo, cone.s_hi, cone.perp_max
        return has[prim], u[prim], lo[prim], hi[prim], pm[prim]

    # ------------------------------------------------------------------ one iteration
    def _sample(self, cams: Sequence[Camera], world_from_link: np.ndarray) -> tuple[np.ndarray, list[BodySamples]]:
        """cam_from_link (V, L, 4, 4) and the visible contour samples of every camera of ``cams``, in one pass."""
        Es = np.array([c.cam_from_world @ world_from_link for c in cams]).reshape(-1, self.n_links, 4, 4)
        Ks = np.array([c.K for c in cams]).reshape(-1, 3, 3)
        spacing = [self.config.spacing_px * self.scale(c) for c in cams]
        return Es, sample_body_views(self.quadrics, Es, Ks, [(c.width, c.height) for c in cams],
                                     spacing, occlusion=self.config.occlusion)

    def scale(self, cam: Camera) -> float:
        """Pixel scale ``s = width / reference_width_px`` of ``cam`` (1 when ``reference_width_px`` is 0): the
        pixel lengths of the config (spacing, search range, polarity side, blur) are multiplied by ``s`` in
        this camera, and its edge distances and Jacobian rows divided by ``s`` (reference pixels)."""
        r = self.config.reference_width_px
        return cam.width / r if r > 0 else 1.0

    def measure(self, grads: Mapping[str, tuple[np.ndarray, np.ndarray, np.ndarray]], world_from_link: np.ndarray,
                timings: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-link statistics at ``world_from_link`` (L, 4, 4), link frames: (xi_hat (L, 6), C (L, 6, 6),
        measured (L,) bool; zero where unmeasured), without the damping prior (see :meth:`damped`);
        ``grads``: camera name -> :meth:`prepare` output."""
        cfg = self.config
        rows: list[np.ndarray] = []
        dists: list[np.ndarray] = []
        owners: list[np.ndarray] = []
        self.last_measurements = {}
        t0 = time.perf_counter()
        cams = [c for c in self.cameras if c.name in grads]
        Es, samples = self._sample(cams, world_from_link)
        timings["sampling"] += (time.perf_counter() - t0) * 1e3
        for cam, E, s in zip(cams, Es, samples):
            t1 = time.perf_counter()
            g = grads[cam.name]
            sc = self.scale(cam)
            model = self._colour_model(s.prim, 1 if g[2].ndim == 2 else g[2].shape[2])
            d, found = normal_search(None, s.uv, s.normals, cfg.search_px * sc, threshold=cfg.threshold,
                                     gradients=g[:2], select=cfg.select, colour_image=g[2], colour_model=model,
                                     side_px=cfg.polarity_side_px * sc)
            d = d / sc - self.outline_offset_px  # reference pixels
            t2 = time.perf_counter()
            J = _jacobian_batch(s.points_cam, s.normals, cam.K, E[s.link]) / sc
            rows.append(J)
            dists.append(d)
            owners.append(s.link)
            self.last_measurements[cam.name] = CameraMeasurements(s, d * sc, found, np.zeros(len(d)))
            timings["search"] += (t2 - t1) * 1e3
            timings["statistics"] += (time.perf_counter() - t2) * 1e3
        t0 = time.perf_counter()
        xi_hat = np.zeros((self.n_links, 6))
        C = np.zeros((self.n_links, 6, 6))
        measured = np.zeros(self.n_links, dtype=bool)
        if rows:
            J = np.vstack(rows)
            m = np.concatenate(dists)
            link = np.concatenate(owners)
            order = np.argsort(link, kind="stable")
            bounds = np.searchsorted(link[order], np.arange(self.n_links + 1))
            for i in range(self.n_links):
                idx = order[bounds[i]:bounds[i + 1]]
                if np.count_nonzero(np.isfinite(m[idx])) < cfg.min_found:
                    continue
                xi_hat[i], C[i] = motion_statistics(J[idx], m[idx], cfg.c_robust, cfg.robust_iterations)
                measured[i] = True
            for meas, Jc, dc in zip(self.last_measurements.values(), rows, dists):  # final weights, for publishing
                r = dc - np.einsum("mj,mj->m", Jc, xi_hat[meas.samples.link])
                meas.weight = np.where(meas.found, robust_weights(np.nan_to_num(r), cfg.c_robust), 0.0)
        timings["statistics"] += (time.perf_counter() - t0) * 1e3
        return xi_hat, C, measured

    def damped(self, xi_hat: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(xi_hat', C + D): the statistics with the zero-motion prior ``D`` (module docstring),
        ``xi_hat' = (C + D)⁻¹ C xi_hat`` (unchanged when a damping weight is 0)."""
        cfg = self.config
        D = np.diag([cfg.damping_translation] * 3 + [cfg.damping_rotation] * 3)
        if not np.all(np.diag(D) > 0):
            return xi_hat, C + D
        eta = np.einsum("nij,nj->ni", C, xi_hat)
        return np.linalg.solve(C + D, eta[..., None])[..., 0], C + D

    def carried_links(self, measured: np.ndarray) -> np.ndarray:
        """(L,) bool: non-root links with no measured link in their subtree (itself included)."""
        seen = np.asarray(measured, dtype=bool).copy()
        for i in range(self.n_links - 1, 0, -1):  # links are in topological order: children after parents
            p = self.body.parent_index[i]
            if p >= 0 and seen[i]:
                seen[p] = True
        carried = ~seen
        carried[self.body.parent_index < 0] = False
        return carried

    def _camera(self, name: str) -> Camera:
        return next(c for c in self.cameras if c.name == name)

    # ------------------------------------------------------------------ public
    def step(self, images_by_camera: Mapping[str, np.ndarray], link_poses_world: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
        """Track one frame from the predicted poses.

        images_by_camera: camera name -> BGR uint8 (H, W, 3) (or grey (H, W)) image, any subset of the
        cameras; link_poses_world: (L, 4, 4) predicted world_from_link.
        Returns (new world_from_link (L, 4, 4), xi_hat (L, 6) and C (L, 6, 6) of the last iteration (link
        frames, before propagation; both include the damping prior), timings_ms {stage: ms} for :data:`STAGES`).
        """
        timings = dict.fromkeys(STAGES, 0.0)
        t0 = time.perf_counter()
        grads = {c.name: self.prepare(c, images_by_camera[c.name]) for c in self.cameras
                 if c.name in images_by_camera}
        timings["gradients"] = (time.perf_counter() - t0) * 1e3
        E = np.array(link_poses_world, dtype=float, copy=True)
        if E.shape != (self.n_links, 4, 4):
            raise ValueError(f"EdgeTracker.step: link_poses_world must be ({self.n_links}, 4, 4), got {E.shape}")
        if self.config.polarity and self.appearance is None:
            self.learn_appearance(images_by_camera, E)
        E, xi_hat, C = self.track(grads, E, timings)
        return E, xi_hat, C, timings

    def track(self, grads: Mapping[str, Any], link_poses_world: np.ndarray, timings: dict[str, float]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``iterations`` cycles of :meth:`step` on prepared images (``grads``: camera name ->
        :meth:`prepare`), from (L, 4, 4) world_from_link; adds its times to ``timings``. Returns
        (world_from_link reached, xi_hat, C of the last iteration)."""
        E = np.asarray(link_poses_world, dtype=float)
        xi_hat = np.zeros((self.n_links, 6))
        C = np.zeros((self.n_links, 6, 6))
        for _ in range(self.config.iterations):
            xi_hat, C, measured = self.measure(grads, E, timings)
            t1 = time.perf_counter()
            xi_hat, C = self.damped(xi_hat, C)
            timings["statistics"] += (time.perf_counter() - t1) * 1e3
            t1 = time.perf_counter()
            carried = self.carried_links(measured)
            Cs = C.copy()
            Cs[carried] = self.config.eps * np.eye(6)  # no pull on the parent; the pose is set below
            E_new, _ = articulated_update(E, xi_hat, Cs, self.schedule, self.joints, eps=self.config.eps)
            for i in np.flatnonzero(carried):  # topological order: the parent is already final
                p = self.body.parent_index[i]
                E_new[i] = E_new[p] @ inverse_se3(E[p]) @ E[i]
            E = E_new
            timings["propagation"] += (time.perf_counter() - t1) * 1e3
        return E, xi_hat, C
